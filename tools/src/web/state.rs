//! What `GET /api/state` answers: the typed view of every output that the
//! page draws, and the pure rules that make it from the shared-memory
//! samples (the line's state, the edge-error histogram of the last seconds).
//!
//! - [`State`], [`OutputView`] and their parts: the JSON contract with
//!   `tools/web/app.js`.
//! - [`line_state`]: silent, flying, failsafe or not running, from ppmd's
//!   samples.
//! - [`HistoryWindow`]: ppmd's cumulative histograms, differenced over the
//!   last seconds.

use ppm_shared::ipc::{LineSample, ReadbackSample, Summary, TimingSnapshot, HIST_BUCKETS};
use ppm_shared::status::StatusReply;
use serde::Serialize;
use std::collections::VecDeque;

/// A line sample older than this means the line carries no frames: ppmd
/// publishes one at most every 100 ms while frames go out.
pub const SILENT_AFTER_NS: u64 = 250_000_000;
/// A timing snapshot older than this means ppmd has stopped (it publishes
/// one about every second; udp-ingress's status replies use the same 3 s).
pub const PPMD_STALE_NS: u64 = 3_000_000_000;
/// A read-back sample older than this is `stale` (ppmd publishes one every
/// tenth of a second even while nothing is read).
pub const READBACK_STALE_NS: u64 = 1_000_000_000;
/// The edge-error histogram covers about this much of the newest snapshots.
pub const HISTOGRAM_WINDOW_NS: u64 = 5_000_000_000;

/// The whole answer of `GET /api/state`.
#[derive(Debug, Clone, Serialize)]
pub struct State {
    /// ppm-web's version.
    pub version: &'static str,
    /// Age of this state when it was made, ms since ppm-web started.
    pub uptime_ms: u64,
    /// Every output shown, in the configuration's order.
    pub outputs: Vec<OutputView>,
}

/// One output, as the page shows it.
#[derive(Debug, Clone, Serialize)]
pub struct OutputView {
    /// Its name.
    pub name: String,
    /// `ppm`, `sbus` or `crsf`.
    pub protocol: &'static str,
    /// Its line, as the configuration names it (`ppmd.output`).
    pub output: String,
    /// The channel names, transmitter order.
    pub channels: Vec<String>,
    /// Each channel's limits, us (the bars' ends).
    pub min_us: Vec<f64>,
    /// See `min_us`.
    pub max_us: Vec<f64>,
    /// The line's state: `not_running`, `silent`, `flying` or `failsafe`.
    pub line_state: LineState,
    /// Why the shared memory could not be read, if it could not.
    pub ipc_error: Option<String>,
    /// ppmd's newest timing snapshot, summarised; `None` while ppmd runs
    /// not (or has published nothing for [`PPMD_STALE_NS`]).
    pub ppmd: Option<PpmdView>,
    /// The newest command udp-ingress handed over.
    pub command: Option<CommandView>,
    /// The newest frame the line carried.
    pub line: Option<LineView>,
    /// What the radio transmits; `None` when no read-back is configured.
    pub readback: Option<ReadbackView>,
    /// udp-ingress, from its status reply.
    pub ingress: IngressView,
    /// The edge error of the last seconds.
    pub histogram: Option<HistogramView>,
}

/// The line's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LineState {
    /// No ppmd publishes for this output.
    NotRunning,
    /// ppmd runs and the line carries no frames.
    Silent,
    /// The line carries a fresh command.
    Flying,
    /// The line carries the failsafe action's frames (`hold` or `default`).
    Failsafe,
}

/// The line's state from what ppmd publishes: `running` says whether a
/// ppmd publishes snapshots for the output, `line` is its newest line
/// sample, `now_ns` CLOCK_MONOTONIC.
pub fn line_state(running: bool, line: Option<&LineSample>, now_ns: u64) -> LineState {
    if !running {
        return LineState::NotRunning;
    }
    match line {
        Some(l) if now_ns.saturating_sub(l.start_mono_ns) <= SILENT_AFTER_NS => match l.state {
            2 => LineState::Failsafe,
            _ => LineState::Flying,
        },
        _ => LineState::Silent,
    }
}

