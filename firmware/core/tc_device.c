/* Board-free firmware logic: see tc_device.h. */
#include "tc_device.h"

void tc_forceps_init(tc_forceps *f, const char *info_json, tc_calibration cal,
                     tc_write_fn write, void *ctx)
{
    tc_decoder_init(&f->decoder);
    f->info_json = info_json;
    f->cal = cal;
    f->write = write;
    f->ctx = ctx;
    f->streaming = 0;
    f->seq = 0;
    f->sent = 0;
}

static void send_info(const char *json, tc_write_fn write, void *ctx)
{
    uint8_t frame[TC_INFO_MAX + TC_INFO_MAX / 254 + 6];
    size_t n = tc_info_frame(json, frame, sizeof frame);
    if (n)
        write(ctx, frame, n);
}

void tc_forceps_receive(tc_forceps *f, const uint8_t *data, size_t n)
{
    tc_message m;
    for (size_t i = 0; i < n; i++) {
        if (!tc_decoder_feed(&f->decoder, data[i], &m) || m.type != TC_COMMAND)
            continue;
        if (m.code == TC_IDENTIFY)
            send_info(f->info_json, f->write, f->ctx);
        else if (m.code == TC_START)
            f->streaming = 1;
        else if (m.code == TC_STOP)
            f->streaming = 0;
    }
}

void tc_forceps_sample(tc_forceps *f, uint32_t clock_us, int16_t force, int16_t position)
{
    if (f->streaming) {
        uint8_t frame[TC_SAMPLE_FRAME];
        f->write(f->ctx, frame, tc_sample_frame(f->seq, clock_us, force, position, frame));
        f->sent++;
    }
    f->seq++;
}

size_t tc_text_line(const tc_calibration *cal, uint32_t clock_us, int16_t force,
                    int16_t position, char *out)
{
    size_t n = tc_format_uint(out, clock_us);
    out[n++] = ',';
    n += tc_format_fixed(out + n, cal->force_gain * force + cal->force_offset, 5);
    out[n++] = ',';
    n += tc_format_fixed(out + n, (cal->position_gain * position + cal->position_offset) * 1e3f, 4);
    out[n++] = '\n';
    return n;
}

void tc_display_init(tc_display *d, const char *info_json, float v_max, tc_write_fn write,
                     void *ctx)
{
    tc_decoder_init(&d->decoder);
    tc_watchdog_init(&d->watchdog, v_max);
    d->info_json = info_json;
    d->write = write;
    d->ctx = ctx;
    d->seq = 0;
    d->answers = d->streamed = 0;
}

void tc_display_receive(tc_display *d, const uint8_t *data, size_t n)
{
    tc_message m;
    for (size_t i = 0; i < n; i++) {
        if (!tc_decoder_feed(&d->decoder, data[i], &m))
            continue;
        if (m.type == TC_SET_VOLTAGE) {
            tc_watchdog_command(&d->watchdog, m.volts);
            d->answers = m.seq; /* the Encoder frame it answers */
        } else if (m.type == TC_COMMAND) {
            if (m.code == TC_IDENTIFY)
                send_info(d->info_json, d->write, d->ctx);
            else if (m.code == TC_START) {
                if (!d->watchdog.streaming)
                    d->streamed = 0;
                tc_watchdog_start(&d->watchdog);
            } else if (m.code == TC_STOP)
                tc_watchdog_stop(&d->watchdog);
        }
    }
}

float tc_display_tick(tc_display *d, uint32_t clock_us, int32_t counts, uint8_t at_limit)
{
    tc_watchdog_tick(&d->watchdog);
    if (d->watchdog.streaming) {
        uint8_t frame[TC_ENCODER_FRAME];
        uint8_t flags = (uint8_t)(tc_watchdog_flags(&d->watchdog) | (at_limit ? TC_FLAG_LIMIT : 0));
        /* once commanded, a period not run on the answer to the frame before is stale */
        if (d->watchdog.armed && d->streamed
            && (d->watchdog.tripped || d->answers != (uint32_t)(d->seq - 1u)))
            flags |= TC_FLAG_STALE;
        d->write(d->ctx, frame,
                 tc_encoder_frame(d->seq++, clock_us, counts, d->watchdog.volts, flags, frame));
        d->streamed++;
    }
    return d->watchdog.volts;
}
