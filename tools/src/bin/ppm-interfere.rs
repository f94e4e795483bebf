//! `ppm-interfere`: holds a CPU busy at a high SCHED_FIFO priority for short
//! bursts at random times, to see what ppmd makes of a timing thread that is
//! held up (see docs/signal.md).

use anyhow::{Context, Result};
use clap::Parser;
use ppm_shared::config::CpuChoice;
use ppm_shared::sched;
use ppm_tools::interfere::{parse_range, run, Plan};
use ppm_tools::parse_duration;
use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

/// Hold a CPU busy in bursts, above ppmd's priority.
///
/// Pins itself to the CPU, takes SCHED_FIFO at the priority given and, for
/// the duration, spins for a burst of random length, sleeps a random gap,
/// and so on. Needs the privileges ppmd needs (root or CAP_SYS_NICE). Mind
/// the kernel's real-time throttling: bursts of a few hundred microseconds
/// are far below it.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// The CPU to hold: ppmd's (`rt.cpu`; "last" is the highest online one).
    #[arg(long, default_value = "last", value_name = "N|last")]
    cpu: String,
    /// SCHED_FIFO priority, above ppmd's (`rt.priority`, 80 by default).
    #[arg(long, default_value_t = 90, value_parser = clap::value_parser!(u8).range(1..=99))]
    priority: u8,
    /// Length of each burst in microseconds: MIN..MAX, or one value.
    #[arg(long, default_value = "100..500", value_name = "MIN..MAX")]
    burst_us: String,
    /// Time between bursts in milliseconds: MIN..MAX, or one value.
    #[arg(long, default_value = "20..200", value_name = "MIN..MAX")]
    gap_ms: String,
    /// How long to run (e.g. 10s, 500ms).
    #[arg(long, default_value = "10s", value_parser = parse_duration, value_name = "TIME")]
    duration: Duration,
    /// Seed of the random times (the same seed gives the same bursts).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Write each burst as a line `START_NS LENGTH_NS` (CLOCK_MONOTONIC) to FILE.
    #[arg(long, value_name = "FILE")]
    log: Option<PathBuf>,
}

fn main() {
    if let Err(e) = try_main(Cli::parse()) {
        eprintln!("ppm-interfere: {e:#}");
        std::process::exit(1);
    }
}

fn try_main(cli: Cli) -> Result<()> {
    let plan = Plan {
        burst_ns: parse_range(&cli.burst_us, "us")
            .map_err(anyhow::Error::msg)
            .context("--burst-us")?,
        gap_ns: parse_range(&cli.gap_ms, "ms")
            .map_err(anyhow::Error::msg)
            .context("--gap-ms")?,
        seed: cli.seed,
    };
    let choice = match cli.cpu.as_str() {
        "last" => CpuChoice::Last,
        n => CpuChoice::Index(
            n.parse()
                .with_context(|| format!("--cpu: `{n}` is neither a CPU number nor \"last\""))?,
        ),
    };
    let cpu = sched::resolve_rt_cpu(choice).expect("a CPU was named");
    sched::pin(cpu, "--cpu")?;
    sched::set_fifo(cli.priority, "ppm-interfere")?;
    let bursts = run(&plan, cli.duration);
    let held: u64 = bursts.iter().map(|b| b.len_ns).sum();
    let longest = bursts.iter().map(|b| b.len_ns).max().unwrap_or(0);
    if let Some(path) = &cli.log {
        let mut f = std::io::BufWriter::new(
            std::fs::File::create(path)
                .with_context(|| format!("--log: cannot create {}", path.display()))?,
        );
        for b in &bursts {
            writeln!(f, "{} {}", b.start_ns, b.len_ns)?;
        }
        f.flush()
            .with_context(|| format!("--log: cannot write {}", path.display()))?;
    }
    println!(
        "ppm-interfere: {} bursts on CPU {cpu} at SCHED_FIFO {}, {:.1} ms held in all, longest {:.0} us",
        bursts.len(),
        cli.priority,
        held as f64 / 1e6,
        longest as f64 / 1e3
    );
    Ok(())
}
