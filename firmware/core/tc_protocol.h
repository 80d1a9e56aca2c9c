/*
 * tissuecli wire protocol, version 1: the portable core shared by the forceps and
 * display firmware (docs/protocol.md is the reference; tissuecli/hw/protocol.py the
 * reference implementation, which the test suite holds this code to byte for byte).
 *
 * Plain C99, no allocation, no floating-point printf, no dependence on the CPU's byte
 * order or on struct packing: it builds for an 8-bit AVR, a Cortex-M and a PC alike.
 */
#ifndef TC_PROTOCOL_H
#define TC_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define TC_PROTOCOL_VERSION 1
/* a run longer than this without a 0x00 is garbage (docs/protocol.md, section 3) */
#define TC_MAX_FRAME 1024
/* the longest frame a receiver keeps: a device receives only Commands and SetVoltage
   (13 bytes), so a small board keeps little; longer runs count as bad frames */
#ifndef TC_RX_MAX
#if defined(__AVR__)
#define TC_RX_MAX 64
#else
#define TC_RX_MAX TC_MAX_FRAME
#endif
#endif
/* the longest Info JSON text a device sends (keep it below 1000, section 3) */
#ifndef TC_INFO_MAX
#define TC_INFO_MAX 512
#endif

/* message types (section 5) */
enum {
    TC_SAMPLE = 0x01,
    TC_ENCODER = 0x02,
    TC_INFO = 0x03,
    TC_COMMAND = 0x10,
    TC_SET_VOLTAGE = 0x21
};
/* command codes (section 6) */
enum { TC_IDENTIFY = 1, TC_START = 2, TC_STOP = 3 };
/* Encoder flags (section 7) */
#define TC_FLAG_WATCHDOG 0x01u
#define TC_FLAG_LIMIT 0x02u
/* the voltage in use is not the host's answer to the frame before (a late answer) */
#define TC_FLAG_STALE 0x04u
/* the display zeroes the voltage after this many periods without a valid SetVoltage */
#define TC_WATCHDOG_PERIODS 5u

/* frame sizes on the wire, delimiter included */
#define TC_SAMPLE_FRAME 17u
#define TC_ENCODER_FRAME 22u
#define TC_COMMAND_FRAME 6u
#define TC_SET_VOLTAGE_FRAME 13u

/* ---------------------------------------------------------------- framing */

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final XOR. */
uint16_t tc_crc16(const uint8_t *p, size_t n);
/* COBS-encode n bytes; out needs n + n / 254 + 1 bytes. Returns the encoded length. */
size_t tc_cobs_encode(const uint8_t *in, size_t n, uint8_t *out);
/* COBS-decode one frame (delimiter removed); out needs n bytes. -1 if not valid COBS. */
long tc_cobs_decode(const uint8_t *in, size_t n, uint8_t *out);
/* One whole frame of a payload: COBS(payload || CRC big-endian) || 0x00. out needs
   n + 2 + (n + 2) / 254 + 2 bytes; n at most TC_MAX_FRAME - 8. Returns its length. */
size_t tc_frame(const uint8_t *payload, size_t n, uint8_t *out);

/* ---------------------------------------------------------------- messages out */

size_t tc_sample_frame(uint32_t seq, uint32_t clock, int16_t force, int16_t position,
                       uint8_t out[TC_SAMPLE_FRAME]);
size_t tc_encoder_frame(uint32_t seq, uint32_t clock, int32_t position, float volts,
                        uint8_t flags, uint8_t out[TC_ENCODER_FRAME]);
size_t tc_set_voltage_frame(uint32_t seq, float volts, uint8_t out[TC_SET_VOLTAGE_FRAME]);
size_t tc_command_frame(uint8_t code, uint8_t out[TC_COMMAND_FRAME]);
/* An Info frame of a JSON object (text without terminator); 0 if it does not fit cap. */
size_t tc_info_frame(const char *json, uint8_t *out, size_t cap);

/* ---------------------------------------------------------------- messages in */

typedef struct {
    uint8_t type;       /* TC_SAMPLE, ... */
    uint32_t seq;       /* Sample, Encoder, SetVoltage */
    uint32_t clock;     /* Sample, Encoder */
    int16_t force;      /* Sample */
    int16_t position;   /* Sample */
    int32_t counts;     /* Encoder position */
    float volts;        /* Encoder, SetVoltage */
    uint8_t flags;      /* Encoder */
    uint8_t code;       /* Command */
    const uint8_t *info; /* Info: the JSON text, inside the decoder's buffer */
    size_t info_len;
} tc_message;

/* Decode one frame (delimiter removed) into m; scratch needs n bytes (it may be the
   frame itself: decoding never overtakes its input) and holds an Info's text
   afterwards. 0 if good, -1 for bad COBS, CRC, type or length (section 10). */
int tc_decode_frame(const uint8_t *frame, size_t n, uint8_t *scratch, tc_message *m);

/* A byte stream to messages: corrupt frames dropped and counted, resynchronised at the
   next 0x00, however the stream is cut (section 10). */
typedef struct {
    uint8_t buf[TC_RX_MAX]; /* a frame's bytes, decoded in place */
    size_t len;
    uint8_t skipping; /* inside an overlong run: drop bytes until the next delimiter */
    uint32_t good, bad;
} tc_decoder;

void tc_decoder_init(tc_decoder *d);
/* Feed one byte; 1 when it completed a good message (in *m), else 0. */
int tc_decoder_feed(tc_decoder *d, uint8_t byte, tc_message *m);

/* ---------------------------------------------------------------- sequence numbers */

/* Losses from gaps in a 32-bit sequence number (section 8). */
typedef struct {
    uint32_t last;
    uint8_t has_last;
    uint32_t lost, restarts;
} tc_seq_tracker;

void tc_seq_init(tc_seq_tracker *t);
/* Record seq; the number of messages lost just before it. */
uint32_t tc_seq_update(tc_seq_tracker *t, uint32_t seq);

/* ---------------------------------------------------------------- display watchdog */

/* The display's rule (section 7): the latest valid SetVoltage, clamped to [0, v_max]
   (NaN to 0), is applied; after TC_WATCHDOG_PERIODS periods without one the voltage is
   cut to 0 and FLAG_WATCHDOG raised until the next. Armed by the first SetVoltage after
   START, so a host's start-up is not a trip. */
typedef struct {
    float v_max;
    float volts;          /* what the amplifier is told now, V */
    uint8_t streaming, armed, tripped;
    uint32_t silent;      /* periods since the last valid SetVoltage */
    uint32_t trips;       /* cuts so far */
} tc_watchdog;

float tc_clamp_volts(float volts, float v_max);
void tc_watchdog_init(tc_watchdog *w, float v_max);
void tc_watchdog_start(tc_watchdog *w);
void tc_watchdog_stop(tc_watchdog *w);
void tc_watchdog_command(tc_watchdog *w, float volts);
/* Once per control period, before the Encoder frame: 1 if it cut the voltage now. */
int tc_watchdog_tick(tc_watchdog *w);
uint8_t tc_watchdog_flags(const tc_watchdog *w);

/* ---------------------------------------------------------------- text lines */

/* Decimal text without printf (AVR's has no %f): return the characters written. */
size_t tc_format_uint(char *out, uint32_t value);
size_t tc_format_int(char *out, int32_t value);
/* value with `decimals` digits after the point (0..6), rounded; |value| < 2^31 / 10^d */
size_t tc_format_fixed(char *out, float value, uint8_t decimals);

#ifdef __cplusplus
}
#endif

#endif /* TC_PROTOCOL_H */
