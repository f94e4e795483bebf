//! The PPM frame model and the encoder.
//!
//! A frame of `n` channels is `n + 1` separator pulses. Pulse `i` starts at
//! `t_i`, with `t_0 = 0` (the frame start) and `t_{i+1} = t_i + value_i`: a
//! channel's value is the period between the starts of two consecutive pulses,
//! which is what a transmitter measures. After the last pulse the line rests
//! at its idle level until the next frame starts; that gap is the sync period
//! `frame - sum(values)`.

use crate::config::{self, ConfigError, PpmSection, Timing, FOLLOW_SYNC_CEILING_US};
use crate::receiver::{ReceiverChoice, Rules, SYNC_MARGIN_US};
use serde::Deserialize;

/// Most channels one frame carries (the transmitters' limit).
pub const MAX_CHANNELS: usize = 16;
/// Most edges one frame has: a rising and a falling edge for each of the
/// `MAX_CHANNELS + 1` pulses.
pub const MAX_EDGES: usize = 2 * (MAX_CHANNELS + 1);
/// Shortest separator pulse accepted in the configuration, in microseconds.
pub const PULSE_MIN_US: f64 = 50.0;

/// A logic level of the output line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Level {
    /// 0
    Low,
    /// 1
    High,
}

impl Level {
    /// The other level.
    pub fn opposite(self) -> Level {
        match self {
            Level::Low => Level::High,
            Level::High => Level::Low,
        }
    }

    /// 0 or 1.
    pub fn as_u8(self) -> u8 {
        self as u8
    }

    /// `Low` for 0, `High` for anything else.
    pub fn from_bit(bit: bool) -> Level {
        if bit {
            Level::High
        } else {
            Level::Low
        }
    }
}

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

/// The validated PPM signal: channel count, names, limits, timing, idle level.
/// Built once at start by [`FrameModel::from_config`]; encoding with it never
/// allocates.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameModel {
    names: Vec<String>,
    default_ns: [u32; MAX_CHANNELS],
    min_ns: [u32; MAX_CHANNELS],
    max_ns: [u32; MAX_CHANNELS],
    mapping: [UnitMapping; MAX_CHANNELS],
    channels: usize,
    frame_ns: u64,
    pulse_ns: u64,
    idle: Level,
    timing: Timing,
    follow_sync_ns: (u64, u64),
    receiver: ReceiverChoice,
}

