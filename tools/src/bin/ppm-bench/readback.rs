//! Part 7, the read-back (`ppmd.readback`), with the real ppmd and
//! udp-ingress, the simulated line, and a simulated radio played by the
//! bench: it follows ppm's line trace as it grows, decodes it as EdgeTX's
//! trainer input does, and transmits its own PPM frames (8 channels, 300 us
//! pulses, one every 22.5 ms: 44 Hz) into the read-back trace, each edge
//! written once its time has passed (as `tests/tests/readback.rs`'s radio
//! does): ppm's channels while the trainer switch is on, the instructor's
//! sticks when it is flipped. Commands go at 50 Hz from one UDP socket,
//! which also hears the `{"event":"readback"}` datagrams. Measured:
//!
//! 1. edge to published frame: from each frame's closing edge
//!    (`end_mono_ns` in the read-back log, the radio trace's time of the
//!    edge that ends its sync) to ppmd publishing the sample that carries
//!    it (`published_mono_ns`) and to a subscriber of `ppm/NAME/readback`
//!    in the bench seeing it; also from the edge the decoder hands the
//!    frame on at (the end of the pulse the closing edge begins) as the
//!    bench wrote it, to published: ppmd's own share;
//! 2. CPU: the `ppmd-readback` thread's share of one CPU over 10 s at 50 Hz
//!    commands and the radio at 44 Hz, and ppmd's and udp-ingress's
//!    totals with and without `ppmd.readback` (the radio runs in both);
//! 3. switch flip to the sender hearing `overridden` (and flip back to
//!    `following`) over 20 flips, and every event that was not one of the
//!    expected changes (a relaying radio must never be `overridden`).

use super::Setup;
use anyhow::{bail, Context, Result};
use ppm_shared::ipc::{self, ReadbackSample};
use ppm_shared::receiver::{Receiver, ReceiverDecoder};
use ppm_shared::signal::Level;
use ppm_shared::time::now_ns;
use ppm_tools::analysis::Percentiles;
use serde_json::Value;
use std::collections::HashMap;
use std::io::Write;
use std::net::UdpSocket;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::SeqCst};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// The radio's frame period and pulse, ns.
const RADIO_FRAME_NS: u64 = 22_500_000;
const RADIO_PULSE_NS: u64 = ppm_tools::radio::PULSE_NS;
/// The radio's channel count (ppm sends 4; the radio sends 8).
const RADIO_CHANNELS: usize = 8;
/// What the instructor's sticks send on the first four channels.
const INSTRUCTOR_US: [u64; 4] = [1_600, 1_450, 1_100, 1_550];
/// Command rate, Hz.
const COMMAND_HZ: f64 = 50.0;
/// Seconds of the CPU measurement.
const CPU_SECONDS: u64 = 10;
/// Switch flips (each one over and one back).
const FLIPS: usize = 20;
/// How often the bench's subscriber looks for a new sample.
const WATCH_POLL: Duration = Duration::from_micros(100);

/// Command `i`: the first channel sweeps 1300..1498 us in 2 us steps (the
/// instructor's 1600 is far from all of them), the others hold.
fn command(i: u64) -> Vec<u8> {
    format!("[{}, 1700, 1000, 1200]", 1300 + 2 * (i % 100)).into_bytes()
}

/// What the radio controls share with the bench.
#[derive(Default)]
struct RadioCtl {
    /// The trainer switch: the instructor flies.
    instructor: AtomicBool,
    /// Start of the radio's first frame from the newest switch position.
    flipped_at: AtomicU64,
    stop: AtomicBool,
}

