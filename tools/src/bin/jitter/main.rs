//! `jitter`: the timing instrument of ppm.
//!
//! - With no target: a cyclictest-style latency test of this machine, using
//!   the very sleep-then-spin timer ppmd uses, in cyclictest's formats.
//! - `--attach NAME`: a running ppmd's edge error, live, in the same format.
//! - `--trace FILE`: edge error and channel-period error of a sim trace.
//! - `--capture CHIP:LINE`: kernel-timestamped edges of an input line wired to
//!   the output pin, decoded as a transmitter does.
//! - `loopback`: the self-test with a jumper wire: ppmd's own loop drives
//!   an output line with a sweep while an input line wired to it is read
//!   with kernel timestamps (`loopback/`).
//!
//! The flags choose one [`Mode`]; the cyclictest-style test (plan, run,
//! report) is in `cyclictest.rs`.

use anyhow::{bail, Context, Result};
use clap::{ArgAction, Parser};
use ppm_shared::config::Config;
use ppm_shared::decode::{Decoder, DecoderLimits};
use ppm_shared::frame::Level;
use ppm_shared::ipc::{self, TimingSnapshot, HIST_BUCKETS};
use ppm_shared::receiver::{Receiver, ReceiverChoice, ReceiverDecoder, TIMED_EDGE};
use ppm_shared::trace::Trace;
use ppm_shared::wire::reader::{LineReader, Reading};
use ppm_tools::analysis::{analyse_trace, Percentiles};
use ppm_tools::cyclic::{parse_cyclictest_duration, LatencyStats};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

mod cyclictest;
mod loopback;