impl FrameModel {
    /// Validates `[ppm]` against what transmitters accept and builds the model.
    pub fn from_config(ppm: &PpmSection) -> Result<FrameModel, ConfigError> {
        let (names, limits) = config::resolve_channels(ppm)?;
        let mut m = FrameModel {
            names,
            default_ns: [0; MAX_CHANNELS],
            min_ns: [0; MAX_CHANNELS],
            max_ns: [0; MAX_CHANNELS],
            mapping: [UnitMapping::default(); MAX_CHANNELS],
            channels: limits.len(),
            frame_ns: 0,
            pulse_ns: 0,
            idle: ppm.idle_level,
            timing: ppm.timing,
            follow_sync_ns: (0, 0),
            receiver: ppm.receiver,
        };
        let rules = ppm.receiver.rules();
        let (fewest, most) = (rules.min_channels, rules.max_channels);
        if !(fewest.0..=most.0).contains(&limits.len()) {
            let rule = if limits.len() < fewest.0 {
                fewest.1
            } else {
                most.1
            };
            return Err(invalid(
                "ppm.channels",
                format!(
                    "{} channels: {rule}; under {}: use {}..={} channels, or set ppm.receiver to the one receiver you use",
                    limits.len(),
                    receiver_key(ppm.receiver),
                    fewest.0,
                    most.0
                ),
            ));
        }
        for l in &limits {
            let (lo, hi) = (rules.channel_min_us, rules.channel_max_us);
            let (key, v, bound, rule, nearest) = if l.min_us < lo.0 {
                (&l.min_key, l.min_us, lo, "raise", lo.0)
            } else if l.max_us > hi.0 {
                (&l.max_key, l.max_us, hi, "lower", hi.0)
            } else {
                continue;
            };
            return Err(invalid(
                key,
                format!(
                    "{v} us: {}, less {} us for edge error, so {}..={} us under {}: {rule} {key} to {nearest} us",
                    bound.1,
                    crate::receiver::CHANNEL_MARGIN_US,
                    lo.0,
                    hi.0,
                    receiver_key(ppm.receiver),
                ),
            ));
        }
        for (i, l) in limits.iter().enumerate() {
            m.default_ns[i] = us_to_ns(l.default_us) as u32;
            m.min_ns[i] = us_to_ns(l.min_us) as u32;
            m.max_ns[i] = us_to_ns(l.max_us) as u32;
            m.mapping[i] = l.mapping;
        }
        let smallest_min = m.min_ns[..m.channels].iter().copied().min().unwrap_or(0) as u64;
        if !ppm.pulse_us.is_finite()
            || ppm.pulse_us < PULSE_MIN_US
            || us_to_ns(ppm.pulse_us) >= smallest_min
        {
            return Err(invalid(
                "ppm.pulse_us",
                format!(
                    "{} us must be at least {PULSE_MIN_US} us and shorter than the smallest channel minimum, {} us",
                    ppm.pulse_us,
                    smallest_min as f64 / 1e3
                ),
            ));
        }
        m.pulse_ns = us_to_ns(ppm.pulse_us);
        if !ppm.frame_us.is_finite() || ppm.frame_us <= 0.0 {
            return Err(invalid(
                "ppm.frame_us",
                format!("{} us is not a frame length", ppm.frame_us),
            ));
        }
        let frame_ns = us_to_ns(ppm.frame_us);
        m.follow_sync_ns = follow_sync(ppm, &rules)?;
        m.frame_ns = frame_ns;
        if ppm.timing == Timing::Follow {
            // Frames follow the commands: the sync gaps are the follow
            // limits, whatever the channel values; frame_us is not used.
            return Ok(m);
        }
        let sum_max: u64 = m.max_ns[..m.channels].iter().map(|&v| v as u64).sum();
        let sum_min: u64 = m.min_ns[..m.channels].iter().map(|&v| v as u64).sum();
        let (sync_min, sync_max) = (rules.sync_min_us, rules.sync_max_us);
        let sync_min_ns = us_to_ns(sync_min.0);
        if frame_ns < sum_max + sync_min_ns {
            return Err(invalid(
                "ppm.frame_us",
                format!(
                    "{} us leaves a sync gap of {} us when all {} channels are at their maximum (sum {} us); {}, and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: the gap must be at least {} us under {}: raise ppm.frame_us to at least {} us or lower the channel maximums",
                    ppm.frame_us,
                    (frame_ns as f64 - sum_max as f64) / 1e3,
                    m.channels,
                    sum_max as f64 / 1e3,
                    sync_min.1,
                    sync_min.0,
                    receiver_key(ppm.receiver),
                    (sum_max + sync_min_ns) as f64 / 1e3
                ),
            ));
        }
        if frame_ns > sum_min + us_to_ns(sync_max.0) {
            let sync_max_ns = us_to_ns(sync_max.0);
            return Err(invalid(
                "ppm.frame_us",
                format!(
                    "{} us leaves a sync gap of {} us when all {} channels are at their minimum (sum {} us); {} (a longer gap is signal loss), and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: the gap must be at most {} us under {}: lower ppm.frame_us to at most {} us or add channels",
                    ppm.frame_us,
                    (frame_ns - sum_min) as f64 / 1e3,
                    m.channels,
                    sum_min as f64 / 1e3,
                    sync_max.1,
                    sync_max.0,
                    receiver_key(ppm.receiver),
                    (sum_min + sync_max_ns) as f64 / 1e3
                ),
            ));
        }
        Ok(m)
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

    /// Separator pulse width in nanoseconds.
    pub fn pulse_ns(&self) -> u64 {
        self.pulse_ns
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
                at_ns: t + self.pulse_ns,
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

/// `ppm.receiver = "NAME"`, for messages.
fn receiver_key(r: ReceiverChoice) -> String {
    match r {
        ReceiverChoice::Any => "ppm.receiver = \"any\" (every supported receiver)".into(),
        ReceiverChoice::One(r) => format!("ppm.receiver = \"{}\"", r.name()),
    }
}

/// `ppm.follow_sync_min_us` and `ppm.follow_sync_max_us` in ns, checked
/// against the sync window of the receiver (checked in either timing, so a
/// file stays valid when its timing is switched).
fn follow_sync(ppm: &PpmSection, rules: &Rules) -> Result<(u64, u64), ConfigError> {
    let (min, max) = (ppm.follow_sync_min_us, ppm.follow_sync_max_us);
    let floor = rules.sync_min_us;
    let ceiling = rules.sync_max_us.0.min(FOLLOW_SYNC_CEILING_US);
    if !min.is_finite() || min < floor.0 {
        return Err(invalid(
            "ppm.follow_sync_min_us",
            format!(
                "{min} us: {}, and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: at least {} us under {}",
                floor.1,
                floor.0,
                receiver_key(ppm.receiver)
            ),
        ));
    }
    if !max.is_finite() || max > ceiling {
        return Err(invalid(
            "ppm.follow_sync_max_us",
            format!(
                "{max} us is above {ceiling} us: EdgeTX and OpenTX read a sync only below 19000 us, and a late frame must not take it there ({SYNC_MARGIN_US} us kept; the most for every receiver)"
            ),
        ));
    }
    if max < min {
        return Err(invalid(
            "ppm.follow_sync_max_us",
            format!("{max} us is below ppm.follow_sync_min_us = {min} us"),
        ));
    }
    Ok((us_to_ns(min), us_to_ns(max)))
}

fn invalid(key: &str, message: String) -> ConfigError {
    ConfigError::Invalid {
        key: key.into(),
        message,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    #[test]
    fn default_frame_edges() {
        let m = Config::default().validate().unwrap();
        let s = m.encode(&Channels::from_ns(&[
            1_000_000, 1_200_000, 1_700_000, 2_000_000,
        ]));
        let e = s.edges();
        assert_eq!(e.len(), 18);
        assert_eq!(
            e[0],
            Edge {
                at_ns: 0,
                level: Level::High
            }
        );
        assert_eq!(
            e[1],
            Edge {
                at_ns: 300_000,
                level: Level::Low
            }
        );
        let starts: Vec<u64> = e.iter().step_by(2).map(|e| e.at_ns).collect();
        assert_eq!(
            starts,
            [
                0, 1_000_000, 2_200_000, 3_900_000, 5_900_000, 7_400_000, 8_900_000, 10_400_000,
                11_900_000
            ]
        );
    }

    #[test]
    fn encode_clamps_and_fills_defaults() {
        let m = Config::default().validate().unwrap();
        let s = m.encode(&Channels::from_ns(&[3_000_000]));
        let starts: Vec<u64> = s.edges().iter().step_by(2).map(|e| e.at_ns).collect();
        assert_eq!(starts[1], 2_000_000, "clamped to max");
        assert_eq!(starts[2] - starts[1], 1_500_000, "ele default");
        assert_eq!(
            starts[3] - starts[2],
            1_000_000,
            "thr default is its minimum"
        );
    }

    #[test]
    fn idle_high_inverts() {
        let c = Config::parse("[ppm]\nidle_level = 'high'").unwrap();
        let m = c.validate().unwrap();
        let s = m.encode(&m.defaults());
        assert_eq!(s.edges()[0].level, Level::Low);
        assert_eq!(s.edges().last().unwrap().level, Level::High);
    }
}

#[cfg(test)]
mod units_tests {
    use crate::config::Config;
    use crate::frame::FrameModel;

    /// The defaults plus `[ppm.channel.ail]` with a -15..15 degree range and `extra` keys.
    fn ail_deg(extra: &str) -> FrameModel {
        let text =
            format!("[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\nunit = 'deg'\n{extra}");
        Config::parse(&text).unwrap().validate().unwrap()
    }

    #[test]
    fn aileron_degrees_map_linearly() {
        let m = ail_deg("");
        assert_eq!(
            m.units_to_ns(0, 3.0),
            Some((1_600_000, false)),
            "3 deg is 1600 us"
        );
        assert_eq!(m.units_to_ns(0, -15.0), Some((1_000_000, false)));
        assert_eq!(m.units_to_ns(0, 0.0), Some((1_500_000, false)));
        assert_eq!(m.units_to_ns(0, 15.0), Some((2_000_000, false)));
        // A tenth of a microsecond (and finer) survives the mapping.
        assert_eq!(m.units_to_ns(0, 3.0333), Some((1_601_110, false)));
        assert_eq!(m.ns_to_units(0, 1_600_000), Some(3.0));
        assert_eq!(m.units_to_ns(1, 3.0), None, "ele has no unit range");
    }

    #[test]
    fn reverse_and_trim() {
        assert_eq!(
            ail_deg("reverse = true").units_to_ns(0, 3.0),
            Some((1_400_000, false))
        );
        assert_eq!(
            ail_deg("trim_us = 10.0").units_to_ns(0, 3.0),
            Some((1_610_000, false))
        );
        assert_eq!(
            ail_deg("trim_us = -2.5\nreverse = true").units_to_ns(0, 3.0),
            Some((1_397_500, false))
        );
        let m = ail_deg("unit_us_min = 1100.0\nunit_us_max = 1900.0");
        assert_eq!(m.units_to_ns(0, 3.0), Some((1_580_000, false)));
        assert_eq!(m.norm_to_ns(0, -1.0), (1_100_000, false));
        assert_eq!(m.norm_to_ns(0, 1.0), (1_900_000, false));
    }

    #[test]
    fn range_ends_clamp_and_count() {
        let m = ail_deg("");
        assert_eq!(m.units_to_ns(0, 15.01), Some((2_000_000, true)));
        assert_eq!(m.units_to_ns(0, -90.0), Some((1_000_000, true)));
        assert_eq!(m.units_to_ns(0, f64::MAX), Some((2_000_000, true)));
        // Trim past the channel's max_us is clamped to it, and counted.
        let m = ail_deg("trim_us = 10.0");
        assert_eq!(m.units_to_ns(0, 15.0), Some((2_000_000, true)));
        assert_eq!(
            m.units_to_ns(0, 14.0),
            Some((1_976_667, false)),
            "rounded to the ns"
        );
        assert_eq!(m.norm_to_ns(1, 1.5), (2_000_000, true));
        assert_eq!(m.norm_to_ns(1, -1.000001), (1_000_000, true));
    }

    #[test]
    fn norm_on_a_plain_channel_and_on_throttle() {
        let m = Config::default().validate().unwrap();
        // ele: -1 is min_us, 0 the midpoint, +1 max_us.
        assert_eq!(m.norm_to_ns(1, -1.0), (1_000_000, false));
        assert_eq!(m.norm_to_ns(1, 0.0), (1_500_000, false));
        assert_eq!(m.norm_to_ns(1, 1.0), (2_000_000, false));
        assert_eq!(m.norm_to_ns(0, 0.2), (1_600_000, false));
        // thr: the same line; -1 is its minimum, zero actuation (its default).
        assert_eq!(m.norm_to_ns(2, -1.0), (m.default_ns(2), false));
        assert_eq!(m.norm_to_ns(2, 0.0), (1_500_000, false));
        assert_eq!(m.norm_to_ns(2, 1.0), (2_000_000, false));
        assert_eq!(m.ns_to_norm(2, 1_250_000), -0.5);
        let c = "[ppm.channel.thr]\nmax_us = 1900.0\nreverse = true\ntrim_us = 5.0";
        let m = Config::parse(c).unwrap().validate().unwrap();
        assert_eq!(m.norm_to_ns(2, -1.0), (1_900_000, true), "1905 us clamped");
        assert_eq!(m.norm_to_ns(2, 0.5), (1_230_000, false));
    }
}
