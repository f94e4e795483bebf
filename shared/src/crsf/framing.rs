//! How each firmware finds frames in the byte stream, and which it takes.
//!
//! A [`Framer`] is fed each byte with the time its stop bit ends (the
//! receive interrupt's time) and returns the frames the firmware takes, with
//! the time it takes them; the firmware's microsecond clock is that time
//! truncated to whole microseconds. A frame is taken when its framing and
//! its CRC check pass as the firmware checks them; what the firmware then
//! does with it is [`CrsfReceiver::verdict`].
//!
//! Each firmware keeps one frame buffer that the next frame overwrites, and
//! reads an RC frame's channels from it through a fixed struct: a taken
//! frame carries the whole buffer, stale bytes after its end included.
//!
//! Not modelled: iNav hands a frame from its receive interrupt to its RX
//! task through one flag that the next byte clears, so a frame whose
//! successor starts before the task polls is lost there; ArduPilot reads its
//! UART from a thread, so its byte times are when that thread runs.

use super::receiver::CrsfReceiver;
use super::{
    crc8, ADDRESS_FLIGHT_CONTROLLER, BAUD, BYTE_BITS, MAX_FRAME_LEN, MAX_LEN_FIELD, MIN_LEN_FIELD,
    RC_PAYLOAD_LEN, TYPE_LINK_STATISTICS, TYPE_RC_CHANNELS_PACKED,
};
use crate::crsf::link::LinkStatistics;

/// Nanoseconds per microsecond.
const US: u64 = 1_000;

/// Betaflight 2026.6: a byte more than this after the frame's first byte
/// starts a new frame (`crsf.c`, `CRSF_TIME_NEEDED_PER_FRAME_US`, at 420 000
/// baud; 1750 in 4.3 to 2025.12).
pub const BETAFLIGHT_FRAME_TIMEOUT_US: u64 = 1_748;
/// iNav: as [`BETAFLIGHT_FRAME_TIMEOUT_US`] (`crsf.c`,
/// `CRSF_TIME_NEEDED_PER_FRAME_US`).
pub const INAV_FRAME_TIMEOUT_US: u64 = 1_750;
/// ArduPilot: a byte more than this after the frame's first byte starts a
/// new frame (`AP_RCProtocol_CRSF.cpp`, `CRSF_FRAME_TIMEOUT_US`; 2000 us in
/// versions before `check_frame`).
pub const ARDUPILOT_FRAME_TIMEOUT_US: u64 = 50_000;

/// One byte on the wire at [`BAUD`], ns, fractional: the end of byte `i`
/// (from 0) of a stream sent back to back from `start_ns`.
pub fn byte_end_ns(start_ns: u64, i: usize) -> u64 {
    start_ns + (i as u64 + 1) * BYTE_BITS * 1_000_000_000 / BAUD
}

/// The bytes of `frame` sent back to back from `start_ns`, each with the
/// time its stop bit ends: 23.8 us a byte, 619 us for an RC frame.
pub fn on_wire<const N: usize>(frame: &[u8; N], start_ns: u64) -> [(u8, u64); N] {
    let mut out = [(0u8, 0u64); N];
    for (i, (o, &b)) in out.iter_mut().zip(frame).enumerate() {
        *o = (b, byte_end_ns(start_ns, i));
    }
    out
}

/// A frame a firmware's framing took.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Taken {
    /// When it was taken (its last byte's end), ns.
    pub at_ns: u64,
    /// The firmware's frame buffer: the frame, then whatever an earlier,
    /// longer frame left there.
    pub bytes: [u8; MAX_FRAME_LEN],
    /// Bytes of the frame: its `len` field plus 2.
    pub len: usize,
}

impl Taken {
    /// The frame's own bytes.
    pub fn frame(&self) -> &[u8] {
        &self.bytes[..self.len]
    }
}

/// One firmware's byte-stream framing: feed bytes in time order with
/// [`Framer::push`].
#[derive(Debug, Clone)]
pub struct Framer {
    receiver: CrsfReceiver,
    buf: [u8; MAX_FRAME_LEN],
    /// Bytes of the frame in progress.
    pos: usize,
    /// The frame's first byte, us (0 at start, as the firmware's static).
    start_us: u64,
}

impl Framer {
    /// A firmware that has seen nothing yet.
    pub fn new(receiver: CrsfReceiver) -> Framer {
        Framer {
            receiver,
            buf: [0; MAX_FRAME_LEN],
            pos: 0,
            start_us: 0,
        }
    }

    /// The firmware modelled.
    pub fn receiver(&self) -> CrsfReceiver {
        self.receiver
    }

    /// Feeds one byte whose stop bit ends at `end_ns`; returns the frame the
    /// firmware takes with it, if any.
    pub fn push(&mut self, byte: u8, end_ns: u64) -> Option<Taken> {
        let now_us = end_ns / US;
        match self.receiver {
            CrsfReceiver::Betaflight => self.betaflight(byte, now_us, end_ns),
            CrsfReceiver::Inav => self.inav(byte, now_us, end_ns),
            CrsfReceiver::ArduPilot => self.ardupilot(byte, now_us, end_ns),
        }
    }

