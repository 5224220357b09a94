// labbench reference sketch: quadrature encoder stream + force output for an
// Arduino Uno/Nano (ATmega328P, 16 MHz), optionally rendering the VE on board.
// Built and run on the simavr emulator by the test suite (labbench.sim_backend
// avr_build / avr_device, --device avr-sim). Pins: encoder A/B on 2/3, PWM 9, DIR 8.
//
// Protocol v2: docs/serial-protocol.md. Summary:
//   board -> host, every PERIOD_US:   COBS( 'S' | seq u16 | t_us u32 | count i32 | status u8 | crc16 ) 0x00
//                   or, with LABBENCH_ASCII 1:   "<t_us>,<count>\r\n"
//   host -> board, one per sample:   COBS( 'F' | seq u16 | force f32 | crc16 ) 0x00
//   host -> board, on-board VE:      COBS( 'P' | on u8 | K, B, w0, limit, mpc f32 | crc16 ) 0x00
// All fields little-endian; crc16 = CRC-16/CCITT-FALSE over the bytes before it.
//
// Timing: a hardware timer (Timer2, compare match A) ticks every PERIOD_US (every
// PERIOD_US / RENDER_DIV while rendering); the tick latches the encoder count,
// stamps it with the tick's time (t_us = tick index * PERIOD_US, crystal time) and
// drives the force prepared for it. The host's answer to sample k therefore acts
// from tick k+1: one sample of extra delay (td = T). The loop sends the latched
// sample first and decodes at most one command byte between checks, so a burst of
// commands cannot delay a sample. Watchdog: no valid command for 3 periods ->
// output (or, when rendering, the excitation) zero, status bit 0. A sample the loop
// could not send before the next tick is lost (seq gap) and the next one carries
// status bit 2; a frame queued late carries bit 3; a skipped encoder state bit 4.

#include <Arduino.h>

// ---- configuration (each can be set with -DNAME=value) ----------------------
#ifndef LABBENCH_ASCII
#define LABBENCH_ASCII 0          // 1: "t_us,count" lines, no command channel needed
#endif
#ifndef BAUD
#define BAUD 500000UL             // 16 bytes/sample at 1 kHz need >= 230400 baud
#endif
#ifndef PERIOD_US
#define PERIOD_US 1000UL          // must equal the rig's sample_time_s
#endif
#ifndef PWM_PER_NEWTON
#define PWM_PER_NEWTON 40.0f      // duty counts (of 255) per newton at the handle: calibrate
#endif
#ifndef LATE_US
#define LATE_US 100               // a frame queued later than this after its tick is flagged
#endif
#define RENDER_US 120              // tick time the render force may take before a sample
#ifndef RENDER_DIV
#define RENDER_DIV 5              // render ticks per sample: the on-board VE runs at 5 kHz
#endif
#define ENC_A 2                   // encoder channels: PD2 (INT0) and PD3 (INT1)
#define ENC_B 3
#define PWM_PIN 9                 // force magnitude: OC1A (PB1), 8-bit phase-correct PWM, 31.4 kHz
#define DIR_PIN 8                 // force sign: PB0, high = negative force
#define WATCHDOG_PERIODS 3

#define STATUS_WATCHDOG 0x01      // output zeroed: no valid command for WATCHDOG_PERIODS
#define STATUS_BAD_COMMAND 0x02   // a corrupt command frame was discarded
#define STATUS_MISSED_TICK 0x04   // a sample before this one was latched but never sent
#define STATUS_LATE 0x08          // this frame was queued more than LATE_US after its tick
#define STATUS_ENCODER 0x10       // the encoder skipped a state (counted as two steps on)
#define STATUS_RENDERING 0x20     // the board renders the VE itself (on-board mode)
#define STATUS_RENDER_LATE 0x40   // a render force was not ready by its tick (the last one held)

