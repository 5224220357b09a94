// labbench example sketch, style 4: a 16-bit unsigned counter (unsigned int on the
// AVR: 0..65535, wrapping), "<micros>\t<count>" every PERIOD_US on a micros() grid.
// Rig: docs/arduino/styles/count16_unsigned.toml (count_bits = 16, count_signed = false).
// Encoder channels on pins 2 and 3, decoded by one pin-change interrupt on port D.

#include <Arduino.h>

#ifndef BAUD
#define BAUD 115200UL
#endif
#ifndef PERIOD_US
#define PERIOD_US 2000UL
#endif

static volatile unsigned int count = 0;  // 16 bits: wraps from 65535 to 0 and back
static volatile uint8_t prev = 0;

// Pin-change interrupt of PD2/PD3 (PCINT18, PCINT19).
ISR(PCINT2_vect) {
  uint8_t now = (PIND >> 2) & 0x03;  // bit 0: A (pin 2), bit 1: B (pin 3)
  uint8_t a = now & 1, b = (now >> 1) & 1;
  uint8_t changed = now ^ prev;
  prev = now;
  // B leads A going forward (AB: 00, 01, 11, 10): an edge of A is forward when A then
  // equals B, an edge of B when B then differs from A. Both at once: no step known.
  if (changed == 0x01) {
    if (a == b) count++; else count--;
  } else if (changed == 0x02) {
    if (b != a) count++; else count--;
  }
}

void setup() {
  pinMode(2, INPUT_PULLUP);
  pinMode(3, INPUT_PULLUP);
  prev = (PIND >> 2) & 0x03;
  PCICR |= _BV(PCIE2);
  PCMSK2 |= _BV(PCINT18) | _BV(PCINT19);
  Serial.begin(BAUD);
}

void loop() {
  static unsigned long due = micros();
  unsigned long now = micros();
  if ((long)(now - due) < 0) return;
  due += PERIOD_US;
  noInterrupts();
  unsigned int c = count;
  interrupts();
  Serial.print(now);
  Serial.print('\t');
  Serial.println(c);
}
