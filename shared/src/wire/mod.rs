//! What a frame is on the wire: the protocol seam. Everything that differs
//! between PPM and SBUS (and the protocols after them) is asked here, never
//! branched on elsewhere: the configuration's checks and defaults ask a
//! [`Protocol`]'s [`Spec`], the timing loop, the lines and the tools ask the
//! validated [`WireModel`] a [`crate::frame::FrameModel`] holds. It sits
//! below the frame model and the configuration (it imports neither), so a
//! model's build, which checks `[ppm]`, is [`crate::frame`]'s.
//!
//! - here: [`Protocol`] (the list of protocols, `ppm.protocol`), its
//!   [`Spec`] (what the configuration needs to know before a model exists),
//!   [`WireModel`] (one variant a protocol, each with its own validated
//!   settings) and [`FrameKind`] (how the loop paces and hands over a frame).
//! - [`ppm`]: PPM's spec and settings (pulse width).
//! - [`sbus`]: SBUS's spec, settings (its receivers) and encoding.
//! - [`crsf`]: CRSF's spec, settings (firmware, baud rate), timing and
//!   encoding.
//! - [`reader`]: a receiver reading a line edge by edge, whatever the
//!   protocol ([`reader::LineReader`]), for the tools that decode a trace.
//! - [`uart`] (the crate's, below SBUS and here): bytes on a UART in a
//!   protocol's [`UartFormat`] (baud, parity, stop bits), what the serial
//!   line sets and the simulated line draws.
//!
//! Adding a protocol: its module (spec, settings, build, encoding), a
//! variant of [`Protocol`] and of [`WireModel`] with their arms here.

pub mod crsf;
pub mod ppm;
pub mod reader;
pub mod sbus;
pub use crate::uart;

use crate::signal::{Level, MAX_CHANNELS};
use serde::Deserialize;

pub use crsf::CrsfWire;
pub use ppm::PpmWire;
pub use sbus::SbusWire;
pub use uart::UartFormat;

/// The longest frame of bytes any protocol sends, so a frame fits a
/// fixed buffer in the timing loop.
pub const MAX_FRAME_BYTES: usize = 64;

/// What a frame is on the wire (`ppm.protocol`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// PPM: channel values as the periods between separator pulses, for a
    /// trainer jack (the default).
    #[default]
    Ppm,
    /// SBUS: 16 channels of 11 bits in one 25-byte frame at 100 000 baud,
    /// 8E2, for a radio's serial trainer input, its module bay or a flight
    /// controller (see [`crate::sbus`]).
    Sbus,
    /// CRSF: RC_CHANNELS_PACKED and LINK_STATISTICS to a flight
    /// controller's receiver port, 8N1 at 420 000 baud (see
    /// [`crate::crsf`]).
    Crsf,
}

impl Protocol {
    /// Every protocol.
    pub const ALL: [Protocol; 3] = [Protocol::Ppm, Protocol::Sbus, Protocol::Crsf];

    /// What the configuration knows of the protocol before a model exists.
    pub fn spec(self) -> &'static Spec {
        match self {
            Protocol::Ppm => &ppm::SPEC,
            Protocol::Sbus => &sbus::SPEC,
            Protocol::Crsf => &crsf::SPEC,
        }
    }

    /// `"ppm"`, `"sbus"` or `"crsf"`, as in the configuration.
    pub fn name(self) -> &'static str {
        self.spec().name
    }
}

impl std::str::FromStr for Protocol {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Protocol::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| format!("`{s}` is not a protocol"))
    }
}

/// How a protocol's frames leave and how receivers find them: what the
/// timing loop paces by.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameKind {
    /// An edge schedule of pulses, written edge by edge (or handed whole to
    /// a line timed by its own clock). Receivers find a frame by the sync
    /// gap before it, measured from the last pulse's start: after silence a
    /// frame needs a lead-in pulse, a frame too late for the sync window is
    /// skipped, and a late timed edge aborts the frame (the late-edge guard).
    Pulses,
    /// Bytes handed whole to a line at the frame's start, which sends them
    /// back to back. Receivers find a frame by the idle line before it,
    /// measured from the previous frame's end on the wire: no lead-in, no
    /// guard; a late frame is sent late, never skipped for its lateness.
    Bytes,
}

/// The kinds of line an output can be (`ppmd.output`), as a protocol's
/// line check sees them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LineKind {
    /// `gpio:`.
    Gpio,
    /// `spi:`.
    Spi,
    /// `sim` or `sim:PATH`.
    Sim,
    /// `sim-spi`: a simulated line that takes frames whole, as SPI does.
    SimWhole,
    /// `serial:` (a UART).
    Serial,
}

