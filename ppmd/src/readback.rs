//! The read-back thread of one output: reads PPM from the output's
//! `ppmd.readback` input (the radio's module bay), decodes it
//! ([`ppm_shared::capture::Capture`]), compares each frame read with the
//! frames the line carried ([`ppm_shared::capture::Matcher`]), publishes
//! the result for udp-ingress (`ppm/NAME/readback`) and appends every frame
//! read to the read-back log.
//!
//! Why a thread of ppmd, and not in the timing loop or a process of its own:
//! the comparison needs every frame the line carried, with its time, and
//! ppmd already keeps the newest one where other threads read it without
//! ever making the loop wait ([`crate::emitter::Stats::last_frame`], a
//! sequence-counted copy). This thread polls it every
//! [`POLL`] (frames are at least 5 ms apart), so the timing loop is not
//! changed at all: no new ring, no new branch. The thread runs at normal
//! priority, never on the timing thread's CPU, and blocks only on its
//! input (the GPIO character device's edge events, timestamped by the
//! kernel's interrupt handler, so how late this thread wakes does not
//! change a single value read). `ppm-capture` reads an input without an
//! output (a pilot's radio) with the same decoder and log format.

use crate::emitter::Stats;
use crate::input::{self, EdgeSource};
use crate::rotating::{self, RotatingFile, WriterOptions};
use anyhow::{Context, Result};
use ppm_shared::capture::{
    Capture, CaptureCounts, Carried, EdgeEvent, Matcher, ReadFrame, ReadbackState,
};
use ppm_shared::config::ReadbackPlan;
use ppm_shared::ipc::{self, ReadbackSample, READBACK_REASONS};
use ppm_shared::logging::Chain;
use ppm_shared::time::{now_ns, realtime_ns};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// How long the thread waits for edges before it looks at the line's
/// newest frame again.
pub const POLL: Duration = Duration::from_millis(2);
/// How often the state is published while nothing changes.
const PUBLISH_EVERY_NS: u64 = 100_000_000;
/// Rotated read-back logs kept besides the current one.
const KEEP: usize = 3;
/// Edges read in one go.
const BATCH: usize = 256;

/// One row of the read-back log.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Row {
    /// A frame read.
    Read {
        /// Its number among the frames read (1, 2, ...).
        frame: u64,
        /// The frame.
        read: ReadFrame,
        /// CLOCK_REALTIME time of its start, ns.
        start_real_ns: u64,
        /// Whether it carried ppm's values (`None`: nothing to compare
        /// with, as in `ppm-capture`).
        matched: Option<bool>,
        /// Its largest difference to what ppm carried, ns (`u32::MAX`:
        /// ppm carried nothing in the window).
        max_diff_ns: u32,
        /// The state after it.
        state: Option<ReadbackState>,
    },
    /// The state changed.
    Change {
        /// CLOCK_MONOTONIC time, ns.
        mono_ns: u64,
        /// CLOCK_REALTIME time, ns.
        real_ns: u64,
        /// From.
        from: ReadbackState,
        /// To.
        to: ReadbackState,
    },
}

impl Row {
    /// The JSON line (without the newline): keys as the frame log's where
    /// they mean the same (`type`, `frame`, `mono_ns`, `real_ns`, `ch_us`).
    pub fn to_json(&self) -> String {
        match self {
            Row::Read {
                frame,
                read,
                start_real_ns,
                matched,
                max_diff_ns,
                state,
            } => serde_json::json!({
                "type": "read",
                "frame": frame,
                "mono_ns": read.start_ns,
                "real_ns": start_real_ns,
                "end_mono_ns": read.end_ns,
                "ch_us": read.values().iter().map(|&ns| ns as f64 / 1_000.0).collect::<Vec<_>>(),
                "match": matched,
                "max_diff_us": (matched.is_some() && *max_diff_ns != u32::MAX)
                    .then(|| *max_diff_ns as f64 / 1_000.0),
                "state": state.map(|s| s.name()),
            })
            .to_string(),
            Row::Change {
                mono_ns,
                real_ns,
                from,
                to,
            } => serde_json::json!({
                "type": "readback",
                "mono_ns": mono_ns,
                "real_ns": real_ns,
                "from": from.name(),
                "to": to.name(),
            })
            .to_string(),
        }
    }
}

