//! The loop's tests run on a simulated clock ([`crate::clock::sim`]): its
//! time moves only when the loop reads it, spins or sleeps, and commands,
//! stalls and the stop come at set simulated times. So every count in them
//! is exact, on any machine, and no test sleeps.
//!
//! Here: the fixtures (simulated lines and command sources, and
//! [`output`], the one way the tests build an output). The tests are in
//! `grid`, `follow` and `properties`.

use super::pace::align;
use super::*;
use crate::clock::sim::{Sim, START_NS};
use crate::line::{FrameEdge, LineError, WholeFrame};
use crate::meter::MeterReader;
use ppm_shared::config::Config;
use ppm_shared::config::FOLLOW_SYNC_CEILING_US;
use ppm_shared::decode::{decode, DecoderLimits};
use ppm_shared::frame::{us_to_ns, Level};
use ppm_shared::protocol::parse;
use ppm_shared::receiver::{decode_as, Receiver};
use ppm_shared::trace::TraceEdge;
use std::sync::Arc;

mod follow;
mod grid;
mod module;
mod properties;
mod sbus;

const MS: u64 = 1_000_000;
/// The default model's frame.
const FRAME_NS: u64 = 22_500_000;
/// What one output decides ahead of its frame: DECIDE_NS.
const LEAD_1: u64 = DECIDE_NS;

/// Records edges in memory (allocation in a test backend is fine); with
/// a stall, holds the loop up for `stall.1` in its `stall.0`th write.
#[derive(Default)]
struct Recorder {
    edges: Vec<TraceEdge>,
    stall: Option<(usize, u64, Sim)>,
}

impl Line for Recorder {
    fn write(&mut self, edge: &TraceEdge) -> Result<(), LineError> {
        self.edges.push(*edge);
        if let Some((after, ns, sim)) = &self.stall {
            if self.edges.len() == *after {
                sim.advance(*ns);
            }
        }
        Ok(())
    }
    fn park(&mut self, _: Level) -> Result<(), LineError> {
        Ok(())
    }
    fn stamped(&self) -> bool {
        true
    }
}

fn sample(model: &FrameModel, cmd: &[u8], seq: u64) -> CommandSample {
    CommandSample::new(&parse(cmd, model).unwrap(), model.fingerprint(), seq, 0, 0)
}

/// Commands published at set simulated times, each stamped with its
/// time and followed by a wake-up on its wake fd, as udp-ingress
/// publishes them.
struct Feed {
    sim: Sim,
    /// (published at, first value in us, sample), by time.
    cmds: Vec<(u64, u32, CommandSample)>,
    /// Commands handed out or passed over so far.
    taken: usize,
    fd: RawFd,
    with_fd: bool,
    /// Hands out this fd number instead of its own.
    fake_fd: Option<RawFd>,
    /// Clearing the wake-ups fails (they stay pending).
    broken_clear: bool,
}

impl Feed {
    fn new(sim: &Sim, model: &FrameModel, cmds: &[(u64, &str)]) -> Feed {
        let cmds: Vec<(u64, u32, CommandSample)> = cmds
            .iter()
            .enumerate()
            .map(|(k, (at, c))| {
                let mut s = sample(model, c.as_bytes(), k as u64 + 1);
                s.recv_mono_ns = *at;
                (*at, s.channels(model).unwrap().as_ns()[0] / 1_000, s)
            })
            .collect();
        let fd = sim.wake_fd(cmds.iter().map(|c| c.0).collect());
        Feed {
            sim: sim.clone(),
            cmds,
            taken: 0,
            fd,
            with_fd: true,
            fake_fd: None,
            broken_clear: false,
        }
    }

    /// `count` commands `every_ms` apart from 20 ms on, the k-th
    /// `[1100 + 10 k, 1900]`.
    fn paced(sim: &Sim, model: &FrameModel, count: u32, every_ms: u64) -> Feed {
        let cmds: Vec<(u64, String)> = (0..count)
            .map(|k| {
                let at = START_NS + (20 + k as u64 * every_ms) * MS;
                (at, format!("[{}, 1900]", 1_100 + 10 * k))
            })
            .collect();
        let cmds: Vec<(u64, &str)> = cmds.iter().map(|(t, c)| (*t, c.as_str())).collect();
        Feed::new(sim, model, &cmds)
    }