/// Timing measurements for ppm: cyclictest-style tests of this machine with
/// ppmd's own timer, a running ppmd's edge error, sim traces, captured edges,
/// and the self-test with a jumper wire (`jitter loopback`).
#[derive(Parser, Debug)]
#[command(
    name = "jitter",
    version,
    disable_help_flag = true,
    disable_help_subcommand = true,
    args_conflicts_with_subcommands = true
)]
struct Cli {
    /// Print help.
    #[arg(long, action = ArgAction::Help)]
    help: Option<bool>,
    /// A command instead of the flags' measurement.
    #[command(subcommand)]
    command: Option<Command>,
    /// SCHED_FIFO priority of the measuring thread (0: normal scheduler).
    #[arg(
        short = 'p',
        long = "priority",
        default_value_t = 0,
        value_name = "PRIO"
    )]
    priority: u8,
    /// Interval between wake-ups, microseconds.
    #[arg(
        short = 'i',
        long = "interval",
        default_value_t = 1000,
        value_name = "US"
    )]
    interval_us: u64,
    /// Number of loops (0: until Ctrl-C or --duration). With --attach: snapshots.
    #[arg(short = 'l', long = "loops", default_value_t = 0, value_name = "LOOPS")]
    loops: u64,
    /// Pin the measuring threads: to the CPUs of CPUSET in round-robin
    /// order (`2`, `0-3`, `3-5,0`), or without CPUSET thread N to CPU N.
    #[arg(short = 'a', long = "affinity", value_name = "CPUSET", num_args = 0..=1, default_missing_value = "")]
    affinity: Option<String>,
    /// Number of measuring threads; without NUM, one per online CPU.
    #[arg(short = 't', long = "threads", value_name = "NUM", num_args = 0..=1, default_missing_value = "0")]
    threads: Option<usize>,
    /// Standard SMP testing: one thread per CPU, each pinned to its CPU
    /// (cyclictest's -a -t).
    #[arg(short = 'S', long = "smp")]
    smp: bool,
    /// Interval added for each further thread, microseconds (not with -h/-H:
    /// then every thread has the same interval, as in cyclictest).
    #[arg(
        short = 'd',
        long = "distance",
        default_value_t = 500,
        value_name = "US"
    )]
    distance_us: u64,
    /// Stop when a latency exceeds US (as cyclictest's break trace, without
    /// the kernel tracing): prints the thread ids, the thread and the value.
    #[arg(short = 'b', long = "breaktrace", value_name = "US")]
    breaktrace: Option<u64>,
    /// Accepted for cyclictest's command lines: jitter always sleeps with
    /// clock_nanosleep.
    #[arg(short = 'n', long = "nanosleep")]
    nanosleep: bool,
    /// Accepted for cyclictest's command lines: every line is flushed as
    /// it is printed.
    #[arg(short = 'u', long = "unbuffered")]
    unbuffered: bool,
    /// cyclictest's sys_nanosleep and sys_setitimer: not applicable,
    /// ignored (jitter always sleeps with clock_nanosleep).
    #[arg(short = 's', long = "system")]
    system: bool,
    /// Print only the summary at the end.
    #[arg(short = 'q', long = "quiet")]
    quiet: bool,
    /// Print a histogram of latencies up to US (one bucket per unit) at the end.
    #[arg(
        short = 'h',
        long = "histogram",
        value_name = "US",
        conflicts_with = "histofall"
    )]
    histogram: Option<usize>,
    /// As -h, with a column summing every thread.
    #[arg(short = 'H', long = "histofall", value_name = "US")]
    histofall: Option<usize>,
    /// Write cyclictest's JSON summary to FILE.
    #[arg(long = "json", value_name = "FILE")]
    json: Option<PathBuf>,
    /// Lock memory (mlockall) and prefault the stack.
    #[arg(short = 'm', long = "mlockall")]
    mlock: bool,
    /// Latencies in nanoseconds instead of microseconds.
    #[arg(short = 'N', long = "nsecs")]
    nsecs: bool,
    /// Stop after this long: seconds, or with s, m (minutes), h, d as in
    /// cyclictest (10, 30s, 5m, 1h), or ms.
    #[arg(short = 'D', long = "duration", value_parser = parse_cyclictest_duration, value_name = "TIME")]
    duration: Option<Duration>,
    /// Spin margin before each wake-up: `auto` (ppmd's default), microseconds,
    /// or 0 for a plain absolute sleep (what cyclictest measures).
    #[arg(long, default_value = "auto", value_name = "auto|US")]
    spin: String,
    /// Show a running ppmd's edge error, live (NAME is its output name).
    #[arg(long, value_name = "NAME", conflicts_with_all = ["trace", "capture"])]
    attach: Option<String>,
    /// Analyse a sim trace written by ppmd (--output sim:FILE).
    #[arg(long, value_name = "FILE", conflicts_with = "capture")]
    trace: Option<PathBuf>,
    /// Capture edges of an input GPIO line wired to ppmd's output and decode them.
    #[arg(long, value_name = "CHIP:LINE")]
    capture: Option<String>,
    /// With --capture: the channel values ppmd is sending, microseconds
    /// (e.g. 1000,1200,1700,2000,1500,1500,1500,1500); the channel-period
    /// error is measured against them (default: against each channel's median).
    #[arg(long, value_name = "US,US,...", value_delimiter = ',')]
    expect: Vec<f64>,
    /// ppm configuration (for --attach: the shared-memory root; for
    /// --capture: the idle level and the receiver).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Write an SVG histogram with its percentiles marked to FILE: of the
    /// wake-up latency (all threads), of --attach's edge error, of
    /// --trace's edge error, or of --capture's channel-period error.
    #[arg(long, value_name = "FILE.svg")]
    plot: Option<PathBuf>,
    /// With --trace or --capture: count the frames this receiver hands on,
    /// decoding as its firmware does: edgetx, opentx, betaflight or
    /// ardupilot (default: the one the trace or --config names, edgetx for
    /// `any`).
    #[arg(long, value_name = "RECEIVER")]
    receiver: Option<Receiver>,
}

/// jitter's commands (without one, the flags choose the measurement).
#[derive(clap::Subcommand, Debug, Clone, PartialEq)]
enum Command {
    /// Self-test with a jumper wire: the edge error as the line carries it,
    /// and what receivers read of it.
    ///
    /// ppmd's own timing loop drives --output with a sweep of known values
    /// while --input, wired to it, is read with the kernel's edge
    /// timestamps; prints the edge error, what EdgeTX, Betaflight and
    /// ArduPilot read against what was sent, and a verdict (exit status 2
    /// on FAIL). Without hardware: --output sim:PATH --input sim:PATH.
    Loopback(loopback::LoopbackArgs),
}

/// What jitter measures, chosen once from the flags.
#[derive(Debug, Clone, PartialEq)]
enum Mode {
    /// No target: the cyclictest-style test of this machine.
    Cyclic,
    /// `--attach NAME`: a running ppmd's edge error, live.
    Attach(String),
    /// `--trace FILE`: a sim trace's edge and channel-period error.
    Trace(PathBuf),
    /// `--capture CHIP:LINE`: edges captured from an input line.
    Capture(String),
    /// `loopback`: the self-test with a jumper wire.
    Loopback(loopback::LoopbackArgs),
}

