//! `ppmd`: emits the newest command from udp-ingress as a PPM trainer signal.
//!
//! Two threads: the timing thread (real-time setup, then the loop in
//! `ppmd::emitter`) and this main thread, which never touches the line: it
//! reads the loop's counters and histograms, logs, publishes timing
//! snapshots and writes the HdrHistogram log.

use anyhow::{anyhow, bail, Context, Result};
use clap::Parser;
use ppm_shared::config::{Config, SpinMargin, Timing};
use ppm_shared::frame::FrameModel;
use ppm_shared::ipc;
use ppmd::clock::Margin;
use ppmd::emitter::{EmitterConfig, Stats};
use ppmd::lines::{describe, open_lines, tag};
use ppmd::meter::{self, MeterReader};
use ppmd::monitor::{HdrLog, Monitor, SNAPSHOT_EVERY_NS};
use ppmd::rt::RtSetup;
use ppmd::timing::LanePart;
use ppmd::watchdog::Systemd;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

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

fn run(cli: Cli) -> Result<()> {
    let mut cfg = Config::load_or_default(cli.config.as_deref())?;
    if let Some(name) = cli.name.as_deref() {
        // With [[outputs]], --name runs that output alone.
        cfg = cfg.select(Some(name))?;
    }
    ppmd::cli::apply_cli_outputs(&mut cfg, &cli.output)?;
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
            ipc::IpcError::new(
                format!("creating the timing snapshot publisher of `{}`", s.cfg.name),
                e,
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
        let parts: Vec<LanePart> = setups
            .iter_mut()
            .map(|s| LanePart {
                name: s.cfg.name.clone(),
                model: s.model.clone(),
                ecfg: s.ecfg,
                stats: s.stats.clone(),
                meter: s.meter.take().expect("meter"),
                log: s.log.take(),
            })
            .collect();
        ppmd::timing::spawn(parts, lines, root, setup, stop, ready_tx)
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
        log::info!(
            "{}{}",
            tag(several, &s.cfg.name),
            describe(&s.cfg, &s.model)
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
    let mut systemd = Systemd::start(progress(), Instant::now());
    while !stop.load(Relaxed) && !timing.is_finished() {
        std::thread::sleep(MONITOR_EVERY);
        systemd.tick(progress(), Instant::now());
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
    systemd.stopping();
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
        for line in monitor.final_report(s.log_writer.as_ref()) {
            log::warn!("{}{line}", tag(several, &s.cfg.name));
        }
        log::info!("{}{}", tag(several, &s.cfg.name), monitor.summary(errors));
    }
    Ok(())
}
