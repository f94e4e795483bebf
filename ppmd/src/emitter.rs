//! The timing loop. Once per frame, as late as possible before the frame's
//! first edge (the spin margin plus [`DECIDE_NS`]), it takes the newest
//! command, decides what the frame carries (the command, or the failsafe
//! action when the command is too old), encodes it and emits every edge at its
//! scheduled time through an [`EdgeTimer`]: an absolute sleep until a margin
//! before the edge, a spin on CLOCK_MONOTONIC, then one write.
//!
//! Frames sit on a fixed grid (`start_k = start_0 + k * frame`), so a late
//! edge never shifts later ones. When a frame's start has already passed, the
//! frame is moved later as a whole if the sync gaps on both sides stay within
//! what transmitters accept (counted as a late frame: its channel values stay
//! exact); otherwise it is skipped (counted as an overrun). Nothing inside the
//! loop allocates, logs or takes a lock; it updates atomic counters in
//! [`Stats`] and histograms in a [`Meter`].

use crate::clock::{self, EdgeTimer, Margin};
use crate::framelog::{self, CommandInfo, Record};
use crate::meter::Meter;
use crate::output::Output;
use crate::source::CommandSource;
use ppm_shared::config::{FailsafeAction, SYNC_MAX_US, SYNC_MIN_US};
use ppm_shared::frame::{us_to_ns, Channels, FrameModel, MAX_CHANNELS};
use ppm_shared::ipc::CommandSample;
use ppm_shared::trace::TraceEdge;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering::Relaxed};

/// Time budget to take the command and encode the frame, before the margin.
pub const DECIDE_NS: u64 = 100_000;
/// How often the loop looks for a command while the line is silent.
pub const IDLE_POLL_NS: u64 = 2_000_000;
/// An edge written later than this after its scheduled time counts as late.
pub const LATE_EDGE_NS: u64 = 10_000;

/// Settings of the loop, resolved from the configuration.
#[derive(Debug, Clone, Copy)]
pub struct EmitterConfig {
    /// How far before each edge the loop stops sleeping and spins.
    pub margin: Margin,
    /// A command older than this (by its ingress receive time) is not fresh.
    pub failsafe_after_ns: u64,
    /// What to emit when the newest command is not fresh.
    pub failsafe_action: FailsafeAction,
    /// What to emit before the first command (`Silence` or `Default`).
    pub startup: FailsafeAction,
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
    /// Frames skipped because their start had passed beyond what moving them allows.
    pub overruns: AtomicU64,
    /// Frames moved later as a whole because their start had passed.
    pub late_frames: AtomicU64,
    /// Edges written more than [`LATE_EDGE_NS`] after their time.
    pub late_edges: AtomicU64,
    /// Largest edge error seen (actual minus scheduled), ns.
    pub max_edge_error_ns: AtomicU64,
    /// Output writes that failed.
    pub write_errors: AtomicU64,
    /// Times the loop went from fresh commands to the failsafe action.
    pub failsafe_entries: AtomicU64,
    /// Current spin margin, ns.
    pub margin_ns: AtomicU64,
    /// Total time spent spinning, ns.
    pub spin_ns: AtomicU64,
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
/// the line at its idle level. With a frame log, every emitted frame and
/// every line-state change is queued to it.
#[allow(clippy::too_many_arguments)]
pub fn run(
    model: &FrameModel,
    cfg: &EmitterConfig,
    source: &mut dyn CommandSource,
    out: &mut dyn Output,
    stop: &AtomicBool,
    stats: &Stats,
    meter: &mut Meter,
    mut log: Option<&mut framelog::Producer>,
) {
    let frame_ns = model.frame_ns();
    let (sync_min_ns, sync_max_ns) = (us_to_ns(SYNC_MIN_US), us_to_ns(SYNC_MAX_US));
    let mut timer = EdgeTimer::new(cfg.margin);
    let mut newest: Option<(CommandSample, Channels)> = None;
    let mut next_start: Option<u64> = None;
    // Sync gap after the previous frame's last pulse, when frames are running.
    let mut prev_sync_ns = 0;
    let mut state = LineState::Silent;
    let mut frame_no = 0u64;
    meter.start(clock::now_ns());
    while !stop.load(Relaxed) {
        let lead = timer.margin_ns() + DECIDE_NS;
        match next_start {
            Some(start) => clock::sleep_until(start.saturating_sub(lead)),
            None => clock::sleep_until(clock::now_ns() + IDLE_POLL_NS),
        }
        let now = clock::now_ns();
        meter.maybe_hand_over(now);
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
            (None, None) => match cfg.startup {
                FailsafeAction::Default => (Some(model.defaults()), LineState::Failsafe),
                // Nothing to hold before the first command.
                _ => (None, LineState::Silent),
            },
            (None, Some((_, last))) => match cfg.failsafe_action {
                FailsafeAction::Silence => (None, LineState::Silent),
                FailsafeAction::Hold => (Some(last), LineState::Failsafe),
                FailsafeAction::Default => (Some(model.defaults()), LineState::Failsafe),
            },
        };
        if state == LineState::Active && new_state != LineState::Active {
            add(&stats.failsafe_entries, 1);
        }
        if new_state != state {
            if let Some(log) = log.as_deref_mut() {
                log.push(Record::Transition {
                    mono_ns: now,
                    real_ns: clock::realtime_ns(),
                    from: state,
                    to: new_state,
                });
            }
        }
        state = new_state;
        stats.state.store(state as u8, Relaxed);
        let Some(channels) = channels else {
            next_start = None;
            continue;
        };
        let schedule = model.encode(&channels);
        let edges = schedule.edges();
        let last_pulse = edges[edges.len() - 2].at_ns;
        let sync_ns = frame_ns - last_pulse;
        let mut start = match next_start {
            Some(s) => s,
            None => {
                prev_sync_ns = 0;
                now + lead
            }
        };
        let ready = clock::now_ns() + DECIDE_NS / 2;
        if ready > start {
            // Moving the frame later by `late` lengthens the gap before it and
            // shortens the one after it: both must stay sync periods.
            let late = ready - start;
            let fits_after = sync_ns >= sync_min_ns + late;
            let fits_before = prev_sync_ns == 0 || prev_sync_ns + late <= sync_max_ns;
            if fits_after && fits_before {
                add(&stats.late_frames, 1);
                start += late;
            } else {
                let missed = late / frame_ns + 1;
                add(&stats.overruns, missed);
                next_start = Some(start + missed * frame_ns);
                prev_sync_ns = 0;
                continue;
            }
        }
        let grid_start = next_start.unwrap_or(start);
        // Where the frame starts on the wall clock, from one pair of readings.
        let start_real_ns = clock::realtime_ns() + start.saturating_sub(clock::now_ns());
        emit_frame(edges, start, &mut timer, out, stats, meter);
        next_start = Some(grid_start + frame_ns);
        prev_sync_ns = grid_start + frame_ns - (start + last_pulse);
        stats.margin_ns.store(timer.margin_ns(), Relaxed);
        frame_no += 1;
        if let Some(log) = log.as_deref_mut() {
            let mut values_ns = [0; MAX_CHANNELS];
            for (i, v) in values_ns.iter_mut().enumerate().take(model.channels()) {
                let given = channels
                    .as_ns()
                    .get(i)
                    .copied()
                    .unwrap_or(model.default_ns(i));
                *v = model.clamp(i, given).0;
            }
            let from_command =
                state == LineState::Active || cfg.failsafe_action == FailsafeAction::Hold;
            log.push(Record::Frame {
                frame: frame_no,
                start_mono_ns: start,
                start_real_ns,
                state,
                command: newest.filter(|_| from_command).map(|(s, _)| CommandInfo {
                    seq: s.seq(),
                    ingress_seq: s.ingress_seq,
                    recv_mono_ns: s.recv_mono_ns,
                    recv_real_ns: s.recv_real_ns,
                }),
                channels: model.channels() as u8,
                values_ns,
            });
        }
    }
    if out.park(model.idle_level()).is_err() {
        add(&stats.write_errors, 1);
    }
    stats.state.store(LineState::Silent as u8, Relaxed);
}