impl Mode {
    /// The mode the flags ask for (clap refuses two targets at once).
    fn of(cli: &Cli) -> Mode {
        if let Some(Command::Loopback(args)) = &cli.command {
            return Mode::Loopback(args.clone());
        }
        match (&cli.attach, &cli.trace, &cli.capture) {
            (Some(name), _, _) => Mode::Attach(name.clone()),
            (None, Some(path), _) => Mode::Trace(path.clone()),
            (None, None, Some(spec)) => Mode::Capture(spec.clone()),
            (None, None, None) => Mode::Cyclic,
        }
    }
}

fn main() {
    let cli = Cli::parse();
    let r = match Mode::of(&cli) {
        Mode::Attach(name) => attach(&cli, &name),
        Mode::Trace(path) => trace(&path, cli.receiver, cli.plot.as_deref()),
        Mode::Capture(spec) => capture(&cli, &spec),
        Mode::Cyclic => cyclictest::cyclic(&cli),
        Mode::Loopback(args) => match loopback::run(&args) {
            Ok(false) => std::process::exit(2),
            other => other.map(drop),
        },
    };
    if let Err(e) = r {
        eprintln!("jitter: {e:#}");
        std::process::exit(1);
    }
}

fn stop_flag() -> Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    Ok(stop)
}

/// The `--config` file's top-level sections (its `ipc.root`, ...).
fn load_config(cli: &Cli) -> Result<Config> {
    Ok(Config::load_or_default(cli.config.as_deref())?.config)
}

fn unit_ns(cli: &Cli) -> u64 {
    if cli.nsecs {
        1
    } else {
        1_000
    }
}

/// Live view of a running ppmd.
fn attach(cli: &Cli, name: &str) -> Result<()> {
    let cfg = load_config(cli)?;
    ppm_shared::config::validate_name(name)?;
    ipc::init_ipc_logging();
    let node = ipc::create_node(&cfg.ipc.root, &format!("jitter-{}", std::process::id()))?;
    let service = ipc::open_stats_service(&node, name)?;
    let sub = service
        .subscriber_builder()
        .buffer_size(1)
        .create()
        .map_err(|e| ipc::IpcError::new("subscribing to ppmd's timing snapshots", e))?;
    let stop = stop_flag()?;
    let unit = unit_ns(cli);
    let started = Instant::now();
    let mut last: Option<TimingSnapshot> = None;
    let mut seen = 0u64;
    let mut waiting_said = false;
    let mut out = std::io::stdout();
    while !stop.load(Relaxed)
        && (cli.loops == 0 || seen < cli.loops)
        && cli.duration.is_none_or(|d| started.elapsed() < d)
    {
        std::thread::sleep(Duration::from_millis(100));
        let mut newest = None;
        while let Some(s) = sub
            .receive()
            .map_err(|e| ipc::IpcError::new("receiving a timing snapshot", e))?
        {
            newest = Some(*s.payload());
        }
        match newest {
            Some(s) if last.is_none_or(|l| l.seq != s.seq || l.pid != s.pid) => {
                seen += 1;
                if !cli.quiet {
                    write!(out, "{}\r", attach_line(&s, unit))?;
                    out.flush()?;
                }
                last = Some(s);
            }
            _ if last.is_none() && !waiting_said && started.elapsed() > Duration::from_secs(2) => {
                eprintln!(
                    "waiting for ppmd `{name}` (shared-memory root {})...",
                    cfg.ipc.root.display()
                );
                waiting_said = true;
            }
            _ => {}
        }
    }
    let Some(s) = last else {
        bail!(
            "no timing snapshot from ppmd `{name}` (is it running with this --config / ipc.root?)"
        );
    };
    if !cli.quiet {
        println!();
    }
    if let Some(h) = cli.histogram {
        if cli.nsecs {
            bail!("-h with --attach counts whole microseconds; drop -N");
        }
        let mut stats = LatencyStats::new(h);
        for (i, c) in s.hist_us.iter().enumerate() {
            stats.record_n(i as u64, *c);
        }
        stats.record_n(HIST_BUCKETS as u64, s.hist_overflow);
        let stats = stats.with_summary(
            s.total.count,
            s.total.min / unit,
            s.total.max / unit,
            s.last.max / unit,
            (s.total.mean / unit) as u128 * s.total.count as u128,
        );
        print!("{}", stats.histogram_block());
    }
    println!("{}", attach_line(&s, unit));
    println!(
        "# ppmd `{name}`: edge error p50 {:.3} us, p99 {:.3} us, p99.9 {:.3} us, max {:.3} us; write p99 {:.3} us; {} frames ({} aborted, {} glitched), {} late frames, {} overruns, {} late edges; spin margin {} us, spinning {:.1}%{}",
        s.total.p50 as f64 / 1e3,
        s.total.p99 as f64 / 1e3,
        s.total.p999 as f64 / 1e3,
        s.total.max as f64 / 1e3,
        s.write.p99 as f64 / 1e3,
        s.frames,
        s.aborted_frames,
        s.glitched_frames,
        s.late_frames,
        s.overruns,
        s.late_edges,
        s.margin_ns / 1_000,
        s.spin_share_ppm as f64 / 1e4,
        if s.degraded != 0 { "; DEGRADED RUN" } else { "" }
    );
    if let Some(out) = &cli.plot {
        // The snapshot's whole-run histogram: 1 us buckets, each drawn at
        // its middle; the marks are the snapshot's exact percentiles.
        let mut h = ppmd::meter::histogram();
        for (us, c) in s.hist_us.iter().enumerate().filter(|(_, c)| **c > 0) {
            h.saturating_record_n(us as u64 * 1_000 + 500, *c);
        }
        if s.hist_overflow > 0 {
            h.saturating_record_n(s.total.max, s.hist_overflow);
        }
        ppm_tools::plot::histogram_svg(
            out,
            &format!(
                "jitter --attach {name}: edge error of {} edges",
                s.total.count
            ),
            "us",
            &h,
            1_000.0,
            &[
                ("p50", s.total.p50 as f64 / 1e3),
                ("p99", s.total.p99 as f64 / 1e3),
                ("p99.9", s.total.p999 as f64 / 1e3),
                ("max", s.total.max as f64 / 1e3),
            ],
        )?;
        eprintln!("plot: {}", out.display());
    }
    Ok(())
}