// ---- Timer2 tick: prescaler and compare values -------------------------------
// 16 MHz / prescaler must divide the period into at most 256 timer counts; the
// render tick (PERIOD_US / RENDER_DIV, only while the board renders) uses the same.
#if PERIOD_US * 16UL / 64UL <= 256UL && (PERIOD_US * 16UL) % 64UL == 0
#define TICK_PRESCALE_BITS (_BV(CS22))                      // /64: 4 us per count
#define US_PER_COUNT 4
#elif PERIOD_US * 16UL / 128UL <= 256UL && (PERIOD_US * 16UL) % 128UL == 0
#define TICK_PRESCALE_BITS (_BV(CS22) | _BV(CS20))          // /128: 8 us per count
#define US_PER_COUNT 8
#elif PERIOD_US * 16UL / 256UL <= 256UL && (PERIOD_US * 16UL) % 256UL == 0
#define TICK_PRESCALE_BITS (_BV(CS22) | _BV(CS21))          // /256: 16 us per count
#define US_PER_COUNT 16
#else
#error "PERIOD_US must be a multiple of 4 us up to 1024, of 8 up to 2048, or of 16 up to 4096"
#endif
#define PERIOD_COUNTS (PERIOD_US / US_PER_COUNT)
#define RENDER_COUNTS (PERIOD_COUNTS / RENDER_DIV)
#if RENDER_COUNTS * RENDER_DIV != PERIOD_COUNTS
#error "PERIOD_US / RENDER_DIV must be a whole number of timer counts"
#endif

// ---- encoder: 4x quadrature decoding from the port register -----------------
// Both pin-change interrupts run the same two table lookups on PIND (no
// digitalRead, no function pointer): 55 cycles (3.4 us) per edge, in assembly
// because the compiler's version of the same takes twice that. The state lives
// in the general-purpose I/O registers (1-cycle access):
//   GPIOR0 = previous pins (bits 0-1, B << 1 | A) | last direction (bit 4, 1 =
//            backwards) | "a state was skipped" (bit 5, cleared by the tick);
//   GPIOR2:GPIOR1 = a 16-bit counter that the tick extends to 32 bits.
// Table index: new pins (PIND bits 2-3) | GPIOR0. Forward (B leads A) is
// (A, B) = 00, 01, 11, 10. A skipped state (both channels changed: a second edge
// came while another interrupt held this one off) counts two steps in the last
// direction, the only motion that produces it at these rates, and sets bit 5.
const int8_t ENC_STEP[64] PROGMEM __attribute__((aligned(256))) = {
    0, 1, -1, 2, -1, 0, 2, 1, 1, 2, 0, -1, 2, -1, 1, 0,
    0, 1, -1, -2, -1, 0, -2, 1, 1, -2, 0, -1, -2, -1, 1, 0,
    0, 1, -1, 2, -1, 0, 2, 1, 1, 2, 0, -1, 2, -1, 1, 0,
    0, 1, -1, -2, -1, 0, -2, 1, 1, -2, 0, -1, -2, -1, 1, 0};
const uint8_t ENC_NEXT[64] PROGMEM __attribute__((aligned(256))) = {
    0x00, 0x00, 0x10, 0x20, 0x11, 0x01, 0x21, 0x01, 0x02, 0x22, 0x02, 0x12, 0x23, 0x13, 0x03, 0x03,
    0x10, 0x00, 0x10, 0x30, 0x11, 0x11, 0x31, 0x01, 0x02, 0x32, 0x12, 0x12, 0x33, 0x13, 0x03, 0x13,
    0x20, 0x20, 0x30, 0x20, 0x31, 0x21, 0x21, 0x21, 0x22, 0x22, 0x22, 0x32, 0x23, 0x33, 0x23, 0x23,
    0x30, 0x20, 0x30, 0x30, 0x31, 0x31, 0x31, 0x21, 0x22, 0x32, 0x32, 0x32, 0x33, 0x33, 0x23, 0x33};
#define ENC_SKIPPED 0x20

