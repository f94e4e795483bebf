//! The timing loop. Once per frame, [`DECIDE_NS`] before the frame's first
//! edge (woken as precisely as for an edge), it takes the newest command,
//! decides what the frame carries (the command, or the failsafe action when
//! the command is too old), encodes it and emits every edge at its scheduled
//! time through an [`EdgeTimer`]: an absolute sleep until a margin before the
//! edge, a spin on CLOCK_MONOTONIC, then one write. So a command is at most
//! about `DECIDE_NS` old when its frame starts, whatever the spin margin.
//!
//! Frames sit on a fixed grid (`start_k = start_0 + k * frame`), so a late
//! edge never shifts later ones. When a frame's start has already passed, the
//! frame is moved later as a whole if the sync gaps on both sides stay within
//! what transmitters accept (counted as a late frame: its channel values stay
//! exact); otherwise it is skipped (counted as an overrun), and the frame
//! after it gets the lead-in pulse a frame after silence gets.
//!
//! Right before each edge receivers time (the rising edge at the pin), the
//! loop checks its lateness: past the model's guard (`ppm.late_edge_guard_us`)
//! the edge is not written and the frame is aborted (with idle high, the
//! pulse it would end is ended a shortest sync after the last timed edge);
//! the next frame starts a sync after the last timed edge at the earliest,
//! with a lead-in pulse when the gap is longer. After every write, how long
//! it took says how late the edge may have reached the line: the frame log
//! gets the values the line carried and whether the frame was whole,
//! glitched or aborted.
//!
//! Nothing inside the loop allocates, logs or takes a lock; it updates
//! atomic counters in [`Stats`] and histograms in a [`Meter`]. It reads the time and waits only
//! through the [`Clock`] it is given: ppmd's is the [`SystemClock`]; its
//! tests give a simulated one and get the same edges on every machine.
//!
//! The loop is set up, one loop, torn down ([`run_outputs`]); each turn
//! takes the next step (a named `Step`: decide an output's frame, emit the
//! edges due, or end). Its parts, one file each:
//!
//! - `pace`: when an output's next frame starts (its frame timing, grid or
//!   follow, with its own state) and the lead-in pulse after silence.
//! - `decide`: the decision of a frame: the newest command or the failsafe
//!   action, encoded, placed by the pace.
//! - `emit`: the emission of a due step: every output's edge due then, the
//!   way its frames leave ([`LineRef`]), and aborted or glitched frames.
//! - `record`: the recording: counters ([`Stats`]), histograms, frame log.
//! - `wire`: what a frame is on the wire (PPM edges today), the protocol
//!   seam: when its next write is due, which writes receivers time, the
//!   late-edge guard, its last pulse, its whole-frame form and the values a
//!   frame log row records are its methods, so the other parts never reach
//!   into an encoding.

use crate::clock::{Clock, EdgeTimer, Margin, Readable, SystemClock, Wake};
use crate::framelog;
use crate::line::{Bank, FrameLine, Line};
use crate::meter::Meter;
use crate::source::CommandSource;
use decide::decide_frame;
use emit::{emit_due, Frame};
use pace::{DecideAt, Pace};
use ppm_shared::config::{FailsafeAction, Timing};
use ppm_shared::frame::{Channels, FrameModel};
use ppm_shared::ipc::CommandSample;
use std::os::fd::RawFd;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};

mod decide;
mod emit;
pub mod module;
mod pace;
mod record;
mod wire;

pub use ppm_shared::line::LineState;
pub use record::{Recording, Stats};

