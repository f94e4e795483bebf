//! The main thread's view of the timing loop: it merges the meter's
//! intervals, logs line-state changes and failures, builds the timing
//! snapshots udp-ingress reports (published by a [`SnapshotPublisher`]),
//! and writes the HdrHistogram log.

use crate::clock;
use crate::emitter::{self, LineState, Stats};
use crate::meter::{self, Interval, MeterReader};
use anyhow::{Context, Result};
use ppm_shared::config::Timing;
use ppm_shared::frame::FrameModel;
use ppm_shared::ipc::{self, IpcError, LineSample, PublishError, Summary, TimingSnapshot};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

/// How often a histogram interval is handed over and a snapshot published.
pub const SNAPSHOT_EVERY_NS: u64 = 1_000_000_000;
/// How often the timing summary is logged.
pub const LOG_EVERY_NS: u64 = 60_000_000_000;
/// How often a log that goes on failing is said again.
pub const LOG_FAILURE_EVERY_NS: u64 = 10_000_000_000;

/// What the timing thread's real-time setup obtained, as the main thread needs it.
pub struct Obtained {
    pub summary: String,
    pub shortfalls: Vec<String>,
    pub priority: u8,
    pub cpu: Option<usize>,
    pub preempt_rt: bool,
}

impl From<&crate::rt::RtObtained> for Obtained {
    fn from(o: &crate::rt::RtObtained) -> Self {
        Obtained {
            summary: o.summary(),
            shortfalls: o
                .shortfalls
                .iter()
                .map(|s| s.degraded().to_string())
                .collect(),
            priority: o.priority,
            cpu: o.cpu,
            preempt_rt: o.kernel.preempt_rt,
        }
    }
}

/// The main thread's view of the loop: merges intervals, logs, writes the
/// HdrHistogram log and builds snapshots.
pub struct Monitor {
    pub reader: MeterReader,
    pub stats: Arc<Stats>,
    pub total_error: hdrhistogram::Histogram<u64>,
    pub total_write: hdrhistogram::Histogram<u64>,
    pub snapshot: TimingSnapshot,
    pub start_ns: u64,
    pub next_log_ns: u64,
    pub state: LineState,
    /// Commands refused as made under another channel model: said once,
    /// then as a count.
    pub mismatched: Repeated,
    pub expired: u64,
    /// HdrHistogram intervals, and frame-log rows, that could not be written.
    pub hdr_lost: u64,
    pub frame_log_lost: u64,
    /// When a failure of each log may be said again.
    pub next_log_failure_ns: [u64; 2],
    /// The output's `failsafe.after_ms`, for the mismatch message.
    pub failsafe_after_ms: u64,
    pub wake_errors: u64,
    /// `NAME.` before the HdrHistogram log's tags, with several outputs.
    pub tag_prefix: String,
    /// Writes its edge error untagged too (the first output's).
    pub hdr_untagged: bool,
}

impl Monitor {
    pub fn new(
        (model, failsafe_after_ms): (&FrameModel, u64),
        obtained: &Obtained,
        reader: MeterReader,
        stats: Arc<Stats>,
        tag_prefix: String,
    ) -> Monitor {
        let start_ns = clock::now_ns();
        Monitor {
            reader,
            stats,
            total_error: meter::histogram(),
            total_write: meter::histogram(),
            snapshot: TimingSnapshot {
                // Follow timing has no fixed interval.
                frame_ns: match model.timing() {
                    Timing::Grid => model.frame_ns(),
                    Timing::Follow => 0,
                },
                timing: (model.timing() == Timing::Follow) as u32,
                pid: std::process::id(),
                priority: obtained.priority as u32,
                cpu: obtained.cpu.map_or(-1, |c| c as i32),
                degraded: !obtained.shortfalls.is_empty() as u32,
                preempt_rt: obtained.preempt_rt as u32,
                ..TimingSnapshot::default()
            },
            start_ns,
            next_log_ns: start_ns + LOG_EVERY_NS,
            state: LineState::Silent,
            mismatched: Repeated::default(),
            expired: 0,
            hdr_lost: 0,
            frame_log_lost: 0,
            next_log_failure_ns: [0; 2],
            failsafe_after_ms,
            wake_errors: 0,
            tag_prefix,
            hdr_untagged: false,
        }
    }

