//! `timing-bench`: ppmd's emission loop against a plain absolute-sleep loop,
//! in the same run and on the same frame schedule.
//!
//! Both run ppmd's emission loop (`ppmd::emitter::run_outputs`) on the sim
//! backend with a constant command, on one real-time thread, in alternating
//! blocks; the differences are the spin margin (ppmd's `auto` versus 0,
//! which makes the wait a plain `clock_nanosleep(TIMER_ABSTIME)`) and the
//! baseline's lifted late-edge guard (it writes every edge however late, so
//! its lateness is measured rather than its frames aborted). A third
//! kind of block drives a second output beside the first, and a fourth runs
//! the output in follow timing, its frames started by commands that come at
//! 50 Hz and wake the loop. Prints p50, p99, p99.9 and max edge error of
//! each, the frames found late and aborted, the ratios, and the CPU share
//! each costs.

use anyhow::{Context, Result};
use clap::Parser;
use ppm_shared::config::{Config, CpuChoice, FailsafeAction, Timing};
use ppm_shared::frame::FrameModel;
use ppm_shared::ipc::CommandSample;
use ppm_shared::protocol::parse;
use ppm_tools::analysis::Percentiles;
use ppmd::clock::{self, Margin};
use ppmd::emitter::{self, EmitterConfig, LineRef, Output, Recording, Stats};
use ppmd::line::SimLine;
use ppmd::rt::{RtSetup, RT_STACK_BYTES};
use ppmd::source::{CommandSource, RepeatSource, TickSource};
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;

/// Timing benchmark: ppmd's sleep-then-spin loop against a plain absolute sleep.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// Total run time in seconds, split block by block among the four loops
    /// (ppmd's, the plain sleep, two outputs, follow timing); at least one
    /// block each.
    #[arg(long, default_value_t = 20)]
    seconds: u64,
    /// Length of one block in seconds; the four loops take turns block by
    /// block.
    #[arg(long, default_value_t = 2)]
    block: u64,
    /// SCHED_FIFO priority of the timing thread (0: normal scheduler).
    #[arg(long, default_value_t = 80)]
    priority: u8,
    /// CPU to pin the timing thread to (default: the last online CPU).
    #[arg(long)]
    cpu: Option<usize>,
    /// ppm configuration for the frame (default: 8 channels, 22.5 ms).
    #[arg(long)]
    config: Option<std::path::PathBuf>,
}

/// Command rate of the follow-timing blocks, Hz (a groundstation's).
const FOLLOW_HZ: f64 = 50.0;

/// Results of one loop over all its blocks.
struct Totals {
    error: hdrhistogram::Histogram<u64>,
    cpu_ns: u64,
    wall_ns: u64,
    spin_ns: u64,
    late_frames: u64,
    aborted_frames: u64,
    overruns: u64,
    /// Edges the loop counted as written (each one's error is in `error`).
    edges: u64,
}

impl Totals {
    fn new() -> Totals {
        Totals {
            error: ppmd::meter::histogram(),
            cpu_ns: 0,
            wall_ns: 0,
            spin_ns: 0,
            late_frames: 0,
            aborted_frames: 0,
            overruns: 0,
            edges: 0,
        }
    }

    fn percentiles(&self) -> Percentiles {
        Percentiles::of_histogram(&self.error)
    }

    fn cpu_share(&self) -> f64 {
        self.cpu_ns as f64 / self.wall_ns.max(1) as f64
    }
}

fn thread_cpu_ns() -> u64 {
    let t = nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID)
        .expect("thread CPU clock");
    t.tv_sec() as u64 * 1_000_000_000 + t.tv_nsec() as u64
}

