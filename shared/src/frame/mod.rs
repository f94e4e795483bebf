//! The frame model (channels, timing, and its [`WireModel`]) and the PPM
//! encoder.
//!
//! A frame of `n` channels is `n + 1` separator pulses. Pulse `i` starts at
//! `t_i`, with `t_0 = 0` (the frame start) and `t_{i+1} = t_i + value_i`: a
//! channel's value is the period between the starts of two consecutive pulses,
//! which is what a transmitter measures. After the last pulse the line rests
//! at its idle level until the next frame starts; that gap is the sync period
//! `frame - sum(values)`.
//!
//! - [`section`]: the `[ppm]` section of the configuration file.
//! - [`build`]: [`FrameModel::build`], which checks that section against
//!   the receivers and builds the model in one step.
//! - here: the model, and the encoder that turns channel values into one
//!   frame's [`EdgeSchedule`].

use crate::receiver::ReceiverChoice;
use crate::sbus::{self, timing::SbusChoice};
pub use crate::signal::{Level, Timing, MAX_CHANNELS, MAX_EDGES};
pub use crate::wire::{FrameKind, Protocol, WireModel};

pub mod build;
mod build_crsf;
mod build_sbus;
pub mod section;

pub use build::{
    channel_names, InvalidKey, FOLLOW_SYNC_CEILING_US, LATE_EDGE_GUARD_MAX_US, TRIM_MAX_US,
};
pub use section::{ChannelOverride, PpmSection, LATE_EDGE_GUARD_US};

/// Shortest separator pulse accepted in the configuration, in microseconds.
pub const PULSE_MIN_US: f64 = 50.0;

/// One edge of a frame: at `at_ns` after the frame start the line goes to `level`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Edge {
    /// Time from the frame start, in nanoseconds.
    pub at_ns: u64,
    /// The level after the edge.
    pub level: Level,
}

/// One frame's edges in time order. Fixed size, so building one never allocates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EdgeSchedule {
    edges: [Edge; MAX_EDGES],
    len: usize,
}

impl EdgeSchedule {
    /// The edges, earliest first.
    pub fn edges(&self) -> &[Edge] {
        &self.edges[..self.len]
    }
}

/// Channel values of one frame, in nanoseconds, in transmitter order.
/// Fixed size, `Copy`, allocation-free.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Channels {
    len: u8,
    ns: [u32; MAX_CHANNELS],
}

impl Channels {
    /// Channels with the given values (at most [`MAX_CHANNELS`]; extra values are ignored).
    pub fn from_ns(values: &[u32]) -> Channels {
        let mut c = Channels {
            len: values.len().min(MAX_CHANNELS) as u8,
            ns: [0; MAX_CHANNELS],
        };
        c.ns[..c.len as usize].copy_from_slice(&values[..c.len as usize]);
        c
    }

    /// The values, in nanoseconds.
    pub fn as_ns(&self) -> &[u32] {
        &self.ns[..self.len as usize]
    }

    /// Number of channels.
    pub fn len(&self) -> usize {
        self.len as usize
    }

    /// True when there are no channels.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// Rounds microseconds to whole nanoseconds.
pub fn us_to_ns(us: f64) -> u64 {
    (us * 1_000.0).round() as u64
}

/// One output's validated signal: the channel model (count, names, limits,
/// defaults, units, [fingerprint](FrameModel::fingerprint)), when frames
/// start (timing, frame length, sync or idle-line windows, idle level), and
/// what a frame is on the wire ([`WireModel`]: PPM, SBUS, ..., each with its
/// own settings). Built once at start from the checked `[ppm]` section
/// ([`FrameModel::build`]); encoding with it never allocates.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameModel {
    names: Vec<String>,
    default_ns: [u32; MAX_CHANNELS],
    min_ns: [u32; MAX_CHANNELS],
    max_ns: [u32; MAX_CHANNELS],
    mapping: [UnitMapping; MAX_CHANNELS],
    channels: usize,
    frame_ns: u64,
    idle: Level,
    timing: Timing,
    follow_sync_ns: (u64, u64),
    receiver: ReceiverChoice,
    sync_window_ns: (u64, u64),
    late_edge_guard_ns: u64,
    /// What a frame is on the wire, with the protocol's own settings.
    wire: WireModel,
}

impl FrameModel {
    /// What a frame is on the wire: the protocol seam, asked instead of
    /// branching on the protocol.
    pub fn wire(&self) -> &WireModel {
        &self.wire
    }

