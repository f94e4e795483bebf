//! `ppmd`: emits the newest command from udp-ingress as a PPM trainer signal.
//!
//! Two threads: the timing thread (real-time setup, then the loop in
//! `ppmd::emitter`) and this main thread, which never touches the line: it
//! reads the loop's counters and histograms, logs, publishes timing
//! snapshots and writes the HdrHistogram log.

use anyhow::{anyhow, bail, Context, Result};
use clap::Parser;
use ppm_shared::config::{Config, OutputSpec, SpinMargin, Timing};
use ppm_shared::frame::{FrameModel, Level};
use ppm_shared::ipc::{self, Summary, TimingSnapshot};
use ppmd::clock::{self, Margin};
use ppmd::emitter::{self, EmitterConfig, Lane, LineState, Sink, Stats};
use ppmd::meter::{self, Interval, MeterReader};
use ppmd::output::{Bank, Output, SimOutput};
use ppmd::rt::{RtSetup, RT_STACK_BYTES};
use ppmd::source::{CommandSource, IpcSource};
use ppmd::watchdog::{self, Verdict, Watchdog};
use sd_notify::NotifyState;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

/// PPM daemon: takes the newest command from udp-ingress once per frame and
/// emits it as a PPM trainer signal.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Cli {
    /// Configuration file (TOML); every key has a default.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Log lines: `journal` (`<N>` priority prefixes, no timestamp),
    /// `plain` (timestamped), or `auto`: journal when standard error is
    /// systemd's journal (JOURNAL_STREAM), else plain.
    #[arg(long, value_enum, default_value_t = ppm_shared::logging::LogFormat::Auto, value_name = "FORMAT")]
    log_format: ppm_shared::logging::LogFormat,
    /// Output name; must match udp-ingress's. Overrides `name`; with
    /// `[[outputs]]` in the configuration, runs that output alone.
    #[arg(long)]
    name: Option<String>,
    /// `sim` (trace in ppm-NAME.trace), `sim:PATH`, or `gpio:CHIP:LINE` (CHIP:
    /// a path, name or label such as pinctrl-bcm2711; LINE: an offset or a
    /// name such as GPIO18). Overrides `ppmd.output`. Repeat as
    /// `--output NAME=SPEC` to drive several outputs from one timing thread,
    /// each fed by its own `udp-ingress --name NAME`.
    #[arg(long, value_name = "[NAME=]SPEC")]
    output: Vec<String>,
    /// Run even when a real-time setting cannot be had (the run is then
    /// marked degraded). Sets `rt.allow_degraded`.
    #[arg(long)]
    allow_degraded: bool,
    /// Append one JSON line per emitted frame and line-state change to FILE.
    /// Overrides `ppmd.frame_log`.
    #[arg(long, value_name = "FILE")]
    frame_log: Option<PathBuf>,
    /// When frames start: `grid` (one every `ppm.frame_us`) or `follow` (a
    /// fresh command starts its frame as soon as the sync allows). Overrides
    /// `ppm.timing`, for every output.
    #[arg(long, value_name = "grid|follow")]
    timing: Option<Timing>,
    /// Append an HdrHistogram interval log of edge error and write duration
    /// (nanoseconds, one interval a second) to FILE.
    #[arg(long, value_name = "FILE")]
    hdr_log: Option<PathBuf>,
}

/// How often the main thread reads the loop's measurements.
const MONITOR_EVERY: Duration = Duration::from_millis(100);
/// How often a histogram interval is handed over and a snapshot published.
const SNAPSHOT_EVERY_NS: u64 = 1_000_000_000;
/// How often the timing summary is logged.
const LOG_EVERY_NS: u64 = 60_000_000_000;
/// How often a log that goes on failing is said again.
const LOG_FAILURE_EVERY_NS: u64 = 10_000_000_000;

fn main() {
    let cli = Cli::parse();
    ppm_shared::logging::init(cli.log_format);
    ipc::init_ipc_logging();
    if let Err(e) = run(cli) {
        log::error!("{e:#}");
        std::process::exit(1);
    }
}

/// One output as the main thread sets it up.
struct Setup {
    cfg: Config,
    model: FrameModel,
    ecfg: EmitterConfig,
    stats: Arc<Stats>,
    meter: Option<meter::Meter>,
    reader: Option<MeterReader>,
    log: Option<ppmd::framelog::Producer>,
    log_writer: Option<ppmd::framelog::Writer>,
}