/// A configuration key and why its value cannot be had (with the fix).
pub type Refusal = (&'static str, String);

/// What the configuration knows of a protocol before its model is built:
/// its defaults, the keys it leaves unused, the lines it goes through, and
/// what it supports.
pub struct Spec {
    /// As in the configuration (`ppm.protocol`).
    pub name: &'static str,
    /// In messages (`PPM`).
    pub title: &'static str,
    /// How frames leave and are found.
    pub kind: FrameKind,
    /// `ppm.channels`' default.
    pub channels: u32,
    /// `ppm.frame_us`' default.
    pub frame_us: f64,
    /// `ppm.idle_level`'s default on a line that can send either.
    pub idle_level: Level,
    /// The word for the gap between frames (`sync`, `idle line`).
    pub gap: &'static str,
    /// Whether the protocol has a failsafe flag (`failsafe.action = "flag"`).
    pub failsafe_flag: bool,
    /// Whether a read-back (`ppmd.readback`) can compare its frames.
    pub reads_back: bool,
    /// Whether a grid output still checks `ppm.follow_sync_*_us` against
    /// the receivers.
    pub grid_checks_follow: bool,
    /// Whether its `spi:` output runs at `ppmd.spi_hz`.
    pub uses_spi_hz: bool,
    /// `[ppm]` keys it does not use, and why.
    pub unused_keys: &'static [(&'static str, &'static str)],
    /// Whether `ppmd.output` (its kind, `shown` as given) can carry it at
    /// `idle_level` (`None`: not given); the refusal names the key.
    pub check_line: fn(LineKind, Option<Level>, &str) -> Result<(), Refusal>,
    /// `ppm.idle_level`'s default on `ppmd.output`, where it depends on the
    /// line (`None`: the [`Spec::idle_level`]).
    pub line_idle_level: fn(LineKind) -> Option<Level>,
}

/// What a validated model's frames are on the wire: one variant a protocol,
/// each with its own checked settings. Asked by the timing loop (kept by
/// value, `Copy`, never allocating), the lines and the tools.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum WireModel {
    /// PPM pulses.
    Ppm(PpmWire),
    /// SBUS frames.
    Sbus(SbusWire),
    /// CRSF frames.
    Crsf(CrsfWire),
}

impl WireModel {
    /// The protocol.
    pub fn protocol(&self) -> Protocol {
        match self {
            WireModel::Ppm(_) => Protocol::Ppm,
            WireModel::Sbus(_) => Protocol::Sbus,
            WireModel::Crsf(_) => Protocol::Crsf,
        }
    }

    /// What the configuration knows of it.
    pub fn spec(&self) -> &'static Spec {
        self.protocol().spec()
    }

    /// How frames leave and are found.
    pub fn kind(&self) -> FrameKind {
        self.spec().kind
    }

    /// Separator pulse width, ns (0 for a protocol without pulses).
    pub fn pulse_ns(&self) -> u64 {
        match self {
            WireModel::Ppm(p) => p.pulse_ns,
            WireModel::Sbus(_) | WireModel::Crsf(_) => 0,
        }
    }

    /// How long a frame of bytes takes on the wire, sent back to back, ns
    /// (0 for pulses, whose length depends on the values).
    pub fn frame_wire_ns(&self) -> u64 {
        match self {
            WireModel::Ppm(_) => 0,
            WireModel::Sbus(_) => crate::sbus::FRAME_WIRE_NS,
            WireModel::Crsf(c) => c.frame_wire_ns(),
        }
    }

    /// How much later than planned a frame of bytes may leave before the
    /// idle line after it must be measured from its actual end: the margin
    /// the idle lines keep, ns (0 for pulses).
    pub fn late_margin_ns(&self) -> u64 {
        match self {
            WireModel::Ppm(_) => 0,
            WireModel::Sbus(_) => crate::sbus::timing::GAP_MARGIN_US * 1_000,
            WireModel::Crsf(_) => crsf::GAP_MARGIN_US * 1_000,
        }
    }

    /// The UART format its bytes go in on a `serial:` output and the
    /// simulated line (`None` for pulses).
    pub fn uart(&self) -> Option<UartFormat> {
        match self {
            WireModel::Ppm(_) => None,
            WireModel::Sbus(_) => Some(crate::sbus::uart::FORMAT),
            WireModel::Crsf(c) => Some(c.uart()),
        }
    }

    /// The SBUS receivers an SBUS model is for.
    pub fn sbus(&self) -> Option<&crate::sbus::timing::SbusChoice> {
        match self {
            WireModel::Sbus(s) => Some(&s.choice),
            WireModel::Ppm(_) | WireModel::Crsf(_) => None,
        }
    }

    /// One frame of bytes carrying `values_ns` (clamped, every channel
    /// given), flagged failsafe when `failsafe` and the protocol has the
    /// flag, in `out`; how many bytes (0 for pulses). Allocation-free.
    pub fn encode_bytes(
        &self,
        values_ns: &[u64; MAX_CHANNELS],
        failsafe: bool,
        out: &mut [u8; MAX_FRAME_BYTES],
    ) -> usize {
        match self {
            WireModel::Ppm(_) => 0,
            WireModel::Sbus(s) => s.encode(values_ns, failsafe, out),
            WireModel::Crsf(c) => c.encode(values_ns, out),
        }
    }

    /// What the receiver the values are encoded for reads of a frame of
    /// bytes, ns, channel by channel into `values`; how many channels.
    pub fn reads(&self, bytes: &[u8], values: &mut [u64; MAX_CHANNELS]) -> usize {
        match self {
            WireModel::Ppm(_) => 0,
            WireModel::Sbus(s) => s.reads(bytes, values),
            WireModel::Crsf(c) => c.reads(bytes, values),
        }
    }

    /// How a frame is made, for the start-up log (`pulse 300 us`,
    /// `SBUS encoded for edgetx`).
    pub fn describe(&self) -> String {
        match self {
            WireModel::Ppm(p) => format!("pulse {} us", p.pulse_ns as f64 / 1e3),
            WireModel::Sbus(s) => format!("SBUS encoded for {}", s.choice.encode_for().name()),
            WireModel::Crsf(c) => match c.target() {
                crsf::CrsfTarget::FlightController => format!(
                    "CRSF encoded for {}, {}, link statistics after every RC frame",
                    c.encode_for.name(),
                    c.uart().describe()
                ),
                crsf::CrsfTarget::Module => format!(
                    "CRSF to an ExpressLRS module (0xEE), values for {}, {}, following the module's timing",
                    c.encode_for.name(),
                    c.uart().describe()
                ),
            },
        }
    }
}
