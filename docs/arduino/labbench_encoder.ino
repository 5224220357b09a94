// labbench reference sketch: quadrature encoder stream (+ optional force output)
// for an Arduino Uno/Nano (ATmega328P, 16 MHz). Not built in CI.
//
// Protocol: docs/serial-protocol.md. Summary:
//   board -> host, every PERIOD_US:   COBS( 'S' | seq u16 | micros u32 | count i32 | status u8 | crc16 ) 0x00
//                   or, with LABBENCH_ASCII 1:   "<micros>,<count>\r\n"
//   host -> board, one per sample:   COBS( 'F' | seq u16 | force f32 | crc16 ) 0x00
// All fields little-endian; crc16 = CRC-16/CCITT-FALSE over the bytes before it.
//
// Timing: at tick k the board latches the newest command, sends sample k and
// drives the latched force during period k. The host's answer to sample k
// therefore acts in period k+1: one whole sample of extra delay (td = T).
// Watchdog: no valid command for 3 periods -> output zero, status bit 0.

#include <Arduino.h>

// ---- configuration ----------------------------------------------------------
#define LABBENCH_ASCII 0          // 1: "micros,count" lines, no command channel needed
#define BAUD 500000UL             // 16 bytes/sample at 1 kHz need >= 230400 baud
#define PERIOD_US 1000UL          // must equal the rig's sample_time_s
#define ENC_A 2                   // encoder channels on the two external-interrupt pins
#define ENC_B 3
#define PWM_PIN 9                 // force output: PWM magnitude + direction pin
#define DIR_PIN 8
#define PWM_PER_NEWTON 40.0f      // duty counts per newton at the handle: calibrate for your amplifier
#define WATCHDOG_PERIODS 3

// ---- encoder (4x quadrature decoding in both pin interrupts) ----------------
volatile int32_t enc_count = 0;
volatile uint8_t enc_state = 0;
// Index: previous AB << 2 | new AB; value: step (0 for no move or an invalid jump).
const int8_t QUAD_STEP[16] = {0, 1, -1, 0, -1, 0, 0, 1, 1, 0, 0, -1, 0, -1, 1, 0};

void on_edge() {
  uint8_t ab = (digitalRead(ENC_A) << 1) | digitalRead(ENC_B);
  enc_count += QUAD_STEP[(enc_state << 2) | ab];
  enc_state = ab;
}

// ---- CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) --------------------------
uint16_t crc16(const uint8_t *p, uint8_t n) {
  uint16_t crc = 0xFFFF;
  while (n--) {
    crc ^= (uint16_t)(*p++) << 8;
    for (uint8_t i = 0; i < 8; i++) crc = (crc & 0x8000) ? (crc << 1) ^ 0x1021 : crc << 1;
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
int cobs_decode(const uint8_t *in, uint8_t n, uint8_t *out) {
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

// ---- state ------------------------------------------------------------------
uint16_t seq = 0;
uint8_t status_bits = 0;            // bit 0: watchdog zeroed the output, bit 1: bad command
float latest_force = 0.0f;          // newest valid command [N at the handle]
uint16_t periods_since_command = 255;
// Command receiver: the last 10 bytes before a 0x00 (one COBS command frame);
// longer runs are garbage cut off the front, as the host does with samples.
#define CMD_FRAME_LEN 10
uint8_t rx[CMD_FRAME_LEN];
uint8_t rx_len = 0;
bool rx_garbage = false;
unsigned long next_tick;

void put_u16(uint8_t *p, uint16_t v) { p[0] = v; p[1] = v >> 8; }
void put_u32(uint8_t *p, uint32_t v) { for (uint8_t i = 0; i < 4; i++) p[i] = v >> (8 * i); }

void take_command_frame() {
  uint8_t payload[CMD_FRAME_LEN];
  if (rx_garbage) status_bits |= 0x02;
  int n = rx_len == CMD_FRAME_LEN ? cobs_decode(rx, rx_len, payload) : -1;
  if (n != 9 || payload[0] != 'F' || crc16(payload, 7) != (uint16_t)(payload[7] | (payload[8] << 8))) {
    if (rx_len) status_bits |= 0x02;
    return;
  }
  float f;
  memcpy(&f, payload + 3, 4);  // AVR float is IEEE-754 binary32, little-endian
  if (f == f) {                // not NaN
    latest_force = f;
    periods_since_command = 0;
  }
}

void poll_commands() {
  while (Serial.available()) {
    uint8_t b = Serial.read();
    if (b == 0) {
      take_command_frame();
      rx_len = 0;
      rx_garbage = false;
    } else {
      if (rx_len == CMD_FRAME_LEN) {  // keep the newest bytes only
        memmove(rx, rx + 1, CMD_FRAME_LEN - 1);
        rx_len--;
        rx_garbage = true;
      }
      rx[rx_len++] = b;
    }
  }
}

void drive(float force_n) {
  float duty = force_n * PWM_PER_NEWTON;
  digitalWrite(DIR_PIN, duty < 0);
  if (duty < 0) duty = -duty;
  analogWrite(PWM_PIN, duty > 255 ? 255 : (int)duty);
}

void send_sample(unsigned long t_us, int32_t count) {
#if LABBENCH_ASCII
  Serial.print(t_us);
  Serial.print(',');
  Serial.println(count);
#else
  uint8_t payload[14], frame[16];
  payload[0] = 'S';
  put_u16(payload + 1, seq);
  put_u32(payload + 3, t_us);
  put_u32(payload + 7, (uint32_t)count);
  payload[11] = status_bits;
  put_u16(payload + 12, crc16(payload, 12));
  uint8_t n = cobs_encode(payload, 14, frame);
  frame[n++] = 0;
  Serial.write(frame, n);
#endif
  status_bits = 0;  // each sample reports what happened since the previous one
}

void setup() {
  pinMode(ENC_A, INPUT_PULLUP);
  pinMode(ENC_B, INPUT_PULLUP);
  pinMode(DIR_PIN, OUTPUT);
  drive(0.0f);
  enc_state = (digitalRead(ENC_A) << 1) | digitalRead(ENC_B);
  attachInterrupt(digitalPinToInterrupt(ENC_A), on_edge, CHANGE);
  attachInterrupt(digitalPinToInterrupt(ENC_B), on_edge, CHANGE);
  Serial.begin(BAUD);
  Serial.print("#labbench encoder v1\r\n");
#if !LABBENCH_ASCII
  Serial.write((uint8_t)0);  // ends any frame the host's parser started on boot noise
#endif
  next_tick = micros() + PERIOD_US;
}

void loop() {
  poll_commands();
  if ((long)(micros() - next_tick) < 0) return;
  unsigned long t_us = next_tick;
  next_tick += PERIOD_US;

  // Latch the force for this period (the answer to the previous sample).
  if (periods_since_command < 255) periods_since_command++;
  float force = latest_force;
  if (periods_since_command > WATCHDOG_PERIODS) {
    force = 0.0f;
    status_bits |= 0x01;
  }
  drive(force);

  noInterrupts();
  int32_t count = enc_count;
  interrupts();
  send_sample(t_us, count);
  seq++;
}