    /// The protocol of [`FrameModel::wire`].
    pub fn protocol(&self) -> Protocol {
        self.wire.protocol()
    }

    /// The SBUS receivers an SBUS model is for (`None` otherwise).
    pub fn sbus(&self) -> Option<&SbusChoice> {
        self.wire.sbus()
    }

    /// One SBUS frame carrying `values` (clamped to their channel's limits,
    /// missing channels at their default), encoded for the receiver of
    /// `ppm.receiver` ([`SbusChoice::encode_for`]), with the failsafe flag
    /// set when `failsafe`. Allocation-free. A PPM model encodes for
    /// EdgeTX.
    pub fn encode_sbus(&self, values: &Channels, failsafe: bool) -> [u8; sbus::FRAME_LEN] {
        let mut raw = [0u16; sbus::CHANNELS];
        for (i, r) in raw.iter_mut().enumerate().take(self.channels) {
            let v = values.as_ns().get(i).copied().unwrap_or(self.default_ns[i]);
            let ns = u64::from(self.clamp(i, v).0);
            *r = match self.sbus() {
                Some(c) => c.raw(ns),
                None => sbus::raw_for(sbus::SbusReceiver::EdgeTx, ns),
            };
        }
        let flags = sbus::Flags {
            failsafe,
            ..Default::default()
        };
        sbus::encode(&raw, flags)
    }

    /// One frame of bytes ([`WireModel::encode_bytes`]) carrying `values`
    /// (clamped to their channel's limits, missing channels at their
    /// default), flagged failsafe when `failsafe`, in `out`; how many bytes.
    /// Allocation-free.
    pub fn encode_bytes(
        &self,
        values: &Channels,
        failsafe: bool,
        out: &mut [u8; crate::wire::MAX_FRAME_BYTES],
    ) -> usize {
        let mut ns = [0u64; MAX_CHANNELS];
        for (i, n) in ns.iter_mut().enumerate().take(self.channels) {
            let v = values.as_ns().get(i).copied().unwrap_or(self.default_ns[i]);
            *n = u64::from(self.clamp(i, v).0);
        }
        self.wire.encode_bytes(&ns, failsafe, out)
    }

    /// What the receiver values are encoded for reads of an SBUS frame's
    /// channels, ns (its scaling, whatever the header and flags).
    pub fn sbus_reads(&self, frame: &[u8; sbus::FRAME_LEN]) -> [u64; sbus::CHANNELS] {
        let r = self
            .sbus()
            .map_or(sbus::SbusReceiver::EdgeTx, |c| c.encode_for());
        sbus::channels(frame).map(|raw| r.read_ns(raw))
    }
    /// When frames start.
    pub fn timing(&self) -> Timing {
        self.timing
    }

    /// A fingerprint of what a command means under this model: channel
    /// count and names (the order), every channel's default, limits and
    /// `units`/`norm` mapping. udp-ingress stamps it on every command and
    /// ppmd refuses a command made under another model (FNV-1a, 64 bits;
    /// the same on every machine).
    pub fn fingerprint(&self) -> u64 {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        let mut eat = |bytes: &[u8]| {
            for b in bytes {
                h = (h ^ *b as u64).wrapping_mul(0x0000_0100_0000_01b3);
            }
        };
        eat(&(self.channels as u64).to_le_bytes());
        for i in 0..self.channels {
            eat(self.names[i].as_bytes());
            eat(&[0]);
            for v in [self.default_ns[i], self.min_ns[i], self.max_ns[i]] {
                eat(&v.to_le_bytes());
            }
            let m = &self.mapping[i];
            let (lo, hi) = m.units.unwrap_or((f64::NAN, f64::NAN));
            for v in [lo, hi, m.us_lo, m.us_hi, m.trim_us] {
                eat(&v.to_bits().to_le_bytes());
            }
            eat(&[m.units.is_some() as u8, m.reverse as u8]);
        }
        h
    }

    /// The receiver the model was checked for.
    pub fn receiver(&self) -> ReceiverChoice {
        self.receiver
    }

    /// The shortest and the longest sync gap the receivers of
    /// `ppm.receiver` all read, less the margin ppm keeps for a late edge,
    /// ns (4500..18500 us for `any`): how far a late frame may move.
    pub fn sync_window_ns(&self) -> (u64, u64) {
        self.sync_window_ns
    }

    /// How late an edge receivers time may be written, ns: a later one is
    /// not written and its frame is aborted (`ppm.late_edge_guard_us`).
    pub fn late_edge_guard_ns(&self) -> u64 {
        self.late_edge_guard_ns
    }

