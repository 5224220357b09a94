/*
 * labbench AVR harness: runs a sketch for the ATmega328P on simavr (libsimavr.so.2)
 * inside a simulated plant, with the board's UART0 on a pty for the host.
 *
 *   plant -> board: the handle position, quantised to encoder counts, drives the
 *     quadrature pins A = PD2 (Arduino 2) and B = PD3 (Arduino 3); each count
 *     boundary crossed is one edge, at the time the position crosses it.
 *   board -> plant: force = (DIR ? -1 : +1) * duty * full_scale, with DIR = PB0
 *     (Arduino 8) and duty the PWM duty of OC1A = PB1 (Arduino 9), read from the
 *     Timer1 registers (or the pin level when the PWM is not connected): an
 *     amplifier that takes the duty as its set point. The force changes at the
 *     instruction that changes it.
 *   plant: mass-damper m x'' = F - b x' - Fc sign(x') (--coulomb-n Fc, default 0:
 *     sticking while |F| <= Fc), integrated exactly between force changes and
 *     velocity reversals (zero-order hold, the model of labbench.model.linear and of
 *     sim_backend/friction.py); or, with --drive-cps, a prescribed motion (encoder
 *     tests): a constant count rate between --drive-start-ms and --drive-stop-ms, plus
 *     --drive-sine-counts A sin(2 pi --drive-sine-hz f t) counts over the same
 *     window (t from its start). --amp-delay-us D: the amplifier applies each force
 *     D later than the board set it (a slow current loop the rig file may not state).
 *   host <-> board: UART0 bytes to and from a pty. Host bytes are handed to the
 *     UART at the real line rate (10 bits per byte at the set baud): simavr itself
 *     would take a burst faster than any wire delivers it.
 *
 * Pacing. Lock-step (default): when the board has sent a sample frame (a COBS
 * frame of --lockstep-frame-len bytes + its 0x00), emulated time stops until the
 * host's answer (bytes up to a 0x00) has come in, or --lockstep-timeout-ms of wall
 * time passed; the answer reaches the UART --host-latency-us after the frame's
 * last byte left. Runs are deterministic and independent of the machine's speed.
 * --realtime instead keeps emulated time no faster than wall time and never waits.
 *
 * Start: the first line on stdout is "pty <path>"; the board comes out of reset when
 * one byte arrives on stdin (the host has opened the port by then).
 * Output: at exit one line of JSON
 * statistics. --trace FILE writes one line per event (all times in CPU cycles):
 *   tx <first> <last> <nbytes>           a 0x00-terminated run of bytes sent by the board
 *   line <first> <last> <nbytes>         a '\n'-terminated run of bytes sent by the board
 *   rx <first> <last> <nbytes>           a host frame handed to the UART
 *   vec <pending> <running> <return> <c_pending> <c_running>   the --trace-vector ISR:
 *                                         when it was raised, entered and left, and the
 *                                         plant's count when raised and entered
 *   force <cycle> <newton>               the force applied from then on
 * Ends on EOF of stdin, SIGTERM, --max-ms of emulated time, or a crashed CPU.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_ioport.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_interrupts.h"
#include "sim_irq.h"

/* ATmega328P data-space addresses (datasheet, register summary). */
enum { R_PIND = 0x29, R_DDRB = 0x24, R_PORTB = 0x25, R_TCCR1A = 0x80, R_TCCR1B = 0x81,
       R_ICR1L = 0x86, R_ICR1H = 0x87, R_OCR1AL = 0x88, R_OCR1AH = 0x89 };

static struct {
    const char *hex;
    double mass, damping, metres_per_count, full_scale_n, x0, v0, coulomb, amp_delay_us;
    double drive_cps, drive_start_ms, drive_stop_ms, sine_counts, sine_hz;
    long baud;
    double host_latency_us, lockstep_timeout_ms, max_ms;
    int lockstep_frame_len, realtime, trace_vector;
    const char *trace;
} opt = {
    .mass = 0.5, .damping = 2.0, .metres_per_count = 2 * M_PI * 0.1 / 16384,
    .full_scale_n = 255.0 / 40.0, .baud = 500000, .host_latency_us = 30,
    .lockstep_timeout_ms = 1000, .lockstep_frame_len = 15, .trace_vector = -1,
    .drive_cps = NAN,
};

