//! What ppm sends the SBUS receivers of a `ppm.receiver` choice: which
//! receivers that covers, whose scaling the values are encoded for, the
//! channel values every one of them reads, and the idle line it leaves
//! between frames.
//!
//! The idle line between frames is the least each receiver needs
//! ([`SbusReceiver::min_gap_ns`]) plus [`GAP_MARGIN_US`] for a frame that
//! leaves late (the timing thread's write starting the UART later than
//! planned, which shortens the idle line before the frame after it); for
//! ArduPilot, plus its RC thread's polling period too, since it stamps bytes
//! when it reads them, not when they arrive.

use super::{raw_for, SbusReceiver, ARDUPILOT_FAILSAFE_AT_NS, FRAME_WIRE_NS, RAW_MAX};
use crate::receiver::{Receiver, ReceiverChoice};

/// Nanoseconds per microsecond.
const US: u64 = 1_000;

/// Kept on top of a receiver's least idle line for a frame that leaves up to
/// this much later than planned, us.
pub const GAP_MARGIN_US: u64 = 200;
/// ArduPilot reads a UART from its RC thread about once a millisecond and
/// stamps the bytes then (`AP_RCProtocol::check_added_uart`): an idle line
/// looks up to this much shorter there, us.
pub const ARDUPILOT_POLL_US: u64 = 1_000;
/// The grid period's default, us: every modelled receiver takes frames this
/// far apart (ArduPilot's gap with room for its polling).
pub const PERIOD_DEFAULT_US: f64 = 7_000.0;
/// The longest idle line ppm leaves between frames, us: well inside every
/// receiver's signal-loss time (Betaflight 4.5's 100 ms the shortest).
pub const GAP_MAX_US: f64 = 60_000.0;
/// `follow`'s longest idle line by default, us: a frame at least every 23 ms
/// while no fresh command comes.
pub const FOLLOW_GAP_MAX_DEFAULT_US: f64 = 20_000.0;
/// One frame on the wire, us.
pub const FRAME_WIRE_US: f64 = (FRAME_WIRE_NS / US) as f64;

/// The SBUS receivers a `ppm.receiver` choice covers, and how ppm sends
/// to them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SbusChoice {
    /// The receivers covered (the two Betaflight framings for
    /// `betaflight`; all four for `any`).
    receivers: [Option<SbusReceiver>; 4],
    /// Whose scaling the values are encoded for: exact there, the others
    /// read them within their own offset (see [`SbusChoice::encode_for`]).
    encode_for: SbusReceiver,
}

impl SbusChoice {
    /// The SBUS receivers of `choice`, or why there are none (OpenTX's SBUS
    /// input is not modelled).
    pub fn new(choice: ReceiverChoice) -> Result<SbusChoice, String> {
        let (receivers, encode_for) = match choice {
            ReceiverChoice::Any => (SbusReceiver::ALL.map(Some), SbusReceiver::EdgeTx),
            ReceiverChoice::One(Receiver::EdgeTx) => {
                ([Some(SbusReceiver::EdgeTx), None, None, None], SbusReceiver::EdgeTx)
            }
            ReceiverChoice::One(Receiver::Betaflight) => (
                [
                    Some(SbusReceiver::Betaflight2026),
                    Some(SbusReceiver::Betaflight45),
                    None,
                    None,
                ],
                SbusReceiver::Betaflight2026,
            ),
            ReceiverChoice::One(Receiver::ArduPilot) => (
                [Some(SbusReceiver::ArduPilot), None, None, None],
                SbusReceiver::ArduPilot,
            ),
            ReceiverChoice::One(Receiver::OpenTx) => {
                return Err(
                    "OpenTX's SBUS trainer input is not modelled: use edgetx (EdgeTX 2.11 and later), betaflight, ardupilot or any".into(),
                )
            }
        };
        Ok(SbusChoice {
            receivers,
            encode_for,
        })
    }

