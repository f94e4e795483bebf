//! What each flight-controller firmware reads from an RC frame: its raw to
//! microseconds conversion ([`CrsfReceiver::read_ns`]), the raw value that
//! reads closest to a wanted value ([`raw_for`]), and what it does with a
//! frame its framing took ([`CrsfReceiver::verdict`]).

use super::framing::Taken;
use super::link::LinkStatistics;
use super::{
    encode_rc, rc_channels, ADDRESS_FLIGHT_CONTROLLER, CHANNELS, RAW_MAX, RC_FRAME_LEN,
    RC_PAYLOAD_LEN, TYPE_LINK_STATISTICS, TYPE_RC_CHANNELS_PACKED,
};

/// Nanoseconds per microsecond.
const US: u64 = 1_000;

/// A flight-controller firmware whose CRSF input is modelled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CrsfReceiver {
    /// Betaflight 2026.6 (`src/main/rx/crsf.c` at 2026.6.1 and master
    /// 301d01ab): `crsfDataReceive` frames the bytes (a byte more than
    /// 1748 us after a frame's first byte starts a new frame; a `len` outside
    /// 2..=62 drops the frame at its third byte; any first byte), checks the
    /// CRC, and takes an RC frame only at address 0xC8; `crsfReadRawRC`
    /// reads `0.62477120195241f * raw + 881` us in single-precision floats,
    /// and the float is what `rx.c` uses. Betaflight 4.3 to 2025.12 read the
    /// same values and frame alike, but wait 1750 us and check `len` only
    /// against the buffer's size.
    Betaflight,
    /// iNav (`src/main/rx/crsf.c`, master 0223685a): `crsfDataReceive`
    /// frames as Betaflight 4.5 does (1750 us; a frame whose `len + 2`
    /// exceeds 64 is dropped at its fourth byte); for an RC frame
    /// `crsfFrameStatus` checks the CRC of `len - 2` payload bytes against
    /// the byte after the 22nd, whatever `len` says, and no address;
    /// `crsfReadRawRC` reads `raw * 1024 / 1639 + 881` us in integers.
    Inav,
    /// ArduPilot (`libraries/AP_RCProtocol/AP_RCProtocol_CRSF.cpp`, master
    /// with `check_frame` and `skip_to_next_frame`): a frame must start with
    /// 0xC8 and have `len` 2..=62 and fewer than 64 bytes in all, else it
    /// skips to the next 0xC8 it has buffered; 50 ms from a frame's first
    /// byte restarts; the CRC must hold; `decode_11bit_channels(.., 5, 8,
    /// 880)` reads `raw * 5 / 8 + 880` us in integers (the newer
    /// `AP_CRSF_Protocol::decode_11bit_channels`, `(raw - 992) * 5 / 8 +
    /// 1500` in unsigned 32-bit arithmetic cast to 16 bits, reads the same
    /// for every raw).
    ArduPilot,
}

/// Betaflight's scale, exactly the single-precision float the firmware
/// multiplies by (`rx/crsf.h`, `CRSF_RC_CHANNEL_SCALE_LEGACY`).
const BETAFLIGHT_SCALE: f32 = 0.624_771_2;
/// Betaflight's offset, us (`crsfReadRawRC`).
const BETAFLIGHT_OFFSET_US: f32 = 881.0;
/// iNav's `raw * 1024 / 1639 + 881` (`crsfReadRawRC`).
const INAV_MUL: u64 = 1_024;
/// See [`INAV_MUL`].
const INAV_DIV: u64 = 1_639;
/// See [`INAV_MUL`].
const INAV_OFFSET_US: u64 = 881;
/// ArduPilot's `raw * 5 / 8 + 880` (`decode_crsf_packet`).
const ARDUPILOT_MUL: u64 = 5;
/// See [`ARDUPILOT_MUL`].
const ARDUPILOT_DIV: u64 = 8;
/// See [`ARDUPILOT_MUL`].
const ARDUPILOT_OFFSET_US: u64 = 880;

