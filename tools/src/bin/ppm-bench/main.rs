//! `ppm-bench`: the input path under measurement, against the paper's
//! approach, with the real binaries as separate processes on loopback.
//!
//! 1. ingress latency: kernel receive timestamp (SO_TIMESTAMPNS) to the
//!    command published, udp-ingress (sleeping in mio's poll, the default;
//!    the same at SCHED_FIFO on a CPU of its own; busy-polling on that CPU)
//!    against a Python receiver written as the seed's was (blocking socket,
//!    json.loads, hand-off to a generator process), same traffic, same run;
//! 2. flood: datagrams/s drained, memory before and after, ppmd's edge error
//!    and the newest command's age at each frame start during the flood,
//!    for each of those ways of receiving;
//! 3. end to end: send time to the first frame that carries a command, and
//!    whether commands that arrive at least 1 ms before a frame are in it;
//! 4. memory and CPU of both processes at idle and at 50 Hz;
//! 5. late edges: follow and grid, with and without a thread of higher
//!    SCHED_FIFO priority pinned to ppmd's CPU that busy-loops 100..500 us
//!    at random times (`ppm-interfere`'s bursts): frames whole, aborted and glitched, frames whose
//!    values as the line carried them differ from the frame log, and the
//!    commands that reached the line, by the log and by decoding;
//! 6. SBUS against PPM, both following the commands: send to the frame
//!    whole at the receiver, and the share of commands on the line, at 50,
//!    100, 200 and 300 Hz;
//! 7. the read-back (`ppmd.readback`, a simulated radio): a frame's closing
//!    edge to its sample published and seen by a subscriber, the read-back
//!    thread's CPU share at 50 Hz, and the radio's switch flip to the
//!    sender hearing `overridden`;
//! 8. an ExpressLRS module (simulated, with a pilot's radio): send to the
//!    frame whole at the module and to its next radio packet, the share
//!    of commands on the line, and the lead it asks for.

use anyhow::{bail, Context, Result};
use clap::Parser;
use hdrhistogram::Histogram;
use ppm_shared::framelog::{self, FrameRow};
use ppm_shared::status::StatusReply;
use ppm_shared::time::now_ns;
use ppm_tools::analysis::Percentiles;
use ppm_tools::harness::{Proc, Scratch};
use ppm_tools::plot;
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::net::UdpSocket;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

mod late;
mod module;
mod plots;
mod readback;
mod sbus;
use plots::{plot_dir, write_plots, Plots};

/// Benchmarks of ppm's input path (ingress latency, flood, end-to-end
/// latency, memory and CPU), with the paper's approach as baseline.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// Datagrams for the latency comparison (sent at 1 kHz).
    #[arg(long, default_value_t = 3000)]
    latency_count: u32,
    /// Seconds of flood.
    #[arg(long, default_value_t = 3)]
    flood_seconds: u64,
    /// Commands for the end-to-end measurement (sent at 50 Hz).
    #[arg(long, default_value_t = 300)]
    e2e_count: u32,
    /// Run only this part.
    #[arg(long, value_enum)]
    only: Option<Part>,
    /// Commands for the late-edge measurement (sent at 50 Hz, per run;
    /// 1..=10000, each with values of its own).
    #[arg(long, default_value_t = 300, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    late_count: u32,
    /// Burst lengths of the interfering thread in the late-edge
    /// measurement, microseconds (as `ppm-interfere --burst-us` takes them).
    #[arg(long, default_value = "100..500", value_name = "MIN..MAX",
          value_parser = |s: &str| ppm_tools::interfere::parse_range(s, "us"))]
    late_burst_us: (u64, u64),
    /// CPU for the pinned udp-ingress runs (SCHED_FIFO, and
    /// `ingress.busy_poll`); default: the first online CPU that is not
    /// ppmd's (`rt.cpu = "last"`). `none` leaves out these runs.
    #[arg(long, value_name = "CPU|none")]
    pin_cpu: Option<String>,
    /// Also draw the latency distributions measured as SVG files in DIR
    /// (created if missing): ingress.svg, flood.svg, e2e.svg and one
    /// histogram per end-to-end run, e2e-TIMING-HZhz.svg (and
    /// e2e-follow-MAVLink-HZhz.svg).
    #[arg(long, value_name = "DIR")]
    plot: Option<PathBuf>,
}