    /// When the last command is published.
    fn last_at(&self) -> u64 {
        self.cmds.last().unwrap().0
    }

    /// (published at, first value): as `check_follow` takes them.
    fn made(&self) -> Vec<(u64, u32)> {
        self.cmds.iter().map(|c| (c.0, c.1)).collect()
    }
}

impl CommandSource for Feed {
    fn newest(&mut self) -> Option<CommandSample> {
        let now = self.sim.at();
        let there = self.cmds.partition_point(|c| c.0 <= now);
        (there > self.taken).then(|| {
            self.taken = there;
            self.cmds[there - 1].2
        })
    }
    fn wake_fd(&self) -> Option<RawFd> {
        self.with_fd.then(|| self.fake_fd.unwrap_or(self.fd))
    }
    fn clear_wake(&mut self) -> bool {
        if self.broken_clear {
            return false;
        }
        self.sim.clear(self.fd);
        true
    }
}

/// The same command, freshly stamped, at every look.
struct Fresh {
    sim: Sim,
    sample: CommandSample,
}

impl Fresh {
    fn new(sim: &Sim, model: &FrameModel, cmd: &str) -> Fresh {
        Fresh {
            sim: sim.clone(),
            sample: sample(model, cmd.as_bytes(), 1),
        }
    }
}

impl CommandSource for Fresh {
    fn newest(&mut self) -> Option<CommandSample> {
        self.sample.recv_mono_ns = self.sim.at();
        Some(self.sample)
    }
}

/// What a test runs an output with: its failsafe settings and the loop's
/// spin margin.
#[derive(Debug, Clone, Copy)]
struct Settings {
    margin: Margin,
    failsafe: EmitterConfig,
}

/// A fixed 100 us margin and this failsafe, silent at startup.
fn cfg(failsafe_after_ms: u64, action: FailsafeAction) -> Settings {
    Settings {
        margin: Margin::Fixed(100_000),
        failsafe: EmitterConfig {
            failsafe_after_ns: failsafe_after_ms * MS,
            failsafe_action: action,
            startup: FailsafeAction::Silence,
        },
    }
}

/// Runs `outputs` on `sim` with the spin `margin` until the first reading
/// `until_ms` after the simulation's start (frames in progress then are
/// finished).
fn run_until(
    sim: &Sim,
    margin: Margin,
    outputs: &mut [Output],
    banks: &mut [&mut dyn Bank],
    until_ms: u64,
) {
    let stop = AtomicBool::new(false);
    let stop = Arc::new(stop);
    sim.stop_at(START_NS + until_ms * MS, stop.clone());
    run_outputs(sim, margin, outputs, banks, &stop);
}

/// What a test keeps of one output's recording: its counters, and its
/// histograms with their reading side.
struct Kit {
    stats: Stats,
    meter: Meter,
    _reader: MeterReader,
}

impl Default for Kit {
    fn default() -> Kit {
        let (meter, reader) = crate::meter::meter(1_000_000_000);
        Kit {
            stats: Stats::default(),
            meter,
            _reader: reader,
        }
    }
}

/// The one way the tests build an output: `model` with `cfg`'s failsafe
/// settings, from `source` into `line`, recorded in `kit`, without a frame
/// log.
fn output<'a>(
    model: &'a FrameModel,
    cfg: Settings,
    source: &'a mut dyn CommandSource,
    line: LineRef<'a>,
    kit: &'a mut Kit,
) -> Output<'a> {
    Output {
        model,
        cfg: cfg.failsafe,
        source,
        line,
        rec: Recording {
            stats: &kit.stats,
            meter: &mut kit.meter,
            log: None,
        },
        sync: None,
    }
}