/// The log's writing side.
pub type LogProducer = rotating::Producer<Row>;

/// Opens (appends to) a read-back log at `path`, rotated at `max_bytes`.
pub fn open_log(path: &Path, max_bytes: u64) -> std::io::Result<(LogProducer, rotating::Writer)> {
    let file = RotatingFile::append("read-back log", path, max_bytes, KEEP)?;
    rotating::spawn(
        file,
        WriterOptions {
            thread: "ppmd-readback-log",
            capacity: 1024,
            flush_every: Duration::from_millis(100),
            say_write_errors: true,
        },
        |r: &Row, line: &mut String| line.push_str(&r.to_json()),
    )
}

/// CLOCK_REALTIME time of CLOCK_MONOTONIC time `mono_ns`, from the two
/// clocks read now.
pub fn real_of(mono_ns: u64) -> u64 {
    let (mono, real) = (now_ns(), realtime_ns());
    real.saturating_sub(mono.saturating_sub(mono_ns))
}

/// The refusal counts in [`CaptureCounts::reasons`]' order.
pub fn refused(counts: &CaptureCounts) -> [u64; READBACK_REASONS] {
    let mut out = [0; READBACK_REASONS];
    for (o, (_, n)) in out.iter_mut().zip(counts.reasons()) {
        *o = n;
    }
    out
}

/// The decoding, comparison and counting of one read-back, apart from its
/// input and its outputs (so tests drive it with edges and frames).
pub struct Judge {
    capture: Capture,
    matcher: Matcher,
    /// The sample published last, updated as frames are read.
    pub sample: ReadbackSample,
    /// The number of the newest frame of the line noted.
    line_frame: u64,
}

impl Judge {
    /// A read-back of `plan`.
    pub fn new(plan: &ReadbackPlan, idle_hint: Option<ppm_shared::Level>) -> Judge {
        let mut settings = plan.capture;
        if settings.idle.is_none() {
            settings.idle = idle_hint;
        }
        Judge {
            capture: Capture::new(settings),
            matcher: Matcher::new(plan.matching),
            sample: ReadbackSample::default(),
            line_frame: 0,
        }
    }

    /// Notes the line's newest frame from `stats`, if it is new.
    pub fn note_line(&mut self, stats: &Stats) {
        if let Some(s) = stats.last_frame.load() {
            if s.frame != self.line_frame {
                self.line_frame = s.frame;
                self.matcher.carried(Carried {
                    start_ns: s.start_mono_ns,
                    count: s.channels as u8,
                    values_ns: s.values_ns,
                });
            }
        }
    }

    /// Notes a frame the line carried (for tests and tools that know it).
    pub fn carried(&mut self, c: Carried) {
        self.matcher.carried(c);
    }

    /// Feeds one edge; a frame read comes back as its log rows (the frame,
    /// and the change it made, if any).
    pub fn edge(&mut self, e: EdgeEvent, mut row: impl FnMut(Row)) {
        let Some(f) = self.capture.push(e) else {
            return;
        };
        let v = self.matcher.read(&f);
        let s = &mut self.sample;
        s.frames += 1;
        if v.matched {
            s.matched += 1;
        } else {
            s.mismatched += 1;
        }
        s.start_mono_ns = f.start_ns;
        s.channels = f.count as u32;
        s.values_ns = f.values_ns;
        s.max_diff_ns = v.max_diff_ns;
        row(Row::Read {
            frame: s.frames,
            read: f,
            start_real_ns: real_of(f.start_ns),
            matched: Some(v.matched),
            max_diff_ns: v.max_diff_ns,
            state: Some(self.matcher.state()),
        });
        if let Some((from, to)) = v.changed {
            self.changed(f.end_ns, from, to, row);
        }
    }