/// The radio: relays the trainer channels it reads from ppm's `line`
/// until `ctl.instructor` is set, then sends the instructor's sticks, into
/// the trace `out`; returns, when `ctl.stop` is set, each edge's time and
/// when it was written.
fn radio(line: &Path, out: &Path, ctl: &RadioCtl) -> Result<Vec<(u64, u64)>> {
    let mut follow = ppm_tools::radio::Follow::new(line);
    let mut trainer = ReceiverDecoder::new(Receiver::EdgeTx, Level::High);
    let mut values: Option<Vec<u64>> = None;
    let mut file = std::fs::File::create(out).context("creating the radio's trace")?;
    file.write_all(b"# idle_level 0\n")?;
    let mut next = now_ns();
    let mut pending: std::collections::VecDeque<(u64, u8)> = Default::default();
    let mut was_instructor = false;
    let mut written = Vec::new();
    let mut due = Vec::new();
    while !ctl.stop.load(SeqCst) {
        for (t, level) in follow.edges()? {
            if let Some(f) = trainer.push(t, level) {
                if f.complete && f.channels_us().len() == 4 {
                    values = Some(f.channels_us());
                }
            }
        }
        let now = now_ns();
        let mut text = String::new();
        due.clear();
        while pending.front().is_some_and(|(t, _)| *t <= now) {
            let (t, level) = pending.pop_front().expect("an edge");
            text.push_str(&format!("{t} {t} {level}\n"));
            due.push(t);
        }
        if !text.is_empty() {
            file.write_all(text.as_bytes())?;
            file.flush()?;
            let at = now_ns();
            written.extend(due.iter().map(|&t| (t, at)));
        }
        if now < next {
            std::thread::sleep(Duration::from_nanos((next - now).min(500_000)));
            continue;
        }
        // A frame starts now. The radio is switched on once ppm's line
        // carries commands.
        let start = next;
        next += RADIO_FRAME_NS;
        let Some(v) = &values else { continue };
        let inst = ctl.instructor.load(SeqCst);
        if inst != was_instructor {
            // The switch flipped during the frame before: this frame is
            // the first to carry the new source.
            was_instructor = inst;
            ctl.flipped_at.store(start, SeqCst);
        }
        let mut us = vec![1_500; RADIO_CHANNELS];
        us[..4].copy_from_slice(if inst { &INSTRUCTOR_US[..] } else { &v[..] });
        pending.extend(ppm_tools::radio::frame_edges(start, &us));
    }
    Ok(written)
}

/// A new sample the bench's subscriber saw.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Seen {
    /// The sample's `frames`: the number of the newest frame read.
    frame: u64,
    published_ns: u64,
    seen_ns: u64,
}

/// Subscribes to output `name`'s read-back under `root` and notes every
/// sample carrying a new frame, looking every [`WATCH_POLL`], until
/// `stop`; returns them and the newest sample.
fn watch(root: &Path, name: &str, stop: &AtomicBool) -> Result<(Vec<Seen>, ReadbackSample)> {
    let node = ipc::create_node(root, "ppm-bench-readback")?;
    let service = ipc::open_readback_service(&node, name)?;
    let sub = service
        .subscriber_builder()
        .buffer_size(1)
        .create()
        .map_err(|e| ipc::IpcError::new("creating the read-back subscriber", e))?;
    let (mut seen, mut newest) = (Vec::new(), ReadbackSample::default());
    while !stop.load(SeqCst) {
        while let Some(s) = sub
            .receive()
            .map_err(|e| ipc::IpcError::new("receiving a read-back sample", e))?
        {
            let at = now_ns();
            let p = *s.payload();
            if p.frames != newest.frames {
                seen.push(Seen {
                    frame: p.frames,
                    published_ns: p.published_mono_ns,
                    seen_ns: at,
                });
            }
            newest = p;
        }
        std::thread::sleep(WATCH_POLL);
    }
    Ok((seen, newest))
}

/// An event the sender heard: `(from, to)` and when.
type Heard = (String, String, u64);

/// Sends [`command`]s at [`COMMAND_HZ`] to `port` from one socket until
/// `stop`, passing every `{"event":"readback"}` datagram it receives on
/// to `tx` with the time it was received.
fn sender(port: u16, stop: &AtomicBool, tx: mpsc::Sender<Heard>) -> Result<u64> {
    let s = UdpSocket::bind("127.0.0.1:0")?;
    let period = (1e9 / COMMAND_HZ) as u64;
    let mut due = now_ns();
    let mut i = 0u64;
    let mut buf = [0u8; 4096];
    while !stop.load(SeqCst) {
        let now = now_ns();
        if now >= due {
            s.send_to(&command(i), ("127.0.0.1", port))?;
            i += 1;
            due += period;
        }
        let left = due.saturating_sub(now_ns()).max(100_000);
        s.set_read_timeout(Some(Duration::from_nanos(left)))?;
        if let Ok((n, _)) = s.recv_from(&mut buf) {
            let at = now_ns();
            let Ok(v) = serde_json::from_slice::<Value>(&buf[..n]) else {
                continue;
            };
            if v["event"] == "readback" {
                let name = |k: &str| v[k].as_str().unwrap_or("?").to_string();
                let _ = tx.send((name("from"), name("state"), at));
            }
        }
    }
    Ok(i)
}