ISR(INT0_vect, ISR_NAKED) {
  asm volatile(
      "push r24\n\t"
      "in r24, __SREG__\n\t"
      "push r24\n\t"
      "push r25\n\t"
      "push r30\n\t"
      "push r31\n\t"
      "in r30, %[pind]\n\t"
      "andi r30, 0x0C\n\t"          // new pins, bits 2-3
      "in r24, %[state]\n\t"
      "or r30, r24\n\t"             // index (the tables are 256-byte aligned)
      "ldi r31, hi8(%[next])\n\t"
      "lpm r24, Z\n\t"
      "out %[state], r24\n\t"
      "ldi r31, hi8(%[step])\n\t"
      "lpm r24, Z\n\t"              // step, -2..2
      "in r30, %[lo]\n\t"
      "in r31, %[hi]\n\t"
      "mov r25, r24\n\t"
      "lsl r25\n\t"
      "sbc r25, r25\n\t"            // sign extension
      "add r30, r24\n\t"
      "adc r31, r25\n\t"
      "out %[lo], r30\n\t"
      "out %[hi], r31\n\t"
      "pop r31\n\t"
      "pop r30\n\t"
      "pop r25\n\t"
      "pop r24\n\t"
      "out __SREG__, r24\n\t"
      "pop r24\n\t"
      "reti\n\t"
      :
      : [pind] "I"(_SFR_IO_ADDR(PIND)), [state] "I"(_SFR_IO_ADDR(GPIOR0)),
        [lo] "I"(_SFR_IO_ADDR(GPIOR1)), [hi] "I"(_SFR_IO_ADDR(GPIOR2)),
        [next] "i"(ENC_NEXT), [step] "i"(ENC_STEP));
}
ISR(INT1_vect, ISR_ALIASOF(INT0_vect));

int32_t enc_count = 0;        // the 32-bit count, extended in the tick
uint16_t enc_seen = 0;        // the 16-bit counter at the last extension

// The tick extends the 16-bit counter: fewer than 32768 counts per tick (33 M counts/s).

// ---- force output -------------------------------------------------------------
// Duty is a signed count -255..255; DIR and OCR1A are written together in the tick.
int16_t duty_of(float force_n) {
  float d = force_n * PWM_PER_NEWTON;
  if (d > 255.0f) return 255;
  if (d < -255.0f) return -255;
  return (int16_t)(d < 0 ? d - 0.5f : d + 0.5f);  // nearest, halves away from zero
}

// The force of the coming tick, prepared by the loop (a host command, a rendered
// force) or by the tick itself (the watchdog): the tick's first instructions drive it.
volatile uint8_t drive_ocr = 0;  // |duty|
volatile uint8_t drive_dir = 0;  // 1: negative (DIR high)

void prepare_duty(int16_t duty) {
  uint8_t dir = duty < 0, ocr = duty < 0 ? -duty : duty;
  noInterrupts();
  drive_ocr = ocr;
  drive_dir = dir;
  interrupts();
}

// ---- UART0: own interrupt-driven rings (the core's Serial costs twice the cycles) --
// RX: the interrupt only stores the byte; the loop decodes. TX: the loop queues a
// whole frame, the data-register-empty interrupt sends it.
#define RX_SIZE 128                // power of two: > 8 commands of 11 bytes
#define TX_SIZE 64
volatile uint8_t rx_buf[RX_SIZE], tx_buf[TX_SIZE];
volatile uint8_t rx_head = 0, rx_tail = 0, tx_head = 0, tx_tail = 0;
volatile bool rx_lost = false;     // a byte was lost: ring full or hardware overrun

ISR(USART_RX_vect) {
  bool overrun = UCSR0A & _BV(DOR0);
  uint8_t b = UDR0, next = (rx_head + 1) & (RX_SIZE - 1);
  if (overrun || next == rx_tail) rx_lost = true;
  if (next != rx_tail) {
    rx_buf[rx_head] = b;
    rx_head = next;
  }
}

ISR(USART_UDRE_vect) {
  UDR0 = tx_buf[tx_tail];
  tx_tail = (tx_tail + 1) & (TX_SIZE - 1);
  if (tx_tail == tx_head) UCSR0B &= ~_BV(UDRIE0);
}

void uart_begin() {
  // Double speed: 16 MHz / (8 * (3 + 1)) = 500 kbit/s exactly.
  uint16_t ubrr = (F_CPU / 4 / BAUD - 1) / 2;
  UCSR0A = _BV(U2X0);
  UBRR0H = ubrr >> 8;
  UBRR0L = ubrr;
  UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);  // 8N1
  UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

bool uart_tx_idle() { return tx_head == tx_tail; }  // nothing queued before this frame

// Queues n bytes (the ring never holds more than one frame and the banner).
void uart_write(const uint8_t *p, uint8_t n) {
  while (n--) {
    uint8_t next = (tx_head + 1) & (TX_SIZE - 1);
    while (next == tx_tail) {}  // full: wait for the interrupt to drain it
    tx_buf[tx_head] = *p++;
    tx_head = next;
    UCSR0B |= _BV(UDRIE0);
  }
}