/// The parts of the benchmark, in the order they run.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum Part {
    /// 1. ingress latency against the paper's receiver.
    Ingress,
    /// 2. a flood of datagrams.
    Flood,
    /// 3. end to end, send to the line.
    E2e,
    /// 4. memory and CPU.
    Resources,
    /// 5. late edges: a held-up timing thread, with and without an
    ///    interfering thread.
    Late,
    /// 6. SBUS against PPM, follow timing, 50 to 300 Hz.
    Sbus,
    /// 7. the read-back: edge to published frame, CPU, switch flip to
    ///    `overridden` heard.
    Readback,
    /// 8. an ExpressLRS module: send to the frame at the module and on
    ///    the air, commands on the line, the module's margin.
    Module,
}

/// How udp-ingress receives in one run.
#[derive(Debug, Clone)]
struct Variant {
    /// Row label.
    label: String,
    /// Lines added to `[ingress]`.
    ingress: String,
}

impl Variant {
    /// The default: the receive thread sleeps in mio's poll.
    fn mio() -> Variant {
        Variant {
            label: "udp-ingress (mio)".into(),
            ingress: String::new(),
        }
    }

    /// Sleeping in mio's poll at SCHED_FIFO `priority`, pinned to `cpu`.
    fn fifo(priority: u8, cpu: usize) -> Variant {
        Variant {
            label: format!("udp-ingress (mio, FIFO {priority}, CPU {cpu})"),
            ingress: format!("priority = {priority}\ncpu = {cpu}\n"),
        }
    }

    /// Spinning on the socket, pinned to `cpu`.
    fn busy_poll(cpu: usize) -> Variant {
        Variant {
            label: format!("udp-ingress (busy_poll, CPU {cpu})"),
            ingress: format!("busy_poll = true\ncpu = {cpu}\n"),
        }
    }
}

/// SCHED_FIFO priority of the receive thread in the `fifo` runs: below
/// ppmd's (80 by default).
const INGRESS_FIFO_PRIORITY: u8 = 70;

/// The variants to measure: the default, and when there is a CPU besides
/// ppmd's, pinned to it at SCHED_FIFO and busy-polling on it.
fn variants(cli: &Cli) -> Result<Vec<Variant>> {
    let online = ppm_shared::sched::online_cpus();
    let pin_cpu = match cli.pin_cpu.as_deref() {
        Some("none") => None,
        Some(c) => Some(
            c.parse::<usize>()
                .context("--pin-cpu takes a CPU number or none")?,
        ),
        // ppmd's timing thread takes the last CPU (rt.cpu = "last").
        None if online.len() >= 2 => online.first().copied(),
        None => {
            println!("(one CPU only: no pinned runs, they need a CPU besides ppmd's)");
            None
        }
    };
    let mut v = vec![Variant::mio()];
    if let Some(cpu) = pin_cpu {
        v.push(Variant::fifo(INGRESS_FIFO_PRIORITY, cpu));
        v.push(Variant::busy_poll(cpu));
    }
    Ok(v)
}

/// A scratch directory and port with a config for one setup.
struct Setup {
    scratch: Scratch,
    bins: PathBuf,
}

impl std::ops::Deref for Setup {
    type Target = Scratch;

    fn deref(&self) -> &Scratch {
        &self.scratch
    }
}

impl Setup {
    /// A setup whose `[ingress]` section gets the lines `ingress` too.
    fn new(label: &str, ingress: &str) -> Result<Setup> {
        let scratch = Scratch::new(&format!("ppm-bench-{label}-{}", std::process::id()))?;
        let config = format!(
            "name = \"bench{label}\"\n[ingress]\nlisten = \"127.0.0.1:{}\"\nrecv_buffer_bytes = 1048576\n{ingress}[ipc]\nroot = \"{}\"\n[rt]\nallow_degraded = true\n",
            scratch.port,
            scratch.dir.join("ipc").display()
        );
        std::fs::write(scratch.dir.join("ppm.toml"), config)?;
        let bins = std::env::current_exe()?
            .parent()
            .context("binary directory")?
            .to_owned();
        Ok(Setup { scratch, bins })
    }

