// floornav_uno: motor controller firmware for floornav's Arduino Uno.
//
// Speaks the framed serial protocol of docs/protocol.md (version 1) at 115200 baud,
// drives two DC motors through an H-bridge (PWM + two direction pins each), counts
// wheel encoder pulses on the two external-interrupt pins, and stops the motors when
// no valid DRIVE arrived for 250 ms (the deadman). Wiring: firmware/README.md.

#include <util/atomic.h>

#include "frame_decoder.h"

// ---- wiring -----------------------------------------------------------------------
// PWM on Timer1 (pins 9, 10): Timer0 runs millis() and Timer2's pin 3 is an encoder.
const uint8_t PIN_LEFT_PWM = 9;
const uint8_t PIN_LEFT_IN1 = 7;
const uint8_t PIN_LEFT_IN2 = 8;
const uint8_t PIN_RIGHT_PWM = 10;
const uint8_t PIN_RIGHT_IN1 = 11;
const uint8_t PIN_RIGHT_IN2 = 12;
// Channel A of each encoder must be on an external-interrupt pin (2 = INT0, 3 = INT1).
const uint8_t PIN_LEFT_ENC_A = 2;
const uint8_t PIN_RIGHT_ENC_A = 3;
const uint8_t PIN_LEFT_ENC_B = 4;
const uint8_t PIN_RIGHT_ENC_B = 5;

// 1: quadrature encoders, channel B gives the direction. 0: single-channel encoders,
// the count follows the sign of the applied PWM instead.
#ifndef ENCODER_QUADRATURE
#define ENCODER_QUADRATURE 1
#endif

// ---- protocol constants (docs/protocol.md) -----------------------------------------
const uint8_t PROTOCOL_VERSION = 1;
const uint8_t MOTOR_COUNT = 2;
const char FIRMWARE_NAME[] = "floornav-fw 1.0.0";
const uint32_t DEADMAN_MS = 250;
const int16_t PWM_LIMIT = 255;

enum : uint8_t {
  MSG_HELLO = 0x01,
  MSG_DRIVE = 0x02,
  MSG_STOP = 0x03,
  MSG_PING = 0x04,
  MSG_SET_TELEMETRY = 0x05,
  MSG_RESET_COUNTERS = 0x06,
  MSG_BANNER = 0x81,
  MSG_ACK = 0x82,
  MSG_TELEMETRY = 0x83,
};
enum : uint8_t { ACK_OK = 0, ACK_BAD_ARGUMENT = 1, ACK_UNKNOWN_TYPE = 2 };
enum : uint8_t { FLAG_DEADMAN_TRIPPED = 0x01, FLAG_STOPPED = 0x02 };

// ---- state --------------------------------------------------------------------------
FrameDecoder decoder;
volatile int32_t encoderLeft = 0;   // written by the encoder interrupts: half counts
volatile int32_t encoderRight = 0;  // with quadrature (see encoderStep), else counts
int16_t appliedLeft = 0;            // what the H-bridge is being told right now
int16_t appliedRight = 0;
bool driving = false;               // a DRIVE is in force, so the deadman is armed
bool everDriven = false;
uint32_t lastDriveMs = 0;
uint8_t flags = 0;
uint16_t rxOverruns = 0;
uint16_t telemetryPeriodMs = 0;     // 0 = off
uint32_t lastTelemetryMs = 0;
uint8_t txSeq = 0;                  // seq of frames we send unprompted (telemetry)

// ---- motors -------------------------------------------------------------------------
void driveMotor(uint8_t pwmPin, uint8_t in1, uint8_t in2, int16_t pwm) {
  // Both direction pins low with zero duty lets the motor coast.
  digitalWrite(in1, pwm > 0 ? HIGH : LOW);
  digitalWrite(in2, pwm < 0 ? HIGH : LOW);
  analogWrite(pwmPin, pwm < 0 ? -pwm : pwm);
}

void setMotors(int16_t left, int16_t right) {
  appliedLeft = left;
  appliedRight = right;
  driveMotor(PIN_LEFT_PWM, PIN_LEFT_IN1, PIN_LEFT_IN2, left);
  driveMotor(PIN_RIGHT_PWM, PIN_RIGHT_IN1, PIN_RIGHT_IN2, right);
}