void uart_print(const char *text) { uart_write((const uint8_t *)text, strlen(text)); }

// ---- on-board rendering ("the Hapkit way": the VE from the board's own encoder) ---
// Per render tick j (T_r = PERIOD_US / RENDER_DIV), in duty counts:
//   v[j] = a v[j-1] + (1 - a) (x[j] - x[j-1])      velocity [counts per tick], a = exp(-w0 T_r)
//   u[j] = e - (K' x[j] + B' v[j]),  K' = K mpc PWM_PER_NEWTON,  B' = B mpc PWM_PER_NEWTON / T_r
// clamped to the force limit and driven from tick j+1 (td = T_r): labbench's sampled
// model at the board's own period. The tick latches x[j] and, with interrupts on
// again, computes u[j] (float, ~80 us) well within the 200 us to tick j+1. e is the host's excitation (its 'F' value), taken
// at each sample tick and zero when the host is silent: a stalled host never touches
// the rendering.
struct Render {
  float k, b, c, limit;   // K', B', 1 - a, limit [duty]
  float v;                // filtered velocity
  int32_t x_prev;
};
Render render;
volatile bool render_on = false;

int16_t render_step(int32_t x, float e) {
  render.v += render.c * ((float)(int16_t)(x - render.x_prev) - render.v);
  render.x_prev = x;
  float u = e - (render.k * (float)x + render.b * render.v);
  if (u > render.limit) u = render.limit;
  if (u < -render.limit) u = -render.limit;
  return (int16_t)(u < 0 ? u - 0.5f : u + 0.5f);
}

// ---- tick ---------------------------------------------------------------------
volatile int16_t command_duty = 0;     // newest valid command, as duty
volatile float command_raw = 0;        // the same, unrounded (the excitation when rendering)
volatile uint8_t command_age = 255;    // sample ticks since it arrived (saturates)
volatile bool sample_ready = false;    // a latched sample waits for the loop
volatile uint8_t tick_status = 0;      // status bits found in the tick
volatile uint16_t tick_seq = 0;        // index of the latched sample (wraps)
volatile uint32_t tick_us = 0;         // its time
volatile int32_t tick_count = 0;       // its count
uint32_t next_us = 0;                  // time of the coming sample tick
uint8_t sub_tick = 0;                  // ticks since the sample tick
volatile uint8_t ticks_per_sample = 1; // RENDER_DIV while the board renders, else 1
volatile uint8_t render_wanted = 0;    // 0 off, 1 on: taken at the next sample tick
float excitation = 0;                  // the excitation rendered until the next sample tick

volatile uint8_t tick_lo, tick_hi;     // the 16-bit encoder counter at the tick
extern "C" void tick_after_latch(void) __attribute__((signal, used));

// The tick's first 30 cycles, with interrupts off: latch the counter, drive the
// prepared force (on a change of sign the magnitude goes to zero first: DIR
// flipping under the old magnitude would be a pulse of the wrong force). The rest
// runs with interrupts on, so the encoder is never held off for more than this.
ISR(TIMER2_COMPA_vect, ISR_NAKED) {
  asm volatile(
      "push r24\n\t"
      "in r24, __SREG__\n\t"
      "push r24\n\t"
      "push r25\n\t"
      "in r24, %[lo]\n\t"
      "sts %[tlo], r24\n\t"
      "in r24, %[hi]\n\t"
      "sts %[thi], r24\n\t"
      "clr r25\n\t"
      "lds r24, %[dir]\n\t"
      "sbrs r24, 0\n\t"
      "rjmp 1f\n\t"
      "sbic %[portb], 0\n\t"        // negative wanted: DIR already high?
      "rjmp 2f\n\t"
      "sts %[ocrh], r25\n\t"
      "sts %[ocrl], r25\n\t"
      "sbi %[portb], 0\n\t"
      "rjmp 2f\n\t"
      "1:\n\t"
      "sbis %[portb], 0\n\t"        // positive wanted: DIR already low?
      "rjmp 2f\n\t"
      "sts %[ocrh], r25\n\t"
      "sts %[ocrl], r25\n\t"
      "cbi %[portb], 0\n\t"
      "2:\n\t"
      "lds r24, %[ocr]\n\t"
      "sts %[ocrh], r25\n\t"
      "sts %[ocrl], r24\n\t"
      "pop r25\n\t"
      "pop r24\n\t"
      "out __SREG__, r24\n\t"
      "pop r24\n\t"
      "sei\n\t"
      "jmp tick_after_latch\n\t"
      :
      : [lo] "I"(_SFR_IO_ADDR(GPIOR1)), [hi] "I"(_SFR_IO_ADDR(GPIOR2)),
        [portb] "I"(_SFR_IO_ADDR(PORTB)), [ocrl] "n"(_SFR_MEM_ADDR(OCR1AL)),
        [ocrh] "n"(_SFR_MEM_ADDR(OCR1AH)), [tlo] "i"(&tick_lo), [thi] "i"(&tick_hi),
        [dir] "i"(&drive_dir), [ocr] "i"(&drive_ocr));
}

