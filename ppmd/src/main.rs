//! `ppmd`: emits the newest command from udp-ingress as a PPM trainer signal.

use anyhow::{bail, Context, Result};
use clap::Parser;
use ppm_shared::config::{Config, OutputSpec};
use ppmd::emitter::{self, EmitterConfig, LineState, Stats};
use ppmd::output::{Output, SimOutput};
use ppmd::source::{CommandSource, IpcSource};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

/// PPM daemon: takes the newest command from udp-ingress once per frame and
/// emits it as a PPM trainer signal.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Cli {
    /// Configuration file (TOML); every key has a default.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Output name; must match udp-ingress's. Overrides `name`.
    #[arg(long)]
    name: Option<String>,
    /// `sim` (trace in ppm-NAME.trace), `sim:PATH`, or `gpio:CHIP:LINE`.
    /// Overrides `ppmd.output`.
    #[arg(long, value_name = "SPEC")]
    output: Option<String>,
}

fn main() {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("info"))
        .format_timestamp_millis()
        .init();
    ppm_shared::ipc::init_ipc_logging();
    if let Err(e) = run(Cli::parse()) {
        log::error!("{e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let mut cfg = match &cli.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if let Some(name) = cli.name {
        cfg.name = name;
    }
    if let Some(output) = cli.output {
        cfg.ppmd.output = output;
    }
    let model = cfg.validate()?;
    let mut output: Box<dyn Output> = match cfg.output()? {
        OutputSpec::Sim { path } => {
            let path = path.unwrap_or_else(|| PathBuf::from(format!("ppm-{}.trace", cfg.name)));
            let header = [
                "ppm simulated line: <scheduled_ns> <actual_ns> <level>, CLOCK_MONOTONIC"
                    .to_string(),
                format!("name {}", cfg.name),
                format!("idle_level {}", model.idle_level().as_u8()),
                format!("channels {}", model.names().join(",")),
                format!("frame_ns {}", model.frame_ns()),
                format!("pulse_ns {}", model.pulse_ns()),
            ];
            let sim = SimOutput::create(&path, &header)
                .with_context(|| format!("creating sim trace {}", path.display()))?;
            log::info!("output sim: trace in {}", path.display());
            Box::new(sim)
        }
        OutputSpec::Gpio { chip, line } => bail!(
            "output gpio:{chip}:{line}: this build has no GPIO backend yet; use --output sim[:PATH]"
        ),
    };
    let mut source = IpcSource::open(&cfg.ipc.root, &cfg.name)?;
    log::info!(
        "{} channels ({}), frame {} us, pulse {} us, idle {:?}; commands from `{}` (ipc root {}); failsafe {:?} after {} ms",
        model.channels(),
        model.names().join(" "),
        model.frame_ns() as f64 / 1e3,
        model.pulse_ns() as f64 / 1e3,
        model.idle_level(),
        ppm_shared::ipc::command_service_name(&cfg.name),
        cfg.ipc.root.display(),
        cfg.failsafe.action,
        cfg.failsafe.after_ms,
    );

    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    output
        .park(model.idle_level())
        .context("setting the line to its idle level")?;

    let ecfg = EmitterConfig {
        spin_ns: cfg.ppmd.spin_us as u64 * 1_000,
        failsafe_after_ns: cfg.failsafe.after_ms * 1_000_000,
        failsafe_action: cfg.failsafe.action,
    };
    let stats = Arc::new(Stats::default());
    let reporter = spawn_reporter(stats.clone(), stop.clone());
    emitter::run(&model, &ecfg, &mut source, output.as_mut(), &stop, &stats);
    let _ = reporter.join();
    drop(output); // flushes and closes the sim trace
    log::info!(
        "stopped: {} frames, {} commands, {} late edges (> {} us), max edge error {:.1} us, {} skipped frames, {} write errors, {} mismatched samples, {} receive errors",
        stats.frames.load(Relaxed),
        stats.commands.load(Relaxed),
        stats.late_edges.load(Relaxed),
        emitter::LATE_EDGE_NS / 1_000,
        stats.max_edge_error_ns.load(Relaxed) as f64 / 1e3,
        stats.skipped_frames.load(Relaxed),
        stats.write_errors.load(Relaxed),
        stats.mismatched.load(Relaxed),
        source.errors(),
    );
    Ok(())
}

/// Logs state changes and anomalies of the loop, from outside it.
fn spawn_reporter(stats: Arc<Stats>, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
    std::thread::Builder::new()
        .name("ppmd-report".into())
        .spawn(move || {
            let mut state = LineState::Silent;
            let mut mismatched = 0;
            loop {
                std::thread::sleep(Duration::from_millis(100));
                if stop.load(Relaxed) {
                    break;
                }
                let now = stats.state();
                if now != state {
                    match now {
                        LineState::Active => log::info!("commands arriving: emitting frames"),
                        LineState::Silent => log::warn!("no fresh command: line silent"),
                        LineState::Failsafe => log::warn!("no fresh command: emitting failsafe frames"),
                    }
                    state = now;
                }
                let m = stats.mismatched.load(Relaxed);
                if m != mismatched {
                    log::warn!(
                        "{} command(s) ignored: their channel count differs from this daemon's configuration (udp-ingress runs with another config?)",
                        m - mismatched
                    );
                    mismatched = m;
                }
            }
        })
        .expect("spawning the report thread")
}