// ---- encoders -----------------------------------------------------------------------
// With quadrature, called on both edges of channel A: a half count forward when A and B
// differ just after the edge (A leads B), backward when they agree. Counting only A's
// rising edges, with B as the sign, gains a count each time a wheel turns back across
// that edge (backing up, a spin turn's reversal, a stopped wheel's jitter), since going
// back the wheel crosses a falling edge; both edges keep the count where the wheel is.
// Single channel: called on A's rising edge, the count follows the applied PWM's sign.
int8_t encoderStep(uint8_t pinA, uint8_t pinB, int16_t applied) {
#if ENCODER_QUADRATURE
  (void)applied;
  return digitalRead(pinA) != digitalRead(pinB) ? 1 : -1;
#else
  (void)pinA;
  (void)pinB;
  return applied < 0 ? -1 : 1;
#endif
}

void onLeftEncoder() {
  encoderLeft += encoderStep(PIN_LEFT_ENC_A, PIN_LEFT_ENC_B, appliedLeft);
}
void onRightEncoder() {
  encoderRight += encoderStep(PIN_RIGHT_ENC_A, PIN_RIGHT_ENC_B, appliedRight);
}

// Whole counts (one per cycle of A, as the host's ticks_per_rev counts them).
int32_t encoderCount(int32_t raw) {
#if ENCODER_QUADRATURE
  return raw >> 1;  // floor: half counts round towards minus infinity, both ways
#else
  return raw;
#endif
}

// ---- sending ------------------------------------------------------------------------
void put16(uint8_t *p, uint16_t v) {
  p[0] = v & 0xFF;
  p[1] = v >> 8;
}

void put32(uint8_t *p, uint32_t v) {
  put16(p, v & 0xFFFF);
  put16(p + 2, v >> 16);
}

void sendFrame(uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t len) {
  uint8_t frame[FRAME_OVERHEAD + MAX_PAYLOAD];
  frame[0] = SYNC0;
  frame[1] = SYNC1;
  frame[2] = len;
  frame[3] = seq;
  frame[4] = type;
  memcpy(frame + HEADER_LEN, payload, len);
  uint16_t crc = crc16(frame + 2, 3 + len);
  put16(frame + HEADER_LEN + len, crc);
  // One write call: it only blocks when the 64-byte transmit buffer is full.
  Serial.write(frame, FRAME_OVERHEAD + len);
}

void sendAck(uint8_t seq, uint8_t status) {
  uint8_t payload[2] = {seq, status};
  sendFrame(seq, MSG_ACK, payload, sizeof payload);
}

void sendBanner(uint8_t seq) {
  uint8_t payload[2 + sizeof FIRMWARE_NAME - 1];
  payload[0] = PROTOCOL_VERSION;
  payload[1] = MOTOR_COUNT;
  memcpy(payload + 2, FIRMWARE_NAME, sizeof FIRMWARE_NAME - 1);
  sendFrame(seq, MSG_BANNER, payload, sizeof payload);
}

void sendTelemetry(uint32_t now) {
  int32_t left, right;
  ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {  // 32-bit counts change inside interrupts
    left = encoderCount(encoderLeft);
    right = encoderCount(encoderRight);
  }
  uint32_t since = everDriven ? now - lastDriveMs : 0xFFFF;
  uint8_t p[25];
  put32(p + 0, now);
  put32(p + 4, left);
  put32(p + 8, right);
  put16(p + 12, appliedLeft);
  put16(p + 14, appliedRight);
  put16(p + 16, since > 0xFFFF ? 0xFFFF : since);
  put16(p + 18, decoder.crcErrors);
  put16(p + 20, decoder.garbageBytes);
  put16(p + 22, rxOverruns);
  p[24] = flags;
  sendFrame(txSeq++, MSG_TELEMETRY, p, sizeof p);
}

// ---- commands -----------------------------------------------------------------------
int16_t get16(const uint8_t *p) { return (int16_t)(p[0] | (p[1] << 8)); }

bool pwmValid(int16_t v) { return v >= -PWM_LIMIT && v <= PWM_LIMIT; }