volatile bool in_tick = false;  // the rest of a tick still runs (rendering took too long)

void tick_after_latch(void) {
  if (in_tick) {  // the previous tick's rendering is not done: its force is held
    tick_status |= STATUS_RENDER_LATE;
    return;
  }
  in_tick = true;
  uint16_t now = tick_lo | (uint16_t)tick_hi << 8;
  enc_count += (int16_t)(now - enc_seen);
  enc_seen = now;
  int32_t count = enc_count;
  bool sample = sub_tick == 0;
  if (++sub_tick == ticks_per_sample) sub_tick = 0;
  if (sample) {
    tick_count = count;
    if (command_age < 255) command_age++;
    bool fed = command_age <= WATCHDOG_PERIODS;
    if (!fed) tick_status |= STATUS_WATCHDOG;
    excitation = fed ? command_raw : 0.0f;
    if (render_on != (bool)render_wanted) {
      // Switch between the host loop and rendering on a sample tick: the ticks stay
      // on the sample grid.
      render_on = render_wanted;
      ticks_per_sample = render_on ? RENDER_DIV : 1;
      sub_tick = ticks_per_sample > 1 ? 1 : 0;
      OCR2A = (render_on ? RENDER_COUNTS : PERIOD_COUNTS) - 1;
      render.x_prev = count;
      render.v = 0;
      prepare_duty(render_on || !fed ? 0 : command_duty);
    } else if (!render_on && command_age + 1 > WATCHDOG_PERIODS) {
      prepare_duty(0);  // the next tick finds no fresh command
    }
    if (render_on) tick_status |= STATUS_RENDERING;
    tick_us = next_us;
    next_us += PERIOD_US;
    if (sample_ready) tick_status |= STATUS_MISSED_TICK;
    tick_seq++;
    sample_ready = true;
    if (GPIOR0 & ENC_SKIPPED) {
      GPIOR0 &= ~ENC_SKIPPED;
      tick_status |= STATUS_ENCODER;
    }
  }
  if (render_on) prepare_duty(render_step(count, excitation));  // ~80 us, interrupts on
  in_tick = false;
}


// ---- CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), one table lookup per byte ---
uint16_t crc_table[256];  // built at boot from the bitwise definition

void crc_init() {
  for (uint16_t n = 0; n < 256; n++) {
    uint16_t c = n << 8;
    for (uint8_t i = 0; i < 8; i++) c = (c & 0x8000) ? (c << 1) ^ 0x1021 : c << 1;
    crc_table[n] = c;
  }
}

uint16_t crc16(const uint8_t *p, uint8_t n) {
  uint16_t crc = 0xFFFF;
  while (n--) crc = (crc << 8) ^ crc_table[(uint8_t)(crc >> 8) ^ *p++];
  return crc;
}

// ---- COBS encoder (n + 1 bytes out) -------------------------------------------
uint8_t cobs_encode(const uint8_t *in, uint8_t n, uint8_t *out) {
  uint8_t code_at = 0, code = 1, w = 1;
  for (uint8_t i = 0; i < n; i++) {
    if (in[i] == 0) {
      out[code_at] = code;
      code_at = w++;
      code = 1;
    } else {
      out[w++] = in[i];
      code++;
    }
  }
  out[code_at] = code;
  return w;  // payloads here are < 254 bytes: no 0xFF blocks needed
}