/// Runs one output of `model` from `source` into `line`.
fn run_one(
    sim: &Sim,
    model: &FrameModel,
    cfg: Settings,
    source: &mut dyn CommandSource,
    line: LineRef,
    until_ms: u64,
) -> Stats {
    let mut kit = Kit::default();
    run_until(
        sim,
        cfg.margin,
        &mut [output(model, cfg, source, line, &mut kit)],
        &mut [],
        until_ms,
    );
    kit.stats
}

/// Runs two outputs, each (model, settings, source, line), on `sim` until
/// `until_ms`; their counters. One loop has one spin margin: theirs.
fn run_two(
    sim: &Sim,
    a: (&FrameModel, Settings, &mut dyn CommandSource, LineRef),
    b: (&FrameModel, Settings, &mut dyn CommandSource, LineRef),
    until_ms: u64,
) -> (Stats, Stats) {
    assert_eq!(a.1.margin, b.1.margin, "one loop, one margin");
    let (mut kit_a, mut kit_b) = (Kit::default(), Kit::default());
    run_until(
        sim,
        a.1.margin,
        &mut [
            output(a.0, a.1, a.2, a.3, &mut kit_a),
            output(b.0, b.1, b.2, b.3, &mut kit_b),
        ],
        &mut [],
        until_ms,
    );
    (kit_a.stats, kit_b.stats)
}

/// [`run_one`] with a frame log.
fn run_logged(
    sim: &Sim,
    model: &FrameModel,
    cfg: Settings,
    source: &mut dyn CommandSource,
    line: LineRef,
    log: &mut framelog::Producer,
    until_ms: u64,
) -> Stats {
    let mut kit = Kit::default();
    let mut o = output(model, cfg, source, line, &mut kit);
    o.rec.log = Some(log);
    run_until(sim, cfg.margin, &mut [o], &mut [], until_ms);
    kit.stats
}

/// The defaults, on a grid (the default timing is follow).
fn grid_model() -> FrameModel {
    timed_model(false, "")
}

const CMD: &str = "[1100, 1200, 1300, 1400]";
const CMD_US: [u64; 8] = [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500];

/// One command at the start, then nothing: the default model's frames
/// into `line`, with this failsafe.
fn run_once(
    line: LineRef,
    action: FailsafeAction,
    failsafe_after_ms: u64,
    until_ms: u64,
) -> (Sim, Stats) {
    let sim = Sim::new();
    let model = grid_model();
    let mut src = Feed::new(&sim, &model, &[(START_NS, CMD)]);
    let stats = run_one(
        &sim,
        &model,
        cfg(failsafe_after_ms, action),
        &mut src,
        line,
        until_ms,
    );
    (sim, stats)
}

fn scheduled(edges: &[TraceEdge]) -> Vec<(u64, Level)> {
    edges.iter().map(|e| (e.scheduled_ns, e.level)).collect()
}

fn channels_of(edges: &[(u64, Level)]) -> Vec<Vec<u64>> {
    decode(edges.iter().copied(), Level::High, DecoderLimits::default())
        .iter()
        .map(|f| f.channels_us().to_vec())
        .collect()
}

/// Where each frame a transmitter reads starts.
fn starts_of(edges: &[(u64, Level)]) -> Vec<u64> {
    decode(edges.iter().copied(), Level::High, DecoderLimits::default())
        .iter()
        .map(|f| f.start_ns)
        .collect()
}

/// How many frames an output that decides `lead` before each start, on the
/// grid `first + k * frame`, decides before the stop at `until_ms`.
fn frames_before_stop(first: u64, frame: u64, lead: u64, until_ms: u64) -> u64 {
    (0..)
        .take_while(|k| first + k * frame - lead < START_NS + until_ms * MS)
        .count() as u64
}

