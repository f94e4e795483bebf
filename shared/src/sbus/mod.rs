//! SBUS: the 25-byte frame, and SBUS input as real receivers read it, each
//! modelled on its firmware's decoder (the file and function are named on
//! each [`SbusReceiver`] and each rule's constant).
//!
//! A frame is 25 bytes at 100 000 baud, 8E2 (12 bits, 120 us a byte): the
//! header 0x0F, 16 channels of 11 bits packed little-endian into bytes
//! 1..=22, the flags byte 23 and the end byte 0x00. The receivers agree on
//! that layout and differ in three things, each modelled here:
//!
//! - how a raw value maps to microseconds ([`SbusReceiver::read_ns`]; the
//!   encoder [`raw_for`] inverts it for one receiver);
//! - what they do with the header, the end byte and the flags
//!   ([`SbusReceiver::verdict`]);
//! - how they find frames in the byte stream, which sets the idle gap they
//!   need between frames ([`framing`]).
//!
//! Everything here is fixed-size and allocation-free, so it may run in the
//! real-time loop.
//!
//! - here: the frame ([`encode`], [`decode`]), the scaling and the checks.
//! - [`framing`]: each receiver's byte-stream framing, and the time it takes
//!   a frame.

pub mod framing;
pub mod timing;
pub mod uart;

#[cfg(test)]
mod tests;

pub use framing::{on_wire, Framer, Taken};

/// Bytes in a frame.
pub const FRAME_LEN: usize = 25;
/// The first byte of every frame.
pub const HEADER: u8 = 0x0F;
/// The last byte of an SBUS (not SBUS2) frame.
pub const END: u8 = 0x00;
/// Index of the flags byte.
pub const FLAGS_INDEX: usize = 23;
/// Proportional channels in a frame.
pub const CHANNELS: usize = 16;
/// Bits per channel.
pub const CHANNEL_BITS: u32 = 11;
/// The highest raw channel value.
pub const RAW_MAX: u16 = (1 << CHANNEL_BITS) - 1;
/// Bits on the wire per byte: start, 8 data, even parity, 2 stop.
pub const BYTE_BITS: u64 = 12;
/// The line rate, bits per second.
pub const BAUD: u64 = 100_000;
/// One byte on the wire (one character time), ns: 120 us.
pub const BYTE_NS: u64 = BYTE_BITS * 1_000_000_000 / BAUD;
/// One frame on the wire, sent back to back, ns: 3 ms.
pub const FRAME_WIRE_NS: u64 = FRAME_LEN as u64 * BYTE_NS;

/// The flags byte: the two digital channels and the receiver's link state.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct Flags {
    /// Channel 17 on (bit 0).
    pub ch17: bool,
    /// Channel 18 on (bit 1).
    pub ch18: bool,
    /// The transmitting receiver lost a radio frame (bit 2).
    pub frame_lost: bool,
    /// The transmitting receiver is in failsafe (bit 3).
    pub failsafe: bool,
}

impl Flags {
    const CH17: u8 = 1 << 0;
    const CH18: u8 = 1 << 1;
    const FRAME_LOST: u8 = 1 << 2;
    const FAILSAFE: u8 = 1 << 3;

    /// The flags byte, the upper four bits clear.
    pub fn to_byte(self) -> u8 {
        let bit = |on: bool, b: u8| if on { b } else { 0 };
        bit(self.ch17, Self::CH17)
            | bit(self.ch18, Self::CH18)
            | bit(self.frame_lost, Self::FRAME_LOST)
            | bit(self.failsafe, Self::FAILSAFE)
    }

    /// The flags of a flags byte; its upper four bits are ignored.
    pub fn from_byte(b: u8) -> Flags {
        Flags {
            ch17: b & Self::CH17 != 0,
            ch18: b & Self::CH18 != 0,
            frame_lost: b & Self::FRAME_LOST != 0,
            failsafe: b & Self::FAILSAFE != 0,
        }
    }
}