    /// At `now`: the input is lost when no whole frame came for a second.
    pub fn tick(&mut self, now: u64, row: impl FnMut(Row)) {
        if !self.capture.valid_at(now) {
            if let Some((from, to)) = self.matcher.input_lost() {
                self.changed(now, from, to, row);
            }
        }
    }

    fn changed(
        &mut self,
        at: u64,
        from: ReadbackState,
        to: ReadbackState,
        mut row: impl FnMut(Row),
    ) {
        self.sample.changes += 1;
        self.sample.changed_mono_ns = at;
        row(Row::Change {
            mono_ns: at,
            real_ns: real_of(at),
            from,
            to,
        });
    }

    /// The sample to publish at `now`.
    pub fn publish_at(&mut self, now: u64) -> ReadbackSample {
        let counts = self.capture.counts();
        self.sample.state = self.matcher.state() as u32;
        self.sample.edges = counts.edges;
        self.sample.refused = refused(&counts);
        self.sample.published_mono_ns = now;
        self.sample
    }

    /// The state.
    pub fn state(&self) -> ReadbackState {
        self.matcher.state()
    }
}

/// A read-back whose input and log are open, its thread not yet started.
pub struct Opened {
    name: String,
    tag: String,
    source: Box<dyn EdgeSource>,
    judge: Judge,
    log: Option<LogProducer>,
    writer: Option<rotating::Writer>,
}

impl Opened {
    /// Opens output `name`'s read-back input and log; errors name
    /// `ppmd.readback` or `ppmd.readback_log`.
    pub fn open(
        name: &str,
        tag: &str,
        plan: &ReadbackPlan,
        keys: &ppm_shared::config::SetKeys,
        log_max_bytes: u64,
    ) -> Result<Opened> {
        let source = input::open(&plan.input).with_context(|| {
            format!(
                "{}: opening {}",
                keys.name("ppmd.readback").as_str(),
                plan.input
            )
        })?;
        let (log, writer) = match &plan.log {
            Some(path) => {
                let (p, w) = open_log(path, log_max_bytes).map_err(|e| {
                    ppm_shared::config::fault::path_error(
                        &keys.name("ppmd.readback_log"),
                        &format!("opening the read-back log {}", path.display()),
                        path,
                        e,
                        "name a file ppmd may create and append to, in a directory that exists",
                    )
                })?;
                log::info!("{tag}read-back log: {}", path.display());
                (Some(p), Some(w))
            }
            None => (None, None),
        };
        log::info!("{tag}read-back: {}", source.description());
        let judge = Judge::new(plan, source.idle_level());
        Ok(Opened {
            name: name.to_owned(),
            tag: tag.to_owned(),
            source,
            judge,
            log,
            writer,
        })
    }

    /// Starts the thread, which publishes under the shared-memory `root`,
    /// reads the line's frames from `stats`, and stays off `avoid_cpu` (the
    /// timing thread's). Returns once it publishes, or why it cannot.
    pub fn start(
        self,
        root: &Path,
        stats: Arc<Stats>,
        avoid_cpu: Option<usize>,
    ) -> Result<Readback> {
        let stop = Arc::new(AtomicBool::new(false));
        let ctx = Ctx {
            tag: self.tag,
            source: self.source,
            judge: self.judge,
            log: self.log,
            stats,
            stop: stop.clone(),
        };
        let (name, root) = (self.name, root.to_owned());
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("ppmd-readback".into())
            .spawn(move || {
                avoid(avoid_cpu);
                let opened = (|| -> Result<_, ipc::IpcError> {
                    let node = ipc::create_node(&root, &format!("ppmd-{name}-readback"))?;
                    let service = ipc::open_readback_service(&node, &name)?;
                    let publisher = service.publisher_builder().create().map_err(|e| {
                        ipc::IpcError::new(
                            format!("creating the read-back publisher of `{name}`"),
                            e,
                        )
                    })?;
                    Ok((node, service, publisher))
                })();
                match opened {
                    Ok((_node, _service, publisher)) => {
                        let _ = ready_tx.send(Ok(()));
                        ctx.run(&publisher);
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                }
            })
            .context("spawning the read-back thread")?;
        let mut rb = Readback {
            stop,
            thread: Some(thread),
            log: self.writer,
        };
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(rb),
            Ok(Err(e)) => {
                rb.finish();
                Err(e.into())
            }
            Err(_) => {
                rb.finish();
                anyhow::bail!("the read-back thread stopped at start")
            }
        }
    }
}