/// One output's line, as the timing thread owns it.
enum Line {
    /// A line of its own (sim, or the only one of ours on its GPIO chip).
    Own(Box<dyn Output>),
    /// Line `bit` of bank `bank` of [`Lines::banks`].
    Banked { bank: usize, bit: u32 },
}

/// Every output's line, and the banks (several lines of one GPIO chip in
/// one request) some of them are in.
struct Lines {
    each: Vec<Line>,
    banks: Vec<ppmd::output::gpio::GpioBank>,
}

fn run(cli: Cli) -> Result<()> {
    let mut cfg = Config::load_or_default(cli.config.as_deref())?;
    if let Some(name) = cli.name.as_deref() {
        // With [[outputs]], --name runs that output alone.
        cfg = cfg.select(Some(name))?;
    }
    cfg.apply_cli_outputs(&cli.output)?;
    cfg.rt.allow_degraded |= cli.allow_degraded;
    if let Some(t) = cli.timing {
        cfg.ppm.timing = t;
    }
    for out in cfg.outputs.iter_mut() {
        out.rt.allow_degraded = cfg.rt.allow_degraded;
        if let Some(t) = cli.timing {
            out.ppm.timing = t;
        }
    }
    if let Some(path) = cli.frame_log {
        if !cfg.outputs.is_empty() {
            bail!("--frame-log with several outputs: set frame_log in each output's [[outputs]] entry instead");
        }
        cfg.ppmd.frame_log = Some(path);
    }
    let outputs = cfg.validate_outputs()?;
    let several = outputs.len() > 1;
    // Shared settings (rt, ipc) are the same in every output.
    let shared = outputs[0].0.clone();
    let lines = open_lines(&outputs)?;

    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    let margin = match shared.rt.spin_margin_us {
        SpinMargin::Fixed(us) => Margin::Fixed(us as u64 * 1_000),
        SpinMargin::Auto => Margin::Auto {
            min_ns: shared.rt.spin_margin_min_us as u64 * 1_000,
            max_ns: shared.rt.spin_margin_max_us as u64 * 1_000,
        },
    };
    let mut setups = Vec::new();
    for (c, model) in outputs {
        let (log, log_writer) = match &c.ppmd.frame_log {
            Some(path) => {
                let (p, w) = ppmd::framelog::open(path, c.ppmd.frame_log_max_mb << 20)
                    .with_context(|| format!("opening the frame log {}", path.display()))?;
                log::info!("{}frame log: {}", tag(several, &c.name), path.display());
                (Some(p), Some(w))
            }
            None => (None, None),
        };
        let (meter, reader) = meter::meter(SNAPSHOT_EVERY_NS);
        setups.push(Setup {
            ecfg: EmitterConfig {
                margin,
                failsafe_after_ns: c.failsafe.after_ms * 1_000_000,
                failsafe_action: c.failsafe.action,
                startup: c.failsafe.startup,
            },
            cfg: c,
            model,
            stats: Arc::new(Stats::default()),
            meter: Some(meter),
            reader: Some(reader),
            log,
            log_writer,
        });
    }
    let mut nodes = Vec::new();
    let mut publishers = Vec::new();
    for s in &setups {
        let node = ipc::create_node(&shared.ipc.root, &format!("ppmd-{}", s.cfg.name))?;
        let service = ipc::open_stats_service(&node, &s.cfg.name)?;
        let publisher = service.publisher_builder().create().map_err(|e| {
            anyhow!(
                "creating the timing snapshot publisher of `{}`: {e:?}",
                s.cfg.name
            )
        })?;
        publishers.push(publisher);
        nodes.push((node, service));
    }

    let setup = RtSetup::from_config(&shared.rt);
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let timing = {
        let stop = stop.clone();
        let root = shared.ipc.root.clone();
        let mut parts: Vec<_> = setups
            .iter_mut()
            .map(|s| {
                (
                    s.cfg.name.clone(),
                    s.model.clone(),
                    s.ecfg,
                    s.stats.clone(),
                    s.meter.take().expect("meter"),
                    s.log.take(),
                )
            })
            .collect();
        let mut lines = lines;
        std::thread::Builder::new()
            .name("ppmd-timing".into())
            .stack_size(RT_STACK_BYTES)
            .spawn(move || -> Result<Vec<u64>> {
                let started = parts
                    .iter()
                    .map(|p| IpcSource::open(&root, &p.0, p.1.timing() == Timing::Follow))
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(anyhow::Error::from)
                    .and_then(|sources| Ok((sources, setup.apply()?)));
                let (mut sources, obtained) = match started {
                    Ok(v) => v,
                    Err(e) => {
                        let _ = ready_tx.send(None);
                        return Err(e);
                    }
                };
                let _ = ready_tx.send(Some(Obtained::from(&obtained)));
                {
                    let Lines { each, banks } = &mut lines;
                    let mut lanes: Vec<Lane> = parts
                        .iter_mut()
                        .zip(sources.iter_mut())
                        .zip(each.iter_mut())
                        .map(|((p, source), line)| Lane {
                            model: &p.1,
                            cfg: p.2,
                            source,
                            sink: match line {
                                Line::Own(out) => Sink::Line(out.as_mut()),
                                Line::Banked { bank, bit } => Sink::Bank {
                                    bank: *bank,
                                    bit: *bit,
                                },
                            },
                            stats: &p.3,
                            meter: &mut p.4,
                            log: p.5.as_mut(),
                        })
                        .collect();
                    let mut bank_refs: Vec<&mut dyn Bank> =
                        banks.iter_mut().map(|b| b as &mut dyn Bank).collect();
                    emitter::run_lanes(&mut lanes, &mut bank_refs, &stop);
                }
                drop(lines); // sets the lines idle, flushes the sim traces
                drop(obtained); // releases /dev/cpu_dma_latency
                Ok(sources.iter().map(|s| s.errors()).collect())
            })
            .context("spawning the timing thread")?
    };
    let Ok(Some(obtained)) = ready_rx.recv() else {
        return match timing.join() {
            Ok(Err(e)) => Err(e),
            _ => bail!("the timing thread stopped at start"),
        };
    };
    log::info!("real-time: {}", obtained.summary);
    for s in &obtained.shortfalls {
        log::warn!("DEGRADED RUN: {s}");
    }
    for s in &setups {
        let (c, model) = (&s.cfg, &s.model);
        let timing = match model.timing() {
            Timing::Grid => format!("grid timing, frame {} us", model.frame_ns() as f64 / 1e3),
            Timing::Follow => {
                let (min, max) = model.follow_sync_ns();
                format!(
                    "follow timing, sync {}..{} us",
                    min as f64 / 1e3,
                    max as f64 / 1e3
                )
            }
        };
        log::info!(
            "{}{} channels ({}), {timing}, pulse {} us, idle {:?}; commands from `{}` (ipc root {}); failsafe {:?} after {} ms; spin margin {:?}",
            tag(several, &c.name),
            model.channels(),
            model.names().join(" "),
            model.pulse_ns() as f64 / 1e3,
            model.idle_level(),
            ipc::command_service_name(&c.name),
            shared.ipc.root.display(),
            c.failsafe.action,
            c.failsafe.after_ms,
            shared.rt.spin_margin_us,
        );
    }

    let mut hdr = cli
        .hdr_log
        .as_deref()
        .map(HdrLog::open)
        .transpose()
        .with_context(|| {
            let p = cli
                .hdr_log
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default();
            format!("opening the HdrHistogram log {p}")
        })?;
    let mut monitors = Vec::new();
    for s in setups.iter_mut() {
        monitors.push(Monitor::new(
            (&s.model, s.cfg.failsafe.after_ms),
            &obtained,
            s.reader.take().expect("reader"),
            s.stats.clone(),
            if several {
                format!("{}.", s.cfg.name)
            } else {
                String::new()
            },
        ));
    }
    if let Some(first) = monitors.first_mut() {
        first.hdr_untagged = true;
    }
    let progress = || -> u64 { setups.iter().map(|s| s.stats.decisions.load(Relaxed)).sum() };
    let mut watchdog = Watchdog::from_env(progress(), Instant::now());
    if let Some(w) = &watchdog {
        log::info!(
            "systemd watchdog: {:?}, petted while the timing loop makes progress",
            w.timeout()
        );
    }
    // Under Type=notify: the outputs are open and the loop runs.
    if let Err(e) = watchdog::notify(NotifyState::Ready) {
        log::warn!("cannot tell systemd ppmd is ready: {e}");
    }
    let mut notify_failed = false;
    while !stop.load(Relaxed) && !timing.is_finished() {
        std::thread::sleep(MONITOR_EVERY);
        let pet = match watchdog
            .as_mut()
            .map(|w| (w.tick(progress(), Instant::now()), w.timeout()))
        {
            Some((Verdict::Pet, _)) => true,
            Some((Verdict::Resumed, _)) => {
                log::warn!("the timing loop makes progress again: petting systemd's watchdog");
                true
            }
            Some((Verdict::Stalled(quiet), timeout)) => {
                log::error!(
                    "the timing loop has made no progress for {quiet:?}: systemd's watchdog is no longer petted and restarts ppmd {timeout:?} after the last pet"
                );
                false
            }
            Some((Verdict::Wait, _)) | None => false,
        };
        if pet {
            match watchdog::notify(NotifyState::Watchdog) {
                Ok(()) => notify_failed = false,
                Err(e) if !notify_failed => {
                    notify_failed = true;
                    log::warn!("cannot pet systemd's watchdog: {e}");
                }
                Err(_) => {}
            }
        }
        for ((monitor, publisher), s) in monitors.iter_mut().zip(&publishers).zip(&setups) {
            if let Some(snapshot) = monitor.tick(hdr.as_mut(), s.log_writer.as_ref()) {
                let sent = publisher
                    .loan_uninit()
                    .map(|s| s.write_payload(snapshot))
                    .map_err(|e| format!("{e:?}"))
                    .and_then(|s| s.send().map_err(|e| format!("{e:?}")));
                if let Err(e) = sent {
                    log::debug!("publishing timing snapshot: {e}");
                }
            }
        }
    }
    let _ = watchdog::notify(NotifyState::Stopping);
    let receive_errors = timing
        .join()
        .map_err(|_| anyhow!("the timing thread panicked"))??;
    for ((s, monitor), errors) in setups
        .iter_mut()
        .zip(monitors.iter_mut())
        .zip(receive_errors)
    {
        if let Some(w) = s.log_writer.as_mut() {
            w.finish();
        }
        monitor.tick(hdr.as_mut(), s.log_writer.as_ref());
        if let Some(w) = s.log_writer.as_ref() {
            if w.lost() > 0 {
                log::warn!(
                    "{}frame log: {} rows could not be written ({})",
                    tag(several, &s.cfg.name),
                    w.lost(),
                    w.last_error().unwrap_or_default()
                );
            }
            if w.dropped() > 0 {
                log::warn!(
                    "{}frame log: {} rows dropped (the writer fell behind)",
                    tag(several, &s.cfg.name),
                    w.dropped()
                );
            }
        }
        let t = &monitor.snapshot;
        log::info!(
            "{}stopped{}: {} frames{}, {} commands; edge error p50 {:.2} us, p99 {:.2} us, p99.9 {:.2} us, max {:.1} us; {} late edges (> {} us), {} late frames, {} overruns, {} write errors, {} mismatched samples, {} receive errors",
            tag(several, &s.cfg.name),
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
            t.late_frames,
            t.overruns,
            t.write_errors,
            s.stats.mismatched.load(Relaxed),
            errors,
        );
    }
    Ok(())
}

