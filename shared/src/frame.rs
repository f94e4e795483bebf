//! The PPM frame model and the encoder.
//!
//! A frame of `n` channels is `n + 1` separator pulses. Pulse `i` starts at
//! `t_i`, with `t_0 = 0` (the frame start) and `t_{i+1} = t_i + value_i`: a
//! channel's value is the period between the starts of two consecutive pulses,
//! which is what a transmitter measures. After the last pulse the line rests
//! at its idle level until the next frame starts; that gap is the sync period
//! `frame - sum(values)`.

use crate::config::{self, ConfigError, PpmSection, SYNC_MAX_US, SYNC_MIN_US};
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
    channels: usize,
    frame_ns: u64,
    pulse_ns: u64,
    idle: Level,
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
            channels: limits.len(),
            frame_ns: 0,
            pulse_ns: 0,
            idle: ppm.idle_level,
        };
        for (i, l) in limits.iter().enumerate() {
            m.default_ns[i] = us_to_ns(l.default_us) as u32;
            m.min_ns[i] = us_to_ns(l.min_us) as u32;
            m.max_ns[i] = us_to_ns(l.max_us) as u32;
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
        let sum_max: u64 = m.max_ns[..m.channels].iter().map(|&v| v as u64).sum();
        let sum_min: u64 = m.min_ns[..m.channels].iter().map(|&v| v as u64).sum();
        let sync_min_ns = us_to_ns(SYNC_MIN_US);
        let sync_max_ns = us_to_ns(SYNC_MAX_US);
        if frame_ns < sum_max + sync_min_ns {
            return Err(invalid(
                "ppm.frame_us",
                format!(
                    "{} us leaves a sync gap of {} us when all {} channels are at their maximum (sum {} us); transmitters need at least {SYNC_MIN_US} us: raise ppm.frame_us to at least {} us or lower the channel maximums",
                    ppm.frame_us,
                    (frame_ns as f64 - sum_max as f64) / 1e3,
                    m.channels,
                    sum_max as f64 / 1e3,
                    (sum_max + sync_min_ns) as f64 / 1e3
                ),
            ));
        }
        if frame_ns > sum_min + sync_max_ns {
            return Err(invalid(
                "ppm.frame_us",
                format!(
                    "{} us leaves a sync gap of {} us when all {} channels are at their minimum (sum {} us); transmitters read a gap over {SYNC_MAX_US} us as signal loss: lower ppm.frame_us to at most {} us or add channels",
                    ppm.frame_us,
                    (frame_ns - sum_min) as f64 / 1e3,
                    m.channels,
                    sum_min as f64 / 1e3,
                    (sum_min + sync_max_ns) as f64 / 1e3
                ),
            ));
        }
        m.frame_ns = frame_ns;
        Ok(m)
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