    /// Starts `bin` with this setup's config and `extra`, its stderr in
    /// `<bin>.log`, and waits until it has started.
    fn spawn(&self, bin: &str, extra: &[&str]) -> Result<Proc> {
        let mut cmd = Command::new(self.bins.join(bin));
        cmd.arg("--config")
            .arg(self.dir.join("ppm.toml"))
            .args(extra)
            .stdout(Stdio::null());
        let r = Proc::start(cmd, self.dir.join(format!("{bin}.log")))
            .with_context(|| format!("starting {} (build with `cargo build --release`)", bin))?;
        let needle = if bin == "ppmd" {
            "commands from"
        } else {
            "listening on"
        };
        if !r.log_shows(needle, Duration::from_secs(20)) {
            bail!("{bin} did not start: {}", std::fs::read_to_string(&r.log)?);
        }
        Ok(r)
    }

    /// Asks this setup's udp-ingress for its status.
    fn status(&self) -> Result<StatusReply> {
        let s = UdpSocket::bind("127.0.0.1:0")?;
        s.set_read_timeout(Some(Duration::from_secs(2)))?;
        s.send_to(
            &ppm_shared::protocol::padded_status_query(),
            ("127.0.0.1", self.port),
        )?;
        let mut buf = vec![0u8; 65536];
        let n = s
            .recv(&mut buf)
            .context("no status reply from udp-ingress")?;
        Ok(serde_json::from_slice(&buf[..n])?)
    }
}

/// Sends `n` datagrams at `hz`, `make(i)` each; returns the send times.
fn paced(port: u16, n: u32, hz: f64, mut make: impl FnMut(u32) -> Vec<u8>) -> Result<Vec<u64>> {
    let s = UdpSocket::bind("127.0.0.1:0")?;
    let period = 1e9 / hz;
    let start = now_ns();
    let mut sent = Vec::with_capacity(n as usize);
    for i in 0..n {
        let due = start + (i as f64 * period) as u64;
        loop {
            let left = due.saturating_sub(now_ns());
            if left == 0 {
                break;
            }
            if left > 200_000 {
                std::thread::sleep(Duration::from_nanos(left - 100_000));
            }
        }
        let bytes = make(i);
        sent.push(now_ns());
        s.send_to(&bytes, ("127.0.0.1", port))?;
    }
    Ok(sent)
}

fn us(v: f64) -> String {
    format!("{v:.1}")
}

/// The "DEGRADED" mark of a row whose program ran without some of its
/// real-time settings (it logged DEGRADED RUN).
fn degraded_mark(setup: &Setup, bin: &str) -> &'static str {
    let log = std::fs::read_to_string(setup.dir.join(format!("{bin}.log"))).unwrap_or_default();
    if log.contains("DEGRADED RUN") {
        " DEGRADED"
    } else {
        ""
    }
}

/// Latency of one udp-ingress variant under the latency traffic, written
/// as `wire` says: the row label and its status reply.
fn ingress_run(cli: &Cli, v: &Variant, wire: Wire) -> Result<(String, StatusReply)> {
    let setup = Setup::new("lat", &v.ingress)?;
    let ingress = setup.spawn("udp-ingress", &[])?;
    paced(setup.port, cli.latency_count, 1000.0, |i| {
        command_bytes(wire, i, &[1000 + i % 1000, 1500, 1000, 1500])
    })?;
    std::thread::sleep(Duration::from_millis(200));
    let st = setup.status()?;
    ingress.terminate();
    Ok((
        format!("{}{}", v.label, degraded_mark(&setup, "udp-ingress")),
        st,
    ))
}