/// One block: the loop drives one output per `(model, sample)` (the same
/// command, freshly stamped, every frame) until the first has emitted
/// `frames` frames. Every output's edge errors are counted.
fn run_block(
    outputs: &[(&FrameModel, CommandSample)],
    margin: Margin,
    frames: u64,
    totals: &mut Totals,
) -> Result<()> {
    let stop = Arc::new(AtomicBool::new(false));
    let mut sources: Vec<Box<dyn CommandSource>> = Vec::new();
    for (i, (model, sample)) in outputs.iter().enumerate() {
        // The first output's count ends the block.
        let frames = if i == 0 { frames } else { u64::MAX };
        sources.push(match model.timing() {
            Timing::Grid => Box::new(RepeatSource {
                sample: *sample,
                frames,
                stop: stop.clone(),
            }),
            // Commands at FOLLOW_HZ, each waking the loop, as from udp-ingress.
            Timing::Follow => {
                Box::new(TickSource::start(*sample, FOLLOW_HZ, frames, stop.clone())?)
            }
        });
    }
    let mut outs = outputs
        .iter()
        .map(|_| SimLine::create(std::path::Path::new("/dev/null"), &[], u64::MAX))
        .collect::<std::io::Result<Vec<_>>>()?;
    let cfg = EmitterConfig {
        failsafe_after_ns: 1_000_000_000,
        failsafe_action: FailsafeAction::Silence,
        startup: FailsafeAction::Silence,
    };
    let stats: Vec<Stats> = outputs.iter().map(|_| Stats::default()).collect();
    let mut meters: Vec<_> = outputs
        .iter()
        .map(|_| ppmd::meter::meter(u64::MAX))
        .collect();
    let (cpu0, wall0) = (thread_cpu_ns(), clock::now_ns());
    {
        let mut driven: Vec<Output> = outputs
            .iter()
            .zip(sources.iter_mut())
            .zip(outs.iter_mut())
            .zip(stats.iter().zip(meters.iter_mut()))
            .map(
                |((((model, _), source), out), (stats, (meter, _)))| Output {
                    model,
                    cfg,
                    source: source.as_mut(),
                    line: LineRef::Edges(out),
                    rec: Recording {
                        stats,
                        meter,
                        log: None,
                    },
                    sync: None,
                },
            )
            .collect();
        emitter::run_outputs(
            &ppmd::clock::SystemClock,
            margin,
            &mut driven,
            &mut [],
            &stop,
        );
    }
    totals.cpu_ns += thread_cpu_ns() - cpu0;
    totals.wall_ns += clock::now_ns() - wall0;
    for (s, (m, reader)) in stats.iter().zip(&mut meters) {
        totals.spin_ns += s.spin_ns.load(Relaxed);
        totals.late_frames += s.late_frames.load(Relaxed);
        totals.aborted_frames += s.aborted_frames.load(Relaxed);
        totals.overruns += s.overruns.load(Relaxed);
        totals.edges += s.edges.load(Relaxed);
        // The loop hands its interval over when it ends: what it measured
        // is in the reader's intervals (and whatever the meter still holds).
        let mut merged = Ok(());
        reader.drain(|iv| {
            if merged.is_ok() {
                merged = totals.error.add(&iv.edge_error);
            }
        });
        merged.context("merging histograms")?;
        totals
            .error
            .add(&m.current().edge_error)
            .context("merging histograms")?;
    }
    Ok(())
}