static avr_t *avr;
static FILE *trace;
static int pty_master = -1;
static volatile sig_atomic_t stop_requested;
static uint64_t cycles_per_byte;  /* real line rate: 10 bits per byte */

/* ---- plant ------------------------------------------------------------------- */
static struct {
    double x, v;        /* state at cycle t */
    uint64_t t;
    double force;       /* applied since t */
    int64_t count;      /* count the encoder pins show now */
    uint32_t sig;       /* register signature of the last force computed */
    uint64_t edges;
} plant;

/* Edges still to emit in the current step: absolute cycles, ascending. */
#define MAX_EDGES 4096
static uint64_t edge_at[MAX_EDGES];
static int edge_dir[MAX_EDGES];
static int n_edges, next_edge;
static uint64_t step_end;
static avr_irq_t *pin_a, *pin_b;
static unsigned long long pins_restored;

static int64_t count_of(double x) { return (int64_t)floor(x / opt.metres_per_count + 0.5); }

/* Exact mass-damper response over dt seconds under constant force f (no friction). */
static void integrate(double dt, double f, double *x, double *v) {
    double m = opt.mass, b = opt.damping;
    if (dt <= 0) return;
    if (b == 0) {
        *x += *v * dt + f * dt * dt / (2 * m);
        *v += f * dt / m;
        return;
    }
    double a = b / m, e1 = -expm1(-a * dt);       /* 1 - e^{-a dt} */
    double xs = (a * dt - e1) / (a * a * m);      /* x response to a unit force */
    *x += *v * e1 / a + f * xs;
    *v = *v * (1 - e1) + f * e1 / b;
}

/* Exact response with Coulomb friction: between velocity reversals the friction is a
 * constant force, so each piece is integrate(); at a reversal the handle sticks while
 * |f| <= Fc (as sim_backend/friction.py, so the two simulators share one model). */
static void evolve(double dt, double f, double *x, double *v) {
    double fc = opt.coulomb, m = opt.mass, b = opt.damping;
    while (dt > 0) {
        double s = *v > 0 ? 1.0 : *v < 0 ? -1.0 : 0.0;
        if (s == 0) {
            if (fabs(f) <= fc) return;  /* sticks */
            s = f > 0 ? 1.0 : -1.0;
        }
        double f1 = f - fc * s;
        if (*v == 0 || f1 * s >= 0) {  /* friction cannot stop it within this piece */
            integrate(dt, f1, x, v);
            return;
        }
        double t_rest = b > 0 ? log1p(-*v * b / f1) * m / b : -*v * m / f1;
        if (t_rest >= dt) {
            integrate(dt, f1, x, v);
            return;
        }
        integrate(t_rest, f1, x, v);
        *v = 0;
        dt -= t_rest;
    }
}

static double drive_position(uint64_t cycle) {
    double t_ms = cycle * 1e3 / avr->frequency;
    double tt = fmin(fmax(t_ms, opt.drive_start_ms), opt.drive_stop_ms) - opt.drive_start_ms;
    double counts = opt.drive_cps * tt * 1e-3 + opt.sine_counts * sin(2 * M_PI * opt.sine_hz * tt * 1e-3);
    return counts * opt.metres_per_count + opt.x0;
}

static void state_at(uint64_t cycle, double *x, double *v) {
    if (!isnan(opt.drive_cps)) {
        *x = drive_position(cycle);
        *v = 0;
        return;
    }
    *x = plant.x;
    *v = plant.v;
    evolve((double)(cycle - plant.t) / avr->frequency, plant.force, x, v);
}

/* Schedule the edges that bring the pins from the count they show to the count of
 * the position at step_end, at the times (linear in the step) the boundaries are crossed. */
static void plan_edges(void) {
    double x0, v0, x1, v1;
    state_at(avr->cycle, &x0, &v0);
    state_at(step_end, &x1, &v1);
    int64_t target = count_of(x1), c = plant.count;
    n_edges = next_edge = 0;
    int dir = target > c ? 1 : -1;
    double span = (double)(step_end - avr->cycle);
    while (c != target && n_edges < MAX_EDGES) {
        double boundary = (c + (dir > 0 ? 0.5 : -0.5)) * opt.metres_per_count;
        double frac = x1 != x0 ? (boundary - x0) / (x1 - x0) : 1.0;
        frac = fmin(fmax(frac, 0.0), 1.0);
        uint64_t at = avr->cycle + (uint64_t)(frac * span);
        if (n_edges && at < edge_at[n_edges - 1]) at = edge_at[n_edges - 1];
        edge_at[n_edges] = at;
        edge_dir[n_edges++] = dir;
        c += dir;
    }
}

