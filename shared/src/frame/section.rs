//! The `[ppm]` section of the configuration file: what the file says about
//! the frame. [`FrameModel::build`](super::FrameModel::build) checks it and
//! builds the model.

use crate::receiver::ReceiverChoice;
use crate::signal::{Level, Timing};
use crate::wire::Protocol;
use serde::Deserialize;
use std::collections::BTreeMap;

/// `[ppm]`: the signal a transmitter's trainer port (or, with
/// `protocol = "sbus"`, its serial trainer input) receives. Keys whose
/// default depends on the protocol are options here; the model
/// ([`FrameModel::build`](super::FrameModel::build)) resolves them.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PpmSection {
    /// What a frame is on the wire: `"ppm"` (default), `"sbus"` or `"crsf"`.
    pub protocol: Protocol,
    /// Number of channels in a frame, 1..=16. Default 8; SBUS frames carry
    /// 16, its only value.
    pub channels: Option<u32>,
    /// Frame length in microseconds (frame start to next frame start) under
    /// grid timing. Default 22500; SBUS: the grid period, default 7000.
    pub frame_us: Option<f64>,
    /// Width of the separator pulse before every channel, in microseconds.
    /// Default 300. PPM only.
    pub pulse_us: f64,
    /// Line level between pulses and while silent: `"low"` or `"high"`.
    /// Default `"low"`. SBUS: the level the line idles at, `"high"` for a
    /// plain UART's SBUS (the default on a serial output), `"low"` for true
    /// (inverted) SBUS (the default on an SPI output).
    pub idle_level: Option<Level>,
    /// Channel order of the transmitter, a permutation of the letters A (aileron),
    /// E (elevator), T (throttle), R (rudder): `"AETR"` (default), `"TAER"`,
    /// `"ATER"`, ... Channels after the fourth are `aux1`, `aux2`, ...
    pub order: String,
    /// Default value of every channel, in microseconds. Default 1500; the
    /// throttle channel defaults to its minimum instead (zero actuation).
    pub default_us: f64,
    /// Lowest value of every channel; commands below it are clamped. Default 1000.
    pub min_us: f64,
    /// Highest value of every channel; commands above it are clamped. Default 2000.
    pub max_us: f64,
    /// Per-channel overrides, keyed by channel name: `[ppm.channel.thr]`.
    pub channel: BTreeMap<String, ChannelOverride>,
    /// The receiver the signal is for: `"any"` (default: what EdgeTX,
    /// OpenTX, Betaflight and ArduPilot all read), `"edgetx"` (2.10 and
    /// later), `"opentx"` (and EdgeTX before 2.10), `"betaflight"` or
    /// `"ardupilot"`. Settings it would misread are refused at start. SBUS
    /// values are encoded for it (EdgeTX's scaling under `"any"`).
    pub receiver: ReceiverChoice,
    /// When frames start: `"follow"` (default: a fresh command starts its
    /// frame as soon as the previous frame's sync allows) or `"grid"` (every
    /// `frame_us`, whenever commands come); see [`Timing`].
    pub timing: Timing,
    /// `follow`: the shortest sync gap left before a frame, in microseconds,
    /// at least 4500 (EdgeTX's 4000 us plus a margin; 3200 for Betaflight or
    /// ArduPilot alone). Default 5000. SBUS: the shortest idle line between
    /// one frame's last byte and the next frame, default and least by
    /// receiver (see [`crate::sbus::timing`]).
    pub follow_sync_min_us: Option<f64>,
    /// `follow`: the longest sync gap; when no fresh command has come by
    /// then, the last frame is repeated (or the failsafe acts). At most
    /// 18500 (EdgeTX's 19000 us less a margin), and not below
    /// `follow_sync_min_us`. Default 18000. SBUS: the longest idle line,
    /// default 20000, at most 60000.
    pub follow_sync_max_us: Option<f64>,
    /// How late an edge that receivers time (the rising edge at the pin)
    /// may be written, in microseconds, 1..=20. An edge found later than
    /// this just before its write is not written: the frame is aborted
    /// (receivers read a short frame, never a wrong value). Default 3: the
    /// receivers resolve 1 us, so a value off by less is read within a few
    /// of their capture ticks. PPM only.
    pub late_edge_guard_us: f64,
    /// CRSF only: the line rate to the flight controller, 115200..=3000000.
    /// Default 420000, what Betaflight and iNav (`CRSF_BAUDRATE`) and
    /// ExpressLRS receivers use, not the TBS specification's 416666
    /// (ArduPilot's default; 0.8 % apart, which every UART takes).
    pub crsf_baud: Option<u32>,
    /// CRSF only: what the line drives: `"flight_controller"` (default: a
    /// flight controller's receiver port) or `"module"` (an ExpressLRS
    /// transmitter module, as a radio drives one in its bay).
    pub crsf_target: crate::wire::crsf::CrsfTarget,
    /// CRSF to a module only: the model (receiver) ID sent in the model
    /// ID command, 0..=63. Default 0.
    pub crsf_model_id: u8,
}