/// `cfg` on a grid. A frame length that only follow timing takes (follow
/// does not use `ppm.frame_us`) is lengthened, in 100 us steps up to 60 ms,
/// to the shortest the grid takes; the length it had comes back with it.
fn grid_config(cfg: &Config) -> Result<(Config, Option<f64>)> {
    let mut grid = cfg.clone();
    grid.ppm.timing = Timing::Grid;
    let err = match grid.validate() {
        Ok(_) => return Ok((grid, None)),
        Err(e) => e,
    };
    if cfg.ppm.timing != Timing::Follow || cfg.validate().is_err() {
        return Err(err.into());
    }
    let from = grid.ppm.frame_us();
    for k in 1..=600 {
        let mut longer = grid.clone();
        longer.ppm.frame_us = Some(from + 100.0 * k as f64);
        if longer.validate().is_ok() {
            return Ok((longer, Some(from)));
        }
    }
    Err(err.into())
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let loaded = Config::load_or_default(cli.config.as_deref())?;
    // The baseline and the two-output blocks run on a grid, whatever the
    // configuration's timing; the follow block is measured beside them.
    let (cfg, lengthened) = grid_config(&loaded)?;
    let model = cfg.validate()?;
    if let Some(from) = lengthened {
        println!(
            "ppm.frame_us {from:.0} us is too short a grid frame for these channels (follow timing does not use it): the grid blocks use {:.0} us, the shortest that is",
            model.frame_ns() as f64 / 1e3
        );
    }
    let mut rt = cfg.rt.clone();
    rt.priority = cli.priority;
    rt.cpu = cli.cpu.map_or(CpuChoice::Last, CpuChoice::Index);
    rt.allow_degraded = true;
    let setup = RtSetup::from_config(&rt);
    let auto = Margin::Auto {
        min_ns: rt.spin_margin_min_us as u64 * 1_000,
        max_ns: rt.spin_margin_max_us as u64 * 1_000,
    };
    let block_frames = cli.block * 1_000_000_000 / model.frame_ns();
    let blocks = (cli.seconds / cli.block.max(1)).max(4);
    let mut follow_cfg = cfg.clone();
    follow_cfg.ppm.timing = Timing::Follow;
    let follow = follow_cfg.validate()?;
    let follow_commands = cli.block * FOLLOW_HZ as u64;
    let cmd = parse(b"[1000, 1200, 1700, 2000]", &model).context("bench command")?;
    let sample = CommandSample::new(&cmd, model.fingerprint(), 1, 0, 0);
    let mut other_cfg = cfg.clone();
    other_cfg.ppm.channels = Some(6);
    other_cfg.ppm.frame_us = Some(20_000.0);
    let other = other_cfg.validate()?;
    let other_cmd =
        parse(b"[1900, 1111, 1333, 1555, 1777, 1050]", &other).context("bench command")?;
    let other_sample = CommandSample::new(&other_cmd, other.fingerprint(), 1, 0, 0);
    let m2 = model.clone();
    // The baseline writes every edge however late, as a plain loop would:
    // with the guard, its late frames would be aborted and not measured.
    let plain = model.unguarded();
    let other2 = other.clone();
    let worker = std::thread::Builder::new()
        .name("timing-bench".into())
        .stack_size(RT_STACK_BYTES)
        .spawn(move || -> Result<(String, [Totals; 4])> {
            let obtained = setup.apply()?;
            let mut summary = obtained.summary();
            for s in &obtained.shortfalls {
                summary += &format!("\nDEGRADED: {}", s.degraded());
            }
            let [mut spin, mut sleep, mut two, mut fol] =
                [Totals::new(), Totals::new(), Totals::new(), Totals::new()];
            for b in 0..blocks {
                let one = [(&m2, sample)];
                let both = [(&m2, sample), (&other2, other_sample)];
                match b % 4 {
                    0 => run_block(&one, auto, block_frames, &mut spin)?,
                    1 => run_block(
                        &[(&plain, sample)],
                        Margin::Fixed(0),
                        block_frames,
                        &mut sleep,
                    )?,
                    2 => run_block(&both, auto, block_frames, &mut two)?,
                    _ => run_block(&[(&follow, sample)], auto, follow_commands, &mut fol)?,
                }
            }
            Ok((summary, [spin, sleep, two, fol]))
        })?;
    println!(
        "ppm timing benchmark: ppmd's emission loop on the sim backend, {} channels, {:.1} ms frames, {} edges a frame",
        model.channels(),
        model.frame_ns() as f64 / 1e6,
        2 * (model.channels() + 1)
    );
    println!(
        "{} s in {blocks} alternating blocks of {} s, same frame for every loop; \"two outputs\" adds a second line of {} channels at {:.1} ms from the same thread (both lines counted); \"follow timing\" starts each frame when a command comes, {FOLLOW_HZ} a second, each waking the loop",
        blocks * cli.block,
        cli.block,
        other.channels(),
        other.frame_ns() as f64 / 1e6
    );
    let (summary, [spin, sleep, two, fol]) = worker
        .join()
        .map_err(|_| anyhow::anyhow!("benchmark thread panicked"))??;
    println!("real-time: {summary}");
    println!();
    println!(
        "{:<30} {:>8} {:>9} {:>9} {:>9} {:>10} {:>10} {:>6} {:>8} {:>8}",
        "loop",
        "edges",
        "p50 us",
        "p99 us",
        "p99.9 us",
        "max us",
        "CPU share",
        "late",
        "aborted",
        "overrun"
    );
    for (name, t) in [
        ("ppmd (sleep, then spin)", &spin),
        ("ppmd, follow timing", &fol),
        ("ppmd, two outputs", &two),
        ("baseline (absolute sleep)", &sleep),
    ] {
        let p = t.percentiles();
        println!(
            "{name:<30} {:>8} {:>9.3} {:>9.3} {:>9.3} {:>10.3} {:>9.1}% {:>6} {:>8} {:>8}",
            p.count,
            p.p50 / 1e3,
            p.p99 / 1e3,
            p.p999 / 1e3,
            p.max / 1e3,
            t.cpu_share() * 100.0,
            t.late_frames,
            t.aborted_frames,
            t.overruns
        );
    }
    let (a, b, c, f) = (
        spin.percentiles(),
        sleep.percentiles(),
        two.percentiles(),
        fol.percentiles(),
    );
    println!();
    println!(
        "p99 edge error: baseline / ppmd = {:.0}x (p50 {:.0}x, p99.9 {:.0}x)",
        b.p99 / a.p99.max(1.0),
        b.p50 / a.p50.max(1.0),
        b.p999 / a.p999.max(1.0)
    );
    println!(
        "two outputs / one output: p50 {:.2}x, p99 {:.2}x, p99.9 {:.2}x",
        c.p50 / a.p50.max(1.0),
        c.p99 / a.p99.max(1.0),
        c.p999 / a.p999.max(1.0)
    );
    println!(
        "follow timing / grid timing: p50 {:.2}x, p99 {:.2}x, p99.9 {:.2}x",
        f.p50 / a.p50.max(1.0),
        f.p99 / a.p99.max(1.0),
        f.p999 / a.p999.max(1.0)
    );
    println!(
        "spinning costs {:.1}% of the pinned core: ppmd's loop uses {:.1}% CPU, the baseline {:.1}%; time spent spinning {:.1}% of wall time",
        (spin.cpu_share() - sleep.cpu_share()) * 100.0,
        spin.cpu_share() * 100.0,
        sleep.cpu_share() * 100.0,
        spin.spin_ns as f64 * 100.0 / spin.wall_ns.max(1) as f64
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_only_follow_takes_is_lengthened_for_the_grid_blocks() {
        // The default 22.5 ms frame is too short for 12 channels on a grid;
        // follow timing does not use it.
        let cfg = Config::parse("[ppm]\nchannels = 12\ntiming = 'follow'").unwrap();
        assert!(cfg.validate().is_ok());
        let (grid, from) = grid_config(&cfg).unwrap();
        assert_eq!(from, Some(22_500.0));
        assert_eq!(grid.ppm.timing, Timing::Grid);
        let f = grid.ppm.frame_us();
        assert!(grid.validate().is_ok());
        // The shortest in 100 us steps: 100 us less is refused.
        let mut shorter = grid.clone();
        shorter.ppm.frame_us = Some(f - 100.0);
        let e = shorter.validate().unwrap_err();
        assert_eq!(e.key(), Some("ppm.frame_us"), "{e}");
        // A grid frame that validates is kept as it is.
        let (same, none) = grid_config(&Config::default()).unwrap();
        assert_eq!((same.ppm.frame_us(), none), (22_500.0, None));
        // A grid configuration's error stays the error.
        let bad = Config::parse("[ppm]\nchannels = 12\ntiming = 'grid'").unwrap();
        let e = grid_config(&bad).unwrap_err().to_string();
        assert!(e.contains("ppm.frame_us"), "{e}");
    }

    #[test]
    fn a_block_measures_every_edge_the_loop_wrote() {
        // The plain loop writes every edge however late: 5 frames of 18
        // edges, and the lead-in pulse's 2, at least (more lead-ins if the
        // loop skipped frames).
        let (cfg, _) = grid_config(&Config::default()).unwrap();
        let model = cfg.validate().unwrap().unguarded();
        let cmd = parse(b"[1000, 1200, 1700, 2000]", &model).unwrap();
        let sample = CommandSample::new(&cmd, model.fingerprint(), 1, 0, 0);
        let mut totals = Totals::new();
        run_block(&[(&model, sample)], Margin::Fixed(50_000), 5, &mut totals).unwrap();
        assert!(totals.edges >= 5 * 18 + 2, "{} edges", totals.edges);
        assert_eq!(
            totals.error.len(),
            totals.edges,
            "every edge's error measured"
        );
    }
}