/// How long before a frame's start its output takes the newest command and
/// encodes the frame; with several outputs, [`DECIDE_SLOT_NS`] more per
/// further output, so outputs that share a frame start all decide before it.
pub const DECIDE_NS: u64 = 150_000;
/// Time from the end of a decision to the frame's first edge that the loop
/// needs at least; a frame decided later than that is moved (a late frame).
pub const READY_NS: u64 = 20_000;
/// After silence, how long before the first frame a lone pulse goes out: a
/// sync period (4..19 ms) before the frame, so a transmitter reads that first
/// frame instead of waiting for the second.
pub const LEAD_IN_NS: u64 = 5_000_000;
/// EdgeTX's and OpenTX's trainer inputs time pulses with a 16-bit counter
/// at 2 MHz, which wraps every 32.768 ms: they read a gap between two
/// pulses modulo that. After silence or skipped frames, the gap before a
/// lead-in pulse could so read as one more channel (800..=2200 us), handed
/// on as channel N+1. The loop keeps lead-in pulses out of these gaps, with
/// 200 us to spare each side (100 us past ArduPilot's 700..2300 us, should
/// its 1 MHz 16-bit capture wrap: 65.536 ms is two wraps of this), by moving
/// them by at most [`ALIAS_SHIFT_MAX_NS`].
pub const TRAINER_WRAP_NS: u64 = 32_768_000;
/// The longest lead-in: LEAD_IN_NS, moved out of a gap a trainer input
/// would read as a channel.
pub const LEAD_IN_MAX_NS: u64 = LEAD_IN_NS + ALIAS_SHIFT_MAX_NS;
/// The most a lead-in pulse moves to keep out of the gaps a trainer reads
/// as a channel (600..=2400 us modulo [`TRAINER_WRAP_NS`]): a lead-in
/// is between LEAD_IN_NS and LEAD_IN_NS plus this.
pub const ALIAS_SHIFT_MAX_NS: u64 = 1_800_001;
/// How often the loop looks for a command while the line is silent.
pub const IDLE_POLL_NS: u64 = 2_000_000;
/// How often a follow output whose source has no wake fd looks for a command
/// while it waits for one.
pub const FOLLOW_POLL_NS: u64 = 200_000;
/// An edge written later than this after its scheduled time counts as late.
pub const LATE_EDGE_NS: u64 = 10_000;

/// An output's failsafe settings in the loop, resolved from the
/// configuration (the loop's spin margin, one for every output, is an
/// argument of [`run_outputs`]).
#[derive(Debug, Clone, Copy)]
pub struct EmitterConfig {
    /// A command older than this (by its ingress receive time) is not fresh.
    pub failsafe_after_ns: u64,
    /// What to emit when the newest command is not fresh.
    pub failsafe_action: FailsafeAction,
    /// What to emit before the first command (`Silence` or `Default`).
    pub startup: FailsafeAction,
}

/// Time kept free for one decision (take the command, encode the frame), at
/// least; the loop widens it to a decaying peak of the decision times it
/// measures plus a quarter of this. A decision is made only when it can end
/// before the next edge of any output; when its time falls on an edge, it is
/// made early, before the edge.
pub const DECIDE_SLOT_NS: u64 = 50_000;

/// Most outputs one loop drives.
pub const MAX_OUTPUTS: usize = ppm_shared::config::MAX_OUTPUTS;

/// An output's line as the loop writes it: how its frames leave.
pub enum LineRef<'a> {
    /// Edge by edge, each at its time, on a line of its own.
    Edges(&'a mut (dyn Line + 'static)),
    /// Edge by edge on line `bit` of bank `bank` (several lines of one GPIO
    /// chip in one request): edges of a bank's outputs due at the same time
    /// are written together, in one call.
    Banked {
        /// Index into the banks given to [`run_outputs`].
        bank: usize,
        /// The line's index within the bank.
        bit: u32,
    },
    /// Whole, each frame in one call at its first edge, timed by the
    /// line's own clock.
    Whole(&'a mut (dyn FrameLine + 'static)),
}

