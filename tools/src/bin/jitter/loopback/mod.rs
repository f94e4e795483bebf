//! `jitter loopback`: the self-test with a jumper wire. ppmd measures its
//! own writes; how late an edge is on the wire, nobody knows. Here the
//! output line is driven by ppmd's own timing loop with a sweep of known
//! values, and an input line wired to it is read at the same time with the
//! kernel's edge timestamps: the edge error as the line carries it, and
//! what each modelled receiver reads, against what was sent.
//!
//! - `sweep`: the values sent, and the command source the loop takes them
//!   from.
//! - `ring`: the line the loop writes, which records each written edge
//!   into a lock-free ring, so the schedule is known without touching the
//!   loop.
//! - `analysis`: read edges paired with written ones, the edge error, the
//!   receivers' and the capture decoder's frames against the sent ones.
//! - `report`: the checks, the verdict, the summary and the SVG.
//! - here: the options ([`LoopbackArgs`]), resolved once into a [`Plan`];
//!   the run: the input read on a thread of normal priority, the output
//!   driven by the loop on a real-time thread, the ring drained by the main
//!   thread; then the report.

mod analysis;
mod report;
mod ring;
mod sweep;
#[cfg(test)]
mod tests;

use anyhow::{anyhow, bail, Context, Result};
use ppm_shared::capture::{EdgeEvent, InputSpec};
use ppm_shared::config::{CpuChoice, FailsafeAction, OutputSpec, RtSection, Timing};
use ppm_shared::frame::{FrameModel, Level, PpmSection, LATE_EDGE_GUARD_US};
use ppm_shared::receiver::{ReceiverChoice, CHANNEL_MARGIN_US};
use ppm_tools::cyclic::parse_cyclictest_duration;
use ppmd::clock::{Margin, SystemClock};
use ppmd::emitter::{self, EmitterConfig, LineRef, Output, Recording, Stats};
use ppmd::input::EdgeSource;
use ppmd::line::{Line, SimLine};
use ppmd::rt::{RtSetup, RT_STACK_BYTES};
use report::{LoopCounts, Run, Thresholds};
use ring::Recorder;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};
use sweep::{Sweep, SweepSource};

/// Edges the ring between the loop and the main thread holds: 80 s of 8
/// channels at 22.5 ms; the main thread drains it every [`DRAIN_EVERY`].
const RING_EDGES: usize = 1 << 16;
/// How often the main thread drains the ring.
const DRAIN_EVERY: Duration = Duration::from_millis(20);
/// How long the input reader waits for an edge at a time.
const READ_WAIT: Duration = Duration::from_millis(50);
/// After the loop ended, the input is read until it has been quiet this
/// long: the kernel hands edges over at once, a sim trace within its
/// writer's 50 ms.
const QUIET: Duration = Duration::from_millis(500);
/// After the loop ended, the input is read this long at most (an input
/// that never goes quiet is not wired to the output alone).
const DRAIN_MAX: Duration = Duration::from_secs(3);
/// Frames a run sends at least: Betaflight hands nothing on before its
/// 27th frame, ArduPilot before its 3rd.
const MIN_FRAMES: u64 = 50;
/// The grid frame, us, unless `--frame` says (lengthened to fit the
/// channels when it was not given).
const FRAME_US: f64 = 22_500.0;
/// The default limit of the edge error's p99.9, us (see `--max-p999`).
const MAX_P999_US: f64 = 10.0;

