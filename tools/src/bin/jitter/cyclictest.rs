//! jitter's cyclictest-style test of this machine: the measuring threads
//! planned from the flags, run with cyclictest's live view, and their
//! figures reported in cyclictest's formats.

use super::{plot_histogram, stop_flag, unit_ns, Cli};
use anyhow::{bail, Context, Result};
use ppm_tools::analysis::Percentiles;
use ppm_tools::cyclic::{self, JsonThread, LatencyStats};
use ppmd::clock::{self, EdgeTimer, Margin};
use ppmd::rt::{RtSetup, Shortfall, RT_STACK_BYTES};
use std::io::Write;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

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
#[derive(Debug, Clone)]
struct ThreadPlan {
    interval_us: u64,
    cpu: Option<usize>,
    setup: RtSetup,
    /// How long before each wake-up it stops sleeping and spins (`--spin`).
    margin: Margin,
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
    (0..n)
        .map(|i| {
            let cpu = pinned.then(|| cyclic::cpu_for_thread(i, set.as_deref(), cpus));
            let interval_us = cli.interval_us
                + if same_interval {
                    0
                } else {
                    i as u64 * cli.distance_us
                };
            Ok(ThreadPlan {
                interval_us,
                cpu,
                setup: RtSetup {
                    priority: cli.priority,
                    cpu,
                    mlock: cli.mlock && i == 0,
                    cpu_dma_latency: dma && i == 0,
                    allow_degraded: false,
                },
                margin: spin_margin(&cli.spin, interval_us)?,
            })
        })
        .collect()
}