/// ppmd's side: its newest timing snapshot.
#[derive(Debug, Clone, Serialize)]
pub struct PpmdView {
    /// Its process id.
    pub pid: u32,
    /// `grid` or `follow`.
    pub timing: &'static str,
    /// It runs without a real-time setting it asked for.
    pub degraded: bool,
    /// SCHED_FIFO priority (0: the normal scheduler).
    pub priority: u32,
    /// Pinned CPU, if any.
    pub cpu: Option<i32>,
    /// A PREEMPT_RT kernel.
    pub preempt_rt: bool,
    /// Time since ppmd started, s.
    pub uptime_s: f64,
    /// Age of the snapshot, ms.
    pub snapshot_age_ms: f64,
    /// Frames emitted (whole, aborted and glitched).
    pub frames: u64,
    /// Frames cut short at a late edge.
    pub aborted_frames: u64,
    /// Frames with an edge later than the guard.
    pub glitched_frames: u64,
    /// Frames moved later as a whole.
    pub late_frames: u64,
    /// Frames skipped.
    pub overruns: u64,
    /// Entries into the failsafe action.
    pub failsafe_entries: u64,
    /// Follow timing: frames that repeated the previous command.
    pub repeats: u64,
    /// Commands refused: made under another channel model.
    pub mismatched_commands: u64,
    /// Commands refused as too old.
    pub expired_commands: u64,
    /// Edge error over the last interval (about a second), us.
    pub edge_error_last_us: SummaryUs,
    /// Edge error since start, us.
    pub edge_error_total_us: SummaryUs,
}

/// A [`Summary`] in microseconds.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct SummaryUs {
    /// Values.
    pub count: u64,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Largest.
    pub max: f64,
}

impl From<&Summary> for SummaryUs {
    fn from(s: &Summary) -> Self {
        let us = |ns: u64| ns as f64 / 1e3;
        SummaryUs {
            count: s.count,
            p50: us(s.p50),
            p99: us(s.p99),
            p999: us(s.p999),
            max: us(s.max),
        }
    }
}

impl PpmdView {
    /// The view of snapshot `s`, read at `now_ns`.
    pub fn of(s: &TimingSnapshot, now_ns: u64) -> PpmdView {
        PpmdView {
            pid: s.pid,
            timing: if s.timing == 1 { "follow" } else { "grid" },
            degraded: s.degraded != 0,
            priority: s.priority,
            cpu: (s.cpu >= 0).then_some(s.cpu),
            preempt_rt: s.preempt_rt != 0,
            uptime_s: s.uptime_ns as f64 / 1e9,
            snapshot_age_ms: age_ms(s.mono_ns, now_ns),
            frames: s.frames,
            aborted_frames: s.aborted_frames,
            glitched_frames: s.glitched_frames,
            late_frames: s.late_frames,
            overruns: s.overruns,
            failsafe_entries: s.failsafe_entries,
            repeats: s.repeats,
            mismatched_commands: s.mismatched,
            expired_commands: s.expired,
            edge_error_last_us: SummaryUs::from(&s.last),
            edge_error_total_us: SummaryUs::from(&s.total),
        }
    }
}

/// The newest command, as udp-ingress handed it to ppmd.
#[derive(Debug, Clone, Serialize)]
pub struct CommandView {
    /// The values, us, transmitter order.
    pub ch_us: Vec<f64>,
    /// Time since udp-ingress received it, ms.
    pub age_ms: f64,
    /// The sender's `seq`, if it gave one.
    pub seq: Option<u64>,
    /// Values udp-ingress clamped to their limits.
    pub clamped: u32,
    /// Made under another channel model than this output's (udp-ingress
    /// runs with another configuration): ppmd refuses it.
    pub other_model: bool,
    /// ms from udp-ingress's receive of the first command with these
    /// values to the start of the first frame seen carrying them: an upper
    /// bound of the receive-to-line latency, as ppmd publishes a frame at
    /// most every 100 ms; `None` while no frame seen carries them.
    pub to_line_ms: Option<f64>,
}