/// utime + stime of a `/proc/PID/stat` or `/proc/PID/task/TID/stat`
/// line, clock ticks.
fn stat_ticks(stat: &str) -> Option<u64> {
    // After the command's closing bracket: field 3 (the state) first, so
    // fields 14 (utime) and 15 (stime) are the 12th and 13th.
    let f: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    Some(f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?)
}

/// Time on a CPU of a `/proc/.../schedstat` line, ns.
fn schedstat_ns(s: &str) -> Option<u64> {
    s.split_whitespace().next()?.parse().ok()
}

/// The id of process `pid`'s thread named `comm`.
fn find_thread(pid: u32, comm: &str) -> Option<u32> {
    std::fs::read_dir(format!("/proc/{pid}/task"))
        .ok()?
        .filter_map(|e| e.ok())
        .find(|e| {
            std::fs::read_to_string(e.path().join("comm")).is_ok_and(|c| c.trim_end() == comm)
        })?
        .file_name()
        .to_str()?
        .parse()
        .ok()
}

/// CPU time of all of process `pid`'s threads: (utime + stime from its
/// stat, s; the sum of its threads' schedstat, s, if the kernel has it).
fn process_cpu_s(pid: u32) -> (f64, Option<f64>) {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|s| stat_ticks(&s))
        .unwrap_or(0) as f64
        / clock_ticks();
    let sched = (|| {
        let mut ns = 0;
        for e in std::fs::read_dir(format!("/proc/{pid}/task")).ok()? {
            let s = std::fs::read_to_string(e.ok()?.path().join("schedstat")).ok()?;
            ns += schedstat_ns(&s)?;
        }
        Some(ns as f64 / 1e9)
    })();
    (stat, sched)
}

/// Time on a CPU of each of process `pid`'s threads, by name, from their
/// schedstat, ns (empty without schedstat).
fn threads_sched_ns(pid: u32) -> HashMap<String, u64> {
    let mut out = HashMap::new();
    let Ok(dir) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return out;
    };
    for e in dir.filter_map(|e| e.ok()) {
        let read = |f: &str| std::fs::read_to_string(e.path().join(f)).ok();
        if let (Some(comm), Some(ns)) = (read("comm"), read("schedstat")) {
            if let Some(ns) = schedstat_ns(&ns) {
                *out.entry(comm.trim_end().to_string()).or_insert(0) += ns;
            }
        }
    }
    out
}

/// Each thread's share of one CPU, %, from `before` to `after`
/// ([`threads_sched_ns`]) over `wall` seconds, largest first.
fn thread_shares(
    before: &HashMap<String, u64>,
    after: &HashMap<String, u64>,
    wall: f64,
) -> Vec<(String, f64)> {
    let mut v: Vec<(String, f64)> = after
        .iter()
        .map(|(name, &ns)| {
            let d = ns.saturating_sub(before.get(name).copied().unwrap_or(0));
            (name.clone(), d as f64 / 1e9 * 100.0 / wall)
        })
        .collect();
    v.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    v
}

/// Clock ticks per second (`/proc`'s unit of utime and stime).
fn clock_ticks() -> f64 {
    nix::unistd::sysconf(nix::unistd::SysconfVar::CLK_TCK)
        .ok()
        .flatten()
        .unwrap_or(100) as f64
}

/// CPU time of thread `tid` of `pid`: (from stat's ticks, s; from
/// schedstat, s, if the kernel has it).
fn thread_cpu_s(pid: u32, tid: u32) -> (f64, Option<f64>) {
    let ticks = clock_ticks();
    let read = |f: &str| std::fs::read_to_string(format!("/proc/{pid}/task/{tid}/{f}"));
    let stat = read("stat").ok().and_then(|s| stat_ticks(&s)).unwrap_or(0) as f64 / ticks;
    let sched = read("schedstat")
        .ok()
        .and_then(|s| schedstat_ns(&s))
        .map(|ns| ns as f64 / 1e9);
    (stat, sched)
}

/// A frame read, from the read-back log.
#[derive(Debug, Clone, PartialEq)]
struct ReadRow {
    frame: u64,
    end_ns: u64,
    ch_us: Vec<f64>,
    matched: bool,
    max_diff_us: Option<f64>,
    state: String,
}

