// labbench reference sketch: quadrature encoder stream + force output for an
// Arduino Uno/Nano (ATmega328P, 16 MHz). Built and run on the simavr emulator by
// the test suite (labbench.sim_backend.avr_build / avr_device, --device avr-sim).
//
// Protocol v2: docs/serial-protocol.md. Summary:
//   board -> host, every PERIOD_US:   COBS( 'S' | seq u16 | t_us u32 | count i32 | status u8 | crc16 ) 0x00
//                   or, with LABBENCH_ASCII 1:   "<t_us>,<count>\r\n"
//   host -> board, one per sample:   COBS( 'F' | seq u16 | force f32 | crc16 ) 0x00
// All fields little-endian; crc16 = CRC-16/CCITT-FALSE over the bytes before it.
//
// Timing: a hardware timer (Timer2, compare match A) ticks every PERIOD_US; its
// interrupt latches the encoder count, stamps it with the tick's time (t_us =
// tick index * PERIOD_US, crystal time) and applies the newest force command.
// The host's answer to sample k therefore acts from tick k+1: one sample of extra
// delay (td = T). The main loop sends the latched sample first and decodes at most
// one command byte between checks, so a burst of commands cannot delay a sample.
// Watchdog: no valid command for 3 periods -> output zero, status bit 0.
// A sample the loop could not send before the next tick is lost (seq gap) and the
// next one carries status bit 2; a frame queued late carries bit 3.

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
#define LATE_US 40                // a frame queued later than this after its tick is flagged
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
#define STATUS_ENCODER 0x10       // the encoder jumped two states (an edge came too fast)

// ---- Timer2 tick: prescaler and compare value for PERIOD_US ------------------
// 16 MHz / prescaler must divide the period into at most 256 timer counts.
#if PERIOD_US * 16UL / 64UL <= 256UL && (PERIOD_US * 16UL) % 64UL == 0
#define TICK_PRESCALE_BITS (_BV(CS22))                      // /64: 4 us per count
#define TICK_COUNTS (PERIOD_US * 16UL / 64UL)
#define US_PER_COUNT 4
#elif PERIOD_US * 16UL / 128UL <= 256UL && (PERIOD_US * 16UL) % 128UL == 0
#define TICK_PRESCALE_BITS (_BV(CS22) | _BV(CS20))          // /128: 8 us per count
#define TICK_COUNTS (PERIOD_US * 16UL / 128UL)
#define US_PER_COUNT 8
#elif PERIOD_US * 16UL / 256UL <= 256UL && (PERIOD_US * 16UL) % 256UL == 0
#define TICK_PRESCALE_BITS (_BV(CS22) | _BV(CS21))          // /256: 16 us per count
#define TICK_COUNTS (PERIOD_US * 16UL / 256UL)
#define US_PER_COUNT 16
#else
#error "PERIOD_US must be a multiple of 4 us up to 1024, of 8 up to 2048, or of 16 up to 4096"
#endif

// ---- encoder: 4x quadrature decoding from the port register -----------------
// One table lookup on PIND per edge (no digitalRead): about 4 us per edge.
volatile int32_t enc_count = 0;
volatile uint8_t enc_state = 0;     // previous pins in port order (B << 1 | A)
volatile uint8_t enc_jumps = 0;     // transitions with both channels changed
// Index: previous state << 2 | new state; 0 no move, +-1 a step, 2 an impossible
// jump. Forward (B leads A): (A,B) = 00, 01, 11, 10, i.e. states 0, 2, 3, 1.
const int8_t QUAD_STEP[16] = {0, -1, 1, 2, 1, 0, 2, -1, -1, 2, 0, 1, 2, 1, -1, 0};

ISR(INT0_vect) {
  uint8_t s = (PIND >> 2) & 0x03;
  int8_t step = QUAD_STEP[(enc_state << 2) | s];
  enc_state = s;
  if (step == 2) enc_jumps++;
  else enc_count += step;
}
ISR(INT1_vect, ISR_ALIASOF(INT0_vect));