    /// The receivers covered.
    pub fn receivers(&self) -> impl Iterator<Item = SbusReceiver> + '_ {
        self.receivers.iter().flatten().copied()
    }

    /// Whose scaling values are encoded for: EdgeTX for `any` and
    /// `edgetx` (Betaflight reads the same raw within 0.625 us of it,
    /// ArduPilot 5 us lower), Betaflight's for `betaflight`, ArduPilot's
    /// for `ardupilot`.
    pub fn encode_for(&self) -> SbusReceiver {
        self.encode_for
    }

    /// The raw value of `ns` for [`SbusChoice::encode_for`].
    pub fn raw(&self, ns: u64) -> u16 {
        raw_for(self.encode_for, ns)
    }

    /// The least idle line between frames ppm accepts for these receivers,
    /// us: the largest receiver's need plus [`GAP_MARGIN_US`] (and
    /// ArduPilot's [`ARDUPILOT_POLL_US`]), in whole 10 us.
    pub fn least_gap_us(&self) -> u64 {
        self.receivers()
            .map(|r| {
                let need = r.min_gap_ns().div_ceil(US) + GAP_MARGIN_US;
                let need = match r {
                    SbusReceiver::ArduPilot => need + ARDUPILOT_POLL_US,
                    _ => need,
                };
                need.div_ceil(10) * 10
            })
            .max()
            .expect("a receiver")
    }

    /// `follow`'s shortest idle line by default, us: the least, rounded up
    /// to whole 100 us (ArduPilot: 4000, for its polling's jitter).
    pub fn default_gap_us(&self) -> f64 {
        if self.receivers().any(|r| r == SbusReceiver::ArduPilot) {
            return PERIOD_DEFAULT_US - FRAME_WIRE_US;
        }
        (self.least_gap_us().div_ceil(100) * 100) as f64
    }

    /// The whole-microsecond channel values every receiver covered reads
    /// as a value once encoded: inside the encoding receiver's range, where
    /// it reads them exactly, and above ArduPilot's failsafe reading (875
    /// us) when ArduPilot is covered. `(lowest, highest)`, us.
    pub fn value_range_us(&self) -> (u64, u64) {
        let ok = |us: u64| {
            let raw = self.raw(us * US);
            let exact = self.encode_for.read_ns(raw).abs_diff(us * US) <= 312;
            let readable = self
                .receivers()
                .all(|r| r != SbusReceiver::ArduPilot || r.read_ns(raw) > ARDUPILOT_FAILSAFE_AT_NS);
            exact && readable && raw <= RAW_MAX
        };
        let lo = (0..=3_000).find(|&us| ok(us)).expect("a readable value");
        let hi = (lo..=3_000).take_while(|&us| ok(us)).last().unwrap_or(lo);
        (lo, hi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn choice(name: &str) -> SbusChoice {
        SbusChoice::new(name.parse().unwrap()).unwrap()
    }

    #[test]
    fn least_gaps_are_each_receivers_need_and_a_margin() {
        // EdgeTX 120 us idle, Betaflight 481 / 501 us, ArduPilot 1880 us
        // plus its 1 ms polling; each plus 200 us, in whole 10 us.
        assert_eq!(choice("edgetx").least_gap_us(), 320);
        assert_eq!(choice("betaflight").least_gap_us(), 710);
        assert_eq!(choice("ardupilot").least_gap_us(), 3_080);
        assert_eq!(choice("any").least_gap_us(), 3_080);
        assert_eq!(choice("edgetx").default_gap_us(), 400.0);
        assert_eq!(choice("betaflight").default_gap_us(), 800.0);
        assert_eq!(choice("ardupilot").default_gap_us(), 4_000.0);
        assert_eq!(choice("any").default_gap_us(), 4_000.0);
    }

    #[test]
    fn value_ranges_keep_every_receiver_reading_a_value() {
        assert_eq!(choice("edgetx").value_range_us(), (880, 2_159));
        assert_eq!(choice("betaflight").value_range_us(), (880, 2_159));
        // Raw 2 is the lowest ArduPilot reads as no failsafe: 876 us.
        assert_eq!(choice("ardupilot").value_range_us(), (876, 2_154));
        // EdgeTX's encoding, whose raw 3 (882 us there) ArduPilot reads 876.
        assert_eq!(choice("any").value_range_us(), (882, 2_159));
    }

    #[test]
    fn opentx_is_refused_and_betaflight_covers_both_framings() {
        let e = SbusChoice::new("opentx".parse().unwrap()).unwrap_err();
        assert!(e.contains("edgetx"), "{e}");
        let bf: Vec<_> = choice("betaflight").receivers().collect();
        assert_eq!(
            bf,
            [SbusReceiver::Betaflight2026, SbusReceiver::Betaflight45]
        );
        assert_eq!(choice("any").receivers().count(), 4);
        assert_eq!(choice("any").encode_for(), SbusReceiver::EdgeTx);
    }
}