/// `jitter loopback`'s options (its help is the `Loopback` command's).
#[derive(clap::Args, Debug, Clone, PartialEq)]
pub struct LoopbackArgs {
    /// Print help.
    #[arg(short = 'h', long, action = clap::ArgAction::Help)]
    help: Option<bool>,
    /// The line to drive: gpio:CHIP:LINE, gpio:LINE (e.g. gpio:GPIO18, pin
    /// 12 of a Pi) or sim:PATH (the simulated line's trace).
    #[arg(long, value_name = "gpio:[CHIP:]LINE|sim:PATH")]
    pub output: OutputSpec,
    /// The line wired to the output, read with kernel timestamps:
    /// gpio:CHIP:LINE, gpio:LINE (e.g. gpio:GPIO17, pin 11), or with a sim
    /// output its own sim:PATH.
    #[arg(long, value_name = "gpio:[CHIP:]LINE|sim:PATH")]
    pub input: InputSpec,
    /// How long to send the sweep: seconds, or with s, m, h (10, 30s, 5m),
    /// or ms.
    #[arg(short = 'D', long, default_value = "30s", value_parser = parse_cyclictest_duration, value_name = "TIME")]
    pub duration: Duration,
    /// Channels in a frame, 1..=14 (more do not fit a sweep of 1000..2000
    /// us in a frame EdgeTX reads; Betaflight takes 4..=12, ArduPilot 5 and
    /// more: a receiver that does not take the count is left out).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u8).range(1..=14), value_name = "N")]
    pub channels: u8,
    /// Grid frame length, us (default: 22500, or the nearest length that
    /// holds the channels).
    #[arg(long, value_name = "US")]
    pub frame: Option<f64>,
    /// How late an edge receivers time may be written, us, 1..=20, as
    /// ppm.late_edge_guard_us (later: the frame is cut short, never a
    /// wrong value).
    #[arg(long, default_value_t = LATE_EDGE_GUARD_US, value_name = "US")]
    pub late_edge_guard: f64,
    /// SCHED_FIFO priority of the timing thread (0: normal scheduler).
    #[arg(long, default_value_t = 80, value_parser = clap::value_parser!(u8).range(0..=99), value_name = "PRIO")]
    pub priority: u8,
    /// CPU to pin the timing thread to (default: the last online CPU).
    #[arg(long, value_name = "CPU")]
    pub cpu: Option<usize>,
    /// Verdict: the edge error's p99.9 at most this, us (10: the tail of a
    /// loaded real-time board that ppm's 20 us channel margin is sized for).
    #[arg(long, default_value_t = MAX_P999_US, value_name = "US")]
    pub max_p999: f64,
    /// Verdict: every value a receiver reads within this of the value sent,
    /// us (20: the margin ppm keeps inside every receiver's channel window).
    #[arg(long, default_value_t = CHANNEL_MARGIN_US, value_name = "US")]
    pub max_value_error: f64,
    /// Write the edge error's histogram to FILE as SVG.
    #[arg(long, value_name = "FILE.svg")]
    pub svg: Option<PathBuf>,
    /// Write the summary to FILE too.
    #[arg(long, value_name = "FILE")]
    pub summary: Option<PathBuf>,
}

/// The output line as the loopback drives it: edge by edge.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Drive {
    /// The simulated line, its trace at this path, read back by the input.
    Sim(PathBuf),
    /// A GPIO line.
    Gpio { chip: String, line: String },
}

impl std::fmt::Display for Drive {
    /// As given: `sim:PATH`, `gpio:LINE`, `gpio:CHIP:LINE`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Drive::Sim(path) => write!(f, "sim:{}", path.display()),
            Drive::Gpio { chip, line } if chip.is_empty() => write!(f, "gpio:{line}"),
            Drive::Gpio { chip, line } => write!(f, "gpio:{chip}:{line}"),
        }
    }
}

/// The options, resolved and checked once.
#[derive(Debug)]
struct Plan {
    drive: Drive,
    input: InputSpec,
    sweep: Sweep,
    model: FrameModel,
    /// The frame the channels did not fit in, us, when lengthened.
    lengthened_from: Option<f64>,
    frames: u64,
    setup: RtSetup,
    margin: Margin,
    thresholds: Thresholds,
    svg: Option<PathBuf>,
    summary: Option<PathBuf>,
}

impl Plan {
    fn resolve(args: &LoopbackArgs) -> Result<Plan> {
        let drive = drive_of(&args.output, &args.input)?;
        let channels = args.channels as usize;
        let (model, lengthened_from) = model_for(channels, args.frame, args.late_edge_guard)?;
        let frames = (args.duration.as_nanos() as u64).div_ceil(model.frame_ns());
        if frames < MIN_FRAMES {
            bail!(
                "--duration {:?} is {frames} frames of {} ms: give at least {:.1} s ({MIN_FRAMES} frames), so that Betaflight, which hands nothing on before its 27th frame, reads some",
                args.duration,
                model.frame_ns() as f64 / 1e6,
                (MIN_FRAMES * model.frame_ns()) as f64 / 1e9
            );
        }
        for (name, v) in [
            ("--max-p999", args.max_p999),
            ("--max-value-error", args.max_value_error),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                bail!("{name} {v}: give a number of microseconds, 0 or more");
            }
        }
        let rt_section = RtSection {
            priority: args.priority,
            cpu: args.cpu.map_or(CpuChoice::Last, CpuChoice::Index),
            allow_degraded: true,
            ..RtSection::default()
        };
        Ok(Plan {
            drive,
            input: args.input.clone(),
            sweep: Sweep::new(channels),
            lengthened_from,
            frames,
            setup: RtSetup::from_config(&rt_section),
            margin: Margin::Auto {
                min_ns: u64::from(rt_section.spin_margin_min_us) * 1_000,
                max_ns: u64::from(rt_section.spin_margin_max_us) * 1_000,
            },
            thresholds: Thresholds {
                max_p999_ns: (args.max_p999 * 1e3).round() as u64,
                max_value_error_ns: (args.max_value_error * 1e3).round() as u64,
            },
            svg: args.svg.clone(),
            summary: args.summary.clone(),
            model,
        })
    }
}