// ---- commands -------------------------------------------------------------------
// Decoded one byte at a time as it arrives (COBS and CRC), so the loop never
// spends more than one byte's work (or, on the delimiter, one check and one float
// conversion: ~25 us) before it looks at the tick again. Two frames:
//   'F' | seq u16 | value f32 | crc             force [N] (host loop) or excitation (on board)
//   'P' | on u8 | K f32 | B f32 | w0 f32 | limit f32 | mpc f32 | crc   on-board VE
#define CMD_MAX 24
#define FORCE_LEN 9
#define PARAMS_LEN 24
uint8_t cmd[CMD_MAX];
uint8_t cmd_n = 0;                 // decoded bytes so far
uint8_t cobs_left = 0;             // data bytes left in the current COBS block
uint8_t cobs_code = 0;             // code of the current block (0: none yet)
bool cmd_bad = false;              // this frame is broken: skip to its delimiter
bool cmd_any = false;              // bytes since the last delimiter
uint16_t cmd_crc = 0xFFFF;         // over all decoded bytes but the last two
uint8_t loop_status = 0;           // status bits found by the loop

void cmd_push(uint8_t x) {
  if (cmd_n == CMD_MAX) {
    cmd_bad = true;
    return;
  }
  if (cmd_n >= 2) cmd_crc = (cmd_crc << 8) ^ crc_table[(uint8_t)(cmd_crc >> 8) ^ cmd[cmd_n - 2]];
  cmd[cmd_n++] = x;
}

void take_force() {
  float f;
  memcpy(&f, cmd + 3, 4);  // AVR float is IEEE-754 binary32, little-endian
  if (f != f) return;      // NaN: keep the previous command
  float d = f * PWM_PER_NEWTON;
  int16_t duty = duty_of(f);
  noInterrupts();
  command_duty = duty;
  command_raw = d;
  command_age = 0;
  interrupts();
  if (!render_on) prepare_duty(duty);
}

// The VE for on-board rendering (coefficients in duty counts per count and tick).
void take_params() {
  float p[5];  // K, B, w0, limit, mpc
  memcpy(p, cmd + 2, sizeof p);
  for (uint8_t i = 0; i < 5; i++)
    if (p[i] != p[i] || (i != 2 && (p[i] < 0 || p[i] > 1e30f))) {
      loop_status |= STATUS_BAD_COMMAND;
      return;
    }
  const float t_r = RENDER_COUNTS * US_PER_COUNT * 1e-6f;  // the render period
  Render r;
  r.k = p[0] * p[4] * PWM_PER_NEWTON;
  r.b = p[1] * p[4] * PWM_PER_NEWTON / t_r;
  r.c = p[2] > 0 ? 1.0f - expf(-p[2] * t_r) : 1.0f;  // w0 = inf: no filter
  r.limit = p[3] * PWM_PER_NEWTON > 255.0f ? 255.0f : p[3] * PWM_PER_NEWTON;
  noInterrupts();
  r.x_prev = render.x_prev;
  r.v = render.v;
  render = r;
  render_wanted = cmd[1] != 0;  // the tick switches at the next sample
  interrupts();
}

void take_command_frame() {
  bool ok = !cmd_bad && cobs_left == 0 && cmd_n >= 3 &&
            cmd_crc == (uint16_t)(cmd[cmd_n - 2] | (cmd[cmd_n - 1] << 8));
  if (ok && cmd[0] == 'F' && cmd_n == FORCE_LEN) take_force();
  else if (ok && cmd[0] == 'P' && cmd_n == PARAMS_LEN) take_params();
  else if (cmd_any) loop_status |= STATUS_BAD_COMMAND;
}

// One byte of the command stream. A frame run into garbage without a delimiter
// is lost (counted as bad); the next one decodes again.
void take_byte(uint8_t b) {
  if (b == 0) {
    take_command_frame();
    cmd_n = cobs_left = cobs_code = 0;
    cmd_bad = cmd_any = false;
    cmd_crc = 0xFFFF;
    return;
  }
  cmd_any = true;
  if (cmd_bad) return;
  if (cobs_left) {
    cmd_push(b);
    cobs_left--;
    return;
  }
  // A code byte: the block before it ended in a zero (unless it was a full 0xFF block).
  if (cobs_code && cobs_code != 0xFF) cmd_push(0);
  cobs_code = b;
  cobs_left = b - 1;
}

