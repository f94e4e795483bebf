//! How each receiver finds frames in the byte stream, and when it takes one.
//!
//! A [`Framer`] is fed each byte with the time its last stop bit ends (the
//! receive interrupt's time) and returns the frames the receiver takes, with
//! the time it takes them. The firmware's microsecond clocks are modelled as
//! that time truncated to whole microseconds. What a receiver then does with
//! a taken frame is [`SbusReceiver::verdict`].
//!
//! [`SbusReceiver::min_gap_ns`] is the idle each needs between frames sent
//! back to back.

use super::{SbusReceiver, BYTE_NS, FRAME_LEN, FRAME_WIRE_NS, HEADER};

/// Nanoseconds per microsecond.
const US: u64 = 1_000;

/// EdgeTX takes a frame at the UART's idle-line interrupt, which an STM32
/// USART raises after one character time of idle line
/// (`stm32_usart_driver.cpp`, `stm32_usart_isr`, calls the idle callback
/// that `serial.cpp` (AUX port) and `trainer.cpp` (module bay) set to
/// `sbus.cpp`'s `sbusFrameReceived`). The line counts as idle from this long
/// after a stop bit's end to the next start bit, that instant included.
pub const EDGETX_IDLE_NS: u64 = BYTE_NS;

/// Betaflight 2026.6.0-rc2 and later: a gap between byte timestamps of more
/// than this starts the hunt for a header (`sbus.c`,
/// `SBUS_INTERBYTE_TIMEOUT_US`, `5 * SBUS_TIME_NEEDED_PER_BYTE` = 5 * 3000 / 25).
pub const BETAFLIGHT_INTERBYTE_TIMEOUT_US: u64 = 600;

/// Betaflight 4.5, 2025.12 and 2026.6.0-rc1: a byte more than this after the
/// frame's header starts the hunt for a header (`sbus.c`, `sbusDataReceive`,
/// `SBUS_TIME_NEEDED_PER_FRAME + 500`).
pub const BETAFLIGHT45_FRAME_TIMEOUT_US: u64 = 3_500;

/// ArduPilot: a gap between byte timestamps of at least this starts a new
/// frame, and a header counts only after one (`AP_RCProtocol_SBUS.cpp`,
/// `HAL_SBUS_FRAME_GAP`; 4000 for a few weeks in 2022, PR 19899, reverted
/// by PR 20044).
pub const ARDUPILOT_FRAME_GAP_US: u64 = 2_000;

impl SbusReceiver {
    /// The shortest idle line, ns, between the last byte of one frame and
    /// the header of the next (stop bit end to start bit) with which this
    /// receiver takes every frame of a back-to-back stream. A whole number
    /// of microseconds, so it holds at any phase of the receiver's clock.
    ///
    /// - EdgeTX: one character time, [`EDGETX_IDLE_NS`] (120 us).
    /// - Betaflight 2026.6: byte timestamps more than 600 us apart: 481 us.
    /// - Betaflight 4.5: headers more than 3500 us apart, frames of 3 ms:
    ///   501 us.
    /// - ArduPilot: byte timestamps 2000 us apart: 1880 us. On a UART it
    ///   timestamps bytes when its RC thread reads them, about every 1 ms,
    ///   which this model does not include.
    pub fn min_gap_ns(self) -> u64 {
        match self {
            SbusReceiver::EdgeTx => EDGETX_IDLE_NS,
            SbusReceiver::Betaflight2026 => (BETAFLIGHT_INTERBYTE_TIMEOUT_US + 1) * US - BYTE_NS,
            SbusReceiver::Betaflight45 => (BETAFLIGHT45_FRAME_TIMEOUT_US + 1) * US - FRAME_WIRE_NS,
            SbusReceiver::ArduPilot => ARDUPILOT_FRAME_GAP_US * US - BYTE_NS,
        }
    }
}

/// A frame a receiver's framing took.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Taken {
    /// When it was taken, ns: EdgeTX one character time after its last
    /// byte, the others at its last byte.
    pub at_ns: u64,
    /// Its bytes.
    pub frame: [u8; FRAME_LEN],
}

/// The bytes of `frame` sent back to back from `start_ns`, each with the
/// time its last stop bit ends.
pub fn on_wire(frame: &[u8; FRAME_LEN], start_ns: u64) -> [(u8, u64); FRAME_LEN] {
    let mut out = [(0u8, 0u64); FRAME_LEN];
    for (i, (o, &b)) in out.iter_mut().zip(frame).enumerate() {
        *o = (b, start_ns + (i as u64 + 1) * BYTE_NS);
    }
    out
}