fn attach_line(s: &TimingSnapshot, unit: u64) -> String {
    LatencyStats::new(0)
        .with_summary(
            s.total.count,
            s.total.min / unit,
            s.total.max / unit,
            s.last.max / unit,
            (s.total.mean / unit) as u128 * s.total.count as u128,
        )
        .t_line(0, s.pid, s.priority, s.frame_ns / 1_000, unit == 1)
}

/// Analysis of a sim trace.
fn trace(path: &PathBuf, receiver: Option<Receiver>, plot: Option<&Path>) -> Result<()> {
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let t = Trace::read(std::io::BufReader::new(file))?;
    let asked = receiver.or(match t.receiver {
        Some(ReceiverChoice::One(r)) => Some(r),
        _ => None,
    });
    let idle = t.idle_level.unwrap_or(Level::High);
    let reader = LineReader::new(t.protocol, asked, idle, t.baud).map_err(anyhow::Error::msg)?;
    if let Some(format) = reader.uart_format() {
        return bytes_trace(path, &t, reader, format, plot);
    }
    let receiver = receiver.unwrap_or(t.default_receiver());
    let r = analyse_trace(&t, receiver);
    println!("# jitter --trace {}", path.display());
    println!(
        "edges {} frames {} (decoded by scheduled time) {} (by actual time), {} differing",
        r.edges, r.frames_scheduled, r.frames_actual, r.frames_differing
    );
    println!("edge error us: {}", r.edge_error_ns.line(1_000.0));
    println!(
        "channel period error us: {} (|actual - scheduled| of {} periods)",
        r.period_error_ns.line(1_000.0),
        r.period_error_ns.count
    );
    println!(
        "{} hands on {} frames (by actual time, as its firmware decodes)",
        receiver.name(),
        r.frames_read
    );
    if let Some(out) = plot {
        let errors: Vec<f64> = t.edges.iter().map(|e| e.error_ns() as f64).collect();
        plot_values(
            out,
            &format!("jitter --trace: edge error of {} edges", r.edges),
            &errors,
        )?;
    }
    Ok(())
}

