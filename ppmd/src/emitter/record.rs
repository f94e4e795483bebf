//! The recording: what the loop counts ([`Stats`]), measures (the
//! [`Meter`]'s histograms) and logs (the frame log) of each output, all
//! without allocating, logging or taking a lock: counters are atomics, the
//! histograms and the frame log are handed over through lock-free rings.

use super::{Progress, LATE_EDGE_NS};
use crate::framelog::{self, FrameStatus, Record};
use crate::meter::Meter;
use ppm_shared::frame::{FrameModel, MAX_CHANNELS};
use ppm_shared::ipc::LineSample;
use ppm_shared::line::LineState;
use std::sync::atomic::{
    fence, AtomicU32, AtomicU64, AtomicU8,
    Ordering::{Acquire, Relaxed, Release},
};

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
    /// The newest frame the line carried whole (or glitched).
    pub last_frame: LastFrame,
}

/// The newest frame the line carried whole, which the loop writes and other
/// threads read without ever making it wait: a sequence count, odd while
/// the loop writes, tells a reader to read again.
#[derive(Debug, Default)]
pub struct LastFrame {
    version: AtomicU64,
    frame: AtomicU64,
    start_mono_ns: AtomicU64,
    channels: AtomicU32,
    state: AtomicU32,
    values_ns: [AtomicU32; MAX_CHANNELS],
}

impl LastFrame {
    /// The loop (its only writer) stores frame `frame`, started at
    /// `start_mono_ns` in `state`, which carried `values_ns`.
    pub(super) fn store(
        &self,
        frame: u64,
        start_mono_ns: u64,
        state: LineState,
        values_ns: &[u32],
    ) {
        let v = self.version.load(Relaxed);
        self.version.store(v.wrapping_add(1), Relaxed);
        fence(Release);
        self.frame.store(frame, Relaxed);
        self.start_mono_ns.store(start_mono_ns, Relaxed);
        self.channels.store(values_ns.len() as u32, Relaxed);
        self.state.store(state as u32, Relaxed);
        for (a, &v) in self.values_ns.iter().zip(values_ns) {
            a.store(v, Relaxed);
        }
        self.version.store(v.wrapping_add(2), Release);
    }

    /// The newest frame stored, if any (`None` too when the loop kept
    /// writing through every try, which a reader every tenth of a second
    /// does not meet).
    pub fn load(&self) -> Option<LineSample> {
        for _ in 0..64 {
            let v1 = self.version.load(Acquire);
            if v1 & 1 == 1 {
                std::hint::spin_loop();
                continue;
            }
            let mut s = LineSample {
                frame: self.frame.load(Relaxed),
                start_mono_ns: self.start_mono_ns.load(Relaxed),
                channels: self.channels.load(Relaxed),
                state: self.state.load(Relaxed),
                values_ns: [0; MAX_CHANNELS],
            };
            for (v, a) in s.values_ns.iter_mut().zip(&self.values_ns) {
                *v = a.load(Relaxed);
            }
            fence(Acquire);
            if self.version.load(Relaxed) == v1 {
                return (s.frame != 0).then_some(s);
            }
        }
        None
    }
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
        let mut values_ns = [0; MAX_CHANNELS];
        let carried = f
            .wire
            .carried(model, &f.channels, f.aborted, &mut values_ns);
        if !f.aborted {
            stats
                .last_frame
                .store(p.frame_no, f.start, f.state, &values_ns[..carried]);
        }
        if let Some(log) = self.log.as_deref_mut() {
            log.push(Record::Frame {
                frame: p.frame_no,
                start_mono_ns: f.start,
                start_real_ns: f.start_real_ns,
                state: f.state,
                timing: model.timing(),
                command: f.command,
                status,
                channels: carried as u8,
                values_ns,
            });
        }
        if f.aborted {
            let last = f.wire.pulse_of(model, p.timed_ns);
            p.resume_after_abort(model, stats, last);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_last_frame_reads_whole_while_the_loop_writes_it() {
        let last = std::sync::Arc::new(LastFrame::default());
        assert_eq!(last.load(), None, "no frame yet");
        let writer = {
            let last = last.clone();
            std::thread::spawn(move || {
                for k in 1..=20_000u64 {
                    let v = [k as u32; 8];
                    last.store(k, 2 * k, LineState::Active, &v[..(k % 8 + 1) as usize]);
                }
            })
        };
        // Every read, however it meets the writer, is one frame's whole:
        // its start, count and values all of one store.
        let mut seen = 0;
        loop {
            // One read at least after the writer finished.
            let done = writer.is_finished();
            if let Some(s) = last.load() {
                let k = s.frame;
                assert_eq!(s.start_mono_ns, 2 * k);
                assert_eq!(s.channels as u64, k % 8 + 1);
                assert!(s.values_ns[..s.channels as usize]
                    .iter()
                    .all(|&v| v as u64 == k));
                assert_eq!(s.state, LineState::Active as u32);
                seen += 1;
            }
            if done {
                break;
            }
        }
        writer.join().unwrap();
        assert_eq!(last.load().unwrap().frame, 20_000);
        assert!(seen > 0);
    }
}