/// The newest frame the line carried (whole or glitched).
#[derive(Debug, Clone, Serialize)]
pub struct LineView {
    /// The values, us.
    pub ch_us: Vec<f64>,
    /// Its number among ppmd's frames.
    pub frame: u64,
    /// Time since its first edge, ms.
    pub age_ms: f64,
}

/// What the radio transmits (ppmd's read-back).
#[derive(Debug, Clone, Serialize)]
pub struct ReadbackView {
    /// The input read (`ppmd.readback`).
    pub input: String,
    /// `following` (ppm flies), `overridden` (the instructor has taken
    /// over), `no_input` or `stale` (nothing from ppmd for a second).
    pub state: &'static str,
    /// The newest frame read, us per channel.
    pub ch_us: Vec<f64>,
    /// Largest difference from what ppm's line carried, us.
    pub max_diff_us: Option<f64>,
    /// Whole frames read.
    pub frames: u64,
    /// Of those, frames that carried ppm's values.
    pub matched: u64,
    /// Of those, frames that carried something else.
    pub mismatched: u64,
    /// State changes since ppmd started.
    pub changes: u64,
    /// Time since the state last changed, ms.
    pub since_ms: Option<f64>,
}

impl ReadbackView {
    /// The view of sample `s` (if any yet) of input `input`, at `now_ns`.
    pub fn of(input: String, s: Option<&ReadbackSample>, now_ns: u64) -> ReadbackView {
        let Some(s) = s.filter(|s| now_ns.saturating_sub(s.published_mono_ns) <= READBACK_STALE_NS)
        else {
            return ReadbackView {
                input,
                state: "stale",
                ch_us: vec![],
                max_diff_us: None,
                frames: 0,
                matched: 0,
                mismatched: 0,
                changes: 0,
                since_ms: None,
            };
        };
        let state = match s.state {
            1 => "following",
            2 => "overridden",
            _ => "no_input",
        };
        let n = (s.channels as usize).min(s.values_ns.len());
        ReadbackView {
            input,
            state,
            ch_us: us(&s.values_ns[..n]),
            max_diff_us: (s.frames > 0).then(|| f64::from(s.max_diff_ns) / 1e3),
            frames: s.frames,
            matched: s.matched,
            mismatched: s.mismatched,
            changes: s.changes,
            since_ms: (s.changed_mono_ns > 0).then(|| age_ms(s.changed_mono_ns, now_ns)),
        }
    }
}

/// udp-ingress's side.
#[derive(Debug, Clone, Serialize)]
pub struct IngressView {
    /// Where its status is asked (its `ingress.listen`).
    pub address: String,
    /// It answered the newest status query.
    pub running: bool,
    /// Why it did not, if it did not.
    pub error: Option<String>,
    /// Its newest status reply.
    pub status: Option<StatusReply>,
    /// Age of that reply, ms.
    pub status_age_ms: Option<f64>,
}