/// `NAME: ` in front of a log line when there are several outputs.
fn tag(several: bool, name: &str) -> String {
    if several {
        format!("{name}: ")
    } else {
        String::new()
    }
}

/// Opens every output's line. GPIO lines on one chip (however the chip is
/// named) share one request, a bank, so their simultaneous edges are written
/// in one call; a chip with one of our lines gets a request of its own.
fn open_lines(outputs: &[(Config, FrameModel)]) -> Result<Lines> {
    let mut each: Vec<Option<Line>> = outputs.iter().map(|_| None).collect();
    /// A chip's path, its CHIP as first given, and its outputs (index, LINE).
    type Chip = (PathBuf, String, Vec<(usize, String)>);
    let mut chips: Vec<Chip> = Vec::new();
    for (i, (cfg, model)) in outputs.iter().enumerate() {
        match cfg.output()? {
            OutputSpec::Sim { path } => {
                each[i] = Some(Line::Own(open_sim(cfg, model, path)?));
            }
            OutputSpec::Spi { device } => {
                // The longest frame: the lead-in pulse after silence, every
                // channel at its maximum, the last pulse.
                let longest = emitter::LEAD_IN_NS
                    + (0..model.channels())
                        .map(|c| model.max_ns(c) as u64)
                        .sum::<u64>()
                    + model.pulse_ns();
                let out = ppmd::output::spi::SpiOutput::open(&device, cfg.ppmd.spi_hz, longest)
                    .with_context(|| format!("output `{}`: spi:{}", cfg.name, device.display()))?;
                log::info!(
                    "output `{}`: spi {} (each frame one transfer, edges to {} ns)",
                    cfg.name,
                    out.description(),
                    1_000_000_000 / cfg.ppmd.spi_hz as u64
                );
                each[i] = Some(Line::Own(Box::new(out)));
            }
            OutputSpec::Gpio { chip, line } => {
                let (_, summary, _) = ppmd::output::gpio::resolve_line(&chip, &line)
                    .with_context(|| format!("output `{}`: gpio:{chip}:{line}", cfg.name))?;
                match chips.iter_mut().find(|c| c.0 == summary.path) {
                    Some(c) => c.2.push((i, line)),
                    None => chips.push((summary.path, chip, vec![(i, line)])),
                }
            }
        }
    }
    let mut banks = Vec::new();
    for (path, chip, members) in chips {
        if let [(i, line)] = members.as_slice() {
            let (cfg, model) = &outputs[*i];
            let out = ppmd::output::gpio::open(&chip, line, model.idle_level())
                .with_context(|| format!("output `{}`: gpio:{chip}:{line}", cfg.name))?;
            log::info!("output `{}`: gpio {}", cfg.name, out.description());
            each[*i] = Some(Line::Own(Box::new(out)));
            continue;
        }
        let lines: Vec<(String, Level)> = members
            .iter()
            .map(|(i, line)| (line.clone(), outputs[*i].1.idle_level()))
            .collect();
        let names: Vec<&str> = members
            .iter()
            .map(|(i, _)| outputs[*i].0.name.as_str())
            .collect();
        let bank = ppmd::output::gpio::open_bank(&path.to_string_lossy(), &lines)
            .with_context(|| format!("outputs {}: GPIO chip {chip}", names.join(", ")))?;
        for (bit, ((i, _), d)) in members.iter().zip(bank.descriptions()).enumerate() {
            log::info!(
                "output `{}`: gpio {d} (one request with {})",
                outputs[*i].0.name,
                names.join(", ")
            );
            each[*i] = Some(Line::Banked {
                bank: banks.len(),
                bit: bit as u32,
            });
        }
        banks.push(bank);
    }
    let each = each
        .into_iter()
        .map(|l| l.expect("every output got a line above"))
        .collect();
    Ok(Lines { each, banks })
}