// ---- force output -------------------------------------------------------------
// Duty is a signed count -255..255; DIR and OCR1A are written together in the tick.
int16_t duty_of(float force_n) {
  float d = force_n * PWM_PER_NEWTON;
  if (d > 255.0f) return 255;
  if (d < -255.0f) return -255;
  return (int16_t)lroundf(d);
}

inline void drive_duty(int16_t duty) {
  if (duty < 0) {
    PORTB |= _BV(PB0);
    OCR1A = -duty;
  } else {
    PORTB &= ~_BV(PB0);
    OCR1A = duty;
  }
}

// ---- tick ---------------------------------------------------------------------
volatile int16_t command_duty = 0;     // newest valid command, as duty
volatile uint8_t command_age = 255;    // ticks since it arrived (saturates)
volatile bool sample_ready = false;    // a latched sample waits for the loop
volatile uint8_t tick_status = 0;      // status bits found in the tick
volatile uint16_t tick_seq = 0;        // index of the latched sample (wraps)
volatile uint32_t tick_us = 0;         // its time
volatile int32_t tick_count = 0;       // its count
uint32_t next_us = 0;                  // time of the coming tick

ISR(TIMER2_COMPA_vect) {
  // Interrupts are off here: an edge coming now is counted after the latch.
  tick_count = enc_count;
  tick_us = next_us;
  next_us += PERIOD_US;
  if (sample_ready) tick_status |= STATUS_MISSED_TICK;
  tick_seq++;
  sample_ready = true;
  if (command_age < 255) command_age++;
  if (command_age > WATCHDOG_PERIODS) {
    drive_duty(0);
    tick_status |= STATUS_WATCHDOG;
  } else {
    drive_duty(command_duty);
  }
  if (enc_jumps) {
    enc_jumps = 0;
    tick_status |= STATUS_ENCODER;
  }
}

// ---- CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), nibble table ----------------
uint16_t crc_table[16];

void crc_init() {
  for (uint8_t n = 0; n < 16; n++) {
    uint16_t c = (uint16_t)n << 12;
    for (uint8_t i = 0; i < 4; i++) c = (c & 0x8000) ? (c << 1) ^ 0x1021 : c << 1;
    crc_table[n] = c;
  }
}

uint16_t crc16(const uint8_t *p, uint8_t n) {
  uint16_t crc = 0xFFFF;
  while (n--) {
    uint8_t b = *p++;
    crc = (crc << 4) ^ crc_table[(crc >> 12) ^ (b >> 4)];
    crc = (crc << 4) ^ crc_table[(crc >> 12) ^ (b & 0x0F)];
  }
  return crc;
}

// ---- COBS: encode into out (n + 1 bytes), decode in place -------------------
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

// Returns the decoded length, or -1 if the frame is not valid COBS.
int8_t cobs_decode(const uint8_t *in, uint8_t n, uint8_t *out) {
  uint8_t r = 0, w = 0;
  while (r < n) {
    uint8_t code = in[r];
    if (code == 0 || r + code > n) return -1;
    for (uint8_t i = 1; i < code; i++) out[w++] = in[r + i];
    r += code;
    if (code != 0xFF && r < n) out[w++] = 0;
  }
  return w;
}

// ---- commands -------------------------------------------------------------------
// Receiver: the last 10 bytes before a 0x00 (one COBS command frame); longer runs
// are garbage cut off the front, as the host does with samples.
#define CMD_FRAME_LEN 10
uint8_t rx[CMD_FRAME_LEN];
uint8_t rx_len = 0;
bool rx_garbage = false;
uint8_t loop_status = 0;   // status bits found by the loop

void put_u16(uint8_t *p, uint16_t v) { p[0] = v; p[1] = v >> 8; }
void put_u32(uint8_t *p, uint32_t v) { for (uint8_t i = 0; i < 4; i++) p[i] = v >> (8 * i); }