impl LineRef<'_> {
    /// Leaves the line at `level` (at exit).
    fn park(&mut self, banks: &mut [&mut dyn Bank], level: ppm_shared::frame::Level) -> bool {
        match self {
            LineRef::Edges(line) => line.park(level),
            LineRef::Whole(line) => line.park(level),
            LineRef::Banked { bank, bit } => banks[*bank].park(*bit, level),
        }
        .is_ok()
    }
}

/// One output as the loop drives it: its frame model, failsafe settings,
/// commands, line and recording.
pub struct Output<'a> {
    /// The frame this output emits.
    pub model: &'a FrameModel,
    /// Its failsafe settings.
    pub cfg: EmitterConfig,
    /// Where its commands come from.
    pub source: &'a mut dyn CommandSource,
    /// Where its frames go.
    pub line: LineRef<'a>,
    /// Its counters, histograms and frame log.
    pub rec: Recording<'a>,
    /// The timing corrections of the ExpressLRS module it drives, which
    /// its grid follows; `None` for every other output.
    pub sync: Option<&'a module::ModuleTiming>,
}

/// Runs one output on the [`SystemClock`], spinning `margin` before each
/// edge, until `stop` is set, then finishes the frame in progress and
/// leaves the line at its idle level. With a frame log, every emitted
/// frame and every line-state change is queued to it.
#[allow(clippy::too_many_arguments)]
pub fn run(
    model: &FrameModel,
    cfg: &EmitterConfig,
    margin: Margin,
    source: &mut dyn CommandSource,
    line: LineRef,
    stop: &AtomicBool,
    stats: &Stats,
    meter: &mut Meter,
    log: Option<&mut framelog::Producer>,
) {
    let mut outputs = [Output {
        model,
        cfg: *cfg,
        source,
        line,
        rec: Recording { stats, meter, log },
        sync: None,
    }];
    run_outputs(&SystemClock, margin, &mut outputs, &mut [], stop);
}

/// What the loop keeps per output between its turns.
#[derive(Clone, Copy)]
struct Progress {
    /// The newest command taken while fresh: one received by udp-ingress
    /// after `started` and no older than `failsafe.after_ms` when taken.
    newest: Option<(CommandSample, Channels)>,
    /// When the loop started: a command received before it is refused.
    started: u64,
    /// Its frame timing's state.
    pace: Pace,
    state: LineState,
    frame_no: u64,
    /// Where the last pulse scheduled on the line starts (kept through
    /// silence): where a lead-in pulse's gap is measured from.
    prev_pulse: Option<u64>,
    /// When to look for a command again while silent (and, following
    /// without a wake fd, while armed).
    poll_at: u64,
    frame: Option<Frame>,
    /// When the last edge receivers time reached the line, as measured.
    timed_ns: Option<u64>,
    /// The shortest write seen (from the reading before it to the one
    /// after): what a write takes when nothing holds the thread up.
    write_floor_ns: u64,
}

impl Progress {
    /// An output of `timing` at the loop's start, `now`.
    fn new(timing: Timing, now: u64) -> Progress {
        Progress {
            newest: None,
            started: now,
            pace: Pace::new(timing),
            state: LineState::Silent,
            frame_no: 0,
            prev_pulse: None,
            poll_at: now,
            frame: None,
            timed_ns: None,
            write_floor_ns: u64::MAX,
        }
    }
}

/// The loop's next step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    /// Decide output `output`'s next frame at `at`, after waiting so.
    Decide { output: usize, at: u64, wait: Wait },
    /// Wait for `due` and write every edge due then.
    Emit { due: u64 },
    /// Stopping, and no frame is left in progress: the loop ends.
    Done,
}

/// How the loop waits for a decision's time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wait {
    /// As precisely as for an edge: a frame or another line's edge follows
    /// closely.
    Precise,
    /// A plain sleep (a look for a command on a silent line).
    Plain,
    /// None: its time falls on an edge, so it is made now, before it.
    Now,
}