/// The edge error of the last seconds: counts in 1 us buckets.
#[derive(Debug, Clone, Serialize)]
pub struct HistogramView {
    /// The seconds it covers.
    pub window_s: f64,
    /// `[bucket_us, count]` of every bucket with a count (bucket `i`: `i`
    /// up to `i + 1` us), in order.
    pub buckets: Vec<(u32, u64)>,
    /// Edge errors of 1000 us or more.
    pub overflow: u64,
    /// Edges in all.
    pub count: u64,
    /// Percentile marks, as bucket upper bounds (us): p50, p99, p99.9, max.
    pub marks: Vec<(&'static str, f64)>,
}

/// ppmd's cumulative edge-error histograms of the last seconds, to take
/// their difference: what the edges of that window did.
#[derive(Debug, Default)]
pub struct HistoryWindow {
    kept: VecDeque<Kept>,
}

/// One snapshot's histogram, as kept.
#[derive(Debug)]
struct Kept {
    seq: u64,
    pid: u32,
    mono_ns: u64,
    /// Cumulative counts.
    hist: Box<[u64; HIST_BUCKETS]>,
    overflow: u64,
}

impl HistoryWindow {
    /// Takes snapshot `s` (again: a snapshot already taken is ignored). A
    /// snapshot of another ppmd (a restart) starts the window over.
    pub fn push(&mut self, s: &TimingSnapshot) {
        if let Some(newest) = self.kept.back() {
            if newest.seq == s.seq && newest.pid == s.pid {
                return;
            }
            if newest.pid != s.pid || s.seq < newest.seq {
                self.kept.clear();
            }
        }
        self.kept.push_back(Kept {
            seq: s.seq,
            pid: s.pid,
            mono_ns: s.mono_ns,
            hist: Box::new(s.hist_us),
            overflow: s.hist_overflow,
        });
        while self.kept.len() > 2
            && s.mono_ns.saturating_sub(self.kept[1].mono_ns) >= HISTOGRAM_WINDOW_NS
        {
            self.kept.pop_front();
        }
    }

    /// Forgets everything (ppmd stopped).
    pub fn clear(&mut self) {
        self.kept.clear();
    }