/// A running read-back thread.
pub struct Readback {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    log: Option<rotating::Writer>,
}

impl Readback {
    /// Stops the thread and finishes the log.
    pub fn finish(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        if let Some(w) = self.log.as_mut() {
            w.finish();
        }
    }
}

impl Drop for Readback {
    fn drop(&mut self) {
        self.finish();
    }
}

/// Keeps the calling thread off `cpu` (the timing thread's).
pub(crate) fn avoid(cpu: Option<usize>) {
    let Some(cpu) = cpu else { return };
    use nix::sched::{sched_getaffinity, sched_setaffinity, CpuSet};
    use nix::unistd::Pid;
    if let Ok(mut set) = sched_getaffinity(Pid::from_raw(0)) {
        if set.is_set(cpu).unwrap_or(false) {
            let _ = set.unset(cpu);
            let others = (0..CpuSet::count()).any(|c| set.is_set(c).unwrap_or(false));
            if others {
                if let Err(e) = sched_setaffinity(Pid::from_raw(0), &set) {
                    log::debug!("keeping the read-back thread off CPU {cpu}: {e}");
                }
            }
        }
    }
}

struct Ctx {
    tag: String,
    source: Box<dyn EdgeSource>,
    judge: Judge,
    log: Option<LogProducer>,
    stats: Arc<Stats>,
    stop: Arc<AtomicBool>,
}

impl Ctx {
    fn run(mut self, publisher: &ipc::Publisher<ReadbackSample>) {
        let mut buf = [EdgeEvent {
            at_ns: 0,
            level: ppm_shared::Level::Low,
            seq: 0,
        }; BATCH];
        let mut published = 0u64;
        let mut failing = false;
        while !self.stop.load(Relaxed) {
            let n = match self.source.read(&mut buf, POLL) {
                Ok(n) => {
                    if failing {
                        log::info!("{}read-back input reads again", self.tag);
                        failing = false;
                    }
                    n
                }
                Err(e) => {
                    if !failing {
                        log::warn!("{}reading the read-back input: {}", self.tag, Chain(&e));
                        failing = true;
                    }
                    std::thread::sleep(Duration::from_millis(100));
                    0
                }
            };
            self.judge.note_line(&self.stats);
            let before = self.judge.sample;
            let log = &mut self.log;
            let mut row = |r: Row| {
                if let Some(l) = log.as_mut() {
                    l.push(r);
                }
            };
            for e in &buf[..n] {
                self.judge.edge(*e, &mut row);
            }
            let now = now_ns();
            self.judge.tick(now, &mut row);
            let s = self.judge.sample;
            if s.frames != before.frames
                || s.changes != before.changes
                || now.saturating_sub(published) >= PUBLISH_EVERY_NS
            {
                if s.changes != before.changes {
                    log::info!("{}read-back: {}", self.tag, self.judge.state().name());
                }
                let sample = self.judge.publish_at(now);
                if let Err(e) = ipc::publish(publisher, sample) {
                    log::debug!("publishing the read-back: {}", Chain(&e));
                }
                published = now;
            }
        }
    }
}
