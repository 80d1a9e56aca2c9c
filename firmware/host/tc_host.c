/*
 * The firmware core on a PC: the same logic as the boards, behind standard input and
 * output (a pseudo-terminal's master side), paced by the monotonic clock. The test
 * suite builds it with the system C compiler and drives it from the Python host.
 *
 *   tc_host echo                    decode every frame received and send it re-encoded
 *   tc_host forceps RATE            the forceps: Info, START/STOP, Sample frames
 *   tc_host text RATE BROKEN_EVERY  a text logger: t_us,force_N,closure_mm lines, one in
 *                                   BROKEN_EVERY cut short (0: none)
 *   tc_host display RATE V_MAX      the display: Encoder frames, SetVoltage, the watchdog
 *
 * It runs until SIGTERM or SIGINT, then prints its counters on stderr.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "../core/tc_device.h"
#include "../core/tc_protocol.h"

static volatile sig_atomic_t stop_flag = 0;
static void on_signal(int sig)
{
    (void)sig;
    stop_flag = 1;
}

static unsigned long dropped = 0;

/* Write without blocking: bytes nobody takes are dropped, as a UART drops them. */
static void write_out(void *ctx, const uint8_t *data, size_t n)
{
    (void)ctx;
    while (n) {
        ssize_t w = write(STDOUT_FILENO, data, n);
        if (w < 0) {
            if (errno == EINTR)
                continue;
            dropped += n;
            return;
        }
        data += w;
        n -= (size_t)w;
    }
}

static size_t read_in(uint8_t *buf, size_t cap)
{
    ssize_t r = read(STDIN_FILENO, buf, cap);
    return r > 0 ? (size_t)r : 0;
}

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void sleep_until(double t)
{
#if defined(__APPLE__)
    /* no clock_nanosleep: a relative sleep to the deadline */
    double d = t - now_s();
    if (d > 0) {
        struct timespec ts;
        ts.tv_sec = (time_t)d;
        ts.tv_nsec = (long)((d - (double)ts.tv_sec) * 1e9);
        nanosleep(&ts, NULL);
    }
#else
    struct timespec ts;
    ts.tv_sec = (time_t)t;
    ts.tv_nsec = (long)((t - (double)ts.tv_sec) * 1e9);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR && !stop_flag) {
    }
#endif
}

/* The simulated forceps' ADC: a squeeze every 2 s, 12-bit signed counts. */
static void adc(uint32_t k, double rate, int16_t *force, int16_t *position)
{
    double t = k / rate;
    double closure = 0.5 - 0.5 * cos(3.14159265358979323846 * t); /* 0..1, every 2 s */
    *position = (int16_t)lround(-1800.0 + 3600.0 * closure);
    *force = (int16_t)lround(-2000.0 + 3000.0 * closure * closure);
}

/* calibration of the simulated forceps: 12 bits spanning -1..5 N and -0.5..15 mm */
static const tc_calibration CAL = {6.0f / 4095.0f, 2.0f - 6.0f / 4095.0f * 0.5f,
                                   15.5e-3f / 4095.0f, 7.25e-3f - 15.5e-3f / 4095.0f * 0.5f};

static char info_json[512];

static void make_info(const char *device, double rate)
{
    if (device[0] == 'f')
        snprintf(info_json, sizeof info_json,
                 "{\"protocol\":%d,\"device\":\"forceps\",\"model\":\"tissuecli reference "
                 "firmware (host build)\",\"firmware\":\"1.0\",\"rate_hz\":%.17g,"
                 "\"clock_hz\":1000000,\"adc_bits\":12,\"calibration\":{\"force\":"
                 "{\"gain\":%.9g,\"offset\":%.9g,\"unit\":\"N\"},\"position\":{\"gain\":%.9g,"
                 "\"offset\":%.9g,\"unit\":\"m\"}}}",
                 TC_PROTOCOL_VERSION, rate, CAL.force_gain, CAL.force_offset, CAL.position_gain,
                 CAL.position_offset);
    else
        snprintf(info_json, sizeof info_json,
                 "{\"protocol\":%d,\"device\":\"display\",\"model\":\"tissuecli reference "
                 "firmware (host build)\",\"firmware\":\"1.0\",\"rate_hz\":%.17g,"
                 "\"clock_hz\":1000000,\"stale_flag\":true}",
                 TC_PROTOCOL_VERSION, rate);
}

