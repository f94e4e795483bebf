//! `ppm-capture`: reads PPM from an input line (a pilot's radio in trainer
//! "slave" mode, a radio's module bay, a CPPM receiver output) through the
//! GPIO character device's kernel-timestamped edge events, or from a trace
//! in the simulated line's format, and records every whole frame in the
//! read-back log format (one JSON line per frame, CLOCK_MONOTONIC and wall
//! time, the same clock as ppmd's frame log), printing the newest frame as
//! it goes. The same decoder as ppmd's read-back; no output needed.

use anyhow::{bail, Context, Result};
use clap::Parser;
use ppm_shared::capture::{Capture, CaptureSettings, EdgeEvent, InputSpec};
use ppm_shared::signal::Level;
use ppm_tools::parse_duration;
use ppmd::readback::{real_of, Row};
use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Read PPM from an input line and record every frame.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// The input: gpio:CHIP:LINE, gpio:LINE (e.g. gpio:GPIO17) or sim:PATH
    /// (a trace in the simulated line's format, followed while it grows).
    #[arg(long, value_name = "INPUT")]
    input: String,
    /// Append one JSON line per frame read to this file (the read-back
    /// log's format).
    #[arg(long, value_name = "FILE")]
    log: Option<PathBuf>,
    /// The input's idle level, low or high (default: found from the signal).
    #[arg(long, value_name = "LEVEL", value_parser = ["low", "high"])]
    idle_level: Option<String>,
    /// Channels in a frame, 1..=16 (default: found from the signal).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u8).range(1..=16))]
    channels: Option<u8>,
    /// Stop after this long (default: at Ctrl-C).
    #[arg(long, value_parser = parse_duration)]
    duration: Option<Duration>,
    /// Print at most one frame per this interval (0: every frame).
    #[arg(long, default_value = "200ms", value_parser = parse_duration)]
    every: Duration,
    /// Print nothing but the summary at the end.
    #[arg(long)]
    quiet: bool,
}

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("ppm-capture: {e:#}");
        std::process::exit(ppm_shared::daemon::exit_status(&e, ppmd::output_fault));
    }
}

fn settings(cli: &Cli) -> Result<CaptureSettings> {
    let idle = match cli.idle_level.as_deref() {
        None => None,
        Some("low") => Some(Level::Low),
        Some("high") => Some(Level::High),
        // clap takes only low and high.
        Some(other) => bail!("--idle-level {other}: use low or high"),
    };
    Ok(CaptureSettings {
        idle,
        channels: cli.channels,
    })
}

fn run(cli: Cli) -> Result<()> {
    let spec: InputSpec = cli
        .input
        .parse()
        .map_err(|m: String| anyhow::anyhow!("--input {m}"))?;
    let mut settings = settings(&cli)?;
    let mut source = ppmd::input::open(&spec)?;
    if settings.idle.is_none() {
        settings.idle = source.idle_level();
    }
    let mut log = match &cli.log {
        Some(path) => Some(std::io::BufWriter::new(
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .with_context(|| format!("--log: opening {}", path.display()))?,
        )),
        None => None,
    };
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    eprintln!("ppm-capture: reading {}", source.description());
    let mut capture = Capture::new(settings);
    let mut buf = [EdgeEvent {
        at_ns: 0,
        level: Level::Low,
        seq: 0,
    }; 256];
    let started = Instant::now();
    let mut printed: Option<Instant> = None;
    let mut flushed = Instant::now();
    let mut out = std::io::stdout().lock();
    while !stop.load(Relaxed) && cli.duration.is_none_or(|d| started.elapsed() < d) {
        let n = match source.read(&mut buf, Duration::from_millis(50)) {
            Ok(n) => n,
            Err(e) => {
                // As ppmd's read-back: said, and reading goes on (a bad
                // line of a trace, a GPIO read that failed once).
                eprintln!("ppm-capture: {e}");
                std::thread::sleep(Duration::from_millis(100));
                0
            }
        };
        for e in &buf[..n] {
            let Some(f) = capture.push(*e) else { continue };
            let row = Row::Read {
                frame: capture.counts().frames,
                read: f,
                start_real_ns: real_of(f.start_ns),
                matched: None,
                max_diff_ns: 0,
                state: None,
            };
            if let Some(l) = log.as_mut() {
                writeln!(l, "{}", row.to_json()).context("writing the log")?;
            }
            if !cli.quiet && printed.is_none_or(|p| p.elapsed() >= cli.every) {
                printed = Some(Instant::now());
                let ch: Vec<String> = f
                    .values()
                    .iter()
                    .map(|&ns| format!("{:.1}", ns as f64 / 1e3))
                    .collect();
                let _ = writeln!(out, "{} [{}]", f.start_ns, ch.join(", "));
            }
        }
        if flushed.elapsed() >= Duration::from_millis(100) {
            if let Some(l) = log.as_mut() {
                l.flush().context("writing the log")?;
            }
            flushed = Instant::now();
        }
    }
    if let Some(l) = log.as_mut() {
        l.flush().context("writing the log")?;
    }
    let c = capture.counts();
    let refused: Vec<String> = c
        .reasons()
        .iter()
        .filter(|(_, n)| *n > 0)
        .map(|(r, n)| format!("{r} {n}"))
        .collect();
    eprintln!(
        "ppm-capture: {} edges, {} frames, idle level {}, {} channels; refused: {}",
        c.edges,
        c.frames,
        capture
            .idle_level()
            .map_or("not found", |l| if l == Level::High {
                "high"
            } else {
                "low"
            }),
        capture
            .channels()
            .map_or("no count found".to_string(), |n| n.to_string()),
        if refused.is_empty() {
            "none".to_string()
        } else {
            refused.join(", ")
        }
    );
    Ok(())
}