/// The raw value the TBS mapping the firmware conversions approximate
/// (172 -> 988 us, 992 -> 1500 us, 1811 -> 2012 us) puts nearest `ns`.
fn nominal_raw(ns: u64) -> u16 {
    let raw = ((ns as f64 / 1_000.0 - 880.539_353_264_185_5) / 0.624_771_201_952_41).round();
    raw.clamp(0.0, f64::from(RAW_MAX)) as u16
}

/// The raw in 0..=[`RAW_MAX`] near [`nominal_raw`] that `key` ranks first:
/// the firmware conversions stay within 1.5 us (three raws) of the nominal
/// mapping, so the best raw lies within the window searched.
fn best_raw<K: Ord>(ns: u64, key: impl Fn(u16) -> K) -> u16 {
    let estimate = nominal_raw(ns);
    let lo = estimate.saturating_sub(6);
    let hi = (estimate + 6).min(RAW_MAX);
    (lo..=hi).min_by_key(|&raw| key(raw)).unwrap_or(estimate)
}

/// How far each modelled firmware reads `raw` from `ns`: the largest, then
/// the sum.
fn spread_ns(raw: u16, ns: u64) -> (u64, u64) {
    CrsfReceiver::ALL
        .iter()
        .map(|r| r.read_ns(raw).abs_diff(ns))
        .fold((0, 0), |(max, sum), e| (max.max(e), sum.saturating_add(e)))
}

impl CrsfReceiver {
    /// Every modelled firmware.
    pub const ALL: [CrsfReceiver; 3] = [
        CrsfReceiver::Betaflight,
        CrsfReceiver::Inav,
        CrsfReceiver::ArduPilot,
    ];