/// One receiver's byte-stream framing: feed bytes in time order with
/// [`Framer::push`], and the idle line with [`Framer::idle`].
#[derive(Debug, Clone)]
pub struct Framer {
    receiver: SbusReceiver,
    buf: [u8; FRAME_LEN],
    /// Bytes of the frame in progress (EdgeTX: bytes buffered since the last
    /// idle, which may pass 25).
    pos: usize,
    /// End of the previous byte, ns.
    last_end_ns: Option<u64>,
    /// Betaflight 4.5: its header's timestamp, us (0 at start, as the
    /// firmware's static).
    start_us: u64,
}

impl Framer {
    /// A receiver that has seen nothing yet.
    pub fn new(receiver: SbusReceiver) -> Framer {
        Framer {
            receiver,
            buf: [0; FRAME_LEN],
            pos: 0,
            last_end_ns: None,
            start_us: 0,
        }
    }

    /// The receiver modelled.
    pub fn receiver(&self) -> SbusReceiver {
        self.receiver
    }

    /// Feeds one byte whose last stop bit ends at `end_ns`; returns the
    /// frame the receiver takes, if any (EdgeTX: the frame before an idle
    /// line that ended before this byte started).
    pub fn push(&mut self, byte: u8, end_ns: u64) -> Option<Taken> {
        let last = self.last_end_ns.replace(end_ns);
        let now_us = end_ns / US;
        let last_us = last.map(|l| l / US);
        match self.receiver {
            SbusReceiver::EdgeTx => {
                let taken = last.and_then(|l| {
                    let idle_at = l + EDGETX_IDLE_NS;
                    (end_ns.saturating_sub(BYTE_NS) >= idle_at)
                        .then(|| self.edgetx_idle(idle_at))
                        .flatten()
                });
                if self.pos < FRAME_LEN {
                    self.buf[self.pos] = byte;
                }
                self.pos += 1;
                taken
            }
            SbusReceiver::Betaflight2026 => {
                // No byte before: the firmware's first interval is from 0,
                // which is long past.
                let gap = last_us.is_none_or(|l| now_us - l > BETAFLIGHT_INTERBYTE_TIMEOUT_US);
                if gap {
                    self.pos = 0;
                }
                self.betaflight_store(byte, end_ns)
            }
            SbusReceiver::Betaflight45 => {
                if now_us.saturating_sub(self.start_us) > BETAFLIGHT45_FRAME_TIMEOUT_US {
                    self.pos = 0;
                }
                if self.pos == 0 && byte == HEADER {
                    self.start_us = now_us;
                }
                self.betaflight_store(byte, end_ns)
            }
            SbusReceiver::ArduPilot => {
                let gap = last_us.is_none_or(|l| now_us - l >= ARDUPILOT_FRAME_GAP_US);
                if gap {
                    self.pos = 0;
                }
                if self.pos == 0 && (byte != HEADER || !gap) {
                    return None;
                }
                self.buf[self.pos] = byte;
                self.pos += 1;
                (self.pos == FRAME_LEN).then(|| {
                    self.pos = 0;
                    Taken {
                        at_ns: end_ns,
                        frame: self.buf,
                    }
                })
            }
        }
    }

    /// The line has been idle from the last byte up to `now_ns`: EdgeTX
    /// takes or clears its buffer once one character time has passed; the
    /// others wait for the next byte.
    pub fn idle(&mut self, now_ns: u64) -> Option<Taken> {
        let idle_at = self.last_end_ns? + EDGETX_IDLE_NS;
        if self.receiver != SbusReceiver::EdgeTx || now_ns < idle_at {
            return None;
        }
        self.edgetx_idle(idle_at)
    }

    /// EdgeTX's idle interrupt: a frame when exactly 25 bytes are buffered;
    /// the buffer is emptied either way (`sbusFrameReceived`).
    fn edgetx_idle(&mut self, at_ns: u64) -> Option<Taken> {
        let n = std::mem::take(&mut self.pos);
        (n == FRAME_LEN).then_some(Taken {
            at_ns,
            frame: self.buf,
        })
    }

    /// Betaflight: a frame starts only with a header, and bytes after the
    /// 25th are dropped until the position is reset.
    fn betaflight_store(&mut self, byte: u8, end_ns: u64) -> Option<Taken> {
        if self.pos == 0 && byte != HEADER {
            return None;
        }
        if self.pos >= FRAME_LEN {
            return None;
        }
        self.buf[self.pos] = byte;
        self.pos += 1;
        (self.pos == FRAME_LEN).then_some(Taken {
            at_ns: end_ns,
            frame: self.buf,
        })
    }
}
