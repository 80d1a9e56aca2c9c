/*
 * The forceps' and the display's firmware logic, free of any board: what to do with
 * each byte the host sends and at each sampling or control instant. A board's sketch
 * (firmware/forceps, firmware/display) only reads its sensors, drives its outputs and
 * hands bytes to a write function; the test suite runs the same logic on a PC
 * (firmware/host/tc_host.c) behind a pseudo-terminal.
 */
#ifndef TC_DEVICE_H
#define TC_DEVICE_H

#include "tc_protocol.h"

#ifdef __cplusplus
extern "C" {
#endif

/* where frames and lines go: the UART, USB CDC or a pseudo-terminal */
typedef void (*tc_write_fn)(void *ctx, const uint8_t *data, size_t n);

/* counts to SI: value = gain * counts + offset (N for force, m for position) */
typedef struct {
    float force_gain, force_offset;
    float position_gain, position_offset;
} tc_calibration;

typedef struct {
    tc_decoder decoder;
    const char *info_json; /* the Info reply: identity, rate, clock, ADC bits, calibration */
    tc_calibration cal;
    tc_write_fn write;
    void *ctx;
    uint8_t streaming;
    uint32_t seq; /* numbers the sampling instants, streaming or not (section 8) */
    uint32_t sent;
} tc_forceps;

void tc_forceps_init(tc_forceps *f, const char *info_json, tc_calibration cal,
                     tc_write_fn write, void *ctx);
/* Act on bytes from the host: IDENTIFY answers Info, START and STOP the stream. */
void tc_forceps_receive(tc_forceps *f, const uint8_t *data, size_t n);
/* One sampling instant: a Sample frame if streaming. */
void tc_forceps_sample(tc_forceps *f, uint32_t clock_us, int16_t force, int16_t position);

/* The text logger's line for one sample, "t_us,force_N,closure_mm\n" with the
   calibration applied (closure printed in mm, 4 decimals); out needs 48 bytes. */
#define TC_TEXT_HEADER "t_us,force_N,closure_mm\n"
size_t tc_text_line(const tc_calibration *cal, uint32_t clock_us, int16_t force,
                    int16_t position, char *out);

typedef struct {
    tc_decoder decoder;
    tc_watchdog watchdog;
    const char *info_json;
    tc_write_fn write;
    void *ctx;
    uint32_t seq;
    uint32_t answers;  /* seq of the Encoder frame the command in use answers (section 7) */
    uint32_t streamed; /* Encoder frames sent since START */
} tc_display;

void tc_display_init(tc_display *d, const char *info_json, float v_max, tc_write_fn write,
                     void *ctx);
/* Act on bytes from the host: commands, and SetVoltage (the latest valid one wins). */
void tc_display_receive(tc_display *d, const uint8_t *data, size_t n);
/* One control period: the watchdog, then an Encoder frame if streaming. Returns the
   voltage the amplifier must hold until the next period, V. */
float tc_display_tick(tc_display *d, uint32_t clock_us, int32_t counts, uint8_t at_limit);

#ifdef __cplusplus
}
#endif

#endif /* TC_DEVICE_H */