/// The wake fds of the outputs waiting for a command: any wait ends early
/// when one is readable.
struct Watch {
    fds: [RawFd; MAX_OUTPUTS],
    /// The output each fd is of.
    output: [usize; MAX_OUTPUTS],
    len: usize,
}

impl Watch {
    /// The fds of `prog`'s outputs that wait for a command (none when
    /// `stopping`).
    fn new(prog: &[Progress], stopping: bool) -> Watch {
        let mut w = Watch {
            fds: [0; MAX_OUTPUTS],
            output: [0; MAX_OUTPUTS],
            len: 0,
        };
        if !stopping {
            for (i, p) in prog.iter().enumerate() {
                if let Some(fd) = p.watches() {
                    w.fds[w.len] = fd;
                    w.output[w.len] = i;
                    w.len += 1;
                }
            }
        }
        w
    }

    fn fds(&self) -> &[RawFd] {
        &self.fds[..self.len]
    }

    /// Marks the outputs whose fd `r` found readable as woken. A broken fd
    /// would end every wait at once: its output looks for commands every
    /// [`FOLLOW_POLL_NS`] instead.
    fn woke(&self, r: Readable, outputs: &[Output], prog: &mut [Progress]) {
        for (k, &i) in self.output[..self.len].iter().enumerate() {
            let Some(f) = prog[i].pace.follow() else {
                continue;
            };
            if r.readable & (1 << k) != 0 {
                f.woken = true;
            }
            if r.broken & (1 << k) != 0 {
                f.wake_fd = None;
                f.woken = true;
                record::add(&outputs[i].rec.stats.wake_errors, 1);
            }
        }
    }
}

/// Runs every output from one thread until `stop` is set: the edges of all
/// outputs are merged into one schedule and waited for by one
/// [`EdgeTimer`]; edges due at the same time on the lines of one bank are
/// written with one call. Each output keeps its own frame timing, failsafe,
/// counters and frame log. Grid outputs with equal frame lengths that start
/// while another runs join its grid, so their frame starts coincide.
/// Follow outputs waiting for a command sleep on their sources' wake fds
/// along with every other wait. When `stop` is set, frames in progress are
/// finished, every line is left at its idle level and every output's
/// meter hands over its last interval. Every reading of the
/// time and every wait goes through `clk` (ppmd's is the [`SystemClock`]);
/// its one [`EdgeTimer`] spins with the spin `margin` (a setting of the
/// process, not of an output).
pub fn run_outputs<C: Clock + ?Sized>(
    clk: &C,
    margin: Margin,
    outputs: &mut [Output],
    banks: &mut [&mut dyn Bank],
    stop: &AtomicBool,
) {
    assert!(
        (1..=MAX_OUTPUTS).contains(&outputs.len()),
        "1..={MAX_OUTPUTS} outputs"
    );
    let n = outputs.len();
    let mut timer = EdgeTimer::new(margin);
    let now = clk.now_ns();
    let mut prog = [Progress::new(Timing::Grid, now); MAX_OUTPUTS];
    for (out, p) in outputs.iter_mut().zip(prog.iter_mut()) {
        *p = Progress::new(out.model.timing(), now);
        out.rec.meter.start(now);
        // Shown while the line is still silent; updated after every frame.
        out.rec.stats.margin_ns.store(timer.margin_ns(), Relaxed);
        if let Some(f) = p.pace.follow() {
            f.wake_fd = out.source.wake_fd();
        }
    }
    let prog = &mut prog[..n];
    let mut decide_peak_ns = 0u64;
    let lead = DECIDE_NS + DECIDE_SLOT_NS * (n as u64 - 1);
    loop {
        let stopping = stop.load(Relaxed);
        let watch = Watch::new(prog, stopping);
        let slot = DECIDE_SLOT_NS.max(decide_peak_ns + DECIDE_SLOT_NS / 4);
        let woke = match next_step(clk, outputs, prog, lead, slot, stopping) {
            Step::Done => break,
            Step::Emit { due } => emit_due(clk, due, outputs, prog, banks, &mut timer, watch.fds()),
            Step::Decide { output, at, wait } => {
                let woke = match wait {
                    Wait::Precise => match timer.wait_or_readable(clk, at, watch.fds()) {
                        Wake::Due(_) => None,
                        Wake::Readable(r) => Some(r),
                    },
                    Wait::Plain => {
                        let r = clk.sleep_until_or_readable(at, watch.fds());
                        r.any().then_some(r)
                    }
                    Wait::Now => None,
                };
                // A stop that came during the wait leaves the frame
                // undecided: the loop ends without it.
                if woke.is_none() && !stop.load(Relaxed) {
                    let took_from = clk.now_ns();
                    let anchor = grid_anchor(outputs, prog, output);
                    decide_frame(clk, &mut outputs[output], &mut prog[output], lead, anchor);
                    // A decaying peak of the decision time sizes the slot.
                    // A decision that took longer than DECIDE_NS was held
                    // up (preempted, or a page fault): no slot keeps edges
                    // clear of that, and sizing the slot by it would defer
                    // every decision (moving frames late) for hundreds of
                    // frames after.
                    let took = (clk.now_ns() - took_from).min(DECIDE_NS);
                    decide_peak_ns = took.max(decide_peak_ns - decide_peak_ns / 64);
                }
                woke
            }
        };
        if let Some(r) = woke {
            watch.woke(r, outputs, prog);
        }
    }
    let now = clk.now_ns();
    for out in outputs.iter_mut() {
        if !out.line.park(banks, out.model.idle_level()) {
            record::add(&out.rec.stats.write_errors, 1);
        }
        out.rec.stats.state.store(LineState::Silent as u8, Relaxed);
        // What was measured since the last interval, for the reader's
        // last look at exit.
        out.rec.meter.hand_over(now);
    }
}