fn open_sim(cfg: &Config, model: &FrameModel, path: Option<PathBuf>) -> Result<Box<dyn Output>> {
    let path = path.unwrap_or_else(|| PathBuf::from(format!("ppm-{}.trace", cfg.name)));
    let header = [
        "ppm simulated line: <scheduled_ns> <actual_ns> <level>, CLOCK_MONOTONIC".to_string(),
        format!("name {}", cfg.name),
        format!("idle_level {}", model.idle_level().as_u8()),
        format!("channels {}", model.names().join(",")),
        format!("frame_ns {}", model.frame_ns()),
        format!("pulse_ns {}", model.pulse_ns()),
        format!("receiver {}", model.receiver().name()),
    ];
    let sim = SimOutput::create(&path, &header, cfg.ppmd.trace_max_mb << 20)
        .with_context(|| format!("creating sim trace {}", path.display()))?;
    log::info!("output `{}`: sim, trace in {}", cfg.name, path.display());
    Ok(Box::new(sim))
}

/// What the timing thread's real-time setup obtained, as the main thread needs it.
struct Obtained {
    summary: String,
    shortfalls: Vec<String>,
    priority: u8,
    cpu: Option<usize>,
    preempt_rt: bool,
}

impl From<&ppmd::rt::RtObtained> for Obtained {
    fn from(o: &ppmd::rt::RtObtained) -> Self {
        Obtained {
            summary: o.summary(),
            shortfalls: o.shortfalls.iter().map(|s| s.to_string()).collect(),
            priority: o.priority,
            cpu: o.cpu,
            preempt_rt: o.kernel.preempt_rt,
        }
    }
}

