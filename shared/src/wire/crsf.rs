//! CRSF on the wire, to a flight controller's receiver port: what the
//! configuration knows of it ([`SPEC`]), the lines that carry it, its
//! timing rules and its validated settings ([`CrsfWire`]: the firmware the
//! values are encoded for, the baud rate). The frames and the firmware
//! models are [`crate::crsf`]'s; the model's build is [`crate::frame`]'s.
//!
//! A frame of bytes here is an RC_CHANNELS_PACKED frame (26 bytes) followed
//! at once by LINK_STATISTICS ([`LinkStatistics::WIRED`], 14 bytes) in the
//! same write: 40 bytes, 952 us at 420 000 baud. The RC frame leaves first,
//! at its due time, so the link statistics never delay one; every frame
//! carries them, far more often than the 250 ms Betaflight needs, because
//! the loop's frames are stateless (each frame the same bytes for the same
//! values) and a stream that stops stops both, which is the failsafe every
//! firmware expects: no RC frame, and the link shown lost.

use super::uart::{Parity, UartFormat};
use super::{FrameKind, LineKind, Refusal, Spec};
use crate::crsf::{self, raw_for, raw_for_any, CrsfReceiver, LinkStatistics};
use crate::signal::{Level, MAX_CHANNELS};

/// `ppm.crsf_baud`'s default: Betaflight's and iNav's `CRSF_BAUDRATE`
/// (not the TBS specification's 416 666, see [`crsf::BAUD`]).
pub const BAUD_DEFAULT: u32 = crsf::BAUD as u32;
/// `ppm.crsf_baud`'s bounds: the rates ExpressLRS receivers offer their
/// flight controller reach from 115 200 to 5 250 000; a Raspberry Pi's
/// PL011 holds up to 3 000 000 (48 MHz / 16).
pub const BAUD_RANGE: (u32, u32) = (115_200, 3_000_000);

/// Bytes of a frame of bytes: the RC frame, then link statistics.
pub const FRAME_LEN: usize = crsf::RC_FRAME_LEN + LinkStatistics::FRAME_LEN;

/// The time-out the receivers' framing restarts after, us: iNav's 1750 us
/// (Betaflight's 1748), from a frame's first byte. After a lost byte the
/// framing is out of step until a byte comes later than this after the
/// mis-framed frame's start, so an idle line longer than this between
/// frames puts every firmware back in step at the next frame's first byte
/// (ArduPilot finds the next 0xC8 by itself).
pub const RESYNC_US: u64 = crsf::framing::INAV_FRAME_TIMEOUT_US;
/// Margin kept over [`RESYNC_US`] for the firmware's microsecond clock
/// and a frame whose write was held up.
pub const GAP_MARGIN_US: u64 = 50;
/// The least idle line between frames, us: [`RESYNC_US`] and
/// [`GAP_MARGIN_US`]. With the 952 us frame, frame starts are at least
/// 2.75 ms apart (363 Hz): above the 2 ms floor, and within what every
/// firmware reads (an ExpressLRS receiver sends up to 1000 Hz).
pub const GAP_LEAST_US: u64 = RESYNC_US + GAP_MARGIN_US;
/// The longest idle line, us: well inside the shortest signal-loss time
/// (Betaflight's 100 ms without a frame; ArduPilot's receiver is gone after
/// 150 ms).
pub const GAP_MAX_US: f64 = 50_000.0;
/// The longest idle line under `follow`, by default, us.
pub const FOLLOW_GAP_MAX_DEFAULT_US: f64 = 20_000.0;
/// The grid period by default, us: 250 Hz.
pub const PERIOD_DEFAULT_US: f64 = 4_000.0;

/// What a CRSF line drives (`ppm.crsf_target`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CrsfTarget {
    /// A flight controller's receiver port: RC frames to 0xC8, each
    /// followed by link statistics, at 420 000 baud by default.
    #[default]
    FlightController,
    /// An ExpressLRS transmitter module, as a radio drives one: RC frames
    /// to 0xEE alone, at 400 000 baud by default, on a grid that follows
    /// the module's timing corrections.
    Module,
}

impl CrsfTarget {
    /// As in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            CrsfTarget::FlightController => "flight_controller",
            CrsfTarget::Module => "module",
        }
    }
}

