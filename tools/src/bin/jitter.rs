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
use ppm_tools::cyclic::{self, parse_cyclictest_duration, JsonThread, LatencyStats};
use ppmd::clock::{self, EdgeTimer, Margin};
use ppmd::rt::{RtSetup, RT_STACK_BYTES};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

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

fn main() {
    let cli = Cli::parse();
    let r = if let Some(name) = &cli.attach {
        attach(&cli, name)
    } else if let Some(path) = &cli.trace {
        trace(path, cli.receiver, cli.plot.as_deref())
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

/// Counters a measuring thread shares with the printing one.
#[derive(Default)]
struct Live {
    tid: AtomicU64,
    cycles: AtomicU64,
    min: AtomicU64,
    max: AtomicU64,
    act: AtomicU64,
    sum: AtomicU64,
}

/// The first latency over `-b`: which thread, and the value.
#[derive(Default)]
struct Break {
    hit: AtomicBool,
    tid: AtomicU64,
    value: AtomicU64,
}

/// One measuring thread's settings.
struct ThreadPlan {
    interval_us: u64,
    cpu: Option<usize>,
    setup: RtSetup,
}

/// What a measuring thread hands back.
struct ThreadResult {
    stats: LatencyStats,
    hist: hdrhistogram::Histogram<u64>,
    missed: u64,
    cpu: i64,
}

/// The measuring threads cyclictest's options ask for: how many, their
/// intervals and CPUs.
fn plan_threads(cli: &Cli) -> Result<Vec<ThreadPlan>> {
    let online = ppm_shared::sched::online_cpus();
    let cpus = online.len().max(1);
    let n = match (cli.smp, cli.threads) {
        (true, _) | (_, Some(0)) => cpus,
        (false, Some(n)) => n,
        (false, None) => 1,
    };
    if n > 256 {
        bail!("-t {n}: at most 256 threads");
    }
    let set = match cli.affinity.as_deref() {
        Some("") | None => None,
        Some(s) => Some(cyclic::parse_cpuset(s).map_err(|e| anyhow::anyhow!("-a: {e}"))?),
    };
    let pinned = cli.smp || cli.affinity.is_some();
    // /dev/cpu_dma_latency, when this user may hold it (cyclictest's
    // latency target), by the first thread.
    let dma = nix::unistd::access("/dev/cpu_dma_latency", nix::unistd::AccessFlags::W_OK).is_ok();
    let same_interval = cli.histogram.is_some() || cli.histofall.is_some();
    Ok((0..n)
        .map(|i| {
            let cpu = pinned.then(|| cyclic::cpu_for_thread(i, set.as_deref(), cpus));
            ThreadPlan {
                interval_us: cli.interval_us
                    + if same_interval {
                        0
                    } else {
                        i as u64 * cli.distance_us
                    },
                cpu,
                setup: RtSetup {
                    priority: cli.priority,
                    cpu,
                    mlock: cli.mlock && i == 0,
                    cpu_dma_latency: dma && i == 0,
                    allow_degraded: false,
                },
            }
        })
        .collect())
}

/// The `T:` line of a running thread.
fn live_line(l: &Live, index: usize, prio: u32, interval: u64, nsecs: bool) -> String {
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
        .t_line(index, l.tid.load(Relaxed) as u32, prio, interval, nsecs)
}

/// cyclictest's status block (SIGUSR1 to standard error, SIGUSR2 to
/// `/dev/shm/cyclictest<pid>`).
fn status_block(lines: &[String]) -> String {
    let mut s = String::from("#---------------------------\n# cyclictest current status:\n");
    for l in lines {
        s += l;
        s += "\n";
    }
    s + "#---------------------------\n"
}

/// `policy: fifo: loadavg: ...`, the head of cyclictest's live view.
fn policy_line(priority: u8) -> String {
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    format!(
        "policy: {}: loadavg: {}          \n",
        if priority > 0 { "fifo" } else { "other" },
        load.trim_end()
    )
}

/// The cyclictest-style test.
fn cyclic(cli: &Cli) -> Result<()> {
    if cli.interval_us == 0 {
        bail!("-i must be at least 1 microsecond");
    }
    if cli.system {
        eprintln!("jitter: -s (--system): not applicable, ignored: jitter always sleeps with clock_nanosleep");
    }
    let (_, _) = (cli.nanosleep, cli.unbuffered); // accepted: what jitter does anyway
    let spin = cli.spin.as_str();
    let margin = |interval_us: u64| -> Result<Margin> {
        Ok(match spin {
            // Half the interval at most, so every period has a sleep in it.
            "auto" => Margin::Auto {
                min_ns: 20_000.min(interval_us * 250),
                max_ns: 1_000_000.min(interval_us * 500),
            },
            us => Margin::Fixed(
                us.parse::<u64>()
                    .ok()
                    .filter(|v| *v <= 5_000)
                    .with_context(|| format!("--spin `{us}`: use auto or 0..=5000 microseconds"))?
                    * 1_000,
            ),
        })
    };
    let plans = plan_threads(cli)?;
    let n = plans.len();
    let stop = stop_flag()?;
    let usr1 = Arc::new(AtomicBool::new(false));
    let usr2 = Arc::new(AtomicBool::new(false));
    signal_hook::flag::register(signal_hook::consts::SIGUSR1, usr1.clone())
        .context("installing the SIGUSR1 handler")?;
    signal_hook::flag::register(signal_hook::consts::SIGUSR2, usr2.clone())
        .context("installing the SIGUSR2 handler")?;
    let unit = unit_ns(cli);
    let buckets = cli.histogram.or(cli.histofall).unwrap_or(0);
    let loops = cli.loops;
    let deadline = cli.duration.map(|d| clock::now_ns() + d.as_nanos() as u64);
    let brk = Arc::new(Break::default());
    let lives: Arc<Vec<Live>> = Arc::new(
        (0..n)
            .map(|_| Live {
                min: AtomicU64::new(u64::MAX),
                ..Live::default()
            })
            .collect(),
    );
    let start = timestamp_rfc2822();
    let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<bool, String>>();
    let mut workers = Vec::new();
    for (i, plan) in plans.iter().enumerate() {
        let (stop, lives, brk, ready) =
            (stop.clone(), lives.clone(), brk.clone(), ready_tx.clone());
        let (setup, interval_ns) = (plan.setup.clone(), plan.interval_us * 1_000);
        let (margin, breaktrace) = (margin(plan.interval_us)?, cli.breaktrace);
        let pinned = plan.cpu;
        workers.push(
            std::thread::Builder::new()
                .name(format!("jitter-{i}"))
                .stack_size(RT_STACK_BYTES)
                .spawn(move || -> Option<ThreadResult> {
                    let obtained = match setup.apply() {
                        Ok(o) => {
                            let _ = ready.send(Ok(o.dma_latency.is_some()));
                            o
                        }
                        Err(e) => {
                            let _ = ready.send(Err(e.to_string()));
                            return None;
                        }
                    };
                    let live = &lives[i];
                    live.tid
                        .store(nix::unistd::gettid().as_raw() as u64, Relaxed);
                    let mut stats = LatencyStats::new(buckets);
                    let mut hist = ppmd::meter::histogram();
                    let mut timer = EdgeTimer::new(margin);
                    let mut next = clock::now_ns() + interval_ns;
                    let (mut cycle, mut missed) = (0u64, 0u64);
                    while !stop.load(Relaxed)
                        && (loops == 0 || cycle < loops)
                        && deadline.is_none_or(|d| next <= d)
                    {
                        let w = timer.wait(&clock::SystemClock, next);
                        let lat = w.now_ns - next;
                        let v = lat / unit;
                        stats.record(v, cycle);
                        hist.saturating_record(lat);
                        live.cycles.store(cycle + 1, Relaxed);
                        live.min.fetch_min(v, Relaxed);
                        live.max.fetch_max(v, Relaxed);
                        live.act.store(v, Relaxed);
                        live.sum.fetch_add(v, Relaxed);
                        cycle += 1;
                        if breaktrace.is_some_and(|b| v > b) && !brk.hit.swap(true, Relaxed) {
                            brk.tid.store(live.tid.load(Relaxed), Relaxed);
                            brk.value.store(v, Relaxed);
                            stop.store(true, Relaxed);
                        }
                        next += interval_ns;
                        if w.now_ns > next {
                            let k = (w.now_ns - next) / interval_ns + 1;
                            missed += k;
                            next += k * interval_ns;
                        }
                    }
                    drop(obtained);
                    let cpu = pinned.map_or_else(
                        || nix::sched::sched_getcpu().map_or(-1, |c| c as i64),
                        |c| c as i64,
                    );
                    Some(ThreadResult {
                        stats,
                        hist,
                        missed,
                        cpu,
                    })
                })?,
        );
    }
    drop(ready_tx);
    let mut dma = false;
    for r in ready_rx.iter().take(n) {
        match r {
            Ok(d) => dma |= d,
            Err(e) => {
                stop.store(true, Relaxed);
                for w in workers {
                    let _ = w.join();
                }
                bail!("{e}");
            }
        }
    }
    let mut out = std::io::stdout();
    if dma {
        writeln!(out, "# /dev/cpu_dma_latency set to 0us")?;
    }
    let prio = cli.priority as u32;
    let lines = |lives: &[Live]| -> Vec<String> {
        lives
            .iter()
            .zip(&plans)
            .enumerate()
            .map(|(i, (l, p))| live_line(l, i, prio, p.interval_us, cli.nsecs))
            .collect()
    };
    let rstat = std::path::PathBuf::from(format!("/dev/shm/cyclictest{}", std::process::id()));
    while !workers.iter().all(|w| w.is_finished()) {
        std::thread::sleep(Duration::from_millis(100));
        if usr1.swap(false, Relaxed) {
            eprint!("{}", status_block(&lines(&lives)));
        }
        if usr2.swap(false, Relaxed) {
            if let Err(e) = std::fs::write(&rstat, status_block(&lines(&lives))) {
                eprintln!("jitter: SIGUSR2: writing {}: {e}", rstat.display());
            }
        }
        if !cli.quiet {
            write!(
                out,
                "{}\n{}\n\x1b[{}A",
                policy_line(cli.priority),
                lines(&lives).join("\n"),
                n + 2
            )?;
            out.flush()?;
        }
    }
    let _ = std::fs::remove_file(&rstat);
    let results: Vec<ThreadResult> = workers
        .into_iter()
        .map(|w| {
            w.join()
                .map_err(|_| anyhow::anyhow!("a measuring thread panicked"))
        })
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .map(|r| r.context("a measuring thread stopped at start"))
        .collect::<Result<_>>()?;
    let tids: Vec<u32> = lives.iter().map(|l| l.tid.load(Relaxed) as u32).collect();
    let final_lines: Vec<String> = results
        .iter()
        .zip(&plans)
        .enumerate()
        .map(|(i, (r, p))| r.stats.t_line(i, tids[i], prio, p.interval_us, cli.nsecs))
        .collect();
    if !cli.quiet {
        write!(
            out,
            "{}\n{}\n",
            policy_line(cli.priority),
            final_lines.join("\n")
        )?;
    } else if buckets == 0 {
        for l in &final_lines {
            writeln!(out, "{l}")?;
        }
    }
    if buckets > 0 {
        let stats: Vec<&LatencyStats> = results.iter().map(|r| &r.stats).collect();
        write!(
            out,
            "{}",
            cyclic::histogram_block(&stats, cli.histofall.is_some())
        )?;
    }
    if cli.breaktrace.is_some() {
        let ids: Vec<String> = tids.iter().map(|t| format!(" {t:05}")).collect();
        writeln!(out, "# Thread Ids:{}", ids.concat())?;
        if brk.hit.load(Relaxed) {
            writeln!(out, "# Break thread: {}", brk.tid.load(Relaxed))?;
            writeln!(out, "# Break value: {}", brk.value.load(Relaxed))?;
        }
    }
    out.flush()?;
    // jitter's own figures go to standard error: standard output stays
    // cyclictest's.
    for (i, r) in results.iter().enumerate() {
        let p = Percentiles::of_histogram(&r.hist);
        eprintln!(
            "# T:{i} percentiles (us): {}; missed periods {}; spin {}",
            p.line(1_000.0),
            r.missed,
            cli.spin
        );
    }
    if let Some(out) = &cli.plot {
        let mut all = ppmd::meter::histogram();
        for r in &results {
            let _ = all.add(&r.hist);
        }
        plot_histogram(
            out,
            &format!(
                "jitter: wake-up latency, {n} thread{}, -i {} us, spin {}",
                if n == 1 { "" } else { "s" },
                cli.interval_us,
                cli.spin
            ),
            &all,
        )?;
    }
    if let Some(path) = &cli.json {
        let cmdline: Vec<String> = std::env::args().collect();
        let threads: Vec<JsonThread> = results
            .iter()
            .map(|r| JsonThread {
                stats: &r.stats,
                cpu: r.cpu,
            })
            .collect();
        let doc = cyclic::json(
            &threads,
            &cmdline.join(" "),
            &start,
            &timestamp_rfc2822(),
            cli.nsecs,
            buckets > 0,
        );
        std::fs::write(path, serde_json::to_string_pretty(&doc)? + "\n")
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Local time as cyclictest's `--json` writes it: `Mon, 23 Nov 2026 13:16:47 +0000`.
fn timestamp_rfc2822() -> String {
    jiff::Zoned::now()
        .strftime("%a, %d %b %Y %H:%M:%S %z")
        .to_string()
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