/// The main thread's view of the loop: merges intervals, logs, writes the
/// HdrHistogram log and builds snapshots.
struct Monitor {
    reader: MeterReader,
    stats: Arc<Stats>,
    total_error: hdrhistogram::Histogram<u64>,
    total_write: hdrhistogram::Histogram<u64>,
    snapshot: TimingSnapshot,
    start_ns: u64,
    next_log_ns: u64,
    state: LineState,
    mismatched: u64,
    /// HdrHistogram intervals, and frame-log rows, that could not be written.
    hdr_lost: u64,
    frame_log_lost: u64,
    /// When a failure of each log may be said again.
    next_log_failure_ns: [u64; 2],
    /// The output's `failsafe.after_ms`, for the mismatch message.
    failsafe_after_ms: u64,
    wake_errors: u64,
    /// `NAME.` before the HdrHistogram log's tags, with several outputs.
    tag_prefix: String,
    /// Writes its edge error untagged too (the first output's).
    hdr_untagged: bool,
}

impl Monitor {
    fn new(
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
            mismatched: 0,
            hdr_lost: 0,
            frame_log_lost: 0,
            next_log_failure_ns: [0; 2],
            failsafe_after_ms,
            wake_errors: 0,
            tag_prefix,
            hdr_untagged: false,
        }
    }

    /// Reads what the loop handed over; returns a snapshot when an interval ended.
    fn tick(
        &mut self,
        mut hdr: Option<&mut HdrLog>,
        frame_log: Option<&ppmd::framelog::Writer>,
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
        snap.write_errors = s.write_errors.load(Relaxed);
        snap.failsafe_entries = s.failsafe_entries.load(Relaxed);
        snap.mismatched = s.mismatched.load(Relaxed);
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
                "{}timing: {} frames; edge error p50 {:.2} us, p99 {:.2} us, max {:.1} us; {} late frames, {} overruns; spin margin {} us, spinning {:.1}% of the time",
                self.tag_prefix.replace('.', ": "),
                snap.frames,
                snap.total.p50 as f64 / 1e3,
                snap.total.p99 as f64 / 1e3,
                snap.total.max as f64 / 1e3,
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
    fn log_failure(&mut self, which: usize, what: &str, detail: &str) {
        let now = clock::now_ns();
        if now >= self.next_log_failure_ns[which] {
            self.next_log_failure_ns[which] = now + LOG_FAILURE_EVERY_NS;
            log::warn!(
                "{}{what}: cannot write ({detail}); ppmd keeps emitting and tries again",
                self.tag_prefix.replace('.', ": ")
            );
        }
    }

    fn log_changes(&mut self) {
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
        if m != self.mismatched {
            log::warn!(
                "{who}{} command(s) refused: udp-ingress made them under another channel model (channel count, order, limits, defaults or units differ from this daemon's); restart udp-ingress with ppmd's configuration. The line takes the failsafe action once the last good command is {} ms old",
                m - self.mismatched,
                self.failsafe_after_ms
            );
            self.mismatched = m;
        }
    }
}