/// `ppm.crsf_baud`'s default to a module: what EdgeTX sends an external
/// ExpressLRS module at by default, the first rate the module tries.
pub const MODULE_BAUD_DEFAULT: u32 = crsf::module::HANDSET_BAUD;
/// The rates an ExpressLRS module searches for a handset
/// (`CRSFHandset`'s baud list) that a Pi's UART makes (up to 3 000 000).
pub const MODULE_BAUDS: [u32; 5] = [400_000, 115_200, 921_600, 1_870_000, 2_250_000];
/// The least idle line between frames to a module, us: the module frames
/// by bytes alone (no time-out), so this only leaves it room to answer
/// (a half-duplex module turns the line around after each good frame).
pub const MODULE_GAP_LEAST_US: u64 = 100;

/// The firmware the values are encoded for (`ppm.receiver`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CrsfFor {
    /// Every modelled firmware: [`raw_for_any`].
    Any,
    /// This one: [`raw_for`].
    One(CrsfReceiver),
}

impl CrsfFor {
    /// The raw value for `ns`.
    pub fn raw(self, ns: u64) -> u16 {
        match self {
            CrsfFor::Any => raw_for_any(ns),
            CrsfFor::One(r) => raw_for(r, ns),
        }
    }

    /// The firmware whose reading [`super::WireModel::reads`] reports:
    /// the one named, iNav under `any` (which reads [`raw_for_any`]
    /// exactly).
    pub fn reads_as(self) -> CrsfReceiver {
        match self {
            CrsfFor::Any => CrsfReceiver::Inav,
            CrsfFor::One(r) => r,
        }
    }

    /// As in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            CrsfFor::Any => "any",
            CrsfFor::One(r) => r.name(),
        }
    }

    /// The firmware covered.
    pub fn receivers(self) -> &'static [CrsfReceiver] {
        match self {
            CrsfFor::Any => &CrsfReceiver::ALL,
            CrsfFor::One(CrsfReceiver::Betaflight) => &CrsfReceiver::ALL[0..1],
            CrsfFor::One(CrsfReceiver::Inav) => &CrsfReceiver::ALL[1..2],
            CrsfFor::One(CrsfReceiver::ArduPilot) => &CrsfReceiver::ALL[2..3],
        }
    }

    /// The values, whole us, every covered firmware reads within 1 us of
    /// what was sent: the intersection of their ranges.
    pub fn value_range_us(self) -> (u64, u64) {
        let (lo, hi) = self
            .receivers()
            .iter()
            .map(|r| r.range_ns())
            .fold((0, u64::MAX), |(lo, hi), (a, b)| (lo.max(a), hi.min(b)));
        (lo.div_ceil(1_000), hi / 1_000)
    }
}

/// CRSF's validated settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CrsfWire {
    /// The firmware the values are encoded for.
    pub(crate) encode_for: CrsfFor,
    /// The line rate, `ppm.crsf_baud`.
    pub(crate) baud: u32,
    /// What the line drives.
    pub(crate) target: CrsfTarget,
    /// To a module: the model ID its model ID command carries.
    pub(crate) model_id: u8,
}

impl CrsfWire {
    /// The settings: values for `encode_for`, at `baud`.
    pub fn new(encode_for: CrsfFor, baud: u32) -> CrsfWire {
        CrsfWire {
            encode_for,
            baud,
            target: CrsfTarget::FlightController,
            model_id: 0,
        }
    }

    /// The settings to a transmitter module: values for the flight
    /// controller behind its link (`encode_for`), at `baud`,
    /// with model ID `model_id`.
    pub fn module(encode_for: CrsfFor, baud: u32, model_id: u8) -> CrsfWire {
        CrsfWire {
            encode_for,
            baud,
            target: CrsfTarget::Module,
            model_id,
        }
    }

    /// To a module, its model ID command (`None` to a flight controller).
    pub fn model_id_frame(&self) -> Option<[u8; crsf::module::MODEL_ID_FRAME_LEN]> {
        (self.target == CrsfTarget::Module).then(|| crsf::module::model_id_frame(self.model_id))
    }

    /// What the line drives.
    pub fn target(&self) -> CrsfTarget {
        self.target
    }

    /// The address RC frames go to.
    fn address(&self) -> u8 {
        match self.target {
            CrsfTarget::FlightController => crsf::ADDRESS_FLIGHT_CONTROLLER,
            CrsfTarget::Module => crsf::ADDRESS_TRANSMITTER,
        }
    }

    /// Bytes of a frame of bytes: [`FRAME_LEN`] to a flight controller,
    /// the RC frame alone to a module (which sends the link statistics).
    pub fn frame_len(&self) -> usize {
        match self.target {
            CrsfTarget::FlightController => FRAME_LEN,
            CrsfTarget::Module => crsf::RC_FRAME_LEN,
        }
    }

