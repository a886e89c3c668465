// Frame decoding for docs/protocol.md. It follows the host's FrameDecoder
// (app/hardware/protocol.py) step for step, so both ends count garbage bytes and CRC
// errors the same way and resynchronise at the same place after a bad frame.
#pragma once

#include <stdint.h>
#include <string.h>
#include <util/crc16.h>

const uint8_t SYNC0 = 0xAA;
const uint8_t SYNC1 = 0x55;
const uint8_t MAX_PAYLOAD = 32;
const uint8_t HEADER_LEN = 5;                      // sync(2) + len + seq + type
const uint8_t FRAME_OVERHEAD = HEADER_LEN + 2;     // + crc16
const uint8_t MAX_FRAME = FRAME_OVERHEAD + MAX_PAYLOAD;

// CRC-16/CCITT-FALSE over len, seq, type, payload. avr-libc's xmodem update is the same
// unreflected polynomial 0x1021; CCITT-FALSE only starts from 0xFFFF instead of 0.
inline uint16_t crc16(const uint8_t *data, uint8_t n) {
  uint16_t crc = 0xFFFF;
  while (n--) crc = _crc_xmodem_update(crc, *data++);
  return crc;
}

class FrameDecoder {
 public:
  uint16_t crcErrors = 0;
  uint16_t garbageBytes = 0;

  // Append one received byte, then call next() until it returns false.
  void push(uint8_t byte) {
    if (frameReady_) consumeFrame();
    if (used_ == MAX_FRAME) {  // cannot happen when next() is drained; stay safe anyway
      garbageBytes++;
      drop(1);
    }
    buf_[used_++] = byte;
  }

  // True when a whole frame with a good CRC sits at the front of the buffer. Several
  // can come out of one byte: a bad frame's tail may hold complete good frames.
  bool next() {
    if (frameReady_) consumeFrame();
    for (;;) {
      uint8_t start = 0;
      while (start + 1 < used_ && !(buf_[start] == SYNC0 && buf_[start + 1] == SYNC1)) start++;
      if (start + 1 >= used_) {
        // No sync yet. Keep a trailing 0xAA: it may be the first half of one.
        uint8_t keep = (used_ > 0 && buf_[used_ - 1] == SYNC0) ? 1 : 0;
        garbageBytes += used_ - keep;
        drop(used_ - keep);
        return false;
      }
      if (start > 0) {
        garbageBytes += start;
        drop(start);
      }
      if (used_ < HEADER_LEN) return false;
      if (length() > MAX_PAYLOAD) {  // cannot be a frame: skip the sync and hunt on
        garbageBytes += 2;
        drop(2);
        continue;
      }
      uint8_t total = FRAME_OVERHEAD + length();
      if (used_ < total) return false;
      uint16_t crc = buf_[total - 2] | (buf_[total - 1] << 8);
      if (crc != crc16(buf_ + 2, 3 + length())) {
        // Resynchronise from just after this sync: a good frame may start inside.
        crcErrors++;
        drop(2);
        continue;
      }
      frameReady_ = true;
      return true;
    }
  }

  uint8_t length() const { return buf_[2]; }
  uint8_t seq() const { return buf_[3]; }
  uint8_t type() const { return buf_[4]; }
  const uint8_t *payload() const { return buf_ + HEADER_LEN; }

 private:
  uint8_t buf_[MAX_FRAME];
  uint8_t used_ = 0;
  bool frameReady_ = false;

  void consumeFrame() {
    frameReady_ = false;
    drop(FRAME_OVERHEAD + length());
  }

  void drop(uint8_t n) {
    used_ -= n;
    memmove(buf_, buf_ + n, used_);
  }
};