    /// What went wrong with the frame log, to be said once at exit.
    pub fn final_report(&self, frame_log: Option<&crate::framelog::Writer>) -> Vec<String> {
        let mut out = Vec::new();
        if let Some(w) = frame_log {
            if w.lost() > 0 {
                out.push(format!(
                    "frame log: {} rows could not be written ({})",
                    w.lost(),
                    w.last_error().unwrap_or_default()
                ));
            }
            if w.dropped() > 0 {
                out.push(format!(
                    "frame log: {} rows dropped (the writer fell behind)",
                    w.dropped()
                ));
            }
        }
        out
    }

    /// The exit summary: frames, commands, edge error, what went late,
    /// failed or mismatched, and `receive_errors` of the command source.
    pub fn summary(&self, receive_errors: u64) -> String {
        let t = &self.snapshot;
        format!(
            "stopped{}: {} frames{}, {} commands; edge error p50 {:.2} us, p99 {:.2} us, p99.9 {:.2} us, max {:.1} us; {} late edges (> {} us), {} aborted frames, {} glitched frames, {} late frames, {} overruns, {} write errors, {} mismatched samples, {} expired samples, {} receive errors",
            if t.degraded != 0 { " (DEGRADED RUN)" } else { "" },
            t.frames,
            if t.timing == 1 {
                format!(" ({} repeats)", t.repeats)
            } else {
                String::new()
            },
            t.commands,
            t.total.p50 as f64 / 1e3,
            t.total.p99 as f64 / 1e3,
            t.total.p999 as f64 / 1e3,
            t.total.max as f64 / 1e3,
            t.late_edges,
            emitter::LATE_EDGE_NS / 1_000,
            t.aborted_frames,
            t.glitched_frames,
            t.late_frames,
            t.overruns,
            t.write_errors,
            self.stats.mismatched.load(Relaxed),
            self.stats.expired.load(Relaxed),
            receive_errors,
        )
    }