/// One frame: `raw` channel values (each clamped to [`RAW_MAX`], so no
/// value wraps into another) and `flags`, between [`HEADER`] and [`END`].
pub fn encode(raw: &[u16; CHANNELS], flags: Flags) -> [u8; FRAME_LEN] {
    let mut out = [0u8; FRAME_LEN];
    out[0] = HEADER;
    pack_channels(raw, &mut out[1..23]);
    out[FLAGS_INDEX] = flags.to_byte();
    out[FRAME_LEN - 1] = END;
    out
}

/// The raw channel values of `frame`, whatever its header and end byte.
pub fn channels(frame: &[u8; FRAME_LEN]) -> [u16; CHANNELS] {
    unpack_channels(&frame[1..23])
}

/// Packs 16 channels of 11 bits, least significant bit first, into the 22
/// bytes of `out` (the layout SBUS and CRSF's RC_CHANNELS_PACKED share);
/// each value is clamped to [`RAW_MAX`].
pub fn pack_channels(raw: &[u16; CHANNELS], out: &mut [u8]) {
    let mut acc: u32 = 0;
    let mut bits: u32 = 0;
    let mut at = 0;
    for &v in raw {
        acc |= u32::from(v.min(RAW_MAX)) << bits;
        bits += CHANNEL_BITS;
        while bits >= 8 {
            out[at] = acc as u8;
            at += 1;
            acc >>= 8;
            bits -= 8;
        }
    }
}

/// The 16 channels of 11 bits packed in the first 22 bytes of `bytes`
/// ([`pack_channels`]' layout).
pub fn unpack_channels(bytes: &[u8]) -> [u16; CHANNELS] {
    let mut raw = [0u16; CHANNELS];
    let mut acc: u32 = 0;
    let mut bits: u32 = 0;
    let mut at = 0;
    for v in &mut raw {
        while bits < CHANNEL_BITS {
            acc |= u32::from(bytes[at]) << bits;
            at += 1;
            bits += 8;
        }
        *v = (acc & u32::from(RAW_MAX)) as u16;
        acc >>= CHANNEL_BITS;
        bits -= CHANNEL_BITS;
    }
    raw
}

/// The channels and flags of a well-formed frame ([`HEADER`] first, [`END`]
/// last); `None` otherwise. Receivers check less or more:
/// [`SbusReceiver::verdict`].
pub fn decode(frame: &[u8; FRAME_LEN]) -> Option<([u16; CHANNELS], Flags)> {
    (frame[0] == HEADER && frame[FRAME_LEN - 1] == END)
        .then(|| (channels(frame), Flags::from_byte(frame[FLAGS_INDEX])))
}

/// A receiver whose SBUS input is modelled. The two Betaflight variants
/// read values and flags alike and differ only in framing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SbusReceiver {
    /// EdgeTX 2.11 and later, SBUS trainer input on an AUX serial port or
    /// the module bay (`radio/src/sbus.cpp`, `sbusFrameReceived` and
    /// `sbusProcessFrame`, identical from v2.11.0 to v2.12.2 and main
    /// e2bcbd6c): a frame is taken at the UART's idle-line interrupt with
    /// exactly 25 bytes buffered; header 0x0F and end byte exactly 0x00;
    /// a frame with the failsafe or the frame-lost flag is dropped;
    /// `(raw - 992) * 5 / 8` around 1500 us; channels 17 and 18 ignored.
    EdgeTx,
    /// Betaflight 2026.6.0-rc2 and later (`src/main/rx/sbus.c`,
    /// `sbusDataReceive`, commit 3dcb91beaa): a gap of more than 600 us
    /// between byte timestamps starts the hunt for a header, and bytes after
    /// a frame's 25th are ignored until then; the end byte
    /// is not checked; either flag is no signal (`sbus_channels.c`,
    /// `sbusChannelsDecode`, and `rx.c`); `5 * raw / 8 + 880` us; channels
    /// 17 and 18 read as raw 173 or 1812.
    Betaflight2026,
    /// Betaflight 4.5 (read at tag 4.5.5), 2025.12 and 2026.6.0-rc1
    /// (`src/main/rx/sbus.c`, `sbusDataReceive`): as [`Self::Betaflight2026`]
    /// but a byte more than 3500 us after the frame's header starts the hunt
    /// for a header.
    Betaflight45,
    /// ArduPilot (`libraries/AP_RCProtocol/AP_RCProtocol_SBUS.cpp`,
    /// `_process_byte` and `sbus_decode`): a header counts only 2000 us or
    /// more after the byte before it; the end byte is not checked; the
    /// failsafe flag is failsafe, the frame-lost flag alone is not, and so
    /// is a frame with channel 1, 2, 3 or 4 at 875 us or below (raw 0 or 1;
    /// PR 25169, 2023);
    /// `raw * 1000 / 1600 + 875` us in integers. See
    /// [`SbusReceiver::read_ns`] for an older float scaling, and
    /// [`SbusReceiver::digital_ns`] for channels 17 and 18.
    ArduPilot,
}