/// Summary of a histogram (all zero when empty).
fn summarize(h: &hdrhistogram::Histogram<u64>) -> Summary {
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
/// `edge_error` and `write`. Appended to, never rotated (no cap is given);
/// each interval goes to the file whole, flushed at once.
struct HdrLog {
    file: ppmd::rotating::RotatingFile,
    serializer: hdrhistogram::serialization::V2DeflateSerializer,
    started: bool,
    /// One interval's text (the headers before the first).
    buf: Vec<u8>,
}

impl HdrLog {
    fn open(path: &std::path::Path) -> std::io::Result<HdrLog> {
        Ok(HdrLog {
            file: ppmd::rotating::RotatingFile::append("HdrHistogram log", path, u64::MAX, 1)?,
            serializer: hdrhistogram::serialization::V2DeflateSerializer::new(),
            started: false,
            buf: Vec::new(),
        })
    }

    /// Appends one interval: the edge error untagged when `untagged` (the
    /// first output's: what HdrHistogram's log processor reads without
    /// `-tag`, written even when empty so that every interval has one), and
    /// `[NAME.]edge_error` and `[NAME.]write` tagged when not empty. The
    /// first write of a run starts with the headers Java's reader expects:
    /// the format version, start and base time, and the column legend (also
    /// the header of any file a rotation would start). An interval that
    /// cannot be written is lost (the caller counts it); the headers are
    /// tried again with the next.
    fn write(&mut self, iv: &Interval, start_ns: u64, prefix: &str, untagged: bool) -> Result<()> {
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
        for (h, tag) in [(&iv.edge_error, "edge_error"), (&iv.write, "write")] {
            if !h.is_empty() {
                let tag = format!("{prefix}{tag}");
                w.write_histogram(h, from, length, Tag::new(&tag))
                    .with_context(|| format!("serializing {tag}"))?;
            }
        }
        self.file
            .write(&self.buf)
            .and_then(|()| self.file.flush())
            .context("writing to the log")?;
        self.started = true;
        Ok(())
    }
}