fn ingress_latency(cli: &Cli, variants: &[Variant], plots: &mut Plots) -> Result<()> {
    println!(
        "== 1. ingress: kernel receive to command handed over ({} datagrams at 1 kHz)",
        cli.latency_count
    );
    let mut ours = Vec::new();
    for v in variants {
        ours.push(ingress_run(cli, v, Wire::Json)?);
    }
    // The same commands as MAVLink 2 RC_CHANNELS_OVERRIDE, the default way.
    let (label, st) = ingress_run(cli, &variants[0], Wire::Mavlink)?;
    ours.push((format!("{label}, MAVLink"), st));

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("bench/seed_receiver.py");
    let port = UdpSocket::bind("127.0.0.1:0")?.local_addr()?.port();
    let mut py = Command::new("python3")
        .arg(&script)
        .arg(port.to_string())
        .args(["--count", &cli.latency_count.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .context("starting python3 (the baseline needs it)")?;
    let mut out = BufReader::new(py.stdout.take().context("python stdout")?);
    let mut line = String::new();
    out.read_line(&mut line)?;
    if line.trim() != "ready" {
        bail!("the Python baseline did not start: {line}");
    }
    paced(port, cli.latency_count, 1000.0, |i| {
        format!("[{}, 1500, 1000, 1500]", 1000 + i % 1000).into_bytes()
    })?;
    let waiter = std::thread::spawn(move || -> Result<Value> {
        let mut l = String::new();
        out.read_line(&mut l)?;
        Ok(serde_json::from_str(&l)?)
    });
    let end = Instant::now() + Duration::from_secs(10);
    while !waiter.is_finished() && Instant::now() < end {
        std::thread::sleep(Duration::from_millis(20));
    }
    if !waiter.is_finished() {
        // Datagrams lost in the socket: stop it and take what it measured.
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(py.id() as i32),
            nix::sys::signal::Signal::SIGTERM,
        );
    }
    let base = waiter
        .join()
        .map_err(|_| anyhow::anyhow!("python reader"))??;
    let _ = py.wait();

    let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
    let count = |v: &Value| v.as_u64().map_or("?".to_string(), |n| n.to_string());
    println!(
        "{:<44} {:>8} {:>10} {:>10} {:>10} {:>10}",
        "receiver", "count", "superseded", "p50 us", "p99 us", "max us"
    );
    for (label, st) in &ours {
        let l = &st.publish_latency_us;
        println!(
            "{:<44} {:>8} {:>10} {:>10} {:>10} {:>10}",
            label,
            l.count,
            st.datagrams.superseded,
            us(l.p50),
            us(l.p99),
            us(l.max)
        );
    }
    println!(
        "{:<44} {:>8} {:>10} {:>10} {:>10} {:>10}",
        "seed-style Python (blocking, pipe)",
        count(&base["count"]),
        "-",
        us(f(&base["p50_us"])),
        us(f(&base["p99_us"])),
        us(f(&base["max_us"]))
    );
    let superseded: u64 = ours.iter().map(|(_, st)| st.datagrams.superseded).sum();
    if superseded > 0 {
        println!(
            "(superseded: commands replaced by a newer one before being handed over; their latency is not in the figures)"
        );
    }
    let points = |p50: f64, p99: f64, max: f64| vec![(0.5, p50), (0.99, p99), (1.0, max)];
    for (label, st) in &ours {
        let l = &st.publish_latency_us;
        plots
            .ingress
            .push((label.clone(), l.count, points(l.p50, l.p99, l.max)));
    }
    plots.ingress.push((
        "seed-style Python (blocking, pipe)".into(),
        base["count"].as_u64().unwrap_or(0),
        points(f(&base["p50_us"]), f(&base["p99_us"]), f(&base["max_us"])),
    ));
    for (label, st) in &ours {
        let l = &st.publish_latency_us;
        println!(
            "ratio Python / {label}: p50 {:.1}x, p99 {:.1}x, max {:.1}x",
            f(&base["p50_us"]) / l.p50,
            f(&base["p99_us"]) / l.p99,
            f(&base["max_us"]) / l.max
        );
    }
    let (j, m) = (
        &ours[0].1.publish_latency_us,
        &ours[ours.len() - 1].1.publish_latency_us,
    );
    println!(
        "ratio MAVLink / JSON, {}: p50 {:.2}x, p99 {:.2}x, max {:.2}x",
        ours[0].0,
        m.p50 / j.p50,
        m.p99 / j.p99,
        m.max / j.max
    );
    Ok(())
}

/// The frame records of a frame log, in order (a last row ppmd is still
/// writing left out).
fn frame_records(log: &Path) -> Result<Vec<FrameRow>> {
    Ok(framelog::read_frames(log)?)
}

/// Ages (ns) of the command at each frame start, from a frame log.
fn frame_ages(log: &Path, from_ns: u64, to_ns: u64) -> Result<Vec<f64>> {
    Ok(frame_records(log)?
        .iter()
        .filter_map(|r| Some((r.mono_ns, r.recv_mono_ns?)))
        .filter(|(t, _)| (from_ns..=to_ns).contains(t))
        .map(|(t, recv)| t.saturating_sub(recv) as f64)
        .collect())
}

/// Start of the first frame in the frame log at or after `from_ns` whose
/// first channels are `want` (us).
fn first_frame_with(log: &Path, from_ns: u64, want: &[f64]) -> Result<Option<u64>> {
    Ok(frame_records(log)?
        .iter()
        .filter(|r| r.ch_us.starts_with(want))
        .map(|r| r.mono_ns)
        .find(|&t| t >= from_ns))
}

fn flood(cli: &Cli, variants: &[Variant], plots: &mut Plots) -> Result<()> {
    println!(
        "== 2. flood: one sender as fast as it can for {} s, changing values",
        cli.flood_seconds
    );
    for v in variants {
        flood_run(cli, v, plots)?;
    }
    Ok(())
}

fn flood_run(cli: &Cli, v: &Variant, plots: &mut Plots) -> Result<()> {
    let setup = Setup::new("flood", &v.ingress)?;
    let log = setup.dir.join("frames.jsonl");
    let ppmd = setup.spawn(
        "ppmd",
        &[
            "--output",
            "sim:/dev/null",
            "--frame-log",
            log.to_str().unwrap(),
        ],
    )?;
    let ingress = setup.spawn("udp-ingress", &[])?;
    // Two calm seconds first: the reference for ppmd's timing.
    paced(setup.port, 100, 50.0, |i| {
        format!("[{}]", 1000 + i).into_bytes()
    })?;
    let calm = setup.status()?;
    let rss_before = ingress.try_rss_kib().unwrap_or(0);
    let received_before = calm.datagrams.received;
    let stop = Arc::new(AtomicBool::new(false));
    let sent = Arc::new(AtomicU64::new(0));
    let flood_start = now_ns();
    let sender = {
        let (stop, sent, port) = (stop.clone(), sent.clone(), setup.port);
        std::thread::spawn(move || -> Result<()> {
            let s = UdpSocket::bind("127.0.0.1:0")?;
            let mut i = 0u64;
            let mut buf = String::new();
            while !stop.load(Relaxed) {
                buf.clear();
                use std::fmt::Write;
                let _ = write!(buf, "[{}, {}]", 1000 + i % 1000, 1000 + (i / 1000) % 1000);
                if s.send_to(buf.as_bytes(), ("127.0.0.1", port)).is_ok() {
                    i += 1;
                }
            }
            sent.store(i, Relaxed);
            Ok(())
        })
    };
    std::thread::sleep(Duration::from_secs(cli.flood_seconds));
    stop.store(true, Relaxed);
    sender.join().map_err(|_| anyhow::anyhow!("sender"))??;
    let flood_end = now_ns();
    // After the flood the sender goes calm at 50 Hz, as a groundstation does
    // (a single datagram could meet a receive buffer still full and be
    // dropped by the kernel): how soon is the calm command on the line?
    let calm_sent = paced(setup.port, 20, 50.0, |_| b"[1777, 1333]".to_vec())?;
    std::thread::sleep(Duration::from_millis(100));
    let after = setup.status()?;
    let rss_after = ingress.try_rss_kib().unwrap_or(0);
    println!("-- {}{}", v.label, degraded_mark(&setup, "udp-ingress"));
    let secs = (flood_end - flood_start) as f64 / 1e9;
    let received =
        (after.datagrams.received - received_before).saturating_sub(calm_sent.len() as u64);
    let sent = sent.load(Relaxed);
    let mut ages = frame_ages(&log, flood_start + 50_000_000, flood_end)?;
    plots
        .flood
        .push((v.label.clone(), plot::histogram_of(&ages)));
    let age = Percentiles::of(&mut ages);
    println!(
        "sent {sent} ({:.0}/s), drained by udp-ingress {received} ({:.0}/s), lost in the socket {} ({:.1}%)",
        sent as f64 / secs,
        received as f64 / secs,
        sent.saturating_sub(received),
        sent.saturating_sub(received) as f64 * 100.0 / sent.max(1) as f64
    );
    println!(
        "newest command's age at ppmd's frame starts during the flood, us: {} ({} frames)",
        age.line(1_000.0),
        age.count
    );
    match first_frame_with(&log, calm_sent[0], &[1777.0, 1333.0])? {
        Some(t) => println!(
            "the calm command after the flood was on the line {:.1} ms after it was first sent",
            (t - calm_sent[0]) as f64 / 1e6
        ),
        None => println!("the calm command after the flood never reached the line"),
    }
    println!("udp-ingress memory: {rss_before} KiB before, {rss_after} KiB after");
    let edge_error = |st: &StatusReply| st.ppmd.as_ref().map(|p| p.edge_error_us);
    // As JSON writes them (`null` without a snapshot), as this line always had them.
    let json = |v: Option<f64>| serde_json::to_string(&v).unwrap_or_default();
    println!(
        "ppmd edge error p99 since start: {} us before the flood, {} us after it (max {} us)",
        json(edge_error(&calm).map(|e| e.p99)),
        json(edge_error(&after).map(|e| e.p99)),
        edge_error(&after).map_or(f64::NAN, |e| e.max)
    );
    ingress.terminate();
    ppmd.terminate();
    Ok(())
}

/// One end-to-end run: what the line carried of the commands sent.
struct E2e {
    /// Send to the first edge of the first frame carrying each command, ns.
    latency: Percentiles,
    sent: usize,
    /// Commands no frame carried (replaced by a newer one first).
    missed: usize,
    /// Of those, replaced in udp-ingress (two in one wake-up).
    ingress_superseded: u64,
    /// Frames sent, and those that carried an older command than the newest
    /// one sent at least 1 ms before the frame started.
    frames: usize,
    stale_frames: usize,
    /// The latencies, ns.
    hist: Histogram<u64>,
}

/// How the end-to-end commands are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wire {
    /// JSON, a bare array: `[a, b]`.
    Json,
    /// MAVLink 2 RC_CHANNELS_OVERRIDE: chan1 = a, chan2 = b, the others
    /// released (0) to their defaults, as the JSON array leaves them.
    Mavlink,
}

