/* A PC stand-in for a board: the stub's functions, and a main that runs the sketch's
   setup() and a few thousand loop()s with the clock advancing, writing to stdout. */
#include <stdio.h>
#include <time.h>

#include "Arduino.h"

SerialPort Serial;
static uint32_t now_us = 0;

uint32_t micros(void) { return now_us += 7; }
int analogRead(uint8_t pin) { return 512 + pin; }
void analogReadResolution(int) {}
void analogWrite(uint8_t, int) {}
void analogWriteResolution(int) {}
void pinMode(uint8_t, uint8_t) {}
void digitalWrite(uint8_t, uint8_t) {}
int digitalRead(uint8_t) { return HIGH; }
void attachInterrupt(uint8_t, void (*)(void), int) {}
int digitalPinToInterrupt(uint8_t pin) { return pin; }
void noInterrupts(void) {}
void interrupts(void) {}

void SerialPort::begin(unsigned long) {}
int SerialPort::available(void) { return 0; }
int SerialPort::read(void) { return -1; }
size_t SerialPort::write(const uint8_t *data, size_t n) { return fwrite(data, 1, n, stdout); }
size_t SerialPort::print(const char *text) { return (size_t)fputs(text, stdout); }

int main(void)
{
    setup();
    for (int i = 0; i < 20000; i++)
        loop();
    return 0;
}
