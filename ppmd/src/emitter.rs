//! The timing loop. Once per frame, [`LEAD_NS`] before the frame starts, it
//! takes the newest command, decides what the frame carries (the command, or
//! the failsafe action when the command is too old), encodes it and emits
//! every edge at its scheduled time: an absolute sleep until `spin_ns` before
//! the edge, a spin on CLOCK_MONOTONIC, then one write.
//!
//! Frames sit on a fixed grid (`start_k = start_0 + k * frame`): a late edge
//! never shifts later ones, and a frame whose start was missed is skipped and
//! counted. Nothing inside the loop allocates, logs or takes a lock; it only
//! updates the atomic counters in [`Stats`].

use crate::clock;
use crate::output::Output;
use crate::source::CommandSource;
use ppm_shared::config::FailsafeAction;
use ppm_shared::frame::{Channels, FrameModel};
use ppm_shared::ipc::CommandSample;
use ppm_shared::trace::TraceEdge;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering::Relaxed};

/// How long before a frame starts its command is taken and encoded.
pub const LEAD_NS: u64 = 1_000_000;
/// How often the loop looks for a command while the line is silent.
pub const IDLE_POLL_NS: u64 = 2_000_000;
/// An edge written later than this after its scheduled time counts as late.
pub const LATE_EDGE_NS: u64 = 50_000;

/// Settings of the loop, resolved from the configuration.
#[derive(Debug, Clone, Copy)]
pub struct EmitterConfig {
    /// Spin this long before each edge instead of sleeping.
    pub spin_ns: u64,
    /// A command older than this (by its ingress receive time) is not fresh.
    pub failsafe_after_ns: u64,
    /// What to emit when the newest command is not fresh.
    pub failsafe_action: FailsafeAction,
}

/// What the line is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum LineState {
    /// No pulses: no command yet, or failsafe `silence`.
    Silent = 0,
    /// Emitting fresh commands.
    Active = 1,
    /// Emitting a failsafe frame (`hold` or `default`).
    Failsafe = 2,
}

impl LineState {
    fn from_u8(v: u8) -> LineState {
        match v {
            1 => LineState::Active,
            2 => LineState::Failsafe,
            _ => LineState::Silent,
        }
    }
}

/// Counters the loop updates and other threads read.
#[derive(Debug, Default)]
pub struct Stats {
    /// Frames emitted.
    pub frames: AtomicU64,
    /// Edges written.
    pub edges: AtomicU64,
    /// Commands taken from the source.
    pub commands: AtomicU64,
    /// Samples whose channel count did not match this daemon's configuration.
    pub mismatched: AtomicU64,
    /// Frames skipped because their start had already passed.
    pub skipped_frames: AtomicU64,
    /// Edges written more than [`LATE_EDGE_NS`] after their time.
    pub late_edges: AtomicU64,
    /// Largest edge error seen (actual minus scheduled), ns.
    pub max_edge_error_ns: AtomicU64,
    /// Output writes that failed.
    pub write_errors: AtomicU64,
    /// Times the loop went from fresh commands to the failsafe action.
    pub failsafe_entries: AtomicU64,
    /// The current [`LineState`].
    state: AtomicU8,
}

impl Stats {
    /// The current line state.
    pub fn state(&self) -> LineState {
        LineState::from_u8(self.state.load(Relaxed))
    }
}

fn add(c: &AtomicU64, n: u64) {
    c.fetch_add(n, Relaxed);
}

/// Runs until `stop` is set, then finishes the frame in progress and leaves
/// the line at its idle level.
pub fn run(
    model: &FrameModel,
    cfg: &EmitterConfig,
    source: &mut dyn CommandSource,
    out: &mut dyn Output,
    stop: &AtomicBool,
    stats: &Stats,
) {
    let frame_ns = model.frame_ns();
    let mut newest: Option<(CommandSample, Channels)> = None;
    let mut next_start: Option<u64> = None;
    let mut state = LineState::Silent;
    while !stop.load(Relaxed) {
        match next_start {
            Some(start) => clock::sleep_until(start.saturating_sub(LEAD_NS)),
            None => clock::sleep_until(clock::now_ns() + IDLE_POLL_NS),
        }
        let now = clock::now_ns();
        if let Some(sample) = source.newest() {
            match sample.channels(model) {
                Some(ch) => {
                    add(&stats.commands, 1);
                    newest = Some((sample, ch));
                }
                None => add(&stats.mismatched, 1),
            }
        }
        let fresh = newest
            .filter(|(s, _)| now.saturating_sub(s.recv_mono_ns) <= cfg.failsafe_after_ns)
            .map(|(_, ch)| ch);
        let (channels, new_state) = match (fresh, newest) {
            (Some(ch), _) => (Some(ch), LineState::Active),
            // Before the first command the line stays silent whatever the action.
            (None, None) => (None, LineState::Silent),
            (None, Some((_, last))) => match cfg.failsafe_action {
                FailsafeAction::Silence => (None, LineState::Silent),
                FailsafeAction::Hold => (Some(last), LineState::Failsafe),
                FailsafeAction::Default => (Some(model.defaults()), LineState::Failsafe),
            },
        };
        if state == LineState::Active && new_state != LineState::Active {
            add(&stats.failsafe_entries, 1);
        }
        state = new_state;
        stats.state.store(state as u8, Relaxed);
        let Some(channels) = channels else {
            next_start = None;
            continue;
        };
        let mut start = next_start.unwrap_or(now + LEAD_NS);
        if now > start {
            let missed = (now - start) / frame_ns + 1;
            add(&stats.skipped_frames, missed);
            start += missed * frame_ns;
        }
        emit_frame(model, &channels, start, cfg.spin_ns, out, stats);
        next_start = Some(start + frame_ns);
    }
    if out.park(model.idle_level()).is_err() {
        add(&stats.write_errors, 1);
    }
    stats.state.store(LineState::Silent as u8, Relaxed);
}