    /// The same model without a late-edge guard: every edge is written,
    /// however late. Only for measuring how late a loop writes (the
    /// plain-sleep baseline of `timing-bench`); ppmd never runs one.
    pub fn unguarded(&self) -> FrameModel {
        FrameModel {
            late_edge_guard_ns: u64::MAX,
            ..self.clone()
        }
    }

    /// Whether receivers time an edge to `level`: the rising edge at the pin
    /// (the pulses' starts with idle low, their ends with idle high).
    pub fn timed(&self, level: Level) -> bool {
        level == Level::High
    }

    /// How long after its pulse's start a pulse's timed edge comes: 0 with
    /// idle low, the pulse width with idle high.
    pub fn timed_offset_ns(&self) -> u64 {
        match self.idle {
            Level::Low => 0,
            Level::High => self.pulse_ns(),
        }
    }

    /// `follow` timing's shortest and longest sync gap, ns.
    pub fn follow_sync_ns(&self) -> (u64, u64) {
        self.follow_sync_ns
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Channel names in transmitter order (`ail`, `ele`, `thr`, `rud`, `aux1`, ...).
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// The index of a channel name.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Frame length in nanoseconds.
    pub fn frame_ns(&self) -> u64 {
        self.frame_ns
    }

    /// Separator pulse width in nanoseconds (0 without pulses).
    pub fn pulse_ns(&self) -> u64 {
        self.wire.pulse_ns()
    }

    /// The level between pulses and while silent.
    pub fn idle_level(&self) -> Level {
        self.idle
    }

    /// Default of channel `i` in nanoseconds.
    pub fn default_ns(&self, i: usize) -> u32 {
        self.default_ns[i]
    }

    /// Minimum of channel `i` in nanoseconds.
    pub fn min_ns(&self, i: usize) -> u32 {
        self.min_ns[i]
    }

    /// Maximum of channel `i` in nanoseconds.
    pub fn max_ns(&self, i: usize) -> u32 {
        self.max_ns[i]
    }

    /// Every channel at its default.
    pub fn defaults(&self) -> Channels {
        Channels::from_ns(&self.default_ns[..self.channels])
    }

    /// Clamps `ns` to channel `i`'s limits; the flag says whether it changed.
    pub fn clamp(&self, i: usize, ns: u32) -> (u32, bool) {
        let c = ns.clamp(self.min_ns[i], self.max_ns[i]);
        (c, c != ns)
    }

    /// The edge schedule of one frame carrying `values`. Values are clamped to
    /// their channel's limits, missing channels take their default and extra
    /// ones are ignored, so the result always satisfies the validated timing.
    pub fn encode(&self, values: &Channels) -> EdgeSchedule {
        let active = self.idle.opposite();
        let mut s = EdgeSchedule {
            edges: [Edge {
                at_ns: 0,
                level: self.idle,
            }; MAX_EDGES],
            len: 0,
        };
        let mut t = 0u64;
        for i in 0..=self.channels {
            s.edges[s.len] = Edge {
                at_ns: t,
                level: active,
            };
            s.edges[s.len + 1] = Edge {
                at_ns: t + self.pulse_ns(),
                level: self.idle,
            };
            s.len += 2;
            if i < self.channels {
                let v = values.as_ns().get(i).copied().unwrap_or(self.default_ns[i]);
                t += self.clamp(i, v).0 as u64;
            }
        }
        s
    }
}

/// How one channel's `units` and `norm` command values become a period
/// (`[ppm.channel.NAME]` keys `unit_min`, `unit_max`, `unit_us_min`,
/// `unit_us_max`, `reverse`, `trim_us`). `Copy`, so [`FrameModel`] stays
/// cheap to clone.
///
/// A value is first clamped to its range (`unit_min..=unit_max`, or
/// `-1..=1` for `norm`) and turned into a position `f` in `0..=1` along it:
/// `f = (u - unit_min) / (unit_max - unit_min)` (`norm`: `f = (n + 1) / 2`),
/// or `1 - f` computed as `(unit_max - u) / (unit_max - unit_min)` (`norm`:
/// `(1 - n) / 2`) when `reverse`. Then
/// `us = us_lo + f * (us_hi - us_lo) + trim_us`, rounded to whole
/// nanoseconds and clamped to the channel's `min_us..=max_us`. All in f64.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct UnitMapping {
    /// `(unit_min, unit_max)`, when the channel has a unit range.
    pub units: Option<(f64, f64)>,
    /// Microseconds of `unit_min` (and of `norm` -1): `unit_us_min`, default `min_us`.
    pub us_lo: f64,
    /// Microseconds of `unit_max` (and of `norm` +1): `unit_us_max`, default `max_us`.
    pub us_hi: f64,
    /// Swaps the direction: `unit_min` (`norm` -1) maps to `us_hi`.
    pub reverse: bool,
    /// Added after the mapping, in microseconds (may be negative).
    pub trim_us: f64,
}