/// Analysis of the trace of a protocol of bytes (SBUS, CRSF): the edge
/// error, the characters a UART in the wire's format reads, and the frames
/// `reader`'s firmware takes and uses.
fn bytes_trace(
    path: &Path,
    t: &Trace,
    mut reader: LineReader,
    format: ppm_shared::wire::UartFormat,
    plot: Option<&Path>,
) -> Result<()> {
    let mut errors: Vec<f64> = t.edges.iter().map(|e| e.error_ns() as f64).collect();
    let idle = t.idle_level.unwrap_or(Level::High);
    let edges: Vec<(u64, Level)> = t.edges.iter().map(|e| (e.actual_ns, e.level)).collect();
    let chars = ppm_shared::wire::uart::decode(format, &edges, idle);
    let bad = chars.iter().filter(|c| !c.parity_ok || !c.stop_ok).count();
    let (mut used, mut refused, mut last) = (0, 0, 0);
    let mut count = |r: Option<Reading>| match r {
        Some(Reading::Frame { .. }) => used += 1,
        Some(Reading::Refused { .. }) => refused += 1,
        None => {}
    };
    for &(at, level) in &edges {
        count(reader.push(at, level));
        last = at;
    }
    count(reader.idle(last + 1_000_000_000));
    let protocol = t.protocol.name().to_uppercase();
    println!(
        "# jitter --trace {} ({protocol}, {})",
        path.display(),
        format.describe()
    );
    println!(
        "edges {} characters {} ({bad} with a parity or stop bit error), by actual time",
        t.edges.len(),
        chars.len()
    );
    println!(
        "edge error us: {}",
        Percentiles::of(&mut errors).line(1_000.0)
    );
    println!(
        "{} takes {} frames of channels and uses {used} (by actual time, as its UART and framing read them)",
        reader.reads_as(),
        used + refused
    );
    if let Some(out) = plot {
        let errors: Vec<f64> = t.edges.iter().map(|e| e.error_ns() as f64).collect();
        plot_values(
            out,
            &format!(
                "jitter --trace: edge error of {} {protocol} edges",
                t.edges.len()
            ),
            &errors,
        )?;
    }
    Ok(())
}

/// An SVG histogram of `hist` (ns) in microseconds, p50, p99, p99.9 and
/// the maximum marked.
fn plot_histogram(path: &Path, title: &str, hist: &hdrhistogram::Histogram<u64>) -> Result<()> {
    let p = Percentiles::of_histogram(hist);
    ppm_tools::plot::histogram_svg(
        path,
        title,
        "us",
        hist,
        1_000.0,
        &[
            ("p50", p.p50 / 1e3),
            ("p99", p.p99 / 1e3),
            ("p99.9", p.p999 / 1e3),
            ("max", p.max / 1e3),
        ],
    )?;
    eprintln!("plot: {}", path.display());
    Ok(())
}

/// [`plot_histogram`] of values in ns (negative ones, early edges, are
/// left out of the picture).
fn plot_values(path: &Path, title: &str, values_ns: &[f64]) -> Result<()> {
    plot_histogram(path, title, &ppm_tools::plot::histogram_of(values_ns))
}

