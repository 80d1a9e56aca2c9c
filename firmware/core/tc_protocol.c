/* The portable protocol core: see tc_protocol.h. */
#include "tc_protocol.h"

#include <string.h>

uint16_t tc_crc16(const uint8_t *p, size_t n)
{
    uint16_t crc = 0xFFFF;
    while (n--) {
        crc ^= (uint16_t)((uint16_t)(*p++) << 8);
        for (int i = 0; i < 8; i++)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    return crc;
}

size_t tc_cobs_encode(const uint8_t *in, size_t n, uint8_t *out)
{
    size_t code_at = 0, o = 1;
    uint8_t code = 1;
    for (size_t i = 0; i < n; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = in[i];
            if (++code == 0xFF) {
                out[code_at] = code;
                code_at = o++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    return o;
}

long tc_cobs_decode(const uint8_t *in, size_t n, uint8_t *out)
{
    size_t i = 0, o = 0;
    while (i < n) {
        uint8_t code = in[i++];
        if (code == 0 || i + code - 1 > n)
            return -1;
        for (uint8_t k = 1; k < code; k++) {
            if (in[i] == 0)
                return -1;
            out[o++] = in[i++];
        }
        if (code != 0xFF && i < n)
            out[o++] = 0;
    }
    return (long)o;
}

/* COBS encoding one byte at a time, so a frame is built without a copy of its body */
typedef struct {
    uint8_t *out;
    size_t code_at, o;
    uint8_t code;
} cobs_state;

static void cobs_begin(cobs_state *c, uint8_t *out)
{
    c->out = out;
    c->code_at = 0;
    c->o = 1;
    c->code = 1;
}

static void cobs_put(cobs_state *c, uint8_t byte)
{
    if (byte == 0) {
        c->out[c->code_at] = c->code;
        c->code_at = c->o++;
        c->code = 1;
        return;
    }
    c->out[c->o++] = byte;
    if (++c->code == 0xFF) {
        c->out[c->code_at] = c->code;
        c->code_at = c->o++;
        c->code = 1;
    }
}

static size_t cobs_end(cobs_state *c)
{
    c->out[c->code_at] = c->code;
    c->out[c->o++] = 0x00; /* the delimiter */
    return c->o;
}

/* payload = type byte, then body: framed with its CRC (big-endian) */
static size_t frame_of(uint8_t type, const uint8_t *body, size_t n, uint8_t *out)
{
    cobs_state c;
    uint16_t crc = tc_crc16(&type, 1);
    /* continue the CRC over the body: CRC-16/CCITT-FALSE is a running register */
    for (size_t i = 0; i < n; i++) {
        crc ^= (uint16_t)((uint16_t)body[i] << 8);
        for (int b = 0; b < 8; b++)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    cobs_begin(&c, out);
    cobs_put(&c, type);
    for (size_t i = 0; i < n; i++)
        cobs_put(&c, body[i]);
    cobs_put(&c, (uint8_t)(crc >> 8));
    cobs_put(&c, (uint8_t)crc);
    return cobs_end(&c);
}

size_t tc_frame(const uint8_t *payload, size_t n, uint8_t *out)
{
    if (n == 0)
        return 0;
    return frame_of(payload[0], payload + 1, n - 1, out);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static void put_f32(uint8_t *p, float f)
{
    uint32_t v;
    memcpy(&v, &f, 4); /* IEEE 754 binary32 on every target this supports */
    put_u32(p, v);
}

static float get_f32(const uint8_t *p)
{
    uint32_t v = get_u32(p);
    float f;
    memcpy(&f, &v, 4);
    return f;
}

size_t tc_sample_frame(uint32_t seq, uint32_t clock, int16_t force, int16_t position,
                       uint8_t out[TC_SAMPLE_FRAME])
{
    uint8_t p[13];
    p[0] = TC_SAMPLE;
    put_u32(p + 1, seq);
    put_u32(p + 5, clock);
    p[9] = (uint8_t)(uint16_t)force;
    p[10] = (uint8_t)((uint16_t)force >> 8);
    p[11] = (uint8_t)(uint16_t)position;
    p[12] = (uint8_t)((uint16_t)position >> 8);
    return tc_frame(p, sizeof p, out);
}

size_t tc_encoder_frame(uint32_t seq, uint32_t clock, int32_t position, float volts,
                        uint8_t flags, uint8_t out[TC_ENCODER_FRAME])
{
    uint8_t p[18];
    p[0] = TC_ENCODER;
    put_u32(p + 1, seq);
    put_u32(p + 5, clock);
    put_u32(p + 9, (uint32_t)position);
    put_f32(p + 13, volts);
    p[17] = flags;
    return tc_frame(p, sizeof p, out);
}

size_t tc_set_voltage_frame(uint32_t seq, float volts, uint8_t out[TC_SET_VOLTAGE_FRAME])
{
    uint8_t p[9];
    p[0] = TC_SET_VOLTAGE;
    put_u32(p + 1, seq);
    put_f32(p + 5, volts);
    return tc_frame(p, sizeof p, out);
}

size_t tc_command_frame(uint8_t code, uint8_t out[TC_COMMAND_FRAME])
{
    return frame_of(TC_COMMAND, &code, 1, out);
}

size_t tc_info_frame(const char *json, uint8_t *out, size_t cap)
{
    size_t n = strlen(json);
    /* type + text + CRC, one COBS code per 254 bytes, the delimiter */
    size_t need = n + 3 + (n + 3) / 254 + 2;
    if (need > cap || need > TC_MAX_FRAME)
        return 0;
    return frame_of(TC_INFO, (const uint8_t *)json, n, out);
}

int tc_decode_frame(const uint8_t *frame, size_t n, uint8_t *scratch, tc_message *m)
{
    long len = tc_cobs_decode(frame, n, scratch);
    if (len < 3)
        return -1;
    size_t pn = (size_t)len - 2;
    uint16_t crc = (uint16_t)(((uint16_t)scratch[pn] << 8) | scratch[pn + 1]);
    if (tc_crc16(scratch, pn) != crc)
        return -1;
    const uint8_t *b = scratch + 1;
    size_t bn = pn - 1;
    memset(m, 0, sizeof *m);
    m->type = scratch[0];
    switch (m->type) {
    case TC_SAMPLE:
        if (bn != 12)
            return -1;
        m->seq = get_u32(b);
        m->clock = get_u32(b + 4);
        m->force = (int16_t)(uint16_t)(b[8] | (b[9] << 8));
        m->position = (int16_t)(uint16_t)(b[10] | (b[11] << 8));
        return 0;
    case TC_ENCODER:
        if (bn != 17)
            return -1;
        m->seq = get_u32(b);
        m->clock = get_u32(b + 4);
        m->counts = (int32_t)get_u32(b + 8);
        m->volts = get_f32(b + 12);
        m->flags = b[16];
        return 0;
    case TC_SET_VOLTAGE:
        if (bn != 8)
            return -1;
        m->seq = get_u32(b);
        m->volts = get_f32(b + 4);
        return 0;
    case TC_COMMAND:
        if (bn != 1)
            return -1;
        m->code = b[0];
        return 0;
    case TC_INFO:
        /* a JSON object: the host checks it; here only its braces */
        if (bn < 2 || b[0] != '{' || b[bn - 1] != '}')
            return -1;
        m->info = b;
        m->info_len = bn;
        return 0;
    default:
        return -1;
    }
}

void tc_decoder_init(tc_decoder *d)
{
    d->len = 0;
    d->skipping = 0;
    d->good = d->bad = 0;
}

int tc_decoder_feed(tc_decoder *d, uint8_t byte, tc_message *m)
{
    if (byte != 0x00) {
        if (d->skipping)
            return 0;
        if (d->len >= TC_RX_MAX) {
            /* overlong: counted once, dropped until the next delimiter */
            d->bad++;
            d->len = 0;
            d->skipping = 1;
            return 0;
        }
        d->buf[d->len++] = byte;
        return 0;
    }
    if (d->skipping) {
        d->skipping = 0;
        return 0;
    }
    size_t n = d->len;
    d->len = 0;
    if (n == 0)
        return 0; /* back-to-back delimiters: an idle line */
    if (tc_decode_frame(d->buf, n, d->buf, m) != 0) {
        d->bad++;
        return 0;
    }
    d->good++;
    return 1;
}

void tc_seq_init(tc_seq_tracker *t)
{
    t->has_last = 0;
    t->last = 0;
    t->lost = t->restarts = 0;
}

uint32_t tc_seq_update(tc_seq_tracker *t, uint32_t seq)
{
    uint32_t lost = 0;
    if (t->has_last) {
        uint32_t gap = seq - t->last; /* modulo 2^32 */
        if (gap == 0 || gap > (1ul << 24))
            t->restarts++;
        else
            lost = gap - 1;
    }
    t->last = seq;
    t->has_last = 1;
    t->lost += lost;
    return lost;
}

float tc_clamp_volts(float volts, float v_max)
{
    if (volts != volts) /* NaN */
        return 0.0f;
    if (volts < 0.0f)
        return 0.0f;
    if (volts > v_max)
        return v_max;
    return volts;
}

void tc_watchdog_init(tc_watchdog *w, float v_max)
{
    w->v_max = v_max;
    w->volts = 0.0f;
    w->streaming = w->armed = w->tripped = 0;
    w->silent = 0;
    w->trips = 0;
}

void tc_watchdog_start(tc_watchdog *w)
{
    if (w->streaming)
        return; /* START while streaming is harmless */
    w->streaming = 1;
    w->armed = w->tripped = 0;
}

void tc_watchdog_stop(tc_watchdog *w)
{
    w->streaming = w->armed = 0;
    w->volts = 0.0f;
}

void tc_watchdog_command(tc_watchdog *w, float volts)
{
    if (!w->streaming)
        return;
    w->volts = tc_clamp_volts(volts, w->v_max);
    w->silent = 0;
    w->armed = 1;
    w->tripped = 0;
}

int tc_watchdog_tick(tc_watchdog *w)
{
    if (!w->streaming || !w->armed || w->tripped)
        return 0;
    if (++w->silent > TC_WATCHDOG_PERIODS) {
        w->volts = 0.0f;
        w->tripped = 1;
        w->trips++;
        return 1;
    }
    return 0;
}

uint8_t tc_watchdog_flags(const tc_watchdog *w)
{
    return w->tripped ? TC_FLAG_WATCHDOG : 0;
}

size_t tc_format_uint(char *out, uint32_t value)
{
    char tmp[10];
    size_t n = 0;
    do {
        tmp[n++] = (char)('0' + value % 10u);
        value /= 10u;
    } while (value);
    for (size_t i = 0; i < n; i++)
        out[i] = tmp[n - 1 - i];
    return n;
}

size_t tc_format_int(char *out, int32_t value)
{
    if (value < 0) {
        out[0] = '-';
        return 1 + tc_format_uint(out + 1, (uint32_t)(-(value + 1)) + 1u);
    }
    return tc_format_uint(out, (uint32_t)value);
}

size_t tc_format_fixed(char *out, float value, uint8_t decimals)
{
    static const uint32_t scale[] = {1, 10, 100, 1000, 10000, 100000, 1000000};
    if (decimals > 6)
        decimals = 6;
    size_t n = 0;
    if (value < 0.0f) {
        out[n++] = '-';
        value = -value;
    }
    uint32_t whole = (uint32_t)(value * (float)scale[decimals] + 0.5f);
    n += tc_format_uint(out + n, whole / scale[decimals]);
    if (decimals) {
        uint32_t frac = whole % scale[decimals];
        out[n++] = '.';
        for (int8_t d = (int8_t)decimals - 1; d >= 0; d--) {
            out[n + (size_t)d] = (char)('0' + frac % 10u);
            frac /= 10u;
        }
        n += decimals;
    }
    return n;
}