fn emit_frame(
    model: &FrameModel,
    channels: &Channels,
    start: u64,
    spin_ns: u64,
    out: &mut dyn Output,
    stats: &Stats,
) {
    let schedule = model.encode(channels);
    for e in schedule.edges() {
        let due = start + e.at_ns;
        let actual = clock::wait_until(due, spin_ns);
        let edge = TraceEdge {
            scheduled_ns: due,
            actual_ns: actual,
            level: e.level,
        };
        if out.write(&edge).is_err() {
            add(&stats.write_errors, 1);
        }
        let err = actual - due;
        stats.max_edge_error_ns.fetch_max(err, Relaxed);
        if err > LATE_EDGE_NS {
            add(&stats.late_edges, 1);
        }
    }
    add(&stats.edges, schedule.edges().len() as u64);
    add(&stats.frames, 1);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::OutputError;
    use ppm_shared::config::Config;
    use ppm_shared::decode::{decode, DecoderLimits};
    use ppm_shared::frame::Level;
    use ppm_shared::protocol::parse;
    use std::sync::Arc;

    /// Records edges in memory (allocation in a test backend is fine).
    #[derive(Default)]
    struct Recorder(Vec<TraceEdge>);

    impl Output for Recorder {
        fn write(&mut self, edge: &TraceEdge) -> Result<(), OutputError> {
            self.0.push(*edge);
            Ok(())
        }
        fn park(&mut self, _: Level) -> Result<(), OutputError> {
            Ok(())
        }
    }

    /// Hands out one command (stamped now) on the first poll, then `after`
    /// more frames' worth of polls with nothing, then asks the loop to stop.
    struct Script {
        cmd: Option<CommandSample>,
        polls_left: u32,
        stop: Arc<AtomicBool>,
    }

    impl CommandSource for Script {
        fn newest(&mut self) -> Option<CommandSample> {
            if self.polls_left == 0 {
                self.stop.store(true, Relaxed);
            } else {
                self.polls_left -= 1;
            }
            self.cmd.take().map(|mut c| {
                c.recv_mono_ns = clock::now_ns();
                c
            })
        }
    }

    fn run_script(action: FailsafeAction, after_ms: u64, polls: u32) -> (Vec<TraceEdge>, Stats) {
        let model = Config::default().validate().unwrap();
        let cmd = parse(b"[1100, 1200, 1300, 1400]", &model).unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let mut src = Script {
            cmd: Some(CommandSample::new(&cmd, 1, 0, 0)),
            polls_left: polls,
            stop: stop.clone(),
        };
        let cfg = EmitterConfig {
            spin_ns: 100_000,
            failsafe_after_ns: after_ms * 1_000_000,
            failsafe_action: action,
        };
        let mut out = Recorder::default();
        let stats = Stats::default();
        run(&model, &cfg, &mut src, &mut out, &stop, &stats);
        (out.0, stats)
    }

    #[test]
    fn frames_carry_the_command_then_fall_silent() {
        let (edges, stats) = run_script(FailsafeAction::Silence, 100, 12);
        let frames = decode(
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
            DecoderLimits::default(),
        );
        assert!(!frames.is_empty());
        for f in &frames {
            assert_eq!(
                f.channels_us(),
                [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500]
            );
        }
        // 100 ms at 22.5 ms per frame: 5 frames, then silence.
        let n = stats.frames.load(Relaxed);
        assert!((4..=6).contains(&n), "{n} frames");
        assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
        assert_eq!(edges.len() as u64, n * 18);
        // Frames sit on one grid.
        let starts: Vec<u64> = edges.iter().step_by(18).map(|e| e.scheduled_ns).collect();
        for w in starts.windows(2) {
            assert_eq!((w[1] - w[0]) % 22_500_000, 0);
        }
        for e in &edges {
            assert!(e.actual_ns >= e.scheduled_ns, "never early");
        }
    }

    #[test]
    fn default_action_emits_defaults_after_the_command() {
        let (edges, stats) = run_script(FailsafeAction::Default, 50, 30);
        let frames = decode(
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
            DecoderLimits::default(),
        );
        let last = frames.last().unwrap();
        assert_eq!(
            last.channels_us(),
            [1500, 1500, 1000, 1500, 1500, 1500, 1500, 1500]
        );
        assert_eq!(frames[0].channels_us()[0], 1100);
        assert_eq!(stats.state(), LineState::Silent, "stopped");
        assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
    }

    #[test]
    fn hold_repeats_the_last_command() {
        let (edges, _) = run_script(FailsafeAction::Hold, 30, 20);
        let frames = decode(
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
            DecoderLimits::default(),
        );
        assert!(frames.len() >= 10);
        assert!(frames
            .iter()
            .all(|f| f.channels_us()[..4] == [1100, 1200, 1300, 1400]));
    }
}