fn read_rows(log: &Path) -> Vec<ReadRow> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|r| r["type"] == "read")
        .filter_map(|r| {
            Some(ReadRow {
                frame: r["frame"].as_u64()?,
                end_ns: r["end_mono_ns"].as_u64()?,
                ch_us: r["ch_us"]
                    .as_array()?
                    .iter()
                    .filter_map(Value::as_f64)
                    .collect(),
                matched: r["match"] == true,
                max_diff_us: r["max_diff_us"].as_f64(),
                state: r["state"].as_str().unwrap_or("").to_string(),
            })
        })
        .collect()
}

/// Edge to published frame, ns, for each frame the subscriber saw.
#[derive(Debug, Default)]
struct EdgeLatency {
    /// Closing edge (`end_mono_ns`) to `published_mono_ns`.
    published: Vec<f64>,
    /// Closing edge to the subscriber seeing the sample.
    seen: Vec<f64>,
    /// The handing-on edge (closing edge + the pulse) as written by the
    /// bench, to `published_mono_ns`.
    written_to_published: Vec<f64>,
}

/// Joins the frames read (`rows`) with the samples seen, by frame number;
/// `written` maps an edge's time to when the bench wrote it.
fn edge_latency(rows: &[ReadRow], seen: &[Seen], written: &HashMap<u64, u64>) -> EdgeLatency {
    let ends: HashMap<u64, u64> = rows.iter().map(|r| (r.frame, r.end_ns)).collect();
    let mut out = EdgeLatency::default();
    for s in seen {
        let Some(&end) = ends.get(&s.frame) else {
            continue;
        };
        out.published
            .push(s.published_ns.saturating_sub(end) as f64);
        out.seen.push(s.seen_ns.saturating_sub(end) as f64);
        if let Some(&w) = written.get(&(end + RADIO_PULSE_NS)) {
            out.written_to_published
                .push(s.published_ns.saturating_sub(w) as f64);
        }
    }
    out
}

/// Whether a frame read carries the instructor's sticks.
fn is_instructor(ch_us: &[f64]) -> bool {
    ch_us.len() >= 4 && ch_us.iter().zip(INSTRUCTOR_US).all(|(&a, b)| a == b as f64)
}

/// Relayed frames (not the instructor's) read once the state was first
/// `following`, and of those the ones that did not match ppm's values.
fn relayed_mismatches(rows: &[ReadRow]) -> (usize, Vec<&ReadRow>) {
    let from = rows
        .iter()
        .position(|r| r.state == "following")
        .unwrap_or(rows.len());
    let relayed: Vec<&ReadRow> = rows[from..]
        .iter()
        .filter(|r| !is_instructor(&r.ch_us))
        .collect();
    let bad = relayed.iter().copied().filter(|r| !r.matched).collect();
    (relayed.len(), bad)
}

/// A CPU share, % of one CPU: from stat's ticks, and from schedstat.
type Share = (f64, Option<f64>);

/// CPU shares over one measurement.
#[derive(Debug, Default)]
struct Cpu {
    ppmd: Share,
    ingress: Share,
    /// The read-back thread.
    thread: Option<Share>,
    /// ppmd's threads by name, from schedstat, largest first.
    ppmd_threads: Vec<(String, f64)>,
}

/// Measures CPU shares of `ppmd`, `ingress` and (if `tid`) ppmd's thread
/// `tid` over [`CPU_SECONDS`]; every event heard meanwhile is returned.
fn measure_cpu(
    ppmd: &ppm_tools::harness::Proc,
    ingress: &ppm_tools::harness::Proc,
    tid: Option<u32>,
    events: &mpsc::Receiver<Heard>,
) -> (Cpu, Vec<Heard>) {
    let pid = ppmd.pid();
    let whole = |p: &ppm_tools::harness::Proc| process_cpu_s(p.pid());
    let threads0 = threads_sched_ns(pid);
    let (p0, i0, th0, t0) = (
        whole(ppmd),
        whole(ingress),
        tid.map(|t| thread_cpu_s(pid, t)),
        Instant::now(),
    );
    let mut heard = Vec::new();
    let end = t0 + Duration::from_secs(CPU_SECONDS);
    while let Some(left) = end.checked_duration_since(Instant::now()) {
        if let Ok(e) = events.recv_timeout(left) {
            heard.push(e);
        }
    }
    let wall = t0.elapsed().as_secs_f64();
    let pct = |a: f64, b: f64| (b - a) * 100.0 / wall;
    let share = |(s0, q0): (f64, Option<f64>), (s1, q1): (f64, Option<f64>)| {
        (pct(s0, s1), q0.zip(q1).map(|(a, b)| pct(a, b)))
    };
    let thread = tid
        .zip(th0)
        .map(|(t, before)| share(before, thread_cpu_s(pid, t)));
    (
        Cpu {
            ppmd: share(p0, whole(ppmd)),
            ingress: share(i0, whole(ingress)),
            thread,
            ppmd_threads: thread_shares(&threads0, &threads_sched_ns(pid), wall),
        },
        heard,
    )
}

