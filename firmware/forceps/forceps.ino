/*
 * tissuecli reference firmware: the sensorised forceps.
 *
 * Two ADC channels (force, jaw position) sampled at RATE_HZ on the microsecond clock,
 * sent as the binary protocol's Sample frames (docs/protocol.md) between START and STOP,
 * with the calibration constants below in the Info reply; or, with TEXT_MODE 1, printed
 * as "t_us,force_N,closure_mm" lines for `tissuecli record --protocol text`.
 *
 * Wiring and flashing: docs/firmware.md. The protocol itself is in src/ (the portable
 * core in firmware/core, shared with the display and with the test suite's PC build).
 */
#include "src/tc_device.h"

/* ------------------------------------------------------------------ configuration */

#ifndef TEXT_MODE
#define TEXT_MODE 0            /* 1: print text lines instead of binary frames */
#endif
#define BAUD 921600            /* binary at 1 kHz needs >= 460800 on a real UART */
#define RATE_HZ 1000           /* samples per second */
#define FORCE_PIN A0           /* strain-gauge amplifier output */
#define POSITION_PIN A1        /* jaw-position sensor output */

#if defined(__AVR__)
#define ADC_BITS 10            /* AVR: 10-bit ADC */
#else
#define ADC_BITS 12            /* SAMD, Teensy, RP2040, ESP32: analogReadResolution(12) */
#endif

/* Calibration: SI = GAIN * counts + OFFSET, counts signed (ADC reading - 2^(bits-1)).
   Measure them with a known load and known gaps (docs/firmware.md, "Calibration"),
   and write the same numbers here and nowhere else: the Info reply is built from them. */
#define FORCE_GAIN 0.0014652014652    /* N per count */
#define FORCE_OFFSET 2.0              /* N */
#define POSITION_GAIN 3.7851037851e-06 /* m per count */
#define POSITION_OFFSET 0.00725       /* m */

/* ------------------------------------------------------------------ */

#define STR_(x) #x
#define STR(x) STR_(x)

static const char INFO[] =
    "{\"protocol\":1,\"device\":\"forceps\",\"model\":\"tissuecli reference forceps\","
    "\"firmware\":\"1.0\",\"rate_hz\":" STR(RATE_HZ) ",\"clock_hz\":1000000,"
    "\"adc_bits\":" STR(ADC_BITS) ",\"calibration\":{"
    "\"force\":{\"gain\":" STR(FORCE_GAIN) ",\"offset\":" STR(FORCE_OFFSET) ",\"unit\":\"N\"},"
    "\"position\":{\"gain\":" STR(POSITION_GAIN) ",\"offset\":" STR(POSITION_OFFSET)
    ",\"unit\":\"m\"}}}";

static const tc_calibration CAL = {(float)FORCE_GAIN, (float)FORCE_OFFSET,
                                   (float)POSITION_GAIN, (float)POSITION_OFFSET};
static const uint32_t PERIOD_US = 1000000UL / RATE_HZ;

static tc_forceps forceps;
static uint32_t next_us;

static void serial_write(void *ctx, const uint8_t *data, size_t n)
{
    (void)ctx;
    Serial.write(data, n);
}

static int16_t read_signed(uint8_t pin)
{
    return (int16_t)(analogRead(pin) - (1 << (ADC_BITS - 1)));
}

void setup()
{
    Serial.begin(BAUD);
#if !defined(__AVR__)
    analogReadResolution(ADC_BITS);
#endif
    tc_forceps_init(&forceps, INFO, CAL, serial_write, 0);
#if TEXT_MODE
    forceps.streaming = 1;
    Serial.print(TC_TEXT_HEADER);
#endif
    next_us = micros();
}

void loop()
{
#if !TEXT_MODE
    uint8_t buf[32];
    size_t n = 0;
    while (Serial.available() && n < sizeof buf)
        buf[n++] = (uint8_t)Serial.read();
    if (n)
        tc_forceps_receive(&forceps, buf, n);
#endif
    /* sample on the microsecond clock: wraps every 71.6 min, differences stay right */
    if ((int32_t)(micros() - next_us) < 0)
        return;
    uint32_t stamp = next_us;
    next_us += PERIOD_US;
    int16_t force = read_signed(FORCE_PIN);
    int16_t position = read_signed(POSITION_PIN);
#if TEXT_MODE
    char line[48];
    size_t len = tc_text_line(&CAL, stamp, force, position, line);
    Serial.write((const uint8_t *)line, len);
#else
    tc_forceps_sample(&forceps, stamp, force, position);
#endif
}
