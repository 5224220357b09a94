// labbench example sketch, style 1: the encoder count alone, one line each time it
// changes ("1234\r\n"), after a one-line banner. No time field, no fixed rate.
// Rig: docs/arduino/styles/count_on_change.toml (fields = ["count"], on_change = true).
// Encoder channels on pins 2 and 3 (both external interrupts, any edge).

#include <Arduino.h>

#ifndef BAUD
#define BAUD 115200UL
#endif

// Quadrature step by (previous AB << 2 | new AB), AB = pin 2 << 1 | pin 3:
// +1 along 00 -> 01 -> 11 -> 10 -> 00, -1 the other way, 0 for no or a double change.
static const int8_t kStep[16] = {0, 1, -1, 0, -1, 0, 0, 1, 1, 0, 0, -1, 0, -1, 1, 0};
static volatile long count = 0;
static volatile uint8_t ab = 0;

static uint8_t read_ab() {
  uint8_t pins = PIND;
  return ((pins >> 1) & 0x02) | ((pins >> 3) & 0x01);
}

static void edge() {
  uint8_t now = read_ab();
  count += kStep[(ab << 2) | now];
  ab = now;
}

void setup() {
  pinMode(2, INPUT_PULLUP);
  pinMode(3, INPUT_PULLUP);
  ab = read_ab();
  attachInterrupt(digitalPinToInterrupt(2), edge, CHANGE);
  attachInterrupt(digitalPinToInterrupt(3), edge, CHANGE);
  Serial.begin(BAUD);
  Serial.println("quadrature count on pins 2/3, printed on change");
}

void loop() {
  static long shown = 0;
  noInterrupts();
  long now = count;
  interrupts();
  if (now != shown) {
    shown = now;
    Serial.println(now);
  }
}
