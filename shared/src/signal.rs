//! The signal's primitives, shared by the frame model, the decoders, the
//! receiver models and the configuration: line levels, the channel and edge
//! limits, and when frames start.

use serde::{Deserialize, Serialize};

/// Most channels one frame carries (the transmitters' limit).
pub const MAX_CHANNELS: usize = 16;
/// Most edges one frame has: a rising and a falling edge for each of the
/// `MAX_CHANNELS + 1` pulses.
pub const MAX_EDGES: usize = 2 * (MAX_CHANNELS + 1);

/// Shortest sync gap (period from the last channel's pulse to the next
/// frame's first pulse) that EdgeTX/OpenTX trainer inputs recognise.
pub const SYNC_MIN_US: f64 = 4_000.0;
/// Longest sync gap EdgeTX/OpenTX trainer inputs recognise.
pub const SYNC_MAX_US: f64 = 19_000.0;
/// Smallest channel period a transmitter accepts.
pub const CHANNEL_MIN_US: f64 = 800.0;
/// Largest channel period a transmitter accepts.
pub const CHANNEL_MAX_US: f64 = 2_200.0;

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

/// When ppmd starts a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Timing {
    /// On a fixed grid, one frame every `ppm.frame_us`; a command waits for
    /// the next grid start.
    Grid,
    /// Frames follow the commands: a fresh command starts its frame as soon
    /// as the previous frame's last pulse is `ppm.follow_sync_min_us` old;
    /// without one, the last frame repeats when it is
    /// `ppm.follow_sync_max_us` old. `ppm.frame_us` is not used.
    Follow,
}

impl Timing {
    /// `"grid"` or `"follow"`, as in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            Timing::Grid => "grid",
            Timing::Follow => "follow",
        }
    }
}

impl std::str::FromStr for Timing {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "grid" => Ok(Timing::Grid),
            "follow" => Ok(Timing::Follow),
            _ => Err(format!("`{s}` is not a timing: use grid or follow")),
        }
    }
}