    /// The histogram of the window: the newest snapshot less the oldest
    /// kept, or the newest alone (since ppmd started) while only one is.
    pub fn view(&self, uptime_s: f64) -> Option<HistogramView> {
        let newest = self.kept.back()?;
        let oldest = self.kept.front()?;
        let (base, base_overflow, window_s) = if self.kept.len() == 1 {
            (None, 0, uptime_s)
        } else {
            (
                Some(&oldest.hist),
                oldest.overflow,
                newest.mono_ns.saturating_sub(oldest.mono_ns) as f64 / 1e9,
            )
        };
        let buckets: Vec<(u32, u64)> = newest
            .hist
            .iter()
            .enumerate()
            .map(|(i, &n)| (i as u32, n.saturating_sub(base.map_or(0, |b| b[i]))))
            .filter(|&(_, n)| n > 0)
            .collect();
        let overflow = newest.overflow.saturating_sub(base_overflow);
        let count = buckets.iter().map(|b| b.1).sum::<u64>() + overflow;
        Some(HistogramView {
            window_s,
            marks: marks(&buckets, overflow, count),
            buckets,
            overflow,
            count,
        })
    }
}

/// p50, p99, p99.9 and max of a bucketed histogram, each the upper bound
/// of its bucket (1000 for the overflow); none when it is empty.
fn marks(buckets: &[(u32, u64)], overflow: u64, count: u64) -> Vec<(&'static str, f64)> {
    if count == 0 {
        return vec![];
    }
    let at = |p: f64| -> f64 {
        let want = ((p * count as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for &(i, n) in buckets {
            seen += n;
            if seen >= want {
                return f64::from(i + 1);
            }
        }
        HIST_BUCKETS as f64
    };
    let max = if overflow > 0 {
        HIST_BUCKETS as f64
    } else {
        buckets.last().map_or(0.0, |b| f64::from(b.0 + 1))
    };
    vec![
        ("p50", at(0.5)),
        ("p99", at(0.99)),
        ("p99.9", at(0.999)),
        ("max", max),
    ]
}

/// Nanosecond values as microseconds.
pub fn us(values_ns: &[u32]) -> Vec<f64> {
    values_ns.iter().map(|&v| f64::from(v) / 1e3).collect()
}

/// Milliseconds from `then_ns` to `now_ns` (0 when `then_ns` is later).
pub fn age_ms(then_ns: u64, now_ns: u64) -> f64 {
    now_ns.saturating_sub(then_ns) as f64 / 1e6
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(state: u32, start: u64) -> LineSample {
        LineSample {
            frame: 1,
            start_mono_ns: start,
            channels: 1,
            state,
            ..LineSample::default()
        }
    }

    #[test]
    fn the_line_state_follows_the_newest_frame() {
        let now = 10_000_000_000;
        assert_eq!(line_state(false, None, now), LineState::NotRunning);
        assert_eq!(
            line_state(false, Some(&line(1, now)), now),
            LineState::NotRunning
        );
        assert_eq!(line_state(true, None, now), LineState::Silent);
        assert_eq!(
            line_state(true, Some(&line(1, now - 100_000_000)), now),
            LineState::Flying
        );
        assert_eq!(
            line_state(true, Some(&line(2, now - 100_000_000)), now),
            LineState::Failsafe
        );
        assert_eq!(
            line_state(true, Some(&line(1, now - SILENT_AFTER_NS - 1)), now),
            LineState::Silent
        );
        assert_eq!(
            serde_json::to_value(LineState::NotRunning).unwrap(),
            "not_running"
        );
    }

    fn snapshot(seq: u64, pid: u32, mono_s: u64, hist: &[(usize, u64)]) -> TimingSnapshot {
        let mut s = TimingSnapshot {
            seq,
            pid,
            mono_ns: mono_s * 1_000_000_000,
            ..TimingSnapshot::default()
        };
        for &(i, n) in hist {
            s.hist_us[i] = n;
        }
        s
    }

    #[test]
    fn the_histogram_is_the_difference_over_the_window() {
        let mut w = HistoryWindow::default();
        assert!(w.view(0.0).is_none());
        w.push(&snapshot(1, 7, 1, &[(0, 100), (3, 1)]));
        let v = w.view(1.0).unwrap();
        assert_eq!((v.window_s, v.count), (1.0, 101));
        assert_eq!(v.buckets, [(0, 100), (3, 1)]);
        // Seconds later: only what happened since the oldest kept.
        for seq in 2..=9 {
            w.push(&snapshot(seq, 7, seq, &[(0, 100 * seq), (3, 1), (5, seq)]));
        }
        w.push(&snapshot(9, 7, 9, &[(0, 1)])); // the same snapshot again: ignored
        let v = w.view(9.0).unwrap();
        assert_eq!(v.window_s, 5.0);
        assert_eq!(v.buckets, [(0, 500), (5, 5)]);
        assert_eq!(v.count, 505);
        let marks: Vec<f64> = v.marks.iter().map(|m| m.1).collect();
        // 500 of 505 in the first bucket: p99 there, p99.9 in the last.
        assert_eq!(marks, [1.0, 1.0, 6.0, 6.0]);
        // A restarted ppmd starts over.
        w.push(&snapshot(1, 8, 20, &[(2, 4)]));
        let v = w.view(0.5).unwrap();
        assert_eq!((v.window_s, v.count), (0.5, 4));
    }

    #[test]
    fn a_stale_readback_says_so() {
        let now = 5_000_000_000;
        let s = ReadbackSample {
            published_mono_ns: now - 10_000_000,
            state: 2,
            channels: 2,
            frames: 3,
            values_ns: {
                let mut v = [0; ppm_shared::frame::MAX_CHANNELS];
                v[..2].copy_from_slice(&[1_500_000, 1_100_500]);
                v
            },
            ..ReadbackSample::default()
        };
        let v = ReadbackView::of("sim:x".into(), Some(&s), now);
        assert_eq!(
            (v.state, v.ch_us.clone()),
            ("overridden", vec![1500.0, 1100.5])
        );
        let v = ReadbackView::of("sim:x".into(), Some(&s), now + READBACK_STALE_NS);
        assert_eq!(v.state, "stale");
        assert!(v.ch_us.is_empty());
    }
}