/* Quadrature: count mod 4 -> (A, B) = 00, 01, 11, 10 going forward (B leads A). */
static const uint8_t AB[4] = {0, 1, 3, 2};

static void show_count(int64_t count) {
    uint8_t ab = AB[count & 3];
    avr_raise_irq(pin_a, ab >> 1);
    avr_raise_irq(pin_b, ab & 1);
}

/* One edge: only the channel that changes moves (a raise of an unchanged pin
 * would be seen as an edge by the external-interrupt logic). */
static void step_count(int dir) {
    uint8_t was = AB[plant.count & 3];
    plant.count += dir;
    uint8_t now = AB[plant.count & 3];
    if ((was ^ now) & 2) avr_raise_irq(pin_a, now >> 1);
    else avr_raise_irq(pin_b, now & 1);
}

/* The encoder's outputs drive the pins: simavr lets a pull-up switched on later
 * (pinMode INPUT_PULLUP) override a level set before it; set them again at the next
 * instruction, before the firmware can read the pulled-up level (a sketch that reads
 * its encoder's state right after pinMode would count the glitch as steps). */
static void hold_pins(void) {
    uint8_t ab = AB[plant.count & 3], pins = (avr->data[R_PIND] >> 2) & 0x03;
    if (pins != (uint8_t)((ab >> 1) | (ab & 1) << 1)) {
        show_count(plant.count);
        pins_restored++;
    }
}

static void emit_due_edges(void) {
    while (next_edge < n_edges && edge_at[next_edge] <= avr->cycle) {
        step_count(edge_dir[next_edge++]);
        plant.edges++;
    }
}

static uint32_t force_signature(void) {
    const uint8_t *d = avr->data;
    return (uint32_t)(d[R_TCCR1A] & 0xF3) << 24 ^ (uint32_t)(d[R_TCCR1B] & 0x18) << 24 ^
           (uint32_t)d[R_OCR1AH] << 16 ^ (uint32_t)d[R_OCR1AL] << 8 ^
           (uint32_t)(d[R_PORTB] & 0x03) << 4 ^ (uint32_t)(d[R_DDRB] & 0x03);
}

/* Duty of OC1A (PB1) as the pin drives it; 0..1. */
static double duty_oc1a(void) {
    const uint8_t *d = avr->data;
    if (!(d[R_DDRB] & 0x02)) return 0;
    unsigned wgm = (d[R_TCCR1A] & 0x03) | ((d[R_TCCR1B] >> 1) & 0x0C);
    unsigned ocr = d[R_OCR1AL] | d[R_OCR1AH] << 8, icr = d[R_ICR1L] | d[R_ICR1H] << 8;
    unsigned com = d[R_TCCR1A] >> 6;
    static const int top_of[16] = {0, 0xFF, 0x1FF, 0x3FF, 0, 0xFF, 0x1FF, 0x3FF,
                                   -1, 0, -1, 0, 0, 0, -1, 0};
    int top = top_of[wgm] < 0 ? (int)icr : top_of[wgm];
    if (com < 2 || top <= 0) return (d[R_PORTB] & 0x02) ? 1.0 : 0.0;  /* plain output */
    int fast = wgm == 5 || wgm == 6 || wgm == 7 || wgm == 14;
    double duty = ocr >= (unsigned)top ? 1.0
                  : fast ? (ocr + 1.0) / (top + 1.0) : (double)ocr / top;
    return com == 3 ? 1.0 - duty : duty;
}

/* The plant feels force f from now on. */
static void apply_force(double f) {
    if (f == plant.force) return;
    if (isnan(opt.drive_cps)) {
        evolve((double)(avr->cycle - plant.t) / avr->frequency, plant.force, &plant.x, &plant.v);
        plant.t = avr->cycle;
    }
    plant.force = f;
    if (trace) fprintf(trace, "force %llu %.9g\n", (unsigned long long)avr->cycle, f);
    plan_edges();
}

/* Force set points on their way through the amplifier (--amp-delay-us): a ring of
 * (cycle due, force), in order; one per set-point change, so a few per sample. */
