//! `ppmd`: emits the newest command from udp-ingress as a PPM trainer signal.
//!
//! Two threads: the timing thread (real-time setup, then the loop in
//! `ppmd::emitter`) and this main thread, which never touches the line: it
//! reads the loop's counters and histograms, logs, publishes timing
//! snapshots and writes the HdrHistogram log.

use anyhow::{anyhow, bail, Context, Result};
use clap::Parser;
use ppm_shared::config::{fault, CpuChoice, KeyName, Plan};
use ppmd::cli::Cli;
use ppmd::lines::{describe, open_lines, Lines};
use ppmd::monitor::HdrLog;
use ppmd::readback::Opened;
use ppmd::rt::RtSetup;
use ppmd::startup::{self, Output, Watched};
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
        std::process::exit(ppm_shared::daemon::exit_status(&e, ppmd::output_fault));
    }
}

fn run(cli: Cli) -> Result<()> {
    let (Plan { shared, outputs }, inert) = cli.resolve()?;
    for key in &inert {
        log::warn!("{key}");
    }
    // What only this machine can refuse, before anything is opened: a CPU
    // it does not have (with rt.allow_degraded the loop runs unpinned).
    if let (CpuChoice::Index(cpu), false) = (shared.rt.cpu, shared.rt.allow_degraded) {
        ppm_shared::sched::check_online(cpu, &shared.keys.name("rt.cpu"))?;
    }
    let mut hdr = match &cli.hdr_log {
        Some(path) => Some(HdrLog::open(path).map_err(|e| {
            fault::path_error(
                &KeyName::Option("--hdr-log"),
                &format!("opening the HdrHistogram log {}", path.display()),
                path,
                e,
                "name a file ppmd may create and append to, in a directory that exists (under systemd: /var/log/ppm, or add a ReadWritePaths= line)",
            )
        })?),
        None => None,
    };
    let several = outputs.len() > 1;
    // Each output name is this ppmd's alone, before any line is opened.
    let _claims = outputs
        .iter()
        .map(|o| ppmd::instance::claim(&shared.ipc.root, &o.name))
        .collect::<Result<Vec<_>>>()?;
    let Lines { each, banks } = open_lines(&shared, outputs)?;

    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    let margin = startup::spin_margin(&shared.rt);
    let (outputs, timed): (Vec<Output>, Vec<_>) = each
        .into_iter()
        .map(|(o, line)| Output::open(o, line, &shared, several))
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .unzip();

    // Read-back inputs and logs open before the line moves: a fault stops
    // ppmd at start.
    let opened = outputs
        .iter()
        .filter_map(|o| {
            let plan = o.plan.readback.as_ref()?;
            Some(
                Opened::open(
                    &o.plan.name,
                    &o.tag,
                    plan,
                    &o.plan.keys,
                    shared.frame_log_max_mb << 20,
                )
                .map(|r| (r, o.stats.clone())),
            )
        })
        .collect::<Result<Vec<_>>>()?;

    // Pilots' radios, opened before the line moves too. Until their
    // threads read them, their outputs send no groundstation command.
    let pilot_inputs = outputs
        .iter()
        .filter_map(|o| {
            let (plan, slot) = (o.plan.pilot.as_ref()?, o.pilot.clone()?);
            Some(ppmd::pilot::Opened::open(&o.plan.name, &o.tag, plan).map(|p| (p, slot)))
        })
        .collect::<Result<Vec<_>>>()?;

    // The flight controller's telemetry (a CRSF serial: output), opened
    // before the line moves too.
    let ports = outputs
        .iter()
        .filter_map(|o| {
            let port = o.plan.telemetry_port()?;
            let opened = ppmd::telemetry::Opened::open(&o.plan.name, &o.tag, port);
            Some(opened.map(|t| match &o.module {
                Some(timing) => t.module(timing.clone()),
                None => t,
            }))
        })
        .collect::<Result<Vec<_>>>()?;

    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let timing = ppmd::timing::spawn(
        timed,
        banks,
        shared.ipc.root.clone(),
        RtSetup::from_config(&shared.rt),
        margin,
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
    for o in &outputs {
        log::info!("{}{}", o.tag, describe(&shared, &o.plan));
    }

    let mut readbacks = Vec::new();
    for (r, stats) in opened {
        match r.start(&shared.ipc.root, stats, obtained.cpu) {
            Ok(r) => readbacks.push(r),
            Err(e) => {
                stop.store(true, Relaxed);
                let _ = timing.join();
                return Err(e);
            }
        }
    }

    let mut pilots = Vec::new();
    for (p, slot) in pilot_inputs {
        match p.start(&shared.ipc.root, slot, obtained.cpu) {
            Ok(p) => pilots.push(p),
            Err(e) => {
                stop.store(true, Relaxed);
                let _ = timing.join();
                return Err(e);
            }
        }
    }

    let mut telemetry = Vec::new();
    for p in ports {
        match p.start(&shared.ipc.root, obtained.cpu) {
            Ok(t) => telemetry.push(t),
            Err(e) => {
                stop.store(true, Relaxed);
                let _ = timing.join();
                return Err(e);
            }
        }
    }

    let mut watched = startup::watch_all(outputs, &obtained);
    let progress = |watched: &[Watched]| -> u64 {
        watched
            .iter()
            .map(|w| w.stats.decisions.load(Relaxed))
            .sum()
    };
    let mut systemd = Systemd::start(progress(&watched), Instant::now());
    while !stop.load(Relaxed) && !timing.is_finished() {
        std::thread::sleep(MONITOR_EVERY);
        systemd.tick(progress(&watched), Instant::now());
        for w in &mut watched {
            w.tick(hdr.as_mut());
        }
    }
    systemd.stopping();
    timing
        .join()
        .map_err(|_| anyhow!("the timing thread panicked"))??;
    for r in &mut readbacks {
        r.finish();
    }
    for p in &mut pilots {
        p.finish();
    }
    for t in &mut telemetry {
        t.finish();
    }
    for w in &mut watched {
        w.finish(hdr.as_mut());
    }
    Ok(())
}