/// The loop's next step: the earliest decision (none when `stopping`), if
/// it can end `slot` before the next edge due, or else that edge.
fn next_step<C: Clock + ?Sized>(
    clk: &C,
    outputs: &[Output],
    prog: &[Progress],
    lead: u64,
    slot: u64,
    stopping: bool,
) -> Step {
    let edge_due = prog.iter().filter_map(|p| p.frame.map(|f| f.due())).min();
    let decision = if stopping {
        None
    } else {
        (0..prog.len())
            .filter_map(|i| {
                let DecideAt { at, precise } = prog[i].decide_at(outputs[i].model, lead)?;
                Some((at, i, precise))
            })
            .min()
    };
    let decide = |at, output, wait| Step::Decide { output, at, wait };
    match (decision, edge_due) {
        (None, None) => Step::Done,
        (None, Some(due)) => Step::Emit { due },
        (Some((at, i, true)), None) => decide(at, i, Wait::Precise),
        (Some((at, i, false)), None) => decide(at, i, Wait::Plain),
        // A decision made awake may use an edge's spin margin: it only has
        // to end before the edge.
        (Some((at, i, _)), Some(due)) if at + slot <= due => decide(at, i, Wait::Precise),
        // Its time falls on an edge: decide now, before it.
        (Some((at, i, _)), Some(due)) if at <= due && clk.now_ns() + slot <= due => {
            decide(at, i, Wait::Now)
        }
        (Some(_), Some(due)) => Step::Emit { due },
    }
}

/// A grid point of another grid output with output `i`'s frame length,
/// for `i` to join when its frames start.
fn grid_anchor(outputs: &[Output], prog: &[Progress], i: usize) -> Option<u64> {
    let frame_ns = outputs[i].model.frame_ns();
    (0..outputs.len())
        .filter(|&j| {
            j != i
                && outputs[j].model.timing() == Timing::Grid
                && outputs[j].model.frame_ns() == frame_ns
        })
        .find_map(|j| prog[j].next_start())
}

#[cfg(test)]
mod tests;