#define AMPQ 4096
static struct { uint64_t at; double f; } ampq[AMPQ];
static size_t amp_head, amp_tail;
static uint64_t amp_delay_cycles;
static unsigned long long amp_overflow;

static void apply_due_forces(void) {
    while (amp_head != amp_tail && ampq[amp_head].at <= avr->cycle) {
        apply_force(ampq[amp_head].f);
        amp_head = (amp_head + 1) % AMPQ;
    }
}

static void update_force(void) {
    uint32_t sig = force_signature();
    if (sig == plant.sig) return;
    plant.sig = sig;
    double f = ((avr->data[R_PORTB] & 0x01) ? -1.0 : 1.0) * duty_oc1a() * opt.full_scale_n;
    if (!(avr->data[R_DDRB] & 0x01)) f = fabs(f);  /* DIR not an output: reads as low */
    if (!amp_delay_cycles) {
        apply_force(f);
        return;
    }
    size_t next = (amp_tail + 1) % AMPQ;
    if (next == amp_head) {  /* cannot happen at sane rates; counted, never silent */
        amp_overflow++;
        apply_due_forces();
        apply_force(ampq[amp_head].f);
        amp_head = (amp_head + 1) % AMPQ;
    }
    ampq[amp_tail].at = avr->cycle + amp_delay_cycles;
    ampq[amp_tail].f = f;
    amp_tail = next;
}

/* ---- UART <-> pty -------------------------------------------------------------- */
#define RXQ 65536
static uint8_t rxq[RXQ];
static size_t rx_head, rx_tail;  /* bytes from the host not yet handed to the UART */
static uint64_t rx_next;         /* cycle the next host byte may go in */
static uint64_t rx_frame_first; static unsigned rx_frame_n;
static avr_irq_t *uart_in;
static int host_frames_waiting;  /* complete host frames (0x00 seen) in rxq */
static int awaiting_host;
static uint64_t tx_first, line_first; static unsigned tx_run, line_run;
static uint8_t txbuf[4096]; static size_t tx_len;
static unsigned long long tx_bytes, rx_bytes, tx_dropped, lockstep_timeouts, uart_fifo_full;

static void flush_tx(void) {
    size_t off = 0;
    while (off < tx_len) {
        ssize_t n = write(pty_master, txbuf + off, tx_len - off);
        if (n > 0) { off += n; continue; }
        if (n < 0 && errno == EINTR) continue;
        tx_dropped += tx_len - off;  /* host not reading: a full buffer loses bytes */
        break;
    }
    tx_len = 0;
}

static void on_uart_out(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)param;
    uint8_t b = value;
    if (tx_len == sizeof txbuf) flush_tx();
    txbuf[tx_len++] = b;
    tx_bytes++;
    if (tx_run++ == 0) tx_first = avr->cycle;
    if (line_run++ == 0) line_first = avr->cycle;
    if (b == '\n') {  /* a text line is out: flushed now, as a frame is at its 0x00 */
        if (trace) fprintf(trace, "line %llu %llu %u\n", (unsigned long long)line_first,
                           (unsigned long long)avr->cycle, line_run);
        line_run = 0;
        flush_tx();
    }
    if (b == 0) {
        if (trace) fprintf(trace, "tx %llu %llu %u\n", (unsigned long long)tx_first,
                           (unsigned long long)avr->cycle, tx_run);
        if (!opt.realtime && (int)tx_run == opt.lockstep_frame_len + 1) {
            awaiting_host = 1;
            uint64_t earliest = avr->cycle + cycles_per_byte +
                (uint64_t)(opt.host_latency_us * 1e-6 * avr->frequency);
            if (rx_next < earliest) rx_next = earliest;
        }
        tx_run = 0;
        flush_tx();
    }
}

/* simavr's UART holds received bytes in a 64-byte FIFO and hands them to the
 * firmware one per byte time after each read; when it is full, bytes are lost. */
static void on_uart_xoff(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)param;
    if (value) uart_fifo_full++;
}