    /// Its name in messages and reports.
    pub fn name(self) -> &'static str {
        match self {
            CrsfReceiver::Betaflight => "betaflight",
            CrsfReceiver::Inav => "inav",
            CrsfReceiver::ArduPilot => "ardupilot",
        }
    }

    /// What this firmware reads for a raw channel value (its low 11 bits),
    /// ns:
    ///
    /// - Betaflight: `0.62477120195241f * raw + 881` us in single-precision
    ///   floats (each product and sum rounded, as an FPU without fused
    ///   multiply-add computes it; a fused one differs by at most 0.2 ns),
    ///   rounded to the nearest ns: 881..=2159.907 us, steps of 0.6248 us.
    /// - iNav: `raw * 1024 / 1639 + 881` us in integers: whole us,
    ///   881..=2159.
    /// - ArduPilot: `raw * 5 / 8 + 880` us in integers: whole us,
    ///   880..=2159.
    pub fn read_ns(self, raw: u16) -> u64 {
        let raw = raw & RAW_MAX;
        match self {
            CrsfReceiver::Betaflight => {
                let us = BETAFLIGHT_SCALE * f32::from(raw) + BETAFLIGHT_OFFSET_US;
                (f64::from(us) * 1_000.0).round() as u64
            }
            CrsfReceiver::Inav => (u64::from(raw) * INAV_MUL / INAV_DIV + INAV_OFFSET_US) * US,
            CrsfReceiver::ArduPilot => {
                (u64::from(raw) * ARDUPILOT_MUL / ARDUPILOT_DIV + ARDUPILOT_OFFSET_US) * US
            }
        }
    }

    /// The lowest and highest value this firmware reads, ns.
    pub fn range_ns(self) -> (u64, u64) {
        (self.read_ns(0), self.read_ns(RAW_MAX))
    }

    /// The largest distance, ns, between a whole microsecond inside
    /// [`Self::range_ns`] and what this firmware reads for
    /// [`raw_for`] of it: 0 for iNav and ArduPilot, half of Betaflight's
    /// step (0.3124 us) for Betaflight.
    pub fn whole_us_error_ns(self) -> u64 {
        match self {
            CrsfReceiver::Betaflight => 313,
            CrsfReceiver::Inav | CrsfReceiver::ArduPilot => 0,
        }
    }

    /// What this firmware does with a frame its framing took
    /// ([`Framer`](super::Framer)):
    ///
    /// - RC_CHANNELS_PACKED: used, its channels read from the first 22
    ///   payload bytes whatever `len` says (each firmware reads its frame
    ///   buffer through a fixed struct); Betaflight only at address 0xC8
    ///   (ArduPilot's framing takes nothing else), iNav at any address.
    /// - LINK_STATISTICS: read; Betaflight only at address 0xC8 with `len`
    ///   12.
    /// - anything else: ignored here.
    pub fn verdict(self, taken: &Taken) -> Verdict {
        let b = &taken.bytes;
        let (address, len, kind) = (b[0], b[1], b[2]);
        let betaflight = self == CrsfReceiver::Betaflight;
        match kind {
            TYPE_RC_CHANNELS_PACKED if !betaflight || address == ADDRESS_FLIGHT_CONTROLLER => {
                let mut payload = [0u8; RC_PAYLOAD_LEN];
                payload.copy_from_slice(&b[3..3 + RC_PAYLOAD_LEN]);
                let raw = rc_channels(&payload);
                let mut channels_ns = [0u64; CHANNELS];
                for (ns, &r) in channels_ns.iter_mut().zip(&raw) {
                    *ns = self.read_ns(r);
                }
                Verdict::Used { channels_ns }
            }
            TYPE_LINK_STATISTICS
                if !betaflight
                    || (address == ADDRESS_FLIGHT_CONTROLLER
                        && usize::from(len) == LinkStatistics::PAYLOAD_LEN + 2) =>
            {
                let mut payload = [0u8; LinkStatistics::PAYLOAD_LEN];
                payload.copy_from_slice(&b[3..3 + LinkStatistics::PAYLOAD_LEN]);
                Verdict::LinkStatistics(LinkStatistics::from_payload(&payload))
            }
            _ => Verdict::Ignored,
        }
    }
}

/// What a firmware does with a frame its framing took.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// It uses these channel values, ns (channels 1..=16).
    Used {
        /// Channels 1..=16, ns.
        channels_ns: [u64; CHANNELS],
    },
    /// It reads these link statistics.
    LinkStatistics(LinkStatistics),
    /// It does nothing with the frame that this model follows.
    Ignored,
}

/// The raw value whose reading on `receiver` is closest to `ns`, within
/// 0..=[`RAW_MAX`]: exact for whole microseconds inside the receiver's range
/// on iNav and ArduPilot, within half a step (0.3124 us) on Betaflight. Of
/// the raws a receiver reads alike, the one the other firmware read closest
/// to `ns`.
pub fn raw_for(receiver: CrsfReceiver, ns: u64) -> u16 {
    best_raw(ns, |raw| {
        (receiver.read_ns(raw).abs_diff(ns), spread_ns(raw, ns))
    })
}

/// The raw value that every modelled firmware reads closest to `ns`: the
/// one whose largest error is least. For whole microseconds from 881 to
/// 2159 us, iNav reads it exactly and Betaflight and ArduPilot within 1 us.
pub fn raw_for_any(ns: u64) -> u16 {
    best_raw(ns, |raw| spread_ns(raw, ns))
}

/// An RC frame of channel values in ns, each encoded with [`raw_for`] for
/// `receiver`.
pub fn encode_ns(receiver: CrsfReceiver, channels_ns: &[u64; CHANNELS]) -> [u8; RC_FRAME_LEN] {
    let mut raw = [0u16; CHANNELS];
    for (r, &ns) in raw.iter_mut().zip(channels_ns) {
        *r = raw_for(receiver, ns);
    }
    encode_rc(&raw)
}