/// EdgeTX's raw centre, read as 1500 us (`sbus.cpp`, `SBUS_CH_CENTER`).
const EDGETX_CENTER_RAW: i32 = 0x3E0;
/// The microseconds EdgeTX's ±500 trainer units sit around (the µs
/// equivalent of its channel 0; `sbus.cpp` stores the offset only).
const EDGETX_CENTER_US: i32 = 1_500;
/// Betaflight's offset, us (`sbus_channels.c`, `sbusChannelsReadRawRC`).
const BETAFLIGHT_OFFSET_US: u64 = 880;
/// Betaflight's channels 17 and 18, raw (`sbus_channels.c`,
/// `SBUS_DIGITAL_CHANNEL_MIN` and `_MAX`).
const BETAFLIGHT_DIGITAL_RAW: [u16; 2] = [173, 1812];
/// ArduPilot's offset, us: `1000 - 1000 * 200 / 1600`
/// (`AP_RCProtocol_SBUS.cpp`, `SBUS_SCALE_OFFSET`).
const ARDUPILOT_OFFSET_US: u64 = 875;
/// ArduPilot's channels 17 and 18, us (`AP_RCProtocol_SBUS.cpp`,
/// `sbus_decode`).
const ARDUPILOT_DIGITAL_US: [u64; 2] = [998, 1_998];

/// ArduPilot takes a frame whose channels 1 to 4 include one at or below
/// [`ARDUPILOT_FAILSAFE_AT_NS`] as a failsafe frame
/// (`AP_RCProtocol_SBUS.cpp`, `sbus_decode`, since PR 25169).
pub const ARDUPILOT_FAILSAFE_CHANNELS: usize = 4;
/// See [`ARDUPILOT_FAILSAFE_CHANNELS`]: 875 us, raw 0 and 1.
pub const ARDUPILOT_FAILSAFE_AT_NS: u64 = 875 * US;

/// Nanoseconds per microsecond.
const US: u64 = 1_000;

impl SbusReceiver {
    /// Every modelled receiver.
    pub const ALL: [SbusReceiver; 4] = [
        SbusReceiver::EdgeTx,
        SbusReceiver::Betaflight2026,
        SbusReceiver::Betaflight45,
        SbusReceiver::ArduPilot,
    ];