/// Command `values` (the first channels, us) written as `wire` says; `i`
/// numbers MAVLink frames.
fn command_bytes(wire: Wire, i: u32, values: &[u32]) -> Vec<u8> {
    match wire {
        Wire::Json => {
            let v: Vec<String> = values.iter().map(|v| v.to_string()).collect();
            format!("[{}]", v.join(", ")).into_bytes()
        }
        Wire::Mavlink => {
            let mut chan = [0u16; 18];
            for (c, &v) in chan.iter_mut().zip(values) {
                *c = v as u16;
            }
            let (spec, payload) =
                ppm_shared::mavlink::Message::RcOverride(ppm_shared::mavlink::RcOverride {
                    target_system: 1,
                    target_component: 1,
                    chan,
                })
                .encode();
            ppm_shared::mavlink::frame(2, (i as u8, 255, 190), spec, &payload)
        }
    }
}

/// Sends `count` commands at `hz`, written as `wire` says, to udp-ingress
/// and a ppmd in `timing`, and reads the line's trace back.
fn e2e_run(timing: &str, wire: Wire, hz: f64, count: u32) -> Result<E2e> {
    let setup = Setup::new(&format!("e2e-{timing}-{wire:?}-{hz}"), "")?;
    let trace = setup.dir.join("line.trace");
    let ppmd = setup.spawn(
        "ppmd",
        &[
            "--output",
            &format!("sim:{}", trace.display()),
            "--timing",
            timing,
        ],
    )?;
    let ingress = setup.spawn("udp-ingress", &[])?;
    let code = |i: u32| [1000 + i % 1000, 1000 + (i / 1000) % 1000];
    let sent = paced(setup.port, count, hz, |i| command_bytes(wire, i, &code(i)))?;
    std::thread::sleep(Duration::from_millis(100));
    let status = setup.status()?;
    ingress.terminate();
    ppmd.terminate();
    let f = std::fs::File::open(&trace)?;
    let t = ppm_shared::trace::Trace::read(BufReader::new(f))?;
    // Every emitted frame: when its first edge was written, and which
    // command it carries (decoded from the scheduled edges, which are exact).
    let written: std::collections::HashMap<u64, u64> = t
        .edges
        .iter()
        .map(|e| (e.scheduled_ns, e.actual_ns))
        .collect();
    let frames: Vec<(u64, u32)> = t
        .decode(false)
        .iter()
        // A frame aborted at a late edge before its second channel carries
        // no command.
        .filter(|f| f.channels_us().len() >= 2)
        .map(|f| {
            let c = f.channels_us();
            let start = written.get(&f.start_ns).copied().unwrap_or(f.start_ns);
            (start, ((c[1] - 1000) * 1000 + (c[0] - 1000)) as u32)
        })
        .collect();
    let mut latency = Vec::new();
    for (i, &s) in sent.iter().enumerate() {
        if let Some(&(start, _)) = frames.iter().find(|&&(_, c)| c == i as u32) {
            latency.push(start.saturating_sub(s) as f64);
        }
    }
    let stale_frames = frames
        .iter()
        .filter(|&&(start, carried)| {
            sent.iter()
                .rposition(|&s| s + 1_000_000 <= start)
                .is_some_and(|newest| (carried as usize) < newest)
        })
        .count();
    Ok(E2e {
        ingress_superseded: status.datagrams.superseded,
        missed: sent.len() - latency.len(),
        hist: plot::histogram_of(&latency),
        latency: Percentiles::of(&mut latency),
        sent: sent.len(),
        frames: frames.len(),
        stale_frames,
    })
}