// Runs one valid frame. Anything malformed gets BAD_ARGUMENT and changes nothing.
void handleFrame(uint8_t seq, uint8_t type, const uint8_t *p, uint8_t len) {
  switch (type) {
    case MSG_HELLO:
      sendBanner(seq);  // the banner is the reply; HELLO does not touch the deadman
      return;
    case MSG_DRIVE: {
      if (len != 4 || !pwmValid(get16(p)) || !pwmValid(get16(p + 2))) break;
      setMotors(get16(p), get16(p + 2));
      lastDriveMs = millis();
      driving = true;
      everDriven = true;
      flags = 0;
      sendAck(seq, ACK_OK);
      return;
    }
    case MSG_STOP:
      if (len != 0) break;
      setMotors(0, 0);
      driving = false;
      flags |= FLAG_STOPPED;
      sendAck(seq, ACK_OK);
      return;
    case MSG_PING:
      if (len != 0) break;
      sendAck(seq, ACK_OK);
      return;
    case MSG_SET_TELEMETRY: {
      if (len != 2) break;
      uint16_t period = (uint16_t)get16(p);
      if (period != 0 && (period < 20 || period > 1000)) break;
      telemetryPeriodMs = period;
      lastTelemetryMs = millis();
      sendAck(seq, ACK_OK);
      return;
    }
    case MSG_RESET_COUNTERS:
      if (len != 0) break;
      ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        encoderLeft = 0;
        encoderRight = 0;
      }
      decoder.crcErrors = 0;
      decoder.garbageBytes = 0;
      rxOverruns = 0;
      sendAck(seq, ACK_OK);
      return;
    default:
      // Unknown types are counted with the garbage: their bytes were not acted on.
      decoder.garbageBytes += FRAME_OVERHEAD + len;
      sendAck(seq, ACK_UNKNOWN_TYPE);
      return;
  }
  sendAck(seq, ACK_BAD_ARGUMENT);
}

// ---- main loop ----------------------------------------------------------------------
void readSerial() {
  // Read only what is there now, so a flood of input cannot starve the deadman check.
  int count = Serial.available();
  while (count-- > 0) {
    // HardwareSerial holds at most SERIAL_RX_BUFFER_SIZE - 1 bytes and silently drops
    // the rest, so finding it full is the only sign that bytes were (probably) lost.
    // Check before every byte: replies can block in Serial.write() while input piles up.
    if (Serial.available() >= SERIAL_RX_BUFFER_SIZE - 1) rxOverruns++;
    decoder.push(Serial.read());
    while (decoder.next()) {
      handleFrame(decoder.seq(), decoder.type(), decoder.payload(), decoder.length());
    }
  }
}

void setup() {
  // Motors off before anything else: the pins float (inputs) until here.
  pinMode(PIN_LEFT_IN1, OUTPUT);
  pinMode(PIN_LEFT_IN2, OUTPUT);
  pinMode(PIN_RIGHT_IN1, OUTPUT);
  pinMode(PIN_RIGHT_IN2, OUTPUT);
  pinMode(PIN_LEFT_PWM, OUTPUT);
  pinMode(PIN_RIGHT_PWM, OUTPUT);
  setMotors(0, 0);

  pinMode(PIN_LEFT_ENC_A, INPUT_PULLUP);
  pinMode(PIN_RIGHT_ENC_A, INPUT_PULLUP);
  pinMode(PIN_LEFT_ENC_B, INPUT_PULLUP);
  pinMode(PIN_RIGHT_ENC_B, INPUT_PULLUP);
#if ENCODER_QUADRATURE
  const int encoderEdges = CHANGE;
#else
  const int encoderEdges = RISING;
#endif
  attachInterrupt(digitalPinToInterrupt(PIN_LEFT_ENC_A), onLeftEncoder, encoderEdges);
  attachInterrupt(digitalPinToInterrupt(PIN_RIGHT_ENC_A), onRightEncoder, encoderEdges);

  Serial.begin(115200);
  sendBanner(0);
}

void loop() {
  readSerial();

  uint32_t now = millis();
  if (driving && now - lastDriveMs >= DEADMAN_MS) {
    setMotors(0, 0);
    driving = false;
    flags |= FLAG_DEADMAN_TRIPPED;
  }

  if (telemetryPeriodMs != 0 && now - lastTelemetryMs >= telemetryPeriodMs) {
    // Step by the period (not to `now`) so the rate does not drift; after a long stall
    // skip ahead instead of sending a burst.
    lastTelemetryMs += telemetryPeriodMs;
    if (now - lastTelemetryMs >= telemetryPeriodMs) lastTelemetryMs = now;
    sendTelemetry(now);
  }
}