/// Capture of a real line's edges with kernel timestamps.
fn capture(cli: &Cli, spec: &str) -> Result<()> {
    use gpiocdev::line::{EdgeDetection, EdgeKind};
    let cfg = load_config(cli)?;
    let (chip, line) = spec
        .rsplit_once(':')
        .filter(|(c, l)| !c.is_empty() && !l.is_empty())
        .with_context(|| format!("--capture `{spec}`: use CHIP:LINE, e.g. gpiochip0:GPIO23"))?;
    let (_, summary, info) = ppmd::line::gpio::resolve_line(chip, line)?;
    let req = gpiocdev::Request::builder()
        .on_chip(&summary.path)
        .with_consumer("jitter")
        .with_line(info.offset)
        .as_input()
        .with_edge_detection(EdgeDetection::BothEdges)
        .request()
        .with_context(|| {
            format!(
                "requesting {} on {} for edge events",
                ppmd::line::gpio::describe_line(&info),
                summary.name
            )
        })?;
    let stop = stop_flag()?;
    let leading = cfg.ppm.idle_level().opposite();
    let mut decoder = Decoder::new(leading, DecoderLimits::default());
    let receiver = cli.receiver.unwrap_or(match cfg.ppm.receiver {
        ReceiverChoice::One(r) => r,
        ReceiverChoice::Any => Receiver::EdgeTx,
    });
    let mut as_receiver = ReceiverDecoder::new(receiver, TIMED_EDGE);
    let mut read = 0usize;
    let mut frames = Vec::new();
    let mut events = 0u64;
    let started = Instant::now();
    let duration = cli.duration.unwrap_or(Duration::from_secs(5));
    eprintln!(
        "capturing {} on {} for {:?} (Ctrl-C to stop)",
        ppmd::line::gpio::describe_line(&info),
        summary,
        duration
    );
    while !stop.load(Relaxed)
        && started.elapsed() < duration
        && (cli.loops == 0 || (frames.len() as u64) < cli.loops)
    {
        if !req.wait_edge_event(Duration::from_millis(100))? {
            continue;
        }
        let e = req.read_edge_event()?;
        events += 1;
        let level = match e.kind {
            EdgeKind::Rising => Level::High,
            EdgeKind::Falling => Level::Low,
        };
        frames.extend(decoder.push(e.timestamp_ns, level));
        read += as_receiver.push(e.timestamp_ns, level).is_some() as usize;
    }
    frames.extend(decoder.finish());
    read += as_receiver.finish().is_some() as usize;
    let complete: Vec<_> = frames.iter().filter(|f| f.complete).collect();
    println!(
        "# jitter --capture {spec}: {events} edges, {} frames ({} complete); {} hands on {read}",
        frames.len(),
        complete.len(),
        receiver.name()
    );
    let Some(first) = complete.first() else {
        bail!("no complete PPM frame captured: is the input wired to ppmd's output and ppmd emitting?");
    };
    let n = first.channels_ns.len();
    let mut starts: Vec<f64> = complete
        .windows(2)
        .map(|w| (w[1].start_ns - w[0].start_ns) as f64)
        .collect();
    println!(
        "frame period us: {}",
        Percentiles::of(&mut starts).line(1_000.0)
    );
    let mut all_err = Vec::new();
    for ch in 0..n {
        let mut v: Vec<f64> = complete
            .iter()
            .filter_map(|f| f.channels_ns.get(ch).map(|&x| x as f64))
            .collect();
        let reference = match cli.expect.get(ch) {
            Some(us) => us * 1_000.0,
            None => Percentiles::of(&mut v.clone()).p50,
        };
        let mut err: Vec<f64> = v.iter().map(|x| (x - reference).abs()).collect();
        all_err.extend(err.iter().copied());
        let p = Percentiles::of(&mut v);
        println!(
            "channel {:2}: period us {} | error vs {:.1} us: p99 {:.3} max {:.3}",
            ch + 1,
            p.line(1_000.0),
            reference / 1_000.0,
            Percentiles::of(&mut err).p99 / 1_000.0,
            Percentiles::of(&mut err).max / 1_000.0,
        );
    }
    println!(
        "channel period error us: {} ({} periods, vs {})",
        Percentiles::of(&mut all_err).line(1_000.0),
        all_err.len(),
        if cli.expect.is_empty() {
            "each channel's median"
        } else {
            "--expect"
        }
    );
    if let Some(out) = &cli.plot {
        plot_values(
            out,
            &format!(
                "jitter --capture: channel-period error of {} periods",
                all_err.len()
            ),
            &all_err,
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("jitter").chain(args.iter().copied()))
    }

    #[test]
    fn the_flags_choose_one_mode() {
        let mode = |args: &[&str]| Mode::of(&parse(args).unwrap());
        assert_eq!(mode(&[]), Mode::Cyclic);
        assert_eq!(mode(&["-p", "80", "-i", "200", "-t", "2"]), Mode::Cyclic);
        assert_eq!(mode(&["--attach", "ppm"]), Mode::Attach("ppm".into()));
        assert_eq!(
            mode(&["--trace", "line.trace", "--receiver", "betaflight"]),
            Mode::Trace("line.trace".into())
        );
        assert_eq!(
            mode(&["--capture", "gpiochip0:17", "--expect", "1000,1200"]),
            Mode::Capture("gpiochip0:17".into())
        );
        // Two targets at once are refused, never chosen between.
        for two in [
            ["--attach", "ppm", "--trace", "t"],
            ["--attach", "ppm", "--capture", "c:1"],
            ["--trace", "t", "--capture", "c:1"],
        ] {
            assert!(parse(&two).is_err(), "{two:?}");
        }
        // The loopback command, with its own options (-h is its help) and
        // none of the flags' measurement.
        let loopback = ["loopback", "--output", "sim:a", "--input", "sim:a"];
        assert!(matches!(mode(&loopback), Mode::Loopback(a) if a.channels == 8));
        assert!(parse(&["-p", "80", "loopback", "--output", "sim:a", "--input", "sim:a"]).is_err());
        let help = parse(&["loopback", "-h"]).unwrap_err();
        assert_eq!(help.kind(), clap::error::ErrorKind::DisplayHelp);
    }
}