impl Default for PpmSection {
    fn default() -> Self {
        PpmSection {
            protocol: Protocol::Ppm,
            channels: None,
            frame_us: None,
            pulse_us: 300.0,
            idle_level: None,
            order: "AETR".into(),
            default_us: 1_500.0,
            min_us: 1_000.0,
            max_us: 2_000.0,
            channel: BTreeMap::new(),
            receiver: ReceiverChoice::Any,
            timing: Timing::Follow,
            follow_sync_min_us: None,
            follow_sync_max_us: None,
            late_edge_guard_us: LATE_EDGE_GUARD_US,
            crsf_baud: None,
            crsf_target: crate::wire::crsf::CrsfTarget::FlightController,
            crsf_model_id: 0,
        }
    }
}

/// PPM's defaults of the keys whose default depends on the protocol.
pub mod ppm_defaults {
    /// `ppm.channels`.
    pub const CHANNELS: u32 = crate::wire::ppm::CHANNELS_DEFAULT;
    /// `ppm.frame_us`.
    pub const FRAME_US: f64 = crate::wire::ppm::FRAME_US_DEFAULT;
    /// `ppm.follow_sync_min_us`.
    pub const FOLLOW_SYNC_MIN_US: f64 = 5_000.0;
    /// `ppm.follow_sync_max_us`.
    pub const FOLLOW_SYNC_MAX_US: f64 = 18_000.0;
}

impl PpmSection {
    /// `ppm.channels`, or the protocol's default (PPM 8, SBUS 16).
    pub fn channels(&self) -> u32 {
        self.channels.unwrap_or(self.protocol.spec().channels)
    }

    /// `ppm.frame_us`, or the protocol's default (PPM 22500, SBUS 7000).
    pub fn frame_us(&self) -> f64 {
        self.frame_us.unwrap_or(self.protocol.spec().frame_us)
    }

    /// `ppm.idle_level`, or the protocol's default on a line that can send
    /// either (PPM low, SBUS high: a plain UART's).
    pub fn idle_level(&self) -> Level {
        self.idle_level.unwrap_or(self.protocol.spec().idle_level)
    }
}

/// `[ppm.channel.NAME]`: limits of one channel; an absent key takes the
/// `[ppm]` value.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelOverride {
    /// This channel's default in microseconds.
    pub default_us: Option<f64>,
    /// This channel's minimum in microseconds.
    pub min_us: Option<f64>,
    /// This channel's maximum in microseconds.
    pub max_us: Option<f64>,
    /// Lower end of the channel's engineering-unit range (e.g. -15.0 degrees);
    /// `unit_min` and `unit_max` are given both or neither. With them,
    /// commands may use the `units` form for this channel.
    pub unit_min: Option<f64>,
    /// Upper end of the engineering-unit range, above `unit_min`.
    pub unit_max: Option<f64>,
    /// Microseconds `unit_min` (and `norm` -1) maps to, 800..=2200. Default `min_us`.
    pub unit_us_min: Option<f64>,
    /// Microseconds `unit_max` (and `norm` +1) maps to, 800..=2200, above
    /// `unit_us_min`. Default `max_us`.
    pub unit_us_max: Option<f64>,
    /// Swaps the direction of the `units` and `norm` mappings. Default false.
    #[serde(default)]
    pub reverse: bool,
    /// Added to a `units` or `norm` value after the mapping, in microseconds,
    /// -500..=500. Default 0.
    #[serde(default)]
    pub trim_us: f64,
    /// A label for the unit (`"deg"`, `"m/s"`, ...), for people reading the
    /// configuration; needs a unit range.
    pub unit: Option<String>,
}

/// `ppm.late_edge_guard_us`'s default, us: three ticks of the receivers'
/// 1 MHz capture clocks (EdgeTX's 2 MHz capture is truncated to whole us).
pub const LATE_EDGE_GUARD_US: f64 = 3.0;