    /// The firmware the values are encoded for.
    pub fn encode_for(&self) -> CrsfFor {
        self.encode_for
    }

    /// The UART format: 8N1 at `ppm.crsf_baud`.
    pub fn uart(&self) -> UartFormat {
        UartFormat {
            baud: self.baud,
            parity: Parity::None,
            stop_bits: 1,
        }
    }

    /// How long a frame of bytes ([`Self::frame_len`]) takes on the wire, ns.
    pub fn frame_wire_ns(&self) -> u64 {
        self.uart().wire_ns(self.frame_len())
    }

    /// See [`super::WireModel::encode_bytes`]: the RC frame, then
    /// [`LinkStatistics::WIRED`] (to a module: the RC frame to 0xEE alone).
    /// CRSF has no failsafe flag.
    pub(crate) fn encode(
        &self,
        values_ns: &[u64; MAX_CHANNELS],
        out: &mut [u8; super::MAX_FRAME_BYTES],
    ) -> usize {
        let mut raw = [0u16; crsf::CHANNELS];
        for (r, &ns) in raw.iter_mut().zip(values_ns) {
            *r = self.encode_for.raw(ns);
        }
        out[..crsf::RC_FRAME_LEN].copy_from_slice(&crsf::encode_rc_to(self.address(), &raw));
        if self.target == CrsfTarget::Module {
            return crsf::RC_FRAME_LEN;
        }
        out[crsf::RC_FRAME_LEN..FRAME_LEN].copy_from_slice(&LinkStatistics::WIRED.encode());
        FRAME_LEN
    }

    /// See [`super::WireModel::reads`]: the RC frame's channels as the
    /// firmware encoded for reads them.
    pub(crate) fn reads(&self, bytes: &[u8], values: &mut [u64; MAX_CHANNELS]) -> usize {
        let Some(Ok(rc)) = bytes.get(..crsf::RC_FRAME_LEN).map(<[u8; 26]>::try_from) else {
            return 0;
        };
        let Some(raw) = crsf::decode_rc_to(self.address(), &rc) else {
            return 0;
        };
        let r = self.encode_for.reads_as();
        for (v, &raw) in values.iter_mut().zip(&raw) {
            *v = r.read_ns(raw);
        }
        crsf::CHANNELS
    }
}

/// What the configuration knows of CRSF.
pub static SPEC: Spec = Spec {
    name: "crsf",
    title: "CRSF",
    kind: FrameKind::Bytes,
    channels: crsf::CHANNELS as u32,
    frame_us: PERIOD_DEFAULT_US,
    idle_level: Level::High,
    gap: "idle line",
    failsafe_flag: false,
    reads_back: false,
    grid_checks_follow: false,
    uses_spi_hz: false,
    unused_keys: &[
        (
            "ppm.pulse_us",
            "a CRSF frame is bytes on a UART, without separator pulses",
        ),
        (
            "ppm.late_edge_guard_us",
            "a CRSF frame leaves whole, in one write, so no edge of it is guarded",
        ),
    ],
    check_line,
    line_idle_level: |_| Some(Level::High),
};

/// A CRSF output: a UART (`serial:`), idling high, or the simulated line.
fn check_line(output: LineKind, idle: Option<Level>, out: &str) -> Result<(), Refusal> {
    match (output, idle) {
        (LineKind::Serial | LineKind::Sim, None | Some(Level::High)) => Ok(()),
        (LineKind::Serial | LineKind::Sim, Some(Level::Low)) => Err((
            "ppm.idle_level",
            format!(
                "\"low\" through `{out}`: CRSF is a plain UART's line, not inverted, idling high: remove the key or set idle_level = \"high\""
            ),
        )),
        (LineKind::SimWhole, _) => Err((
            "ppmd.output",
            format!(
                "`{out}` simulates a PPM output sent whole through SPI; a CRSF output's simulated line (sim or sim:PATH) already takes each frame whole"
            ),
        )),
        (LineKind::Gpio | LineKind::Spi, _) => Err((
            "ppmd.output",
            format!(
                "`{out}`: CRSF goes to a flight controller's UART (ppm.crsf_baud, 8N1), which needs a UART: use serial:DEVICE (the Pi's /dev/ttyAMA0: its TX to the flight controller's RX, RX to its TX, ground to ground, 3.3 V levels)"
            ),
        )),
    }
}

#[cfg(test)]
mod tests;