/// How the output is driven, given the input it is read back on: a GPIO
/// line read on another GPIO line, or a sim trace read back itself.
fn drive_of(output: &OutputSpec, input: &InputSpec) -> Result<Drive> {
    match (output, input) {
        (OutputSpec::Gpio { chip, line }, InputSpec::Gpio { chip: c, line: l }) => {
            if chip == c && line == l {
                bail!("--output and --input are the same line ({input}): wire the output pin to another pin and name that one as --input");
            }
            Ok(Drive::Gpio {
                chip: chip.clone(),
                line: line.clone(),
            })
        }
        (OutputSpec::Gpio { .. }, InputSpec::Sim { .. }) => bail!(
            "--input {input}: a GPIO output is read back on a GPIO input wired to it (--input gpio:[CHIP:]LINE)"
        ),
        (
            OutputSpec::Sim {
                path: Some(p),
                whole: false,
            },
            _,
        ) => match input {
            InputSpec::Sim { path } if path == p => Ok(Drive::Sim(p.clone())),
            _ => bail!(
                "--input {input}: a sim output is read back through its own trace: --input sim:{}",
                p.display()
            ),
        },
        (OutputSpec::Sim { whole: false, .. }, _) => bail!(
            "--output sim: give the trace a path, and read that trace back: --output sim:PATH --input sim:PATH"
        ),
        _ => bail!(
            "--output: loopback drives a line edge by edge through the timing loop: gpio:[CHIP:]LINE, or sim:PATH without hardware (not sim-spi, spi or serial)"
        ),
    }
}

/// The sweep's frame model: `channels` channels of 1000..=2000 us, a
/// late-edge guard of `guard_us`, on a grid of `frame_us`, or by default the nearest frame to 22500 us that
/// holds them (in 100 us steps, longer first, as timing-bench lengthens
/// its frame), for every receiver that takes that many channels.
fn model_for(
    channels: usize,
    frame_us: Option<f64>,
    guard_us: f64,
) -> Result<(FrameModel, Option<f64>)> {
    let receiver = if (5..=12).contains(&channels) {
        ReceiverChoice::Any
    } else {
        ReceiverChoice::One(ppm_shared::receiver::Receiver::EdgeTx)
    };
    let section = |frame: f64| PpmSection {
        channels: Some(channels as u32),
        frame_us: Some(frame),
        timing: Timing::Grid,
        receiver,
        late_edge_guard_us: guard_us,
        ..PpmSection::default()
    };
    let first = frame_us.unwrap_or(FRAME_US);
    let err = match FrameModel::build(&section(first)) {
        Ok(m) => return Ok((m, None)),
        Err(e) => e,
    };
    if err.key == "ppm.late_edge_guard_us" {
        bail!("--late-edge-guard {guard_us}: {err}");
    }
    if let Some(f) = frame_us {
        bail!("--frame {f}: {err}");
    }
    (1..=400)
        .flat_map(|k| [first + 100.0 * k as f64, first - 100.0 * k as f64])
        .filter(|f| *f > 0.0)
        .find_map(|f| FrameModel::build(&section(f)).ok())
        .map(|m| (m, Some(first)))
        .ok_or_else(|| {
            anyhow!("--channels {channels}: no grid frame holds {channels} channels of 1000..2000 us for EdgeTX: {err}")
        })
}

