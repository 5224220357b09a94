// labbench example sketch, style 2: "<millis> <count>" every PERIOD_MS, scheduled on
// millis(). Timer0 makes millis() advance in 1.024 ms steps (twice 1 ms now and
// then), so the lines come 9.2 to 10.24 ms apart around a 10 ms mean.
// Rig: docs/arduino/styles/millis_count.toml (fields = ["millis", "count"]).
// Encoder channels on pins 2 and 3 (both external interrupts, any edge).

#include <Arduino.h>

#ifndef BAUD
#define BAUD 115200UL
#endif
#ifndef PERIOD_MS
#define PERIOD_MS 10UL
#endif

static volatile long count = 0;
static volatile uint8_t state = 0;  // A << 1 | B as last seen

// One edge on either channel: forward is 00 -> 01 -> 11 -> 10 (B leads A).
static void on_edge() {
  uint8_t a = (PIND >> 2) & 1, b = (PIND >> 3) & 1;
  uint8_t now = (a << 1) | b;
  uint8_t was = state;
  state = now;
  if (now == was) return;
  // Gray code to position 0..3 along the forward cycle, then the shortest step.
  static const uint8_t kPhase[4] = {0, 1, 3, 2};
  int8_t d = (int8_t)((kPhase[now] - kPhase[was]) & 3);
  if (d == 1) count++;
  else if (d == 3) count--;
}

void setup() {
  pinMode(2, INPUT_PULLUP);
  pinMode(3, INPUT_PULLUP);
  state = ((PIND >> 1) & 0x02) | ((PIND >> 3) & 0x01);
  attachInterrupt(digitalPinToInterrupt(2), on_edge, CHANGE);
  attachInterrupt(digitalPinToInterrupt(3), on_edge, CHANGE);
  Serial.begin(BAUD);
}

void loop() {
  static unsigned long due = 0;
  unsigned long now = millis();
  if ((long)(now - due) < 0) return;
  due += PERIOD_MS;
  noInterrupts();
  long c = count;
  interrupts();
  Serial.print(now);
  Serial.print(' ');
  Serial.println(c);
}