    /// Reads what the loop handed over; returns a snapshot when an interval ended.
    pub fn tick(
        &mut self,
        mut hdr: Option<&mut HdrLog>,
        frame_log: Option<&crate::framelog::Writer>,
    ) -> Option<TimingSnapshot> {
        let mut intervals = 0;
        let (mut last, mut hdr_failed) = (None, None);
        let (total_error, total_write, snap, start_ns, prefix, untagged) = (
            &mut self.total_error,
            &mut self.total_write,
            &mut self.snapshot,
            self.start_ns,
            &self.tag_prefix,
            self.hdr_untagged,
        );
        self.reader.drain(|iv: &Interval| {
            intervals += 1;
            let _ = total_error.add(&iv.edge_error);
            let _ = total_write.add(&iv.write);
            for v in iv.edge_error.iter_recorded() {
                let bucket = (v.value_iterated_to() / 1_000) as usize;
                match snap.hist_us.get_mut(bucket) {
                    Some(b) => *b += v.count_at_value(),
                    None => snap.hist_overflow += v.count_at_value(),
                }
            }
            last = Some(summarize(&iv.edge_error));
            if let Some(h) = hdr.as_mut() {
                if let Err(e) = h.write(iv, start_ns, prefix, untagged) {
                    hdr_failed = Some(e);
                }
            }
        });
        // A log is not worth the line: its failures are said and counted,
        // and the next interval tries again.
        if let Some(e) = hdr_failed {
            self.hdr_lost += 1;
            self.log_failure(0, "HdrHistogram log", &format!("{e:#}"));
        }
        if let Some(w) = frame_log {
            let lost = w.lost();
            if lost > self.frame_log_lost {
                self.frame_log_lost = lost;
                let e = w.last_error().unwrap_or_default();
                self.log_failure(1, "frame log", &format!("{lost} rows lost so far: {e}"));
            }
        }
        self.snapshot.log_errors = self.hdr_lost + self.frame_log_lost;
        self.log_changes();
        // The counters are brought up to date on every tick (the summary at
        // exit reads them); a snapshot goes out once an interval ended.
        let now = clock::now_ns();
        let s = &self.stats;
        let snap = &mut self.snapshot;
        snap.seq += (intervals > 0) as u64;
        snap.mono_ns = now;
        snap.uptime_ns = now - self.start_ns;
        snap.margin_ns = s.margin_ns.load(Relaxed);
        snap.frames = s.frames.load(Relaxed);
        snap.edges = s.edges.load(Relaxed);
        snap.commands = s.commands.load(Relaxed);
        snap.overruns = s.overruns.load(Relaxed);
        snap.late_frames = s.late_frames.load(Relaxed);
        snap.late_edges = s.late_edges.load(Relaxed);
        snap.aborted_frames = s.aborted_frames.load(Relaxed);
        snap.glitched_frames = s.glitched_frames.load(Relaxed);
        snap.write_errors = s.write_errors.load(Relaxed);
        snap.failsafe_entries = s.failsafe_entries.load(Relaxed);
        snap.mismatched = s.mismatched.load(Relaxed);
        snap.expired = s.expired.load(Relaxed);
        snap.repeats = s.repeats.load(Relaxed);
        snap.spin_share_ppm = s.spin_ns.load(Relaxed) * 1_000_000 / snap.uptime_ns.max(1);
        snap.state = s.state() as u32;
        if let Some(l) = last {
            snap.last = l;
        }
        snap.total = summarize(&self.total_error);
        snap.write = summarize(&self.total_write);
        if now >= self.next_log_ns {
            self.next_log_ns = now + LOG_EVERY_NS;
            log::info!(
                "{}timing: {} frames; edge error p50 {:.2} us, p99 {:.2} us, max {:.1} us; {} aborted and {} glitched frames, {} late frames, {} overruns; spin margin {} us, spinning {:.1}% of the time",
                self.tag_prefix.replace('.', ": "),
                snap.frames,
                snap.total.p50 as f64 / 1e3,
                snap.total.p99 as f64 / 1e3,
                snap.total.max as f64 / 1e3,
                snap.aborted_frames,
                snap.glitched_frames,
                snap.late_frames,
                snap.overruns,
                snap.margin_ns / 1_000,
                snap.spin_share_ppm as f64 / 1e4,
            );
        }
        (intervals > 0).then_some(*snap)
    }

    /// Says log `which` (0: HdrHistogram, 1: frame log) failed: at once,
    /// then at most every LOG_FAILURE_EVERY_NS while it goes on failing.
    pub fn log_failure(&mut self, which: usize, what: &str, detail: &str) {
        let now = clock::now_ns();
        if now >= self.next_log_failure_ns[which] {
            self.next_log_failure_ns[which] = now + LOG_FAILURE_EVERY_NS;
            log::warn!(
                "{}{what}: cannot write ({detail}); ppmd keeps emitting and tries again",
                self.tag_prefix.replace('.', ": ")
            );
        }
    }

