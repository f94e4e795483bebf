//! `jitter`: the timing instrument of ppm.
//!
//! - With no target: a cyclictest-style latency test of this machine, using
//!   the very sleep-then-spin timer ppmd uses, in cyclictest's formats.
//! - `--attach NAME`: a running ppmd's edge error, live, in the same format.
//! - `--trace FILE`: edge error and channel-period error of a sim trace.
//! - `--capture CHIP:LINE`: kernel-timestamped edges of an input line wired to
//!   the output pin, decoded as a transmitter does.

use anyhow::{bail, Context, Result};
use clap::{ArgAction, Parser};
use ppm_shared::config::Config;
use ppm_shared::decode::{Decoder, DecoderLimits};
use ppm_shared::frame::Level;
use ppm_shared::ipc::{self, TimingSnapshot, HIST_BUCKETS};
use ppm_shared::receiver::{Receiver, ReceiverChoice, ReceiverDecoder};
use ppm_shared::trace::Trace;
use ppm_tools::analysis::{analyse_trace, Percentiles};
use ppm_tools::cyclic::LatencyStats;
use ppm_tools::parse_duration;
use ppmd::clock::{self, EdgeTimer, Margin};
use ppmd::rt::{RtSetup, RT_STACK_BYTES};
use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

/// Timing measurements for ppm: cyclictest-style tests of this machine with
/// ppmd's own timer, a running ppmd's edge error, sim traces, captured edges.
#[derive(Parser, Debug)]
#[command(name = "jitter", version, about, disable_help_flag = true)]
struct Cli {
    /// Print help.
    #[arg(long, action = ArgAction::Help)]
    help: Option<bool>,
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
    /// Pin the measuring thread to this CPU.
    #[arg(short = 'a', long = "affinity", value_name = "CPU")]
    cpu: Option<usize>,
    /// Print only the summary at the end.
    #[arg(short = 'q', long = "quiet")]
    quiet: bool,
    /// Print a histogram of latencies up to US (one bucket per unit) at the end.
    #[arg(short = 'h', long = "histogram", value_name = "US")]
    histogram: Option<usize>,
    /// Write cyclictest's JSON summary to FILE.
    #[arg(long = "json", value_name = "FILE")]
    json: Option<PathBuf>,
    /// Lock memory (mlockall) and prefault the stack.
    #[arg(short = 'm', long = "mlockall")]
    mlock: bool,
    /// Latencies in nanoseconds instead of microseconds.
    #[arg(short = 'N', long = "nsecs")]
    nsecs: bool,
    /// Stop after this long (e.g. 10s, 500ms).
    #[arg(short = 'D', long = "duration", value_parser = parse_duration, value_name = "TIME")]
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
    /// With --trace or --capture: count the frames this receiver hands on,
    /// decoding as its firmware does: edgetx, opentx, betaflight or
    /// ardupilot (default: the one the trace or --config names, edgetx for
    /// `any`).
    #[arg(long, value_name = "RECEIVER")]
    receiver: Option<Receiver>,
}