fn emit_frame(
    edges: &[ppm_shared::frame::Edge],
    start: u64,
    timer: &mut EdgeTimer,
    out: &mut dyn Output,
    stats: &Stats,
    meter: &mut Meter,
) {
    let mut spun = 0;
    for e in edges {
        let due = start + e.at_ns;
        let w = timer.wait(due);
        let edge = TraceEdge {
            scheduled_ns: due,
            actual_ns: w.now_ns,
            level: e.level,
        };
        if out.write(&edge).is_err() {
            add(&stats.write_errors, 1);
        }
        let written = clock::now_ns();
        let err = w.now_ns - due;
        meter.edge(err, written - w.now_ns);
        if let Some(late) = w.woke_late_ns {
            meter.wake(late);
        }
        spun += w.spun_ns;
        stats.max_edge_error_ns.fetch_max(err, Relaxed);
        if err > LATE_EDGE_NS {
            add(&stats.late_edges, 1);
        }
    }
    meter.frame(spun);
    add(&stats.spin_ns, spun);
    add(&stats.edges, edges.len() as u64);
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
            margin: Margin::Fixed(100_000),
            failsafe_after_ns: after_ms * 1_000_000,
            failsafe_action: action,
            startup: FailsafeAction::Silence,
        };
        let mut out = Recorder::default();
        let stats = Stats::default();
        let (mut meter, _reader) = crate::meter::meter(1_000_000_000);
        run(
            &model, &cfg, &mut src, &mut out, &stop, &stats, &mut meter, None,
        );
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
        // Frames sit on one grid, but for those moved later as a whole.
        let starts: Vec<u64> = edges.iter().step_by(18).map(|e| e.scheduled_ns).collect();
        let off_grid = starts
            .iter()
            .filter(|&&s| !(s - starts[0]).is_multiple_of(22_500_000))
            .count() as u64;
        assert!(
            off_grid <= stats.late_frames.load(Relaxed),
            "{off_grid} frames off the grid"
        );
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