/// Waits up to `limit` for an event; unexpected ones (not `from` -> `to`)
/// met on the way are added to `unexpected`.
fn await_change(
    events: &mpsc::Receiver<Heard>,
    from: &str,
    to: &str,
    limit: Duration,
    unexpected: &mut Vec<Heard>,
) -> Option<u64> {
    let end = Instant::now() + limit;
    while let Some(left) = end.checked_duration_since(Instant::now()) {
        match events.recv_timeout(left) {
            Ok((f, t, at)) if f == from && t == to => return Some(at),
            Ok(e) => unexpected.push(e),
            Err(_) => break,
        }
    }
    None
}

/// The next number of splitmix64 from `state`.
fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A pause of `base` plus a random part of one radio frame, so that flips
/// land at every phase of the radio's frames.
fn pause(base: Duration, rng: &mut u64) {
    std::thread::sleep(base + Duration::from_nanos(splitmix64(rng) % RADIO_FRAME_NS));
}

/// The running programs and the bench's threads of one setup.
struct Rig {
    setup: Setup,
    ppmd: ppm_tools::harness::Proc,
    ingress: ppm_tools::harness::Proc,
    ctl: Arc<RadioCtl>,
    radio: std::thread::JoinHandle<Result<Vec<(u64, u64)>>>,
    stop_sender: Arc<AtomicBool>,
    sender: std::thread::JoinHandle<Result<u64>>,
    events: mpsc::Receiver<Heard>,
}

impl Rig {
    /// Starts ppmd (with `readback`: reading the radio's trace back),
    /// udp-ingress, the radio and the sender.
    fn start(readback: bool) -> Result<Rig> {
        let setup = Setup::new(&format!("readback-{readback}"), "")?;
        let radio_trace = setup.dir.join("radio.trace");
        let log = setup.dir.join("readback.jsonl");
        let cfg = setup.dir.join("ppm.toml");
        let mut text = std::fs::read_to_string(&cfg)?;
        if readback {
            text += &format!(
                "[ppmd]\nreadback = \"sim:{}\"\nreadback_log = {:?}\n[readback]\nframes = 2\n",
                radio_trace.display(),
                log.to_str().context("a UTF-8 path")?
            );
        }
        text += "[ppm]\nchannels = 4\nreceiver = \"edgetx\"\n[failsafe]\nafter_ms = 500\naction = \"hold\"\n";
        std::fs::write(&cfg, text)?;
        let line = setup.dir.join("line.trace");
        let ppmd = setup.spawn("ppmd", &["--output", &format!("sim:{}", line.display())])?;
        let ingress = setup.spawn("udp-ingress", &[])?;
        let ctl = Arc::new(RadioCtl::default());
        let radio = {
            let ctl = ctl.clone();
            std::thread::spawn(move || radio(&line, &radio_trace, &ctl))
        };
        let stop_sender = Arc::new(AtomicBool::new(false));
        let (tx, events) = mpsc::channel();
        let sender = {
            let (stop, port) = (stop_sender.clone(), setup.port);
            std::thread::spawn(move || sender(port, &stop, tx))
        };
        Ok(Rig {
            setup,
            ppmd,
            ingress,
            ctl,
            radio,
            stop_sender,
            sender,
            events,
        })
    }

    /// Stops everything; returns the radio's edges with their write times.
    fn stop(self) -> Result<(Setup, HashMap<u64, u64>)> {
        self.stop_sender.store(true, SeqCst);
        self.sender
            .join()
            .map_err(|_| anyhow::anyhow!("the sender panicked"))??;
        self.ctl.stop.store(true, SeqCst);
        let written = self
            .radio
            .join()
            .map_err(|_| anyhow::anyhow!("the radio panicked"))??;
        self.ingress.terminate();
        self.ppmd.terminate();
        Ok((self.setup, written.into_iter().collect()))
    }
}