/// The frame, in words, for the summary.
fn describe_frame(model: &FrameModel, frames: u64) -> String {
    format!(
        "grid timing, {} ms frame, {} us pulse, idle {}, late-edge guard {} us, for receiver {}; {frames} frames planned",
        model.frame_ns() as f64 / 1e6,
        model.pulse_ns() as f64 / 1e3,
        match model.idle_level() {
            Level::Low => "low",
            Level::High => "high",
        },
        model.late_edge_guard_ns() as f64 / 1e3,
        model.receiver().name()
    )
}

/// Opens the output line at its idle level.
fn open_output(plan: &Plan) -> Result<Box<dyn Line>> {
    let model = &plan.model;
    match &plan.drive {
        Drive::Sim(path) => {
            let header = [
                "ppm simulated line: <scheduled_ns> <actual_ns> <level>, CLOCK_MONOTONIC"
                    .to_string(),
                "name jitter-loopback".into(),
                format!("idle_level {}", model.idle_level().as_u8()),
                format!("channels {}", model.names().join(",")),
                format!("frame_ns {}", model.frame_ns()),
                format!("pulse_ns {}", model.pulse_ns()),
                format!("receiver {}", model.receiver().name()),
                format!("protocol {}", model.protocol().name()),
            ];
            let sim = SimLine::create(path, &header, u64::MAX).with_context(|| {
                format!(
                    "output {}: creating the trace (in a directory that exists and may be written)",
                    plan.drive
                )
            })?;
            Ok(Box::new(sim))
        }
        Drive::Gpio { chip, line } => {
            let out = ppmd::line::gpio::open(chip, line, model.idle_level())
                .with_context(|| format!("output {}", plan.drive))?;
            Ok(Box::new(out))
        }
    }
}

/// What the timing thread hands back.
struct Driven {
    realtime: String,
    notes: Vec<String>,
    counts: LoopCounts,
    /// The sweep ran to its end (not stopped by a signal).
    finished: bool,
    /// The output line, released only after the input was read to its end
    /// (a released GPIO line may change level).
    recorder: Recorder,
}

/// The timing thread: the real-time setup, then ppmd's loop on `recorder`
/// until the sweep's frames are sent or `stop` is set.
fn drive(
    plan: &Plan,
    mut recorder: Recorder,
    mut source: SweepSource,
    stop: &AtomicBool,
) -> Driven {
    // Allowed to degrade: every shortfall comes back as a note.
    let obtained = plan.setup.apply().unwrap_or_else(|s| ppmd::rt::RtObtained {
        shortfalls: vec![s],
        kernel: ppmd::rt::KernelInfo::read(),
        ..Default::default()
    });
    let notes = obtained
        .shortfalls
        .iter()
        .map(|s| format!("DEGRADED: {}", s.degraded()))
        .collect();
    let stats = Stats::default();
    let (mut meter, _intervals) = ppmd::meter::meter(u64::MAX);
    {
        let mut outputs = [Output {
            model: &plan.model,
            cfg: EmitterConfig {
                failsafe_after_ns: 1_000_000_000,
                failsafe_action: FailsafeAction::Silence,
                startup: FailsafeAction::Silence,
            },
            source: &mut source,
            line: LineRef::Edges(&mut recorder),
            rec: Recording {
                stats: &stats,
                meter: &mut meter,
                log: None,
            },
            sync: None,
        }];
        emitter::run_outputs(&SystemClock, plan.margin, &mut outputs, &mut [], stop);
    }
    let n = |c: &std::sync::atomic::AtomicU64| c.load(Relaxed);
    Driven {
        realtime: obtained.summary(),
        notes,
        counts: LoopCounts {
            frames: n(&stats.frames),
            edges: n(&stats.edges),
            late_frames: n(&stats.late_frames),
            aborted_frames: n(&stats.aborted_frames),
            glitched_frames: n(&stats.glitched_frames),
            overruns: n(&stats.overruns),
            write_errors: n(&stats.write_errors),
        },
        finished: source.done(),
        recorder,
    }
}