void take_command_frame() {
  uint8_t payload[CMD_FRAME_LEN];
  int8_t n = rx_len == CMD_FRAME_LEN ? cobs_decode(rx, rx_len, payload) : -1;
  if (rx_garbage || n != 9 || payload[0] != 'F' ||
      crc16(payload, 7) != (uint16_t)(payload[7] | (payload[8] << 8))) {
    if (rx_len || rx_garbage) loop_status |= STATUS_BAD_COMMAND;
    return;
  }
  float f;
  memcpy(&f, payload + 3, 4);  // AVR float is IEEE-754 binary32, little-endian
  if (f != f) return;          // NaN: keep the previous command
  int16_t duty = duty_of(f);
  noInterrupts();
  command_duty = duty;
  command_age = 0;
  interrupts();
}

// One byte of the command stream: at most one frame decode (~25 us) per call.
void take_byte(uint8_t b) {
  if (b == 0) {
    take_command_frame();
    rx_len = 0;
    rx_garbage = false;
    return;
  }
  if (rx_len == CMD_FRAME_LEN) {  // keep the newest bytes only
    memmove(rx, rx + 1, CMD_FRAME_LEN - 1);
    rx_len--;
    rx_garbage = true;
  }
  rx[rx_len++] = b;
}

// ---- samples --------------------------------------------------------------------
void send_sample() {
  noInterrupts();
  uint16_t seq = tick_seq - 1;  // tick_seq counts ticks; sample k is the k-th tick
  uint32_t t_us = tick_us;
  int32_t count = tick_count;
  uint8_t status = tick_status | loop_status;
  uint8_t since_tick = TCNT2;   // timer counts since the tick (no tick in between:
  bool next_tick = TIFR2 & _BV(OCF2A);  // else the compare flag is up)
  tick_status = 0;
  sample_ready = false;
  interrupts();
  loop_status = 0;
  if (next_tick || (uint16_t)since_tick * US_PER_COUNT > LATE_US ||
      Serial.availableForWrite() < SERIAL_TX_BUFFER_SIZE - 1)
    status |= STATUS_LATE;
#if LABBENCH_ASCII
  Serial.print(t_us);
  Serial.print(',');
  Serial.println(count);
  (void)seq;
  (void)status;
#else
  uint8_t payload[14], frame[16];
  payload[0] = 'S';
  put_u16(payload + 1, seq);
  put_u32(payload + 3, t_us);
  put_u32(payload + 7, (uint32_t)count);
  payload[11] = status;
  put_u16(payload + 12, crc16(payload, 12));
  uint8_t n = cobs_encode(payload, 14, frame);
  frame[n++] = 0;
  Serial.write(frame, n);
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
  drive_duty(0);
  Serial.begin(BAUD);
  Serial.print("#labbench encoder v2\r\n");
#if !LABBENCH_ASCII
  Serial.write((uint8_t)0);  // ends any frame the host's parser started on boot noise
#endif
  enc_state = (PIND >> 2) & 0x03;
  EICRA = _BV(ISC00) | _BV(ISC10);  // INT0, INT1 on any change
  EIFR = _BV(INTF0) | _BV(INTF1);
  EIMSK = _BV(INT0) | _BV(INT1);
  // Timer2: clear on compare match A every PERIOD_US.
  TCCR2A = _BV(WGM21);
  TCCR2B = 0;
  TCNT2 = 0;
  OCR2A = TICK_COUNTS - 1;
  TIFR2 = _BV(OCF2A);
  TIMSK2 = _BV(OCIE2A);
  TCCR2B = TICK_PRESCALE_BITS;
}

void loop() {
  // The sample first; then one command byte, so a tick waits at most one decode.
  if (sample_ready) send_sample();
  else if (Serial.available()) take_byte(Serial.read());
}