fn e2e(cli: &Cli, plots: &mut Plots) -> Result<()> {
    println!(
        "== 3. end to end: send to the first edge of the first frame carrying each command, grid and follow timing, JSON and (follow) MAVLink RC_CHANNELS_OVERRIDE ({} commands at 50 Hz, {} at 100 Hz)",
        cli.e2e_count,
        cli.e2e_count * 2
    );
    println!(
        "{:<15} {:>5} {:>6} {:>8} {:>10} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "timing, wire",
        "Hz",
        "sent",
        "on line",
        "missed",
        "p50 ms",
        "p90 ms",
        "p99 ms",
        "max ms",
        "stale"
    );
    for hz in [50.0, 100.0] {
        let count = cli.e2e_count * (hz / 50.0) as u32;
        let mut rows = Vec::new();
        for (timing, wire) in [
            ("grid", Wire::Json),
            ("follow", Wire::Json),
            ("follow", Wire::Mavlink),
        ] {
            let r = e2e_run(timing, wire, hz, count)?;
            let label = match wire {
                Wire::Json => timing.to_string(),
                Wire::Mavlink => format!("{timing}, MAVLink"),
            };
            plots
                .e2e
                .push((format!("{label}, {hz} Hz"), r.hist.clone()));
            let l = &r.latency;
            println!(
                "{label:<15} {hz:>5} {:>6} {:>8} {:>10} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8}",
                r.sent,
                l.count,
                format!("{} ({})", r.missed, r.ingress_superseded),
                l.p50 / 1e6,
                l.p90 / 1e6,
                l.p99 / 1e6,
                l.max / 1e6,
                format!("{}/{}", r.stale_frames, r.frames),
            );
            rows.push(r);
        }
        let (g, f) = (&rows[0].latency, &rows[1].latency);
        println!(
            "  at {hz} Hz, grid / follow: p50 {:.1}x, p90 {:.1}x, p99 {:.1}x, max {:.1}x; on the line {:.1}% (grid) and {:.1}% (follow) of the commands",
            g.p50 / f.p50.max(1.0),
            g.p90 / f.p90.max(1.0),
            g.p99 / f.p99.max(1.0),
            g.max / f.max.max(1.0),
            g.count as f64 * 100.0 / rows[0].sent.max(1) as f64,
            f.count as f64 * 100.0 / rows[1].sent.max(1) as f64,
        );
        let m = &rows[2].latency;
        println!(
            "  at {hz} Hz, follow, MAVLink / JSON: p50 {:.2}x, p99 {:.2}x; on the line {:.1}% (MAVLink)",
            m.p50 / f.p50.max(1.0),
            m.p99 / f.p99.max(1.0),
            m.count as f64 * 100.0 / rows[2].sent.max(1) as f64,
        );
    }
    println!(
        "(missed: replaced by a newer command before any frame carried it, in brackets those replaced in udp-ingress; stale: frames carrying an older command than the newest one sent at least 1 ms before the frame started, of all frames)"
    );
    Ok(())
}

