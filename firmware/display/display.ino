/*
 * tissuecli reference firmware: the solenoid tissue display.
 *
 * Every control period it applies the latest SetVoltage from the host (clamped to
 * [0, V_MAX], NaN as 0) to the solenoid amplifier through the DAC or a filtered PWM,
 * reads the piston's quadrature encoder, and sends an Encoder frame. The watchdog
 * (docs/protocol.md, section 7) cuts the solenoid after 5 periods without a valid
 * SetVoltage: the amplifier input goes to 0 V and its enable pin low. The board's own
 * watchdog timer resets it if the loop ever hangs; every output is low after a reset.
 *
 * Wiring and flashing: docs/firmware.md.
 */
#include "src/tc_device.h"

#if defined(__AVR__)
#include <avr/wdt.h>
#endif

/* ------------------------------------------------------------------ configuration */

#define BAUD 921600
#define RATE_HZ 1000          /* control loop, Hz */
#define V_MAX 3.0f            /* the largest voltage the solenoid may get, V */
#define V_FULL_SCALE 3.3f     /* amplifier input volts at full DAC/PWM code */
#define ENCODER_A 2           /* interrupt-capable pins */
#define ENCODER_B 3
#define LIMIT_PIN 4           /* end-stop switch to ground: LOW at the stop */
#define ENABLE_PIN 5          /* amplifier enable: HIGH drives the solenoid */
#define OUT_PIN A0            /* a DAC pin (SAMD, Teensy 3.x) or a PWM pin with RC filter */
#define OUT_BITS 10           /* DAC or PWM resolution */
/* metres per encoder count: reported so the host converts counts to m */
#define ENCODER_GAIN 1.0e-05

/* ------------------------------------------------------------------ */

#define STR_(x) #x
#define STR(x) STR_(x)

static const char INFO[] =
    "{\"protocol\":1,\"device\":\"display\",\"model\":\"tissuecli reference display\","
    "\"firmware\":\"1.0\",\"rate_hz\":" STR(RATE_HZ) ",\"clock_hz\":1000000,\"stale_flag\":true,"
    "\"calibration\":{\"position\":{\"gain\":" STR(ENCODER_GAIN) ",\"offset\":0,\"unit\":\"m\"}}}";

static const uint32_t PERIOD_US = 1000000UL / RATE_HZ;
static tc_display display;
static uint32_t next_us;
static volatile int32_t counts;

static void serial_write(void *ctx, const uint8_t *data, size_t n)
{
    (void)ctx;
    Serial.write(data, n);
}

/* quadrature decoding on both edges of A: direction from B */
static void on_encoder()
{
    if (digitalRead(ENCODER_A) == digitalRead(ENCODER_B))
        counts++;
    else
        counts--;
}

static void drive(float volts)
{
    uint32_t full = (1UL << OUT_BITS) - 1;
    uint32_t code = (uint32_t)(volts / V_FULL_SCALE * (float)full + 0.5f);
    if (code > full)
        code = full;
    analogWrite(OUT_PIN, (int)code);
    digitalWrite(ENABLE_PIN, volts > 0.0f ? HIGH : LOW);
}

void setup()
{
    pinMode(ENABLE_PIN, OUTPUT);
    digitalWrite(ENABLE_PIN, LOW); /* off until the host commands */
#if !defined(__AVR__)
    analogWriteResolution(OUT_BITS);
#endif
    drive(0.0f);
    pinMode(ENCODER_A, INPUT_PULLUP);
    pinMode(ENCODER_B, INPUT_PULLUP);
    pinMode(LIMIT_PIN, INPUT_PULLUP);
    attachInterrupt(digitalPinToInterrupt(ENCODER_A), on_encoder, CHANGE);
    Serial.begin(BAUD);
    tc_display_init(&display, INFO, V_MAX, serial_write, 0);
#if defined(__AVR__)
    wdt_enable(WDTO_60MS);
#endif
    next_us = micros();
}

void loop()
{
    uint8_t buf[32];
    size_t n = 0;
    while (Serial.available() && n < sizeof buf)
        buf[n++] = (uint8_t)Serial.read();
    if (n)
        tc_display_receive(&display, buf, n);
    if ((int32_t)(micros() - next_us) < 0)
        return;
    uint32_t stamp = next_us;
    next_us += PERIOD_US;
    noInterrupts();
    int32_t now_counts = counts;
    interrupts();
    float volts = tc_display_tick(&display, stamp, now_counts, digitalRead(LIMIT_PIN) == LOW);
    drive(volts);
#if defined(__AVR__)
    wdt_reset();
#endif
}