/// Switch flips: (switch flipped -> heard, first frame of the new source
/// began -> heard) for each change to overridden and back to following,
/// ns, and the unexpected events.
#[derive(Default)]
struct Flips {
    over: (Vec<f64>, Vec<f64>),
    back: (Vec<f64>, Vec<f64>),
    missed: usize,
    unexpected: Vec<Heard>,
}

fn flips(rig: &Rig) -> Flips {
    let mut out = Flips::default();
    let mut rng = now_ns();
    for _ in 0..FLIPS {
        for (inst, from, to) in [
            (true, "following", "overridden"),
            (false, "overridden", "following"),
        ] {
            pause(Duration::from_millis(300), &mut rng);
            let switched = now_ns();
            rig.ctl.instructor.store(inst, SeqCst);
            let heard = await_change(
                &rig.events,
                from,
                to,
                Duration::from_secs(2),
                &mut out.unexpected,
            );
            let Some(at) = heard else {
                out.missed += 1;
                continue;
            };
            let first = rig.ctl.flipped_at.load(SeqCst);
            let to = if inst { &mut out.over } else { &mut out.back };
            to.0.push(at.saturating_sub(switched) as f64);
            to.1.push(at.saturating_sub(first) as f64);
        }
    }
    out
}

fn ms_row(label: &str, v: &mut [f64]) {
    let p = Percentiles::of(v);
    println!(
        "{label:<58} {:>6} {:>8.3} {:>8.3} {:>8.3}",
        p.count,
        p.p50 / 1e6,
        p.p99 / 1e6,
        p.max / 1e6
    );
}

/// `S% (Q%)`: from stat's ticks, in brackets from schedstat.
fn share(s: Option<Share>) -> String {
    match s {
        Some((stat, Some(sched))) => format!("{stat:.1}% ({sched:.2}%)"),
        Some((stat, None)) => format!("{stat:.1}%"),
        None => "-".into(),
    }
}

fn cpu_row(label: &str, c: &Cpu) {
    println!(
        "{label:<26} {:>22} {:>16} {:>16}",
        share(c.thread),
        share(Some(c.ppmd)),
        share(Some(c.ingress))
    );
    if !c.ppmd_threads.is_empty() {
        let t: Vec<String> = c
            .ppmd_threads
            .iter()
            .filter(|(_, pct)| *pct >= 0.005)
            .map(|(name, pct)| format!("{name} {pct:.2}%"))
            .collect();
        println!("  ppmd's threads (schedstat): {}", t.join(", "));
    }
}