// ---- samples --------------------------------------------------------------------
void send_sample() {
  noInterrupts();
  uint16_t seq = tick_seq - 1;  // tick_seq counts ticks; sample k is the k-th tick
  uint32_t t_us = tick_us;
  int32_t count = tick_count;
  uint8_t status = tick_status | loop_status;
  // Time since the sample tick: whole render ticks since, plus this one's timer count
  // (plus one more tick if its compare flag is already up).
  uint8_t tps = ticks_per_sample, sub = sub_tick, counts = TCNT2, top = OCR2A;
  bool flag = TIFR2 & _BV(OCF2A);
  tick_status = 0;
  sample_ready = false;
  interrupts();  // (the encoder waits for this block: keep it short)
  loop_status = 0;
  uint8_t ticks = (sub == 0 ? tps - 1 : sub - 1) + flag;  // whole ticks since the sample's
  uint16_t since = ticks * (uint16_t)(top + 1) + counts;
  // While rendering, the render force goes first: allow for it.
  uint16_t late_us = tps > 1 ? LATE_US + RENDER_US : LATE_US;
  if (since * US_PER_COUNT > late_us || !uart_tx_idle())
    status |= STATUS_LATE;
#if LABBENCH_ASCII
  char line[24];
  ultoa(t_us, line, 10);
  uint8_t n = strlen(line);
  line[n++] = ',';
  ltoa(count, line + n, 10);
  uart_print(line);
  uart_print("\r\n");
  (void)seq;
  (void)status;
#else
  uint8_t payload[14], frame[16];
  payload[0] = 'S';  // the AVR is little-endian, as the wire
  memcpy(payload + 1, &seq, 2);
  memcpy(payload + 3, &t_us, 4);
  memcpy(payload + 7, &count, 4);
  payload[11] = status;
  uint16_t crc = crc16(payload, 12);
  memcpy(payload + 12, &crc, 2);
  uint8_t n = cobs_encode(payload, 14, frame);
  frame[n++] = 0;
  uart_write(frame, n);
#endif
}

void setup() {
  crc_init();
  pinMode(ENC_A, INPUT_PULLUP);
  pinMode(ENC_B, INPUT_PULLUP);
  pinMode(DIR_PIN, OUTPUT);
  pinMode(PWM_PIN, OUTPUT);
  // Timer1: 8-bit phase-correct PWM on OC1A, no prescaler (31.4 kHz, inaudible;
  // the core's analogWrite runs it at 490 Hz, too slow to change force every tick).
  TCCR1A = _BV(COM1A1) | _BV(WGM10);
  TCCR1B = _BV(CS10);
  prepare_duty(0);
  OCR1A = 0;
  uart_begin();
  uart_print("#labbench encoder v2\r\n");
#if !LABBENCH_ASCII
  uint8_t zero = 0;
  uart_write(&zero, 1);  // ends any frame the host's parser started on boot noise
#endif
  GPIOR0 = (PIND & 0x0C) >> 2;
  GPIOR1 = GPIOR2 = 0;
  EICRA = _BV(ISC00) | _BV(ISC10);  // INT0, INT1 on any change
  EIFR = _BV(INTF0) | _BV(INTF1);
  EIMSK = _BV(INT0) | _BV(INT1);
  // Timer2: clear on compare match A every PERIOD_US (every render tick when rendering).
  TCCR2A = _BV(WGM21);
  TCCR2B = 0;
  TCNT2 = 0;
  OCR2A = PERIOD_COUNTS - 1;
  TIFR2 = _BV(OCF2A);
  TIMSK2 = _BV(OCIE2A);
  TCCR2B = TICK_PRESCALE_BITS;
}

void loop() {
  // The sample first; then one command byte, so a tick waits at most one decode.
  if (sample_ready) {
    send_sample();
  } else if (rx_tail != rx_head) {
    uint8_t b = rx_buf[rx_tail];
    rx_tail = (rx_tail + 1) & (RX_SIZE - 1);
    take_byte(b);
  }
  if (rx_lost) {
    rx_lost = false;
    loop_status |= STATUS_BAD_COMMAND;  // a command lost with the byte
  }
}