/// The first frame: the command is there at the first look, at the
/// start; the frame is decided then and starts `DECIDE_NS` plus a
/// lead-in later.
fn first_start(edges: &[TraceEdge]) -> u64 {
    let start = edges[2].scheduled_ns;
    assert_eq!(
        start - edges[0].scheduled_ns,
        LEAD_IN_NS,
        "the lead-in pulse"
    );
    assert!(
        (start - START_NS).abs_diff(LEAD_1 + LEAD_IN_NS) < 10_000,
        "first frame at {} ns",
        start - START_NS
    );
    start
}

/// A line that takes frames whole (as the SPI line does): each call's
/// edges. It has no single-edge write at all ([`FrameLine`] has none).
#[derive(Default)]
struct WholeFrames {
    frames: Vec<Vec<FrameEdge>>,
    /// SBUS frames: their bytes and when each was due.
    sbus: Vec<([u8; ppm_shared::sbus::FRAME_LEN], u64)>,
    /// When each frame's transfer started, with a simulation to read.
    started: Vec<u64>,
    sim: Option<Sim>,
}

impl FrameLine for WholeFrames {
    fn park(&mut self, _: Level) -> Result<(), LineError> {
        Ok(())
    }
    fn write_frame(&mut self, frame: WholeFrame<'_>) -> Result<(), LineError> {
        match frame {
            WholeFrame::Ppm { edges, .. } => self.frames.push(edges.to_vec()),
            WholeFrame::Bytes { bytes, due_ns } => self
                .sbus
                .push((bytes.try_into().expect("an SBUS frame"), due_ns)),
        }
        if let Some(sim) = &self.sim {
            self.started.push(sim.at());
        }
        Ok(())
    }
}

/// The default model's waveform from a command re-stamped at every look
/// (so every frame carries it), with one stall of the loop, for
/// `until_ms`; and the same without the stall.
fn stalled_run(
    model: &FrameModel,
    stall: Option<(u64, u64)>,
    until_ms: u64,
) -> (Vec<TraceEdge>, Stats) {
    let sim = Sim::new();
    if let Some((at, ns)) = stall {
        sim.stall_at(at, ns);
    }
    let mut src = Fresh::new(&sim, model, CMD);
    let mut out = Recorder::default();
    let stats = run_one(
        &sim,
        model,
        cfg(100, FailsafeAction::Silence),
        &mut src,
        LineRef::Edges(&mut out),
        until_ms,
    );
    (out.edges, stats)
}

/// Records bank writes: (scheduled, mask, levels).
#[derive(Default)]
struct BankRecorder(Vec<(u64, u64, u64)>);

impl Bank for BankRecorder {
    fn write(&mut self, due: u64, mask: u64, levels: u64) -> Result<(), LineError> {
        self.0.push((due, mask, levels));
        Ok(())
    }
    fn park(&mut self, _: u32, _: Level) -> Result<(), LineError> {
        Ok(())
    }
}

/// Checks an output wrote its frames' edges plus one lead-in pulse.
fn assert_edges_add_up(edges: usize, stats: &Stats, per_frame: u64) {
    let frames = stats.frames.load(Relaxed);
    assert_eq!(
        edges as u64,
        frames * per_frame + 2,
        "{edges} edges for {frames} frames of {per_frame}"
    );
    assert_eq!(stats.edges.load(Relaxed), edges as u64);
    assert_eq!(stats.late_frames.load(Relaxed), 0);
    assert_eq!(stats.overruns.load(Relaxed), 0);
    assert_eq!(stats.write_errors.load(Relaxed), 0);
}

/// A follow-timing model: the defaults with `timing = "follow"`.
fn follow_model(extra: &str) -> FrameModel {
    timed_model(true, extra)
}