static void read_host(int timeout_ms) {
    struct pollfd p[2] = {{pty_master, POLLIN, 0}, {0, POLLIN, 0}};
    if (poll(p, 2, timeout_ms) <= 0) return;
    if (p[1].revents & (POLLIN | POLLHUP)) {
        char c;
        if (read(0, &c, 1) <= 0) stop_requested = 1;
    }
    if (!(p[0].revents & POLLIN)) return;
    uint8_t buf[4096];
    ssize_t n = read(pty_master, buf, sizeof buf);
    for (ssize_t i = 0; i < n; i++) {
        if ((rx_tail + 1) % RXQ == rx_head) break;  /* cannot happen at line rate */
        rxq[rx_tail] = buf[i];
        rx_tail = (rx_tail + 1) % RXQ;
        if (buf[i] == 0) host_frames_waiting++;
    }
}

static void feed_uart(void) {
    if (rx_head == rx_tail || avr->cycle < rx_next) return;
    uint8_t b = rxq[rx_head];
    rx_head = (rx_head + 1) % RXQ;
    if (rx_frame_n++ == 0) rx_frame_first = avr->cycle;
    avr_raise_irq(uart_in, b);
    rx_bytes++;
    rx_next = avr->cycle + cycles_per_byte;
    if (b == 0) {
        host_frames_waiting--;
        if (trace) fprintf(trace, "rx %llu %llu %u\n", (unsigned long long)rx_frame_first,
                           (unsigned long long)avr->cycle, rx_frame_n);
        rx_frame_n = 0;
    }
}

/* ---- traced interrupt vector ------------------------------------------------------ */
static uint64_t vec_pending_at, vec_running_at;
static int64_t vec_pending_count, vec_running_count;

static void on_vector_pending(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)param;
    if (value) { vec_pending_at = avr->cycle; vec_pending_count = plant.count; }
}

static void on_vector_running(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)param;
    if (value) {
        vec_running_at = avr->cycle;
        vec_running_count = plant.count;
    } else if (trace) {
        fprintf(trace, "vec %llu %llu %llu %lld %lld\n", (unsigned long long)vec_pending_at,
                (unsigned long long)vec_running_at, (unsigned long long)avr->cycle,
                (long long)vec_pending_count, (long long)vec_running_count);
    }
}

/* ---- firmware ------------------------------------------------------------------- */
static int hexval(const char *s, int n) {
    int v = 0;
    for (int i = 0; i < n; i++) {
        char c = s[i];
        int d = c >= '0' && c <= '9' ? c - '0' : c >= 'A' && c <= 'F' ? c - 'A' + 10
              : c >= 'a' && c <= 'f' ? c - 'a' + 10 : -1;
        if (d < 0) return -1;
        v = v << 4 | d;
    }
    return v;
}

/* Intel HEX (what avr-objcopy -O ihex writes) into flash; returns bytes loaded or -1. */
static long load_hex(const char *path, uint8_t *flash, size_t size) {
    FILE *f = fopen(path, "r");
    if (!f) return -1;
    char line[600];
    long end = 0;
    uint32_t base = 0;
    while (fgets(line, sizeof line, f)) {
        if (line[0] != ':') continue;
        int n = hexval(line + 1, 2), addr = hexval(line + 3, 4), type = hexval(line + 7, 2);
        if (n < 0 || addr < 0 || type < 0) { fclose(f); return -1; }
        if (type == 1) break;
        if (type == 2) base = (uint32_t)hexval(line + 9, 4) << 4;
        if (type == 4) base = (uint32_t)hexval(line + 9, 4) << 16;
        if (type != 0) continue;
        for (int i = 0; i < n; i++) {
            int b = hexval(line + 9 + 2 * i, 2);
            size_t at = base + addr + i;
            if (b < 0 || at >= size) { fclose(f); return -1; }
            flash[at] = b;
            if ((long)at + 1 > end) end = at + 1;
        }
    }
    fclose(f);
    return end;
}

static void no_sleep(avr_t *a, avr_cycle_count_t how_long) { (void)a; (void)how_long; }

static void on_signal(int sig) { (void)sig; stop_requested = 1; }

static int open_pty(void) {
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) || unlockpt(m)) return -1;
    /* Keep the slave open ourselves: the master then never reads as hung up while
     * the host has it closed (before it opens it, between reopens). */
    int s = open(ptsname(m), O_RDWR | O_NOCTTY);
    if (s < 0) return -1;
    struct termios tio;
    tcgetattr(s, &tio);
    cfmakeraw(&tio);
    tcsetattr(s, TCSANOW, &tio);
    fcntl(m, F_SETFL, O_NONBLOCK);
    printf("pty %s\n", ptsname(m));
    fflush(stdout);
    return m;
}