    pub fn log_changes(&mut self) {
        let who = match self.tag_prefix.strip_suffix('.') {
            Some(name) => format!("{name}: "),
            None => String::new(),
        };
        let now = self.stats.state();
        if now != self.state {
            match now {
                LineState::Active => log::info!("{who}commands arriving: emitting frames"),
                LineState::Silent => log::warn!("{who}no fresh command: line silent"),
                LineState::Failsafe => {
                    log::warn!("{who}no fresh command: emitting failsafe frames")
                }
            }
            self.state = now;
        }
        let w = self.stats.wake_errors.load(Relaxed);
        if w != self.wake_errors {
            log::warn!(
                "{who}the command wake-up failed: looking for commands every {} us instead",
                emitter::FOLLOW_POLL_NS / 1_000
            );
            self.wake_errors = w;
        }
        let m = self.stats.mismatched.load(Relaxed);
        match self.mismatched.note(m, clock::now_ns()) {
            Some(Said::First(n)) => log::warn!(
                "{who}{n} command(s) refused: udp-ingress made them under another channel model (channel count, order, limits, defaults or units differ from this daemon's); restart udp-ingress with ppmd's configuration. The line takes the failsafe action once the last good command is {} ms old",
                self.failsafe_after_ms
            ),
            Some(Said::More { since, total }) => log::warn!(
                "{who}{since} more command(s) refused under another channel model ({total} since start); restart udp-ingress with ppmd's configuration"
            ),
            None => {}
        }
        let s = self.stats.expired.load(Relaxed);
        if s != self.expired {
            log::info!(
                "{who}{} expired command(s) ignored: received before ppmd started (the shared-memory service keeps the last one) or older than failsafe.after_ms ({} ms); the line does what failsafe says until a fresh one comes",
                s - self.expired,
                self.failsafe_after_ms
            );
            self.expired = s;
        }
    }
}

/// A fault the timing loop counts (it adds to an atomic, nothing more)
/// and the monitor says, as it says the logs' failures: in full at once
/// the first time, then at most every [`LOG_FAILURE_EVERY_NS`] while it
/// goes on, as a count of how many more came since the last line. (Said
/// every tick, a fault met on every command was 10 lines a second.)
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Repeated {
    /// The loop's count when it was last said.
    pub said: u64,
    /// When it may be said again, CLOCK_MONOTONIC ns.
    pub next_ns: u64,
}

/// What to say of a [`Repeated`] fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Said {
    /// The first `n`: the whole message.
    First(u64),
    /// `since` more since the last line, `total` in all.
    More { since: u64, total: u64 },
}

impl Repeated {
    /// The loop's count is `total` at `now_ns`: what to say, if anything.
    /// What is not said yet is said with the next line.
    pub fn note(&mut self, total: u64, now_ns: u64) -> Option<Said> {
        if total == self.said || now_ns < self.next_ns {
            return None;
        }
        let first = self.said == 0;
        let since = total - self.said;
        self.said = total;
        self.next_ns = now_ns + LOG_FAILURE_EVERY_NS;
        Some(if first {
            Said::First(since)
        } else {
            Said::More { since, total }
        })
    }
}

/// The publisher of one output's timing snapshots and line samples, with
/// the node and services they live in.
pub struct SnapshotPublisher {
    publisher: ipc::Publisher<TimingSnapshot>,
    line: ipc::Publisher<LineSample>,
    /// The number of the last frame published on `line`.
    line_frame: u64,
    _service: ipc::StatsService,
    _line_service: ipc::LineService,
    _node: ipc::Node,
}

impl SnapshotPublisher {
    /// Opens output `name`'s timing snapshot service under the shared-memory
    /// `root`, as the node `ppmd-NAME`.
    pub fn open(root: &std::path::Path, name: &str) -> Result<SnapshotPublisher, IpcError> {
        let node = ipc::create_node(root, &format!("ppmd-{name}"))?;
        let service = ipc::open_stats_service(&node, name)?;
        let publisher = service.publisher_builder().create().map_err(|e| {
            IpcError::new(
                format!("creating the timing snapshot publisher of `{name}`"),
                e,
            )
        })?;
        let line_service = ipc::open_line_service(&node, name)?;
        let line = line_service.publisher_builder().create().map_err(|e| {
            IpcError::new(format!("creating the line sample publisher of `{name}`"), e)
        })?;
        Ok(SnapshotPublisher {
            publisher,
            line,
            line_frame: 0,
            _service: service,
            _line_service: line_service,
            _node: node,
        })
    }