    fn taken(&self, at_ns: u64, len: usize) -> Taken {
        Taken {
            at_ns,
            bytes: self.buf,
            len,
        }
    }

    /// The CRC the firmware computes: type, then `len - 2` payload bytes.
    fn crc(&self) -> u8 {
        let len = usize::from(self.buf[1]);
        crc8(&self.buf[2..(len + 1).clamp(3, MAX_FRAME_LEN)])
    }

    /// Betaflight's `crsfDataReceive` (2026.6.1).
    fn betaflight(&mut self, byte: u8, now_us: u64, end_ns: u64) -> Option<Taken> {
        if now_us.saturating_sub(self.start_us) > BETAFLIGHT_FRAME_TIMEOUT_US {
            self.pos = 0;
        }
        if self.pos == 0 {
            self.start_us = now_us;
        }
        // `crsfFrameLengthIsValid`, at the third byte, which is dropped.
        if self.pos == 2 && !(MIN_LEN_FIELD..=MAX_LEN_FIELD).contains(&self.buf[1]) {
            self.pos = 0;
            return None;
        }
        let full = if self.pos < 3 {
            5
        } else {
            usize::from(self.buf[1]) + 2
        };
        if self.pos >= full {
            return None;
        }
        self.buf[self.pos] = byte;
        self.pos += 1;
        if self.pos < full {
            return None;
        }
        self.pos = 0;
        (self.crc() == self.buf[full - 1]).then(|| self.taken(end_ns, full))
    }

    /// iNav's `crsfDataReceive` and, for RC and link statistics frames, the
    /// CRC check of `crsfFrameStatus`.
    fn inav(&mut self, byte: u8, now_us: u64, end_ns: u64) -> Option<Taken> {
        if now_us.saturating_sub(self.start_us) > INAV_FRAME_TIMEOUT_US {
            self.pos = 0;
        }
        if self.pos == 0 {
            self.start_us = now_us;
        }
        let full = if self.pos < 3 {
            5
        } else {
            usize::from(self.buf[1]) + 2
        };
        if full > MAX_FRAME_LEN {
            self.pos = 0;
            return None;
        }
        if self.pos >= full {
            return None;
        }
        self.buf[self.pos] = byte;
        self.pos += 1;
        if self.pos < full {
            return None;
        }
        self.pos = 0;
        // `crsfFrameStatus` compares an RC frame's CRC with the byte after
        // 22 payload bytes, and link statistics' with the byte after 10,
        // whatever `len` says; other frames with their last byte.
        let at = match self.buf[2] {
            TYPE_RC_CHANNELS_PACKED => 3 + RC_PAYLOAD_LEN,
            TYPE_LINK_STATISTICS => 3 + LinkStatistics::PAYLOAD_LEN,
            _ => full - 1,
        };
        (self.crc() == self.buf[at]).then(|| self.taken(end_ns, full))
    }

    /// ArduPilot's `_process_byte`, `check_frame` and `skip_to_next_frame`.
    fn ardupilot(&mut self, byte: u8, now_us: u64, end_ns: u64) -> Option<Taken> {
        if self.pos >= MAX_FRAME_LEN {
            self.pos = 0;
        }
        if self.pos > 0 && now_us.saturating_sub(self.start_us) > ARDUPILOT_FRAME_TIMEOUT_US {
            self.pos = 0;
        }
        if self.pos == 0 {
            self.start_us = now_us;
        }
        self.buf[self.pos] = byte;
        self.pos += 1;
        match self.ardupilot_check(end_ns) {
            Ok(taken) => taken,
            Err(()) => self.ardupilot_skip(now_us, end_ns),
        }
    }

    /// `check_frame`: `Err` when the buffer cannot start a frame, else the
    /// frame it completes, which leaves the buffer.
    fn ardupilot_check(&mut self, end_ns: u64) -> Result<Option<Taken>, ()> {
        if self.pos >= MAX_FRAME_LEN {
            return Err(());
        }
        if self.pos < 3 {
            return Ok(None);
        }
        let len = self.buf[1];
        if self.buf[0] != ADDRESS_FLIGHT_CONTROLLER
            || !(MIN_LEN_FIELD..=MAX_LEN_FIELD).contains(&len)
        {
            return Err(());
        }
        let full = usize::from(len) + 2;
        if self.pos < full {
            return Ok(None);
        }
        if self.crc() != self.buf[full - 1] {
            return Err(());
        }
        let taken = self.taken(end_ns, full);
        self.buf.copy_within(full..self.pos, 0);
        self.pos -= full;
        Ok(Some(taken))
    }

    /// `skip_to_next_frame`: drop bytes up to the next 0xC8 after the first,
    /// or all of them, and check once more.
    fn ardupilot_skip(&mut self, now_us: u64, end_ns: u64) -> Option<Taken> {
        if self.pos <= 1 {
            return None;
        }
        let Some(at) = self.buf[1..self.pos]
            .iter()
            .position(|&b| b == ADDRESS_FLIGHT_CONTROLLER)
        else {
            self.pos = 0;
            return None;
        };
        let at = at + 1;
        self.buf.copy_within(at..self.pos, 0);
        self.pos -= at;
        self.start_us = now_us;
        self.ardupilot_check(end_ns).ok().flatten()
    }
}
