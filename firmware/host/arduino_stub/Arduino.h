/*
 * The few Arduino functions the reference sketches use, for building them on a PC: the
 * test suite compiles firmware/forceps and firmware/display against this to keep them
 * valid C++ (a board's own core replaces it when flashing).
 */
#ifndef TC_ARDUINO_STUB_H
#define TC_ARDUINO_STUB_H

#include <stddef.h>
#include <stdint.h>

#define HIGH 1
#define LOW 0
#define INPUT 0
#define OUTPUT 1
#define INPUT_PULLUP 2
#define CHANGE 1
#define A0 14
#define A1 15

uint32_t micros(void);
int analogRead(uint8_t pin);
void analogReadResolution(int bits);
void analogWrite(uint8_t pin, int value);
void analogWriteResolution(int bits);
void pinMode(uint8_t pin, uint8_t mode);
void digitalWrite(uint8_t pin, uint8_t value);
int digitalRead(uint8_t pin);
void attachInterrupt(uint8_t irq, void (*fn)(void), int mode);
int digitalPinToInterrupt(uint8_t pin);
void noInterrupts(void);
void interrupts(void);

class SerialPort {
  public:
    void begin(unsigned long baud);
    int available(void);
    int read(void);
    size_t write(const uint8_t *data, size_t n);
    size_t print(const char *text);
};
extern SerialPort Serial;

void setup(void);
void loop(void);

#endif
