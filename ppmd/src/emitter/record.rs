//! The recording: what the loop counts ([`Stats`]), measures (the
//! [`Meter`]'s histograms) and logs (the frame log) of each output, all
//! without allocating, logging or taking a lock: counters are atomics, the
//! histograms and the frame log are handed over through lock-free rings.

use super::emit::Frame;
use super::{Progress, LATE_EDGE_NS};
use crate::framelog::{self, FrameStatus, Record};
use crate::meter::Meter;
use ppm_shared::frame::{FrameModel, MAX_CHANNELS};
use ppm_shared::line::LineState;
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering::Relaxed};

/// Counters the loop updates and other threads read.
#[derive(Debug, Default)]
pub struct Stats {
    /// Frames emitted: whole, glitched or aborted.
    pub frames: AtomicU64,
    /// Edges written.
    pub edges: AtomicU64,
    /// Commands taken from the source.
    pub commands: AtomicU64,
    /// Samples whose channel count did not match this daemon's configuration.
    pub mismatched: AtomicU64,
    /// Samples refused as expired: received by udp-ingress before the loop
    /// started, or older than `failsafe.after_ms` when the loop took them
    /// (a service's history, a stalled ingress). Never flown.
    pub expired: AtomicU64,
    /// Frames skipped because their start had passed beyond what moving them allows.
    pub overruns: AtomicU64,
    /// Frames moved later as a whole because their start had passed.
    pub late_frames: AtomicU64,
    /// Edges written more than [`super::LATE_EDGE_NS`] after their time.
    pub late_edges: AtomicU64,
    /// Frames aborted at an edge receivers time that was found later than
    /// `ppm.late_edge_guard_us` just before its write (also in `frames`).
    pub aborted_frames: AtomicU64,
    /// Frames with an edge receivers time that reached the line later than
    /// the guard (the thread was held up in its write; also in `frames`,
    /// and in `aborted_frames` when the frame was aborted after that).
    pub glitched_frames: AtomicU64,
    /// Largest edge error seen (actual minus scheduled), ns.
    pub max_edge_error_ns: AtomicU64,
    /// Line writes that failed.
    pub write_errors: AtomicU64,
    /// Times the loop went from fresh commands to the failsafe action.
    pub failsafe_entries: AtomicU64,
    /// Follow: frames that repeated the last command (or the failsafe
    /// action's) because no fresh command came before the longest sync.
    pub repeats: AtomicU64,
    /// Follow: times a command's wake-up woke the loop.
    pub wakes: AtomicU64,
    /// Follow: wake fds that broke (the output then polls for commands).
    pub wake_errors: AtomicU64,
    /// Times the loop decided this output's next frame (or that the line
    /// stays silent a while longer): at least once a frame while the loop
    /// runs. ppmd pets systemd's watchdog only while it advances.
    pub decisions: AtomicU64,
    /// Current spin margin, ns.
    pub margin_ns: AtomicU64,
    /// Total time spent spinning, ns.
    pub spin_ns: AtomicU64,
    /// The current [`LineState`].
    pub(super) state: AtomicU8,
}

impl Stats {
    /// The current line state.
    pub fn state(&self) -> LineState {
        LineState::from_code(self.state.load(Relaxed) as u32).unwrap_or(LineState::Silent)
    }
}

/// Adds `n` to counter `c`.
pub(super) fn add(c: &AtomicU64, n: u64) {
    c.fetch_add(n, Relaxed);
}

/// Where the loop records one output: its counters, histograms and frame
/// log.
pub struct Recording<'a> {
    /// Its counters.
    pub stats: &'a Stats,
    /// Its histograms.
    pub meter: &'a mut Meter,
    /// Its frame log, if any.
    pub log: Option<&'a mut framelog::Producer>,
}

impl Recording<'_> {
    /// Counts one written edge: `err` after its time, the write taking
    /// `write_ns`.
    pub(super) fn edge(&mut self, err: u64, write_ns: u64) {
        self.meter.edge(err, write_ns);
        self.stats.max_edge_error_ns.fetch_max(err, Relaxed);
        if err > LATE_EDGE_NS {
            add(&self.stats.late_edges, 1);
        }
        add(&self.stats.edges, 1);
    }

    /// The line's state goes `from` one `to` another (or stays) at `now`;
    /// `real_ns` reads the wall clock, for the frame log's row of a change.
    pub(super) fn transition(
        &mut self,
        now: u64,
        real_ns: impl FnOnce() -> u64,
        from: LineState,
        to: LineState,
    ) {
        if from == LineState::Active && to != LineState::Active {
            add(&self.stats.failsafe_entries, 1);
        }
        if from != to {
            if let Some(log) = self.log.as_deref_mut() {
                log.push(Record::Transition {
                    mono_ns: now,
                    real_ns: real_ns(),
                    from,
                    to,
                });
            }
        }
        self.stats.state.store(to as u8, Relaxed);
    }

    /// Closes the output's frame after its last edge (or its abort):
    /// counters and frame log. After an aborted frame, the next one starts
    /// a sync after the last timed edge written at the earliest, with a
    /// lead-in pulse when that gap is longer than a sync (see
    /// [`Progress::resume_after_abort`]).
    pub(super) fn finish_frame(&mut self, model: &FrameModel, p: &mut Progress, margin_ns: u64) {
        let Some(f) = p.frame.take() else {
            return;
        };
        let stats = self.stats;
        self.meter.frame(f.spun);
        add(&stats.spin_ns, f.spun);
        add(&stats.frames, 1);
        if f.glitched {
            add(&stats.glitched_frames, 1);
            self.meter.glitched(f.late_ns);
        }
        let status = if f.aborted {
            add(&stats.aborted_frames, 1);
            self.meter.aborted(f.found_late_ns);
            FrameStatus::Aborted {
                at: f.wire.aborted_at() as u8,
                glitched: f.glitched,
            }
        } else if f.glitched {
            FrameStatus::Glitched
        } else {
            FrameStatus::Whole
        };
        stats.margin_ns.store(margin_ns, Relaxed);
        p.frame_no += 1;
        if let Some(log) = self.log.as_deref_mut() {
            log.push(frame_row(model, &f, p.frame_no, status));
        }
        if f.aborted {
            let last = f.wire.pulse_of(model, p.timed_ns);
            p.resume_after_abort(model, stats, last);
        }
    }
}

/// Frame `f`'s row in the frame log, numbered `frame_no`: the values the
/// line carried whole, as its wire form measures them.
fn frame_row(model: &FrameModel, f: &Frame, frame_no: u64, status: FrameStatus) -> Record {
    let mut values_ns = [0; MAX_CHANNELS];
    let carried = f
        .wire
        .carried(model, &f.channels, f.aborted, &mut values_ns);
    Record::Frame {
        frame: frame_no,
        start_mono_ns: f.start,
        start_real_ns: f.start_real_ns,
        state: f.state,
        timing: model.timing(),
        command: f.command,
        status,
        channels: carried as u8,
        values_ns,
    }
}