/// Every row of the frame log at `path` (frames and state changes).
fn log_rows(path: &std::path::Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The defaults with follow or grid timing and `extra` `[ppm]` keys.
fn timed_model(follow: bool, extra: &str) -> FrameModel {
    let timing = if follow { "follow" } else { "grid" };
    Config::parse(&format!("[ppm]\ntiming = '{timing}'\n{extra}"))
        .unwrap()
        .validate()
        .unwrap()
}

/// The other outputs' model in the multi-output properties.
const SIX_AT_20_MS: &str = "channels = 6\norder = 'TAER'\nframe_us = 20000.0";

/// A frame as sent: its first edge, its last pulse, its values (the
/// first apart), and whether a lone (lead-in) pulse came before it.
#[derive(Debug)]
struct Sent {
    start: u64,
    last_pulse: u64,
    first_us: u32,
    values_us: Vec<u64>,
    after_lead_in: bool,
    /// Where the lone pulse (or the previous frame's last pulse) was.
    before: Option<u64>,
    /// Cut short: an aborted frame (`values_us` holds what it carried).
    aborted: bool,
}

/// The frames in a recorded single-output waveform of `channels`
/// channels, from the scheduled edges: a run of pulses a channel apart
/// is a frame (an aborted one when it has fewer pulses), a pulse
/// followed by a lead-in's gap a lead-in pulse.
fn sent_frames(edges: &[TraceEdge], channels: usize) -> Vec<Sent> {
    let leading: Vec<u64> = edges
        .iter()
        .filter(|e| e.level == Level::High)
        .map(|e| e.scheduled_ns)
        .collect();
    let mut frames: Vec<Sent> = Vec::new();
    let (mut i, mut lone) = (0, None);
    while i < leading.len() {
        let gap = leading.get(i + 1).map(|n| n - leading[i]);
        let apart = |g: u64| g <= us_to_ns(ppm_shared::config::CHANNEL_MAX_US) * 2;
        // A lead-in is followed by a frame's first pulse, never by
        // another lead-in: after one, a pulse this far from the next is
        // a frame aborted at its first pulse, and then a sync (in follow
        // timing it can be this short).
        let lead_in_gap = |g: u64| (LEAD_IN_NS..=LEAD_IN_NS + ALIAS_SHIFT_MAX_NS).contains(&g);
        if lone.is_none() && gap.is_some_and(lead_in_gap) {
            lone = Some(leading[i]);
            i += 1;
            continue;
        }
        let mut per = 1;
        while per < channels + 1
            && i + per < leading.len()
            && apart(leading[i + per] - leading[i + per - 1])
        {
            per += 1;
        }
        let values_us: Vec<u64> = leading[i..i + per]
            .windows(2)
            .map(|w| (w[1] - w[0] + 500) / 1_000)
            .collect();
        frames.push(Sent {
            start: leading[i],
            last_pulse: leading[i + per - 1],
            first_us: values_us.first().map_or(0, |&v| v as u32),
            aborted: per < channels + 1,
            values_us,
            after_lead_in: lone.is_some(),
            before: lone.or(frames.last().map(|f| f.last_pulse)),
        });
        lone = None;
        i += per;
    }
    frames
}

/// Checks that every receiver hands on every frame sent (but those it
/// reads while it locks on), with its values to the microsecond.
fn assert_read_by_every_receiver(edges: &[TraceEdge], frames: &[Sent]) {
    for r in Receiver::ALL {
        let (read, _) = decode_as(
            r,
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
        );
        // A trainer input uses channels as they come: the last frame
        // too, which no sync closes. The others hand a frame on at the
        // sync after it: not the last one.
        let trainer = matches!(r, Receiver::EdgeTx | Receiver::OpenTx);
        let read: Vec<_> = read.iter().filter(|f| f.complete || trainer).collect();
        let closed = frames.len() - !trainer as usize;
        let want = closed.saturating_sub(r.warmup_frames());
        assert_eq!(
            read.len(),
            want,
            "{r:?} read {} of {} frames",
            read.len(),
            frames.len()
        );
        for f in read {
            let sent = frames
                .iter()
                .find(|s| s.start == f.start_ns)
                .expect("a frame sent");
            assert_eq!(f.channels_us()[0], sent.first_us as u64, "{r:?}");
            assert_eq!(f.channels_us()[1], 1_900, "{r:?}");
        }
    }
}

/// Checks what follow timing promises about a single output's frames, on
/// the scheduled edges: every receiver reads every frame; the sync
/// before a frame is within the follow limits (or the frame had a
/// lead-in); a frame carrying a command that was there at the previous
/// frame's earliest start starts then, at the shortest sync; a repeat
/// comes at the longest sync; a frame carries the newest command
/// published before it was decided (READY_NS before its start at the
/// latest, the output's lead before it at the earliest; after a lead-in,
/// a lead-in earlier). `made`: (published at, first value), by time.
fn check_follow(
    edges: &[TraceEdge],
    model: &FrameModel,
    made: &[(u64, u32)],
    stats: &Stats,
    lead: u64,
) -> Vec<Sent> {
    let frames = sent_frames(edges, model.channels());
    assert!(frames.iter().all(|f| !f.aborted));
    assert_eq!(stats.aborted_frames.load(Relaxed), 0);
    assert_eq!(frames.len() as u64, stats.frames.load(Relaxed));
    assert_read_by_every_receiver(edges, &frames);
    let (min, max) = model.follow_sync_ns();
    for (i, f) in frames.iter().enumerate() {
        let prev = i.checked_sub(1).map(|j| &frames[j]);
        let sync = prev.map(|p| f.start - p.last_pulse);
        let lead_in = sync.is_none_or(|s| s >= us_to_ns(FOLLOW_SYNC_CEILING_US));
        let carried = made
            .iter()
            .position(|m| m.1 == f.first_us)
            .expect("a command's value");
        if let (Some(s), Some(p)) = (sync.filter(|_| !lead_in), prev) {
            if p.first_us == f.first_us {
                assert_eq!(s, max, "frame {i}: a repeat at the longest sync");
            } else if made[carried].0 < p.last_pulse + min - lead {
                assert_eq!(s, min, "frame {i}: waited for, at the shortest sync");
            } else {
                assert!(s > min && s < max, "frame {i}: sync {s} ns");
            }
        }
        let decided_by = f.start - READY_NS;
        let decided_from = f.start - lead - if lead_in { LEAD_IN_NS } else { 0 };
        assert!(
            made[carried].0 <= decided_by,
            "frame {i} carries a command from after its decision"
        );
        let newest = made.iter().rposition(|m| m.0 <= decided_from);
        assert!(
            newest.is_none_or(|a| carried >= a),
            "frame {i} at {} carries command {carried}, not the newest",
            f.start
        );
    }
    frames
}

/// Runs one follow output fed by `source` until `tail_ms` after its last
/// command.
fn run_follow(
    sim: &Sim,
    model: &FrameModel,
    source: &mut Feed,
    action: FailsafeAction,
    tail_ms: u64,
) -> (Vec<TraceEdge>, Stats) {
    let mut out = Recorder::default();
    let until_ms = (source.last_at() - START_NS) / MS + tail_ms;
    let line = LineRef::Edges(&mut out);
    let stats = run_one(sim, model, cfg(100, action), source, line, until_ms);
    (out.edges, stats)
}

/// A line as the simulation carries it: each edge with the time it
/// reached the line. A stall due when a write comes holds the loop up
/// before the edge reaches the line (as a preempted write does), and
/// so does `held.1` in the `held.0`-th write.
struct Wire {
    sim: Sim,
    edges: Vec<(TraceEdge, u64)>,
    held: Vec<(usize, u64)>,
    /// The edge takes the time read before the write (as the
    /// simulated line records it), however long the write is held up.
    stamped: bool,
}

impl Line for Wire {
    fn write(&mut self, edge: &TraceEdge) -> Result<(), LineError> {
        self.sim.hold_due_stalls();
        if let Some(&(_, ns)) = self.held.iter().find(|h| h.0 == self.edges.len()) {
            self.sim.advance(ns);
        }
        let real = if self.stamped {
            edge.actual_ns
        } else {
            self.sim.at()
        };
        self.edges.push((*edge, real));
        Ok(())
    }
    fn park(&mut self, _: Level) -> Result<(), LineError> {
        Ok(())
    }
    fn stamped(&self) -> bool {
        self.stamped
    }
}