    /// Its name in messages and reports.
    pub fn name(self) -> &'static str {
        match self {
            SbusReceiver::EdgeTx => "edgetx",
            SbusReceiver::Betaflight2026 => "betaflight 2026.6",
            SbusReceiver::Betaflight45 => "betaflight 4.5",
            SbusReceiver::ArduPilot => "ardupilot",
        }
    }

    /// What this receiver reads for a raw channel value (its low 11 bits),
    /// ns:
    ///
    /// - EdgeTX: `1500 + ((raw - 992) * 5 / 8)` us, the division truncating
    ///   toward zero as C's does: whole us, 880..=2159.
    /// - Betaflight: `5 * raw / 8 + 880` us in single-precision floats,
    ///   exact for every raw (multiples of 0.125 us): 880..=2159.375 us.
    /// - ArduPilot: `raw * 1000 / 1600 + 875` us in integers: whole us,
    ///   875..=2154. An older, PX4-derived version of the same file scales in
    ///   floats, `(uint16_t)(raw * 0.625 + 0.5) + 874`: the same value when
    ///   `raw % 8` is 1, 3, 4 or 6, 1 us lower for the other raws (192, 992
    ///   and 1792 read 994, 1494 and 1994 there, 995, 1495 and 1995 here).
    pub fn read_ns(self, raw: u16) -> u64 {
        let raw = raw & RAW_MAX;
        match self {
            SbusReceiver::EdgeTx => {
                // Rust's `/` on i32 truncates toward zero, as C's does.
                let offset = (i32::from(raw) - EDGETX_CENTER_RAW) * 5 / 8;
                (EDGETX_CENTER_US + offset) as u64 * US
            }
            SbusReceiver::Betaflight2026 | SbusReceiver::Betaflight45 => {
                // 5 * raw / 8 us is raw * 625 ns, exactly.
                u64::from(raw) * 625 + BETAFLIGHT_OFFSET_US * US
            }
            SbusReceiver::ArduPilot => (u64::from(raw) * 1_000 / 1_600 + ARDUPILOT_OFFSET_US) * US,
        }
    }

    /// What this receiver reads for a digital channel (17 or 18) that is
    /// `on`, ns: EdgeTX ignores them (`None`); Betaflight reads raw 1812 or
    /// 173 (2012.5 or 988.125 us); ArduPilot's `sbus_decode` gives 1998 or
    /// 998 us, but only to a caller asking for more than 17 values, and the
    /// versions of `_process_byte` read ask for 16: there they never reach
    /// the vehicle, and [`Reading::digital_ns`] is `None`.
    pub fn digital_ns(self, on: bool) -> Option<u64> {
        let i = usize::from(on);
        match self {
            SbusReceiver::EdgeTx => None,
            SbusReceiver::Betaflight2026 | SbusReceiver::Betaflight45 => {
                Some(self.read_ns(BETAFLIGHT_DIGITAL_RAW[i]))
            }
            SbusReceiver::ArduPilot => Some(ARDUPILOT_DIGITAL_US[i] * US),
        }
    }

    /// The lowest and highest value this receiver reads, ns.
    pub fn range_ns(self) -> (u64, u64) {
        (self.read_ns(0), self.read_ns(RAW_MAX))
    }

    /// What this receiver does with a frame its framing took.
    pub fn verdict(self, frame: &[u8; FRAME_LEN]) -> Verdict {
        let flags = Flags::from_byte(frame[FLAGS_INDEX]);
        // All check the header (Betaflight in its framing); only EdgeTX the
        // end byte (`sbusProcessFrame`).
        let end_ok = self != SbusReceiver::EdgeTx || frame[FRAME_LEN - 1] == END;
        if frame[0] != HEADER || !end_ok {
            return Verdict::Invalid;
        }
        match self {
            SbusReceiver::EdgeTx | SbusReceiver::Betaflight2026 | SbusReceiver::Betaflight45
                if flags.failsafe || flags.frame_lost =>
            {
                return Verdict::NoSignal;
            }
            SbusReceiver::ArduPilot if flags.failsafe => return Verdict::Failsafe,
            _ => {}
        }
        let raw = channels(frame);
        let mut channels_ns = [0u64; CHANNELS];
        for (ns, &r) in channels_ns.iter_mut().zip(&raw) {
            *ns = self.read_ns(r);
        }
        // ArduPilot (PR 25169, 2023): a frame whose channel 1 to 4 reads
        // 875 us or less (raw 0 or 1) is a receiver's failsafe frame.
        if self == SbusReceiver::ArduPilot
            && channels_ns[..ARDUPILOT_FAILSAFE_CHANNELS]
                .iter()
                .any(|&ns| ns <= ARDUPILOT_FAILSAFE_AT_NS)
        {
            return Verdict::Failsafe;
        }
        let digital_ns = match self {
            SbusReceiver::ArduPilot => None,
            _ => match (self.digital_ns(flags.ch17), self.digital_ns(flags.ch18)) {
                (Some(a), Some(b)) => Some([a, b]),
                _ => None,
            },
        };
        Verdict::Used(Reading {
            channels_ns,
            digital_ns,
        })
    }
}