static double wall_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void usage(void) {
    fprintf(stderr, "usage: avr_harness --hex FILE [--mass KG --damping NS_M --metres-per-count M "
            "--full-scale-n N --x0 M --v0 M_S --coulomb-n N --amp-delay-us US --baud B --host-latency-us US --lockstep-timeout-ms MS "
            "--lockstep-frame-len N --realtime --max-ms MS --trace FILE --trace-vector N "
            "--drive-cps C --drive-start-ms MS --drive-stop-ms MS --drive-sine-counts A "
            "--drive-sine-hz F]\n");
    exit(2);
}

int main(int argc, char **argv) {
    static const struct option longopts[] = {
        {"hex", 1, 0, 'h'}, {"mass", 1, 0, 'm'}, {"damping", 1, 0, 'b'},
        {"metres-per-count", 1, 0, 'q'}, {"full-scale-n", 1, 0, 'f'}, {"x0", 1, 0, 'x'},
        {"v0", 1, 0, 'v'}, {"baud", 1, 0, 'B'}, {"host-latency-us", 1, 0, 'l'},
        {"lockstep-timeout-ms", 1, 0, 'w'}, {"lockstep-frame-len", 1, 0, 'L'},
        {"realtime", 0, 0, 'r'}, {"max-ms", 1, 0, 'M'}, {"trace", 1, 0, 't'},
        {"trace-vector", 1, 0, 'V'}, {"drive-cps", 1, 0, 'c'}, {"drive-start-ms", 1, 0, 's'},
        {"drive-stop-ms", 1, 0, 'S'}, {"coulomb-n", 1, 0, 'C'}, {"amp-delay-us", 1, 0, 'D'},
        {"drive-sine-counts", 1, 0, 'a'}, {"drive-sine-hz", 1, 0, 'F'},
        {0, 0, 0, 0}};
    int c;
    while ((c = getopt_long(argc, argv, "", longopts, NULL)) != -1) {
        switch (c) {
        case 'h': opt.hex = optarg; break;
        case 'm': opt.mass = atof(optarg); break;
        case 'b': opt.damping = atof(optarg); break;
        case 'q': opt.metres_per_count = atof(optarg); break;
        case 'f': opt.full_scale_n = atof(optarg); break;
        case 'x': opt.x0 = atof(optarg); break;
        case 'v': opt.v0 = atof(optarg); break;
        case 'B': opt.baud = atol(optarg); break;
        case 'l': opt.host_latency_us = atof(optarg); break;
        case 'w': opt.lockstep_timeout_ms = atof(optarg); break;
        case 'L': opt.lockstep_frame_len = atoi(optarg); break;
        case 'r': opt.realtime = 1; break;
        case 'M': opt.max_ms = atof(optarg); break;
        case 't': opt.trace = optarg; break;
        case 'V': opt.trace_vector = atoi(optarg); break;
        case 'c': opt.drive_cps = atof(optarg); break;
        case 's': opt.drive_start_ms = atof(optarg); break;
        case 'S': opt.drive_stop_ms = atof(optarg); break;
        case 'C': opt.coulomb = atof(optarg); break;
        case 'D': opt.amp_delay_us = atof(optarg); break;
        case 'a': opt.sine_counts = atof(optarg); break;
        case 'F': opt.sine_hz = atof(optarg); break;
        default: usage();
        }
    }
    if (!opt.hex || opt.mass <= 0 || opt.damping < 0 || opt.metres_per_count <= 0 || opt.baud <= 0
        || !(opt.coulomb >= 0) || !(opt.amp_delay_us >= 0))
        usage();
    if (!isnan(opt.drive_cps) && opt.drive_stop_ms < opt.drive_start_ms) usage();

    avr = avr_make_mcu_by_name("atmega328p");
    if (!avr || avr_init(avr)) { fprintf(stderr, "avr_harness: no atmega328p in simavr\n"); return 1; }
    avr->frequency = 16000000;
    avr->sleep = no_sleep;  /* emulated time only: never sleep the process */
    static uint8_t flash[32768];
    memset(flash, 0xFF, sizeof flash);
    long size = load_hex(opt.hex, flash, sizeof flash);
    if (size <= 0) { fprintf(stderr, "avr_harness: cannot load %s\n", opt.hex); return 1; }
    avr_loadcode(avr, flash, size, 0);
    cycles_per_byte = (uint64_t)llround(10.0 * avr->frequency / opt.baud);
    amp_delay_cycles = (uint64_t)llround(opt.amp_delay_us * 1e-6 * avr->frequency);

    if (opt.trace && !(trace = fopen(opt.trace, "w"))) { perror(opt.trace); return 1; }
    if ((pty_master = open_pty()) < 0) { perror("pty"); return 1; }
    signal(SIGTERM, on_signal);
    signal(SIGINT, on_signal);
    signal(SIGPIPE, SIG_IGN);

    uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            on_uart_out, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                            on_uart_xoff, NULL);
    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    pin_a = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), IOPORT_IRQ_PIN2);
    pin_b = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), IOPORT_IRQ_PIN3);
    if (opt.trace_vector >= 0) {
        avr_irq_t *v = avr_get_interrupt_irq(avr, opt.trace_vector);
        if (!v) { fprintf(stderr, "avr_harness: no vector %d\n", opt.trace_vector); return 1; }
        avr_irq_register_notify(v + AVR_INT_IRQ_PENDING, on_vector_pending, NULL);
        avr_irq_register_notify(v + AVR_INT_IRQ_RUNNING, on_vector_running, NULL);
    }

    /* Reset comes when the host has the port open: opening a tty flushes its input. */
    char go;
    if (read(0, &go, 1) != 1) return 0;

    plant.x = opt.x0;
    plant.v = opt.v0;
    if (!isnan(opt.drive_cps)) plant.x = drive_position(0);
    plant.count = count_of(plant.x);
    show_count(plant.count);
    plant.sig = force_signature();

    /* Plant steps of 4 us: edges are planned one step ahead (linear within it). */
    const uint64_t step = avr->frequency / 250000;
    const uint64_t max_cycles = opt.max_ms > 0 ? (uint64_t)(opt.max_ms * 1e-3 * avr->frequency) : UINT64_MAX;
    double wall0 = wall_s(), waited = 0;
    int state = cpu_Running;
    step_end = 0;
    while (!stop_requested && avr->cycle < max_cycles) {
        if (avr->cycle >= step_end) {
            step_end = avr->cycle - avr->cycle % step + step;
            plan_edges();
            if (opt.realtime) {
                double ahead = (double)avr->cycle / avr->frequency - (wall_s() - wall0);
                read_host(ahead > 0 ? (int)(ahead * 1e3) : 0);
            } else if ((avr->cycle / step) % 64 == 0) {
                read_host(0);
            }
        }
        if (awaiting_host) {
            double t0 = wall_s();
            while (!host_frames_waiting && !stop_requested &&
                   wall_s() - t0 < opt.lockstep_timeout_ms * 1e-3)
                read_host(10);
            if (!host_frames_waiting) lockstep_timeouts++;
            waited += wall_s() - t0;
            awaiting_host = 0;
        }
        feed_uart();
        apply_due_forces();
        emit_due_edges();
        state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed) break;
        hold_pins();
        update_force();
    }
    flush_tx();
    if (trace) fclose(trace);
    double wall = wall_s() - wall0, emulated = (double)avr->cycle / avr->frequency;
    double x, v;
    state_at(avr->cycle, &x, &v);
    printf("{\"cycles\": %llu, \"emulated_s\": %.6f, \"wall_s\": %.6f, \"host_wait_s\": %.6f, "
           "\"edges\": %llu, \"count\": %lld, \"position_m\": %.12g, \"velocity_m_s\": %.12g, "
           "\"tx_bytes\": %llu, \"rx_bytes\": %llu, \"tx_dropped\": %llu, "
           "\"lockstep_timeouts\": %llu, \"uart_fifo_full\": %llu, \"pins_restored\": %llu, "
           "\"amp_overflow\": %llu, \"crashed\": %s}\n",
           (unsigned long long)avr->cycle, emulated, wall, waited,
           (unsigned long long)plant.edges, (long long)plant.count, x, v, tx_bytes, rx_bytes,
           tx_dropped, lockstep_timeouts, uart_fifo_full, pins_restored, amp_overflow, state == cpu_Crashed ? "true" : "false");
    fflush(stdout);
    return state == cpu_Crashed ? 3 : 0;
}
