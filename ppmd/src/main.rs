//! `ppmd`: emits the newest command from udp-ingress as a PPM trainer signal.
//!
//! Two threads: the timing thread (real-time setup, then the loop in
//! `ppmd::emitter`) and this main thread, which never touches the line: it
//! reads the loop's counters and histograms, logs, publishes timing
//! snapshots and writes the HdrHistogram log.

use anyhow::{anyhow, bail, Context, Result};
use clap::Parser;
use ppm_shared::logging::Chain;
use ppmd::cli::Cli;
use ppmd::lines::{describe, open_lines};
use ppmd::monitor::{HdrLog, SnapshotPublisher};
use ppmd::rt::RtSetup;
use ppmd::startup::{self, Output};
use ppmd::watchdog::Systemd;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How often the main thread reads the loop's measurements.
const MONITOR_EVERY: Duration = Duration::from_millis(100);

fn main() {
    let cli = Cli::parse();
    cli.daemon.init_logging();
    if let Err(e) = run(cli) {
        log::error!("{e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let outputs = cli.config()?.validate_outputs()?;
    let several = outputs.len() > 1;
    // Shared settings (rt, ipc) are the same in every output.
    let shared = outputs[0].0.clone();
    let lines = open_lines(&outputs)?;

    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    let margin = startup::spin_margin(&shared.rt);
    let mut setups = outputs
        .into_iter()
        .map(|(c, model)| Output::open(c, model, margin, several))
        .collect::<Result<Vec<_>>>()?;
    let publishers = setups
        .iter()
        .map(|s| SnapshotPublisher::open(&shared.ipc.root, &s.cfg.name))
        .collect::<Result<Vec<_>, _>>()?;

    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let timing = ppmd::timing::spawn(
        setups.iter_mut().map(Output::lane).collect(),
        lines,
        shared.ipc.root.clone(),
        RtSetup::from_config(&shared.rt),
        stop.clone(),
        ready_tx,
    )
    .context("spawning the timing thread")?;
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
        log::info!("{}{}", s.tag, describe(&s.cfg, &s.model));
    }

    let mut hdr = match &cli.hdr_log {
        Some(path) => Some(
            HdrLog::open(path)
                .with_context(|| format!("opening the HdrHistogram log {}", path.display()))?,
        ),
        None => None,
    };
    let mut monitors = startup::monitors(&mut setups, &obtained);
    let progress = || -> u64 { setups.iter().map(|s| s.stats.decisions.load(Relaxed)).sum() };
    let mut systemd = Systemd::start(progress(), Instant::now());
    while !stop.load(Relaxed) && !timing.is_finished() {
        std::thread::sleep(MONITOR_EVERY);
        systemd.tick(progress(), Instant::now());
        for ((monitor, publisher), s) in monitors.iter_mut().zip(&publishers).zip(&setups) {
            if let Some(snapshot) = monitor.tick(hdr.as_mut(), s.log_writer.as_ref()) {
                if let Err(e) = publisher.publish(snapshot) {
                    log::debug!("publishing timing snapshot: {}", Chain(&e));
                }
            }
        }
    }
    systemd.stopping();
    let receive_errors = timing
        .join()
        .map_err(|_| anyhow!("the timing thread panicked"))??;
    for ((s, monitor), errors) in setups.iter_mut().zip(&mut monitors).zip(receive_errors) {
        s.finish(monitor, hdr.as_mut(), errors);
    }
    Ok(())
}
