//! The sweep `jitter loopback` sends: known values, different on every
//! channel and in every frame, over the whole range.
//!
//! - [`Sweep`]: frame `k` carries, on channel `c`, step `(k + offset(c))
//!   mod steps` of `LO_US..=HI_US` in `STEP_US` steps; the offsets spread
//!   the channels evenly over the steps, so no two channels carry the same
//!   value in a frame and a swapped or shifted channel shows.
//! - [`SweepSource`]: the sweep as ppmd's timing loop takes commands (a
//!   [`CommandSource`]), one step a frame, every command made before the
//!   loop starts.

use ppm_shared::frame::{Channels, FrameModel};
use ppm_shared::ipc::CommandSample;
use ppm_shared::protocol::Command;
use ppmd::source::CommandSource;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;

/// The lowest value sent, us: the usual minimum (zero throttle).
pub const LO_US: u32 = 1_000;
/// The highest value sent, us.
pub const HI_US: u32 = 2_000;
/// The step between values, us: 101 values, a whole sweep every 101 frames
/// (2.3 s at 22.5 ms).
pub const STEP_US: u32 = 10;

/// The values of the sweep (see the module's docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sweep {
    channels: usize,
}

impl Sweep {
    /// The sweep of `channels` channels (at least 1).
    pub fn new(channels: usize) -> Sweep {
        Sweep {
            channels: channels.max(1),
        }
    }

    /// Channels in a frame.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Distinct values a channel takes: `LO_US..=HI_US` in `STEP_US` steps.
    pub fn steps(&self) -> usize {
        ((HI_US - LO_US) / STEP_US) as usize + 1
    }

    /// How many steps channel `ch` is ahead of channel 0.
    pub fn offset(&self, ch: usize) -> usize {
        ch * self.steps() / self.channels
    }

    /// The value of channel `ch` in frame `k`, us.
    pub fn value_us(&self, k: usize, ch: usize) -> u32 {
        LO_US + STEP_US * ((k + self.offset(ch)) % self.steps()) as u32
    }

    /// Every channel's value in frame `k`, us.
    pub fn frame_us(&self, k: usize) -> Vec<u32> {
        (0..self.channels).map(|c| self.value_us(k, c)).collect()
    }

    /// Which step of the sweep (`0..steps`) a whole frame of `values_ns`
    /// is, if it is one: every channel's value exactly.
    pub fn step_of(&self, values_ns: &[u64]) -> Option<usize> {
        if values_ns.len() != self.channels {
            return None;
        }
        let first = values_ns[0].checked_sub(u64::from(LO_US) * 1_000)?;
        let step_ns = u64::from(STEP_US) * 1_000;
        if first % step_ns != 0 {
            return None;
        }
        let k = (first / step_ns) as usize;
        (k < self.steps()
            && values_ns
                .iter()
                .enumerate()
                .all(|(c, &v)| v == u64::from(self.value_us(k, c)) * 1_000))
        .then_some(k)
    }

    /// One line for the summary.
    pub fn describe(&self) -> String {
        format!(
            "{} channels, each {LO_US}..{HI_US} us in {STEP_US} us steps ({} values, one step a frame), channel N {} steps ahead of channel 1 times N-1",
            self.channels,
            self.steps(),
            self.offset(1)
        )
    }
}

/// The sweep as commands, one step a frame: asks the loop to stop (through
/// `stop`) after `frames` frames, as ppmd's `RepeatSource` does. Each
/// step's command is made (and checked against the model) before the loop
/// starts; [`CommandSource::newest`] only copies one and stamps it.
pub struct SweepSource {
    samples: Vec<CommandSample>,
    next: usize,
    frames: u64,
    stop: Arc<AtomicBool>,
}

impl SweepSource {
    /// The sweep's commands under `model`; `None` when the model's channel
    /// count is not the sweep's.
    pub fn new(
        sweep: &Sweep,
        model: &FrameModel,
        frames: u64,
        stop: Arc<AtomicBool>,
    ) -> Option<SweepSource> {
        if model.channels() != sweep.channels() {
            return None;
        }
        let samples = (0..sweep.steps())
            .map(|k| {
                let ns: Vec<u32> = sweep.frame_us(k).iter().map(|us| us * 1_000).collect();
                let cmd = Command {
                    seq: Some(k as u64),
                    channels: Channels::from_ns(&ns),
                    clamped: 0,
                };
                CommandSample::new(&cmd, model.fingerprint(), k as u64 + 1, 0, 0)
            })
            .collect();
        Some(SweepSource {
            samples,
            next: 0,
            frames,
            stop,
        })
    }

    /// Whether every frame was handed out (the loop was not stopped
    /// before).
    pub fn done(&self) -> bool {
        self.frames == 0
    }
}

impl CommandSource for SweepSource {
    fn newest(&mut self) -> Option<CommandSample> {
        if self.frames == 0 {
            self.stop.store(true, Relaxed);
        }
        self.frames = self.frames.saturating_sub(1);
        let mut sample = self.samples[self.next % self.samples.len()];
        self.next += 1;
        sample.recv_mono_ns = ppmd::clock::now_ns();
        Some(sample)
    }
}
