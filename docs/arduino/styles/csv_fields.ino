// labbench example sketch, style 3: CSV with a header and two extra fields,
// "<micros>,<count>,<counts per second>,<direction>" every PERIOD_US, scheduled on
// micros() (on the grid: each due time is the previous one plus the period).
// Rig: docs/arduino/styles/csv_fields.toml
//   (fields = ["micros", "count", "speed_cps", "direction"]).
// Encoder channels on pins 2 and 3 (both external interrupts, any edge).

#include <Arduino.h>

#ifndef BAUD
#define BAUD 250000UL
#endif
#ifndef PERIOD_US
#define PERIOD_US 5000UL
#endif

static volatile long count = 0;
static volatile uint8_t last = 0;

// Forward order of the (A, B) states: 0b00, 0b01, 0b11, 0b10.
static int8_t step_between(uint8_t from, uint8_t to) {
  if (from == to) return 0;
  static const uint8_t kNext[4] = {1, 3, 0, 2};  // the state after each one, going forward
  if (kNext[from] == to) return 1;
  if (kNext[to] == from) return -1;
  return 0;  // both channels changed: direction unknown
}

static void encoder_isr() {
  uint8_t pins = PIND;
  uint8_t now = ((pins & _BV(2)) ? 2 : 0) | ((pins & _BV(3)) ? 1 : 0);
  count += step_between(last, now);
  last = now;
}

void setup() {
  pinMode(2, INPUT_PULLUP);
  pinMode(3, INPUT_PULLUP);
  uint8_t pins = PIND;
  last = ((pins & _BV(2)) ? 2 : 0) | ((pins & _BV(3)) ? 1 : 0);
  attachInterrupt(digitalPinToInterrupt(2), encoder_isr, CHANGE);
  attachInterrupt(digitalPinToInterrupt(3), encoder_isr, CHANGE);
  Serial.begin(BAUD);
  Serial.println("t_us,count,speed_cps,dir");
}

void loop() {
  static unsigned long due = micros();
  static long previous = 0;
  unsigned long now = micros();
  if ((long)(now - due) < 0) return;
  due += PERIOD_US;
  noInterrupts();
  long c = count;
  interrupts();
  long speed = (c - previous) * (long)(1000000UL / PERIOD_US);
  previous = c;
  Serial.print(now);
  Serial.print(',');
  Serial.print(c);
  Serial.print(',');
  Serial.print(speed);
  Serial.print(',');
  Serial.println(speed > 0 ? 1 : speed < 0 ? -1 : 0);
}