impl UnitMapping {
    /// Microseconds at position `f` (0..=1, already reversed) along `us_lo..us_hi`.
    fn us_at(&self, f: f64) -> f64 {
        self.us_lo + f * (self.us_hi - self.us_lo) + self.trim_us
    }

    /// Position along `us_lo..us_hi` (0..=1, reversal applied) of `value`
    /// clamped to `lo..=hi`; the flag says whether `value` was outside.
    fn position(&self, value: f64, lo: f64, hi: f64) -> (f64, bool) {
        let v = value.clamp(lo, hi);
        let f = if self.reverse {
            (hi - v) / (hi - lo)
        } else {
            (v - lo) / (hi - lo)
        };
        (f, v != value)
    }

    /// The inverse of both: position of `us` along the value range (0 at
    /// `unit_min` or `norm` -1, reversal undone, not clamped).
    fn position_of(&self, us: f64) -> f64 {
        let f = (us - self.trim_us - self.us_lo) / (self.us_hi - self.us_lo);
        if self.reverse {
            1.0 - f
        } else {
            f
        }
    }
}

/// Engineering units and normalised values (the `units` and `norm` command forms).
impl FrameModel {
    /// The mapping of channel `i`.
    pub fn mapping(&self, i: usize) -> &UnitMapping {
        &self.mapping[i]
    }

    /// `(unit_min, unit_max)` of channel `i`, when it has a unit range.
    pub fn unit_range(&self, i: usize) -> Option<(f64, f64)> {
        self.mapping[i].units
    }

    /// Channel `i`'s period for `value` in its engineering units (see
    /// [`UnitMapping`]), and whether it was clamped (to the unit range or to
    /// the channel's limits). `None` when the channel has no unit range.
    /// `value` must not be NaN.
    pub fn units_to_ns(&self, i: usize, value: f64) -> Option<(u32, bool)> {
        let m = &self.mapping[i];
        let (lo, hi) = m.units?;
        let (f, clamped) = m.position(value, lo, hi);
        let (ns, limited) = self.us_to_clamped_ns(i, m.us_at(f));
        Some((ns, clamped || limited))
    }

    /// Channel `i`'s period for a normalised `value` in -1..=1 (see
    /// [`UnitMapping`]: -1 is `unit_us_min`, default `min_us`; +1 is
    /// `unit_us_max`, default `max_us`; 0 the midpoint; throttle included),
    /// and whether it was clamped. `value` must not be NaN.
    pub fn norm_to_ns(&self, i: usize, value: f64) -> (u32, bool) {
        let m = &self.mapping[i];
        let (f, clamped) = m.position(value, -1.0, 1.0);
        let (ns, limited) = self.us_to_clamped_ns(i, m.us_at(f));
        (ns, clamped || limited)
    }

    /// The unit value channel `i`'s mapping gives `ns` (the inverse of
    /// [`FrameModel::units_to_ns`] before clamping). `None` without a unit range.
    pub fn ns_to_units(&self, i: usize, ns: u32) -> Option<f64> {
        let m = &self.mapping[i];
        let (lo, hi) = m.units?;
        Some(lo + m.position_of(ns as f64 / 1e3) * (hi - lo))
    }

    /// The normalised value channel `i`'s mapping gives `ns` (the inverse of
    /// [`FrameModel::norm_to_ns`] before clamping).
    pub fn ns_to_norm(&self, i: usize, ns: u32) -> f64 {
        self.mapping[i].position_of(ns as f64 / 1e3) * 2.0 - 1.0
    }

    /// Rounds `us` to whole nanoseconds and clamps it to channel `i`'s limits.
    fn us_to_clamped_ns(&self, i: usize, us: f64) -> (u32, bool) {
        let ns = (us * 1e3).round();
        let c = ns.clamp(self.min_ns[i] as f64, self.max_ns[i] as f64);
        (c as u32, c != ns)
    }
}

#[cfg(test)]
mod tests;