/// Channel values a receiver uses, ns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Reading {
    /// Channels 1..=16.
    pub channels_ns: [u64; CHANNELS],
    /// Channels 17 and 18, where the receiver passes them on.
    pub digital_ns: Option<[u64; 2]>,
}

/// What a receiver does with a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// It uses these values.
    Used(Reading),
    /// It throws the frame away as malformed: a header other than 0x0F, or
    /// (EdgeTX) an end byte other than 0x00.
    Invalid,
    /// It throws the frame away for its flags as if none had come, and its
    /// own timeout decides when the link is lost: EdgeTX drops a frame with
    /// either flag without resetting its 1 s trainer timer; Betaflight
    /// marks either as `RX_FRAME_FAILSAFE` or `RX_FRAME_DROPPED`, both of
    /// which `rx.c` takes as no data received.
    NoSignal,
    /// It takes the frame as the receiver's failsafe: ArduPilot hands the
    /// values on with `in_failsafe` set (the failsafe flag, or channel 1 to
    /// 4 at 875 us or below), without counting them as new input, so its
    /// RC failsafe starts once `RC_FS_TIMEOUT` passes without any.
    Failsafe,
}

/// The raw value `receiver` reads closest to `ns` (a tie goes either way),
/// within 0..=[`RAW_MAX`]: exact for whole microseconds in the receiver's
/// range on EdgeTX and ArduPilot, within 0.3125 us on Betaflight.
///
/// Of the raws ArduPilot reads as one value, the highest, which its older
/// float scaling ([`SbusReceiver::read_ns`]) reads the same, except for
/// values that end in 4 or 9 us, which it reads 1 us lower.
pub fn raw_for(receiver: SbusReceiver, ns: u64) -> u16 {
    let (lo, hi) = receiver.range_ns();
    let ns = ns.clamp(lo, hi);
    match receiver {
        SbusReceiver::Betaflight2026 | SbusReceiver::Betaflight45 => ((ns - lo + 312) / 625) as u16,
        SbusReceiver::EdgeTx => {
            // The smallest |raw - 992| that reads the offset: EdgeTX's
            // truncation makes -1..=1 around the centre read 0.
            let us = ((ns + US / 2) / US).min(hi / US) as i32;
            let offset = us - EDGETX_CENTER_US;
            let steps = (offset.abs() * 8 + 4) / 5;
            (EDGETX_CENTER_RAW + offset.signum() * steps) as u16
        }
        SbusReceiver::ArduPilot => {
            let us = ((ns + US / 2) / US).min(hi / US);
            let t = us - ARDUPILOT_OFFSET_US;
            ((8 * t + 7) / 5).min(u64::from(RAW_MAX)) as u16
        }
    }
}

/// A frame of channel values in ns, each encoded with [`raw_for`] for
/// `receiver`, and `flags`.
pub fn encode_ns(
    receiver: SbusReceiver,
    channels_ns: &[u64; CHANNELS],
    flags: Flags,
) -> [u8; FRAME_LEN] {
    let mut raw = [0u16; CHANNELS];
    for (r, &ns) in raw.iter_mut().zip(channels_ns) {
        *r = raw_for(receiver, ns);
    }
    encode(&raw, flags)
}