/// A real-time setting jitter could not have, with a fix in jitter's own
/// options: ppmd's fixes name `rt.cpu`, `--allow-degraded` and the ppmd
/// binary, which jitter does not have.
fn shortfall_for_jitter(s: &Shortfall) -> String {
    let fix = match s.what {
        "CPU pinning" if s.detail.contains("does not exist") => {
            "give -a (--affinity) CPUs from the online list, or leave -a out to run unpinned"
                .to_string()
        }
        "SCHED_FIFO" => "run as root, give jitter CAP_SYS_NICE (`setcap cap_sys_nice+ep jitter`), \
             raise RLIMIT_RTPRIO (`ulimit -r 99`), or measure on the normal scheduler with -p 0"
            .to_string(),
        _ => s.fix.clone(),
    };
    if fix.is_empty() {
        format!("{}: {}", s.what, s.detail)
    } else {
        format!("{}: {}. Fix: {fix}", s.what, s.detail)
    }
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

/// The cyclictest-style test: plan the threads from the flags, run them
/// with the live view, report what they measured.
pub(crate) fn cyclic(cli: &Cli) -> Result<()> {
    let plans = plan_cyclic(cli)?;
    let run = run_cyclic(cli, &plans)?;
    report_cyclic(cli, &plans, &run)
}

/// The spin margin of a thread waking every `interval_us` (`--spin`).
fn spin_margin(spin: &str, interval_us: u64) -> Result<Margin> {
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
}

/// The plan: the flags checked, and each measuring thread's settings.
fn plan_cyclic(cli: &Cli) -> Result<Vec<ThreadPlan>> {
    if cli.interval_us == 0 {
        bail!("-i must be at least 1 microsecond");
    }
    if cli.system {
        eprintln!("jitter: -s (--system): not applicable, ignored: jitter always sleeps with clock_nanosleep");
    }
    let (_, _) = (cli.nanosleep, cli.unbuffered); // accepted: what jitter does anyway
    plan_threads(cli)
}

/// What the measuring threads did.
struct CyclicRun {
    /// Each thread's figures, in thread order.
    results: Vec<ThreadResult>,
    /// Each thread's id.
    tids: Vec<u32>,
    /// The first latency over `-b`, if any.
    brk: Arc<Break>,
    /// When the test started, as cyclictest's `--json` writes it.
    start: String,
}

/// One measuring thread: everything it needs, moved into it.
struct Measure {
    index: usize,
    plan: ThreadPlan,
    /// Histogram buckets of -h/-H (0: none).
    buckets: usize,
    /// ns per unit of the recorded latencies (1 with -N, else 1000).
    unit: u64,
    /// Wake-ups to measure (0: no limit).
    loops: u64,
    /// CLOCK_MONOTONIC time to stop at (--duration).
    deadline: Option<u64>,
    breaktrace: Option<u64>,
    stop: Arc<AtomicBool>,
    lives: Arc<Vec<Live>>,
    brk: Arc<Break>,
    /// Says whether the real-time setup succeeded (and /dev/cpu_dma_latency is held).
    ready: std::sync::mpsc::Sender<Result<bool, String>>,
}

impl Measure {
    /// The thread's body: real-time setup, then the loop until a stop;
    /// `None` when the setup failed (said through `ready`).
    fn run(self) -> Option<ThreadResult> {
        let interval_ns = self.plan.interval_us * 1_000;
        let obtained = match self.plan.setup.apply() {
            Ok(o) => {
                let _ = self.ready.send(Ok(o.dma_latency.is_some()));
                o
            }
            Err(e) => {
                let _ = self.ready.send(Err(shortfall_for_jitter(&e)));
                return None;
            }
        };
        let (unit, stop, brk) = (self.unit, &self.stop, &self.brk);
        let live = &self.lives[self.index];
        live.tid
            .store(nix::unistd::gettid().as_raw() as u64, Relaxed);
        let mut stats = LatencyStats::new(self.buckets);
        let mut hist = ppmd::meter::histogram();
        let mut timer = EdgeTimer::new(self.plan.margin);
        let mut next = clock::now_ns() + interval_ns;
        let (mut cycle, mut missed) = (0u64, 0u64);
        while !stop.load(Relaxed)
            && (self.loops == 0 || cycle < self.loops)
            && self.deadline.is_none_or(|d| next <= d)
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
            if self.breaktrace.is_some_and(|b| v > b) && !brk.hit.swap(true, Relaxed) {
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
        let cpu = self.plan.cpu.map_or_else(
            || nix::sched::sched_getcpu().map_or(-1, |c| c as i64),
            |c| c as i64,
        );
        Some(ThreadResult {
            stats,
            hist,
            missed,
            cpu,
        })
    }
}

/// The run: the measuring threads started, the live view (and SIGUSR1,
/// SIGUSR2) until they stop, their results collected.
fn run_cyclic(cli: &Cli, plans: &[ThreadPlan]) -> Result<CyclicRun> {
    let n = plans.len();
    let stop = stop_flag()?;
    let usr1 = Arc::new(AtomicBool::new(false));
    let usr2 = Arc::new(AtomicBool::new(false));
    signal_hook::flag::register(signal_hook::consts::SIGUSR1, usr1.clone())
        .context("installing the SIGUSR1 handler")?;
    signal_hook::flag::register(signal_hook::consts::SIGUSR2, usr2.clone())
        .context("installing the SIGUSR2 handler")?;
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
        let job = Measure {
            index: i,
            plan: plan.clone(),
            buckets: cli.histogram.or(cli.histofall).unwrap_or(0),
            unit: unit_ns(cli),
            loops: cli.loops,
            deadline,
            breaktrace: cli.breaktrace,
            stop: stop.clone(),
            lives: lives.clone(),
            brk: brk.clone(),
            ready: ready_tx.clone(),
        };
        workers.push(
            std::thread::Builder::new()
                .name(format!("jitter-{i}"))
                .stack_size(RT_STACK_BYTES)
                .spawn(move || job.run())?,
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
            .zip(plans)
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
    Ok(CyclicRun {
        results,
        tids,
        brk,
        start,
    })
}

/// The report: cyclictest's summary (`T:` lines, histogram block, break
/// trace) on standard output, jitter's percentiles on standard error, and
/// the `--plot` and `--json` files.
fn report_cyclic(cli: &Cli, plans: &[ThreadPlan], run: &CyclicRun) -> Result<()> {
    let (results, tids, brk) = (&run.results, &run.tids, &run.brk);
    let n = plans.len();
    let buckets = cli.histogram.or(cli.histofall).unwrap_or(0);
    let mut out = std::io::stdout();
    let prio = cli.priority as u32;
    let final_lines: Vec<String> = results
        .iter()
        .zip(plans)
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
        for r in results {
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
            &run.start,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spin_margins_as_the_flag_says() {
        let auto = |min_ns, max_ns| Margin::Auto { min_ns, max_ns };
        assert_eq!(spin_margin("auto", 1_000).unwrap(), auto(20_000, 500_000));
        // A short interval: half of it at most, so each period sleeps.
        assert_eq!(spin_margin("auto", 50).unwrap(), auto(12_500, 25_000));
        assert_eq!(spin_margin("auto", 5_000).unwrap(), auto(20_000, 1_000_000));
        assert_eq!(spin_margin("0", 1_000).unwrap(), Margin::Fixed(0));
        assert_eq!(spin_margin("300", 1_000).unwrap(), Margin::Fixed(300_000));
        for bad in ["5001", "fast", "-1"] {
            let e = spin_margin(bad, 1_000).unwrap_err().to_string();
            assert_eq!(
                e,
                format!("--spin `{bad}`: use auto or 0..=5000 microseconds")
            );
        }
    }
}