pub fn readback() -> Result<()> {
    println!(
        "== 7. read-back: ppmd reading back a simulated radio (sim input; 8 channels, 300 us pulses, a frame every 22.5 ms: 44 Hz) that relays ppm's line or sends the instructor's sticks; commands at {COMMAND_HZ} Hz, follow timing, readback.frames = 2"
    );
    // The baseline: the same traffic and radio, ppmd without a read-back.
    let rig = Rig::start(false)?;
    std::thread::sleep(Duration::from_secs(1));
    let (base, _) = measure_cpu(&rig.ppmd, &rig.ingress, None, &rig.events);
    rig.stop()?;

    let rig = Rig::start(true)?;
    let name = format!("bench{}", "readback-true");
    let stop_watch = Arc::new(AtomicBool::new(false));
    let watcher = {
        let (root, stop) = (rig.setup.dir.join("ipc"), stop_watch.clone());
        std::thread::spawn(move || watch(&root, &name, &stop))
    };
    let mut unexpected = Vec::new();
    if await_change(
        &rig.events,
        "no_input",
        "following",
        Duration::from_secs(20),
        &mut unexpected,
    )
    .is_none()
    {
        let log = rig.ppmd.log_text();
        rig.stop()?;
        bail!("the read-back never reported following; ppmd's log:\n{log}");
    }
    let tid = find_thread(rig.ppmd.pid(), "ppmd-readback");
    if tid.is_none() {
        println!("  (no thread named ppmd-readback in ppmd: its CPU share is not measured)");
    }
    let (with, heard) = measure_cpu(&rig.ppmd, &rig.ingress, tid, &rig.events);
    unexpected.extend(heard);
    let mut f = flips(&rig);
    unexpected.append(&mut f.unexpected);
    // Frames still being read are logged and published.
    std::thread::sleep(Duration::from_millis(300));
    stop_watch.store(true, SeqCst);
    let (seen, newest) = watcher
        .join()
        .map_err(|_| anyhow::anyhow!("the subscriber panicked"))??;
    let (setup, written) = rig.stop()?;
    let rows = read_rows(&setup.dir.join("readback.jsonl"));
    let mut lat = edge_latency(&rows, &seen, &written);
    let mut write_delay: Vec<f64> = written
        .iter()
        .map(|(&t, &w)| w.saturating_sub(t) as f64)
        .collect();

    println!(
        "-- edge to published frame: {} frames read, {} samples with a new frame seen by the bench's subscriber (polling every {} us)",
        rows.len(),
        seen.len(),
        WATCH_POLL.as_micros()
    );
    println!(
        "{:<58} {:>6} {:>8} {:>8} {:>8}",
        "from -> to", "count", "p50 ms", "p99 ms", "max ms"
    );
    ms_row(
        "closing edge (end_mono_ns) -> published by ppmd",
        &mut lat.published,
    );
    ms_row(
        "closing edge (end_mono_ns) -> seen by a subscriber",
        &mut lat.seen,
    );
    ms_row(
        "handing-on edge (+300 us) written -> published",
        &mut lat.written_to_published,
    );
    ms_row("bench radio: edge's time -> written", &mut write_delay);
    println!(
        "(sim input: these include the 300 us pulse the decoder waits for (a frame is handed on at the falling edge after its closing edge), the bench's write delay (each edge written up to ~0.5 ms after its time) and the trace follower's 1 ms poll; on a Pi's GPIO input the kernel's timestamp is the edge's time, so only the pulse and the thread's wake-up remain)"
    );

    println!(
        "-- CPU over {CPU_SECONDS} s, commands at {COMMAND_HZ} Hz, radio at 44 Hz, % of one CPU"
    );
    println!(
        "{:<26} {:>22} {:>16} {:>16}",
        "", "ppmd-readback thread", "ppmd", "udp-ingress"
    );
    cpu_row("without ppmd.readback", &base);
    cpu_row("with ppmd.readback", &with);
    println!(
        "(utime+stime from /proc/PID/task/TID/stat and /proc/PID/stat, {} ms ticks; in brackets the time on a CPU from schedstat (ns), of the thread and summed over the process's threads)",
        1000.0 / clock_ticks()
    );

    println!(
        "-- switch flip -> the sender hears the change ({FLIPS} flips each way, a flip at a random phase of the radio's frame)"
    );
    println!(
        "{:<58} {:>6} {:>8} {:>8} {:>8}",
        "from -> to", "count", "p50 ms", "p99 ms", "max ms"
    );
    ms_row("switch flipped -> overridden heard", &mut f.over.0);
    ms_row(
        "radio's first instructor frame began -> overridden heard",
        &mut f.over.1,
    );
    ms_row("switch flipped back -> following heard", &mut f.back.0);
    ms_row(
        "radio's first relayed frame began -> following heard",
        &mut f.back.1,
    );
    let (relayed, bad) = relayed_mismatches(&rows);
    println!(
        "events: {} expected heard (1 + 2 x {FLIPS}), {} not heard within 2 s, {} unexpected{}; relayed frames that did not match ppm's values: {} of {relayed}",
        1 + f.over.0.len() + f.back.0.len(),
        f.missed,
        unexpected.len(),
        if unexpected.is_empty() {
            String::new()
        } else {
            format!(
                " ({})",
                unexpected
                    .iter()
                    .map(|(a, b, _)| format!("{a} -> {b}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        },
        bad.len()
    );
    for r in bad.iter().take(5) {
        let at = rows.iter().position(|x| x.frame == r.frame).unwrap_or(0);
        let after = match at.checked_sub(1).map(|i| &rows[i]) {
            Some(p) if is_instructor(&p.ch_us) => "an instructor's frame",
            Some(_) => "a relayed frame",
            None => "none",
        };
        println!(
            "  frame {} (after {after}): {:?} us, largest difference {:?} us, state {}",
            r.frame, r.ch_us, r.max_diff_us, r.state
        );
    }
    let refused: Vec<String> = ppm_shared::capture::CaptureCounts::default()
        .reasons()
        .into_iter()
        .zip(newest.refused)
        .filter(|&(_, n)| n > 0)
        .map(|((name, _), n)| format!("{name} {n}"))
        .collect();
    println!(
        "read-back's newest sample: {} frames, {} matched, {} mismatched, {} changes, refused: {}",
        newest.frames,
        newest.matched,
        newest.mismatched,
        newest.changes,
        if refused.is_empty() {
            "none".into()
        } else {
            refused.join(", ")
        }
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_and_schedstat_lines_give_cpu_time() {
        // A thread whose command has a space and a bracket.
        let stat =
            "4242 (ppmd-read) x) S 1 4242 4242 0 -1 4194368 200 0 0 0 17 5 0 0 20 0 3 0 1234 0 0";
        assert_eq!(stat_ticks(stat), Some(22));
        assert_eq!(stat_ticks("4242 (short) S 1 2"), None);
        assert_eq!(schedstat_ns("852997 23074 2\n"), Some(852_997));
        assert_eq!(schedstat_ns(""), None);
    }

    #[test]
    fn splitmix_spreads_pauses_over_the_frame() {
        let mut state = 1;
        let phases: Vec<u64> = (0..1000)
            .map(|_| splitmix64(&mut state) % RADIO_FRAME_NS)
            .collect();
        // Every tenth of the frame is hit.
        for tenth in 0..10 {
            let lo = tenth * RADIO_FRAME_NS / 10;
            assert!(phases
                .iter()
                .any(|&p| (lo..lo + RADIO_FRAME_NS / 10).contains(&p)));
        }
    }

    #[test]
    fn thread_shares_are_per_name_and_largest_first() {
        let before = HashMap::from([("a".to_string(), 1_000_000_000), ("b".to_string(), 0)]);
        let after = HashMap::from([
            ("a".to_string(), 1_100_000_000),
            ("b".to_string(), 500_000_000),
            ("new".to_string(), 10_000_000),
        ]);
        let v = thread_shares(&before, &after, 10.0);
        let names: Vec<&str> = v.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["b", "a", "new"]);
        assert!((v[0].1 - 5.0).abs() < 1e-9 && (v[1].1 - 1.0).abs() < 1e-9);
        assert!((v[2].1 - 0.1).abs() < 1e-9);
    }

    #[test]
    fn edge_latency_joins_by_frame_and_counts_relayed_mismatches() {
        let row = |frame, end_ns, ch0: f64, matched, state: &str| ReadRow {
            frame,
            end_ns,
            ch_us: vec![ch0, 1450.0, 1100.0, 1550.0],
            matched,
            max_diff_us: None,
            state: state.into(),
        };
        let rows = [
            row(1, 10_000_000, 1300.0, false, "no_input"),
            row(2, 32_500_000, 1300.0, true, "following"),
            row(3, 55_000_000, 1600.0, false, "following"),
            row(4, 77_500_000, 1300.0, false, "overridden"),
        ];
        let seen = [
            Seen {
                frame: 2,
                published_ns: 33_000_000,
                seen_ns: 33_100_000,
            },
            // A frame the log does not have: left out.
            Seen {
                frame: 9,
                published_ns: 1,
                seen_ns: 1,
            },
        ];
        let written = HashMap::from([(32_500_000 + RADIO_PULSE_NS, 32_900_000)]);
        let l = edge_latency(&rows, &seen, &written);
        assert_eq!(l.published, [500_000.0]);
        assert_eq!(l.seen, [600_000.0]);
        assert_eq!(l.written_to_published, [100_000.0]);
        // Frames 2 and 4 relayed after the first following (1 is before
        // it, 3 is the instructor's); 4 did not match.
        let (relayed, bad) = relayed_mismatches(&rows);
        assert_eq!((relayed, bad.len(), bad[0].frame), (2, 1, 4));
        assert!(is_instructor(&[1600.0, 1450.0, 1100.0, 1550.0, 1500.0]));
        assert!(!is_instructor(&[1600.0, 1450.0]));
    }

    #[test]
    fn the_radio_frames_close_with_a_pulse_and_commands_stay_off_the_instructor() {
        let f = ppm_tools::radio::frame_edges(0, &[1_000, 2_000]);
        assert_eq!(
            f,
            [
                (0, 1),
                (RADIO_PULSE_NS, 0),
                (1_000_000, 1),
                (1_000_000 + RADIO_PULSE_NS, 0),
                (3_000_000, 1),
                (3_000_000 + RADIO_PULSE_NS, 0)
            ]
        );
        for i in 0..200 {
            let v: Vec<u64> = serde_json::from_slice(&command(i)).unwrap();
            assert!((1300..=1498).contains(&v[0]), "{v:?}");
            assert!(v[0].abs_diff(INSTRUCTOR_US[0]) > 100);
        }
    }
}