    /// Publishes `sample`, the newest frame the line carried, unless it
    /// was published already.
    pub fn publish_line(&mut self, sample: LineSample) -> Result<(), PublishError> {
        if sample.frame == self.line_frame {
            return Ok(());
        }
        self.line_frame = sample.frame;
        ipc::publish(&self.line, sample).map(|_| ())
    }

    /// Publishes `snapshot` to whoever subscribed (udp-ingress, `jitter
    /// --attach`).
    pub fn publish(&self, snapshot: TimingSnapshot) -> Result<(), PublishError> {
        ipc::publish(&self.publisher, snapshot).map(|_| ())
    }

    /// Hands the last snapshot published (the service's history) to
    /// subscribers that came since: a restarted udp-ingress has ppmd's
    /// timing within one monitor tick, not at the next snapshot, a second
    /// later. iceoryx2 delivers history only from the publisher's side,
    /// when it looks for new subscribers (here, or before a send).
    pub fn serve_new_subscribers(&self) {
        use iceoryx2::port::update_connections::UpdateConnections;
        if let Err(e) = self.publisher.update_connections() {
            log::debug!("handing the last timing snapshot to new subscribers: {e}");
        }
    }
}

/// Summary of a histogram (all zero when empty).
pub fn summarize(h: &hdrhistogram::Histogram<u64>) -> Summary {
    if h.is_empty() {
        return Summary::default();
    }
    Summary {
        count: h.len(),
        min: h.min(),
        max: h.max(),
        mean: h.mean().round() as u64,
        p50: h.value_at_quantile(0.5),
        p99: h.value_at_quantile(0.99),
        p999: h.value_at_quantile(0.999),
    }
}

/// An HdrHistogram interval log (the format of HdrHistogram's
/// HistogramLogProcessor and plotting tools), values in nanoseconds, tags
/// `edge_error` and `write`, and `aborted` and `glitched` (one value per
/// such frame: how late its edge was; the count is the interval's frames). Appended to, never rotated (no cap is given);
/// each interval goes to the file whole, flushed at once.
pub struct HdrLog {
    pub file: crate::rotating::RotatingFile,
    pub serializer: hdrhistogram::serialization::V2DeflateSerializer,
    pub started: bool,
    /// One interval's text (the headers before the first).
    pub buf: Vec<u8>,
}

impl HdrLog {
    pub fn open(path: &std::path::Path) -> std::io::Result<HdrLog> {
        Ok(HdrLog {
            file: crate::rotating::RotatingFile::append("HdrHistogram log", path, u64::MAX, 1)?,
            serializer: hdrhistogram::serialization::V2DeflateSerializer::new(),
            started: false,
            buf: Vec::new(),
        })
    }