fn main() {
    let cli = Cli::parse();
    let r = if let Some(name) = &cli.attach {
        attach(&cli, name)
    } else if let Some(path) = &cli.trace {
        trace(path, cli.receiver)
    } else if let Some(spec) = &cli.capture {
        capture(&cli, spec)
    } else {
        cyclic(&cli)
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

fn load_config(cli: &Cli) -> Result<Config> {
    Ok(Config::load_or_default(cli.config.as_deref())?)
}

fn unit_ns(cli: &Cli) -> u64 {
    if cli.nsecs {
        1
    } else {
        1_000
    }
}

fn timestamp() -> String {
    let t = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or_default();
    format!("{}.{:03}", t.as_secs(), t.subsec_millis())
}

/// Counters the measuring thread shares with the printing one.
#[derive(Default)]
struct Live {
    cycles: AtomicU64,
    min: AtomicU64,
    max: AtomicU64,
    act: AtomicU64,
    sum: AtomicU64,
}

/// The cyclictest-style test.
fn cyclic(cli: &Cli) -> Result<()> {
    if cli.interval_us == 0 {
        bail!("-i must be at least 1 microsecond");
    }
    let margin = match cli.spin.as_str() {
        // Half the interval at most, so every period has a sleep in it.
        "auto" => Margin::Auto {
            min_ns: 20_000.min(cli.interval_us * 250),
            max_ns: 1_000_000.min(cli.interval_us * 500),
        },
        us => Margin::Fixed(
            us.parse::<u64>()
                .ok()
                .filter(|v| *v <= 5_000)
                .with_context(|| format!("--spin `{us}`: use auto or 0..=5000 microseconds"))?
                * 1_000,
        ),
    };
    let setup = RtSetup {
        priority: cli.priority,
        cpu: cli.cpu,
        mlock: cli.mlock,
        cpu_dma_latency: cli.priority > 0,
        allow_degraded: false,
    };
    let stop = stop_flag()?;
    let unit = unit_ns(cli);
    let buckets = cli.histogram.unwrap_or(0);
    let (loops, interval_ns) = (cli.loops, cli.interval_us * 1_000);
    let deadline = cli.duration.map(|d| clock::now_ns() + d.as_nanos() as u64);
    let live = Arc::new(Live {
        min: AtomicU64::new(u64::MAX),
        ..Live::default()
    });
    let start = timestamp();
    let (stop2, live2) = (stop.clone(), live.clone());
    let worker = std::thread::Builder::new()
        .name("jitter".into())
        .stack_size(RT_STACK_BYTES)
        .spawn(
            move || -> Result<(LatencyStats, hdrhistogram::Histogram<u64>, u64, bool)> {
                let obtained = setup.apply()?;
                let mut stats = LatencyStats::new(buckets);
                let mut hist = ppmd::meter::histogram();
                let mut timer = EdgeTimer::new(margin);
                let mut next = clock::now_ns() + interval_ns;
                let (mut cycle, mut missed) = (0u64, 0u64);
                while !stop2.load(Relaxed)
                    && (loops == 0 || cycle < loops)
                    && deadline.is_none_or(|d| next <= d)
                {
                    let w = timer.wait(next);
                    let lat = w.now_ns - next;
                    stats.record(lat / unit, cycle);
                    hist.saturating_record(lat);
                    live2.cycles.store(cycle + 1, Relaxed);
                    live2.min.fetch_min(lat / unit, Relaxed);
                    live2.max.fetch_max(lat / unit, Relaxed);
                    live2.act.store(lat / unit, Relaxed);
                    live2.sum.fetch_add(lat / unit, Relaxed);
                    cycle += 1;
                    next += interval_ns;
                    if w.now_ns > next {
                        let n = (w.now_ns - next) / interval_ns + 1;
                        missed += n;
                        next += n * interval_ns;
                    }
                }
                Ok((stats, hist, missed, obtained.dma_latency.is_some()))
            },
        )?;
    let tid = nix::unistd::getpid().as_raw() as u32;
    let prio = cli.priority as u32;
    let t_line = |l: &Live| {
        let c = l.cycles.load(Relaxed);
        let min = if c == 0 { 0 } else { l.min.load(Relaxed) };
        LatencyStats::new(0)
            .with_summary(
                c,
                min,
                l.max.load(Relaxed),
                l.act.load(Relaxed),
                l.sum.load(Relaxed) as u128,
            )
            .t_line(0, tid, prio, cli.interval_us)
    };
    let mut out = std::io::stdout();
    while !worker.is_finished() {
        std::thread::sleep(Duration::from_millis(100));
        if !cli.quiet {
            write!(out, "{}\r", t_line(&live))?;
            out.flush()?;
        }
    }
    let (stats, hist, missed, dma) = worker
        .join()
        .map_err(|_| anyhow::anyhow!("the measuring thread panicked"))??;
    if dma {
        println!("# /dev/cpu_dma_latency set to 0us");
    }
    if cli.histogram.is_some() {
        print!("{}", stats.histogram_block());
    }
    println!("{}", stats.t_line(0, tid, prio, cli.interval_us));
    let p = Percentiles::of_histogram(&hist);
    println!(
        "# Percentiles (us): {}; missed periods {missed}; spin {}",
        p.line(1_000.0),
        cli.spin
    );
    if let Some(path) = &cli.json {
        let cmdline: Vec<String> = std::env::args().collect();
        let doc = stats.json(
            &cmdline.join(" "),
            &start,
            &timestamp(),
            cli.cpu.map_or(-1, |c| c as i64),
            if cli.nsecs { 1 } else { 0 },
        );
        std::fs::write(path, serde_json::to_string_pretty(&doc)? + "\n")
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
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
        .map_err(|e| anyhow::anyhow!("subscribing to ppmd's timing snapshots: {e:?}"))?;
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
            .map_err(|e| anyhow::anyhow!("receiving: {e:?}"))?
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
        "# ppmd `{name}`: edge error p50 {:.3} us, p99 {:.3} us, p99.9 {:.3} us, max {:.3} us; write p99 {:.3} us; {} frames, {} late frames, {} overruns, {} late edges; spin margin {} us, spinning {:.1}%{}",
        s.total.p50 as f64 / 1e3,
        s.total.p99 as f64 / 1e3,
        s.total.p999 as f64 / 1e3,
        s.total.max as f64 / 1e3,
        s.write.p99 as f64 / 1e3,
        s.frames,
        s.late_frames,
        s.overruns,
        s.late_edges,
        s.margin_ns / 1_000,
        s.spin_share_ppm as f64 / 1e4,
        if s.degraded != 0 { "; DEGRADED RUN" } else { "" }
    );
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
        .t_line(0, s.pid, s.priority, s.frame_ns / 1_000)
}

/// Analysis of a sim trace.
fn trace(path: &PathBuf, receiver: Option<Receiver>) -> Result<()> {
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let t = Trace::read(std::io::BufReader::new(file))?;
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
    Ok(())
}

/// Capture of a real line's edges with kernel timestamps.
fn capture(cli: &Cli, spec: &str) -> Result<()> {
    use gpiocdev::line::{EdgeDetection, EdgeKind};
    let cfg = load_config(cli)?;
    let (chip, line) = spec
        .rsplit_once(':')
        .filter(|(c, l)| !c.is_empty() && !l.is_empty())
        .with_context(|| format!("--capture `{spec}`: use CHIP:LINE, e.g. gpiochip0:GPIO23"))?;
    let (_, summary, info) = ppmd::output::gpio::resolve_line(chip, line)?;
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
                ppmd::output::gpio::describe_line(&info),
                summary.name
            )
        })?;
    let stop = stop_flag()?;
    let leading = cfg.ppm.idle_level.opposite();
    let mut decoder = Decoder::new(leading, DecoderLimits::default());
    let receiver = cli.receiver.unwrap_or(match cfg.ppm.receiver {
        ReceiverChoice::One(r) => r,
        ReceiverChoice::Any => Receiver::EdgeTx,
    });
    let mut as_receiver = ReceiverDecoder::new(receiver, leading);
    let mut read = 0usize;
    let mut frames = Vec::new();
    let mut events = 0u64;
    let started = Instant::now();
    let duration = cli.duration.unwrap_or(Duration::from_secs(5));
    eprintln!(
        "capturing {} on {} for {:?} (Ctrl-C to stop)",
        ppmd::output::gpio::describe_line(&info),
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
    Ok(())
}