static int run_echo(void)
{
    tc_decoder d;
    tc_decoder_init(&d);
    uint8_t buf[256], frame[TC_MAX_FRAME];
    char json[TC_MAX_FRAME];
    tc_message m;
    unsigned long echoed = 0;
    while (!stop_flag) {
        size_t n = read_in(buf, sizeof buf);
        if (!n) {
            sleep_until(now_s() + 2e-4);
            continue;
        }
        for (size_t i = 0; i < n; i++) {
            if (!tc_decoder_feed(&d, buf[i], &m))
                continue;
            size_t len = 0;
            switch (m.type) {
            case TC_SAMPLE:
                len = tc_sample_frame(m.seq, m.clock, m.force, m.position, frame);
                break;
            case TC_ENCODER:
                len = tc_encoder_frame(m.seq, m.clock, m.counts, m.volts, m.flags, frame);
                break;
            case TC_SET_VOLTAGE:
                len = tc_set_voltage_frame(m.seq, m.volts, frame);
                break;
            case TC_COMMAND:
                len = tc_command_frame(m.code, frame);
                break;
            case TC_INFO:
                memcpy(json, m.info, m.info_len);
                json[m.info_len] = 0;
                len = tc_info_frame(json, frame, sizeof frame);
                break;
            }
            write_out(NULL, frame, len);
            echoed++;
        }
    }
    fprintf(stderr, "echo: %lu frames echoed, %lu bad\n", echoed, (unsigned long)d.bad);
    return 0;
}

static int run_forceps(double rate, int text, unsigned long broken_every)
{
    make_info("forceps", rate);
    tc_forceps f;
    tc_forceps_init(&f, info_json, CAL, write_out, NULL);
    if (text)
        f.streaming = 1; /* a text logger prints from the start, whoever listens */
    uint8_t buf[256];
    double t0 = now_s(), next_header = t0;
    uint32_t k = 0;
    unsigned long broken = 0;
    while (!stop_flag) {
        size_t n = read_in(buf, sizeof buf);
        if (!text && n)
            tc_forceps_receive(&f, buf, n);
        double now = now_s();
        /* the samples due by now, each at its own instant on the microsecond clock */
        while (!stop_flag && k <= (uint32_t)((now - t0) * rate)) {
            uint32_t clock = (uint32_t)llround((double)k / rate * 1e6);
            int16_t force, position;
            adc(k, rate, &force, &position);
            if (text) {
                char line[64];
                size_t len = 0;
                if (now >= next_header) {
                    write_out(NULL, (const uint8_t *)TC_TEXT_HEADER, strlen(TC_TEXT_HEADER));
                    next_header = now + 1.0;
                }
                len = tc_text_line(&CAL, clock, force, position, line);
                if (broken_every && k % broken_every == broken_every - 1) {
                    /* cut before its last field, as a line lost halfway */
                    while (len && line[len - 1] != ',')
                        len--;
                    line[len - 1] = '\n';
                    broken++;
                }
                write_out(NULL, (const uint8_t *)line, len);
            } else {
                tc_forceps_sample(&f, clock, force, position);
            }
            k++;
        }
        sleep_until(t0 + (double)k / rate);
    }
    fprintf(stderr, "%s: %lu samples, %lu sent, %lu broken, %lu bytes dropped\n",
            text ? "text" : "forceps", (unsigned long)k,
            text ? (unsigned long)k : (unsigned long)f.sent, broken, dropped);
    return 0;
}

static int run_display(double rate, float v_max)
{
    make_info("display", rate);
    tc_display d;
    tc_display_init(&d, info_json, v_max, write_out, NULL);
    uint8_t buf[256];
    double t0 = now_s();
    uint32_t k = 0;
    uint32_t trips = 0;
    while (!stop_flag) {
        size_t n;
        while ((n = read_in(buf, sizeof buf)) > 0)
            tc_display_receive(&d, buf, n);
        uint32_t clock = (uint32_t)llround((double)k / rate * 1e6);
        tc_display_tick(&d, clock, 0, 0);
        if (d.watchdog.trips != trips) {
            trips = d.watchdog.trips;
            fprintf(stderr, "watchdog: no SetVoltage for %u periods; solenoid off\n",
                    TC_WATCHDOG_PERIODS);
        }
        k++;
        double due = t0 + (double)k / rate;
        if (now_s() > due + 0.5) /* descheduled for long: skip, as a real loop never runs late */
            t0 = now_s() - (double)k / rate;
        sleep_until(due);
    }
    fprintf(stderr, "display: %lu periods, %lu watchdog trips, %lu bad frames\n",
            (unsigned long)k, (unsigned long)d.watchdog.trips, (unsigned long)d.decoder.bad);
    return 0;
}

int main(int argc, char **argv)
{
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    fcntl(STDIN_FILENO, F_SETFL, fcntl(STDIN_FILENO, F_GETFL) | O_NONBLOCK);
    fcntl(STDOUT_FILENO, F_SETFL, fcntl(STDOUT_FILENO, F_GETFL) | O_NONBLOCK);
    if (argc >= 2 && !strcmp(argv[1], "echo"))
        return run_echo();
    if (argc >= 3 && !strcmp(argv[1], "forceps"))
        return run_forceps(atof(argv[2]), 0, 0);
    if (argc >= 4 && !strcmp(argv[1], "text"))
        return run_forceps(atof(argv[2]), 1, strtoul(argv[3], NULL, 10));
    if (argc >= 4 && !strcmp(argv[1], "display"))
        return run_display(atof(argv[2]), (float)atof(argv[3]));
    fprintf(stderr, "usage: tc_host echo | forceps RATE | text RATE BROKEN_EVERY | "
                    "display RATE V_MAX\n");
    return 2;
}