/// The input thread (normal priority): every edge until `done` is set and
/// the input has been quiet for [`QUIET`] (or [`DRAIN_MAX`] has passed);
/// on an error, `stop` is set so the loop ends too.
fn read_input(
    mut input: Box<dyn EdgeSource>,
    done: &AtomicBool,
    stop: &AtomicBool,
) -> Result<Vec<EdgeEvent>> {
    let mut buf = [EdgeEvent {
        at_ns: 0,
        level: Level::Low,
        seq: 0,
    }; 256];
    let mut edges = Vec::new();
    let mut done_at: Option<Instant> = None;
    let mut quiet_since: Option<Instant> = None;
    loop {
        let n = match input.read(&mut buf, READ_WAIT) {
            Ok(n) => n,
            Err(e) => {
                stop.store(true, Relaxed);
                return Err(e).context("reading the input");
            }
        };
        edges.extend_from_slice(&buf[..n]);
        if n > 0 {
            quiet_since = None;
        }
        if !done.load(Relaxed) {
            continue;
        }
        let now = Instant::now();
        let quiet = now - *quiet_since.get_or_insert(now);
        if quiet >= QUIET || now - *done_at.get_or_insert(now) >= DRAIN_MAX {
            return Ok(edges);
        }
    }
}

/// Runs `jitter loopback`; true when the verdict is PASS.
pub fn run(args: &LoopbackArgs) -> Result<bool> {
    let plan = Arc::new(Plan::resolve(args)?);
    let stop = super::stop_flag()?;
    // The input first: a missing or busy input line stops the test before
    // the output is touched, and every edge the output makes is seen.
    let input = ppmd::input::open(&plan.input)?;
    let input_name = input.description().to_string();
    let line = open_output(&plan)?;
    let (producer, mut consumer) = ring::ring(RING_EDGES);
    let recorder = Recorder::new(line, producer);
    let source = SweepSource::new(&plan.sweep, &plan.model, plan.frames, stop.clone())
        .context("the sweep's channels are the model's")?;
    let done = Arc::new(AtomicBool::new(false));
    let reader = {
        let (done, stop) = (done.clone(), stop.clone());
        std::thread::Builder::new()
            .name("jitter-input".into())
            .spawn(move || read_input(input, &done, &stop))
            .context("starting the input thread")?
    };
    let timing = {
        let (plan, stop) = (plan.clone(), stop.clone());
        std::thread::Builder::new()
            .name("jitter-loopback".into())
            .stack_size(RT_STACK_BYTES)
            .spawn(move || drive(&plan, recorder, source, &stop))
            .context("starting the timing thread")?
    };
    eprintln!(
        "jitter loopback: the sweep on {} for {:.1} s ({} frames), read back on {input_name} (Ctrl-C stops early)",
        plan.drive,
        (plan.frames * plan.model.frame_ns()) as f64 / 1e9,
        plan.frames
    );
    let started = Instant::now();
    let mut written = Vec::new();
    while !timing.is_finished() {
        std::thread::sleep(DRAIN_EVERY);
        consumer.drain(&mut written);
    }
    let driven = timing
        .join()
        .map_err(|_| anyhow!("the timing thread panicked"))?;
    consumer.drain(&mut written);
    let seconds = started.elapsed().as_secs_f64();
    done.store(true, Relaxed);
    let read = reader
        .join()
        .map_err(|_| anyhow!("the input thread panicked"))??;
    drop(driven.recorder);

    let mut notes = driven.notes;
    if let Some(from) = plan.lengthened_from {
        notes.push(format!(
            "a {from:.0} us frame does not hold {} channels of 1000..2000 us: the grid frame is {:.0} us, the nearest that does",
            plan.sweep.channels(),
            plan.model.frame_ns() as f64 / 1e3
        ));
    }
    if !driven.finished {
        notes.push("stopped early by a signal: the figures are of the frames sent".into());
    }
    let run = Run {
        output: plan.drive.to_string(),
        input: input_name,
        sim: matches!(plan.drive, Drive::Sim(_)),
        seconds,
        frame: describe_frame(&plan.model, plan.frames),
        realtime: driven.realtime,
        notes,
        counts: driven.counts,
        dropped: consumer.dropped(),
    };
    let a = analysis::analyse(&written, &read, &plan.sweep, plan.model.idle_level());
    let checks = report::checks(&a, run.dropped, &plan.thresholds);
    let text = report::summary(&run, &plan.sweep, &a, &checks);
    print!("{text}");
    if let Some(path) = &plan.summary {
        std::fs::write(path, &text).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("summary: {}", path.display());
    }
    if let Some(path) = &plan.svg {
        report::svg(path, &run, &a)?;
        eprintln!("plot: {}", path.display());
    }
    Ok(checks.iter().all(|c| c.ok))
}