fn resources() -> Result<()> {
    println!("== 4. memory and CPU (3 s idle, then 3 s at 50 Hz), grid and follow timing");
    for timing in ["grid", "follow"] {
        let setup = Setup::new(&format!("res-{timing}"), "")?;
        let ppmd = setup.spawn("ppmd", &["--output", "sim:/dev/null", "--timing", timing])?;
        let ingress = setup.spawn("udp-ingress", &[])?;
        let measure = |label: &str, traffic: bool| -> Result<()> {
            let (c0p, c0i, t0) = (ppmd.cpu_s(), ingress.cpu_s(), Instant::now());
            if traffic {
                paced(setup.port, 150, 50.0, |i| {
                    format!("[{}]", 1000 + i).into_bytes()
                })?;
            } else {
                std::thread::sleep(Duration::from_secs(3));
            }
            let wall = t0.elapsed().as_secs_f64();
            println!(
                "{timing:<7} {label:<6} ppmd: {:5.1}% CPU, {:6} KiB RSS   udp-ingress: {:5.1}% CPU, {:6} KiB RSS",
                (ppmd.cpu_s() - c0p) * 100.0 / wall,
                ppmd.try_rss_kib().unwrap_or(0),
                (ingress.cpu_s() - c0i) * 100.0 / wall,
                ingress.try_rss_kib().unwrap_or(0)
            );
            Ok(())
        };
        measure("idle", false)?;
        measure("50 Hz", true)?;
        ingress.terminate();
        ppmd.terminate();
    }
    Ok(())
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let runs = |p: Part| cli.only.is_none_or(|o| o == p);
    if let Some(dir) = &cli.plot {
        plot_dir(dir)?;
    }
    println!(
        "ppm-bench: the real binaries on loopback ({} CPUs)",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let variants = variants(&cli)?;
    let mut plots = Plots::default();
    if runs(Part::Ingress) {
        ingress_latency(&cli, &variants, &mut plots)?;
    }
    if runs(Part::Flood) {
        flood(&cli, &variants, &mut plots)?;
    }
    if runs(Part::E2e) {
        e2e(&cli, &mut plots)?;
    }
    if runs(Part::Resources) {
        resources()?;
    }
    if runs(Part::Late) {
        late::late(&cli)?;
    }
    if runs(Part::Sbus) {
        sbus::sbus(cli.e2e_count)?;
    }
    if runs(Part::Readback) {
        readback::readback()?;
    }
    if runs(Part::Module) {
        module::module()?;
    }
    if let Some(dir) = &cli.plot {
        write_plots(dir, &plots)?;
    }
    Ok(())
}