    /// Appends one interval: the edge error untagged when `untagged` (the
    /// first output's: what HdrHistogram's log processor reads without
    /// `-tag`, written even when empty so that every interval has one), and
    /// `[NAME.]edge_error`, `[NAME.]write`, `[NAME.]aborted` and
    /// `[NAME.]glitched` tagged, every one in every interval, empty ones
    /// too (a silent line's, a run without a late edge's), so a reader
    /// picking a tag finds every interval. The
    /// first write of a run starts with the headers Java's reader expects:
    /// the format version, start and base time, and the column legend (also
    /// the header of any file a rotation would start). An interval that
    /// cannot be written is lost (the caller counts it); the headers are
    /// tried again with the next.
    pub fn write(
        &mut self,
        iv: &Interval,
        start_ns: u64,
        prefix: &str,
        untagged: bool,
    ) -> Result<()> {
        use hdrhistogram::serialization::interval_log::{IntervalLogWriterBuilder, Tag};
        self.buf.clear();
        if !self.started {
            let now = SystemTime::now();
            IntervalLogWriterBuilder::new()
                .add_comment("ppmd edge error and write duration, nanoseconds")
                .add_comment("[Histogram log format version 1.3]")
                .with_start_time(now)
                .with_base_time(now)
                .begin_log_with(&mut self.buf, &mut self.serializer)
                .context("starting the log")?;
            self.buf.extend_from_slice(
                b"\"StartTimestamp\",\"Interval_Length\",\"Interval_Max\",\"Interval_Compressed_Histogram\"\n",
            );
            self.file.set_header(&self.buf);
        }
        let mut w = IntervalLogWriterBuilder::new()
            .begin_log_with(&mut self.buf, &mut self.serializer)
            .context("writing to the log")?;
        let from = Duration::from_nanos(iv.start_ns.saturating_sub(start_ns));
        let length = Duration::from_nanos(iv.end_ns.saturating_sub(iv.start_ns));
        if untagged {
            w.write_histogram(&iv.edge_error, from, length, None)
                .context("serializing the edge error")?;
        }
        for (h, tag) in [
            (&iv.edge_error, "edge_error"),
            (&iv.write, "write"),
            (&iv.aborted, "aborted"),
            (&iv.glitched, "glitched"),
        ] {
            let tag = format!("{prefix}{tag}");
            w.write_histogram(h, from, length, Tag::new(&tag))
                .with_context(|| format!("serializing {tag}"))?;
        }
        self.file
            .write(&self.buf)
            .and_then(|()| self.file.flush())
            .context("writing to the log")?;
        self.started = true;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mismatch met on every command (50 a second, the monitor looking
    /// 10 times a second) is said once, then once per
    /// LOG_FAILURE_EVERY_NS with the count since; a quiet spell says
    /// nothing, and the next one is a count again.
    #[test]
    fn a_repeated_fault_is_said_once_then_counted() {
        let mut r = Repeated::default();
        let tick = 100_000_000; // the monitor's 100 ms
        let mut said = Vec::new();
        for t in 1..=300u64 {
            // 5 more commands refused each tick, for 30 s.
            if let Some(s) = r.note(5 * t, 1_000_000_000 + t * tick) {
                said.push((t, s));
            }
        }
        assert_eq!(
            said,
            [
                (1, Said::First(5)),
                (
                    101,
                    Said::More {
                        since: 500,
                        total: 505
                    }
                ),
                (
                    201,
                    Said::More {
                        since: 500,
                        total: 1005
                    }
                ),
            ]
        );
        // They stop: what came since the last line is said when due, then
        // nothing however long it stays quiet.
        assert_eq!(
            r.note(1500, 1_000_000_000 + 301 * tick),
            Some(Said::More {
                since: 495,
                total: 1500
            })
        );
        for t in 302..=600u64 {
            assert_eq!(r.note(1500, 1_000_000_000 + t * tick), None);
        }
        // One more, long after: said at once, as a count.
        assert_eq!(
            r.note(1501, 1_000_000_000 + 601 * tick),
            Some(Said::More {
                since: 1,
                total: 1501
            })
        );
    }

    #[test]
    fn snapshots_reach_a_subscriber_of_the_outputs_stats_service() {
        let root = std::env::temp_dir().join(format!("ppm-monitor-test-{}", std::process::id()));
        let name = format!("montest{}", std::process::id());
        {
            let publisher = SnapshotPublisher::open(&root, &name).unwrap();
            let node = ipc::create_node(&root, &format!("{name}-reader")).unwrap();
            let service = ipc::open_stats_service(&node, &name).unwrap();
            let subscriber = service.subscriber_builder().create().unwrap();
            let snapshot = TimingSnapshot {
                seq: 3,
                frames: 150,
                ..TimingSnapshot::default()
            };
            publisher.publish(snapshot).unwrap();
            let got = subscriber.receive().unwrap().expect("the snapshot");
            assert_eq!(*got.payload(), snapshot);
        }
        let _ = std::fs::remove_dir_all(&root);
    }
}
