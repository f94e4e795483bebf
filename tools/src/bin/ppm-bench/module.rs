//! Part 8, an ExpressLRS transmitter module: ppmd and udp-ingress with a
//! simulated module on a pseudo-terminal ([`SimModule`]: ExpressLRS's own
//! framing and sync arithmetic, its packet timer at an arbitrary phase) and
//! a simulated pilot's radio with its takeover switch off, commands over
//! UDP at 50 to 500 Hz against modules at 250 and 500 Hz. For each command:
//! send to the first RC frame carrying it at the module (its arrival on the
//! pseudo-terminal, which delivers a write at once: on a wire at 400 000
//! baud the frame is whole 650 us after its write, and the module's
//! corrections move the writes that much earlier), and send to the
//! module's next radio packet after that frame (the command on the air);
//! the share of commands on the line; and how long before each radio
//! packet the newest frame came (the module asks for its 100 us margin).

use super::{paced, Setup};
use anyhow::{bail, Result};
use ppm_shared::crsf::{self, CrsfReceiver, LinkStatistics, ADDRESS_TRANSMITTER};
use ppm_shared::time::now_ns;
use ppm_tools::analysis::Percentiles;
use ppm_tools::harness::Pty;
use ppm_tools::module::{pilot_radio, SimModule};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::SeqCst};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Command rates, Hz.
const RATES: [f64; 4] = [50.0, 100.0, 250.0, 500.0];
/// Module packet intervals, us: 250 and 500 Hz.
const INTERVALS_US: [i64; 2] = [4_000, 2_000];
/// Seconds of commands at each rate.
const SECONDS: f64 = 5.0;

/// Command `i`'s aileron and elevator, us: 1000 + i % 1000 and
/// 1000 + i / 1000.
fn code(i: u32) -> [u32; 2] {
    [1_000 + i % 1_000, 1_000 + i / 1_000]
}

pub fn module() -> Result<()> {
    println!(
        "== 8. an ExpressLRS module (simulated, on a pseudo-terminal; a pilot's radio, switch off): send to the frame at the module and to the module's next radio packet, the share of commands on the line, and how long before each radio packet the newest frame came ({SECONDS} s of commands at each rate)"
    );
    println!(
        "{:<12} {:>5} {:>6} {:>8} {:>9} {:>9} {:>9} {:>9}",
        "module", "Hz", "sent", "on line", "frame p50", "frame p99", "air p50", "air p99"
    );
    let mut leads = Vec::new();
    for interval in INTERVALS_US {
        let (rows, lead) = module_runs(interval)?;
        for (hz, sent, on_line, whole, air) in rows {
            println!(
                "{:<12} {:>5} {:>6} {:>7.1}% {:>6.2} ms {:>6.2} ms {:>6.2} ms {:>6.2} ms",
                format!("{} Hz", 1_000_000 / interval),
                hz,
                sent,
                on_line as f64 * 100.0 / sent.max(1) as f64,
                whole.p50 / 1e6,
                whole.p99 / 1e6,
                air.p50 / 1e6,
                air.p99 / 1e6
            );
        }
        leads.push((interval, lead));
    }
    for (interval, l) in leads {
        println!(
            "  module at {} Hz: the newest frame came before its radio packet: min {:.0} us, p50 {:.0} us, p90 {:.0} us, p99 {:.0} us, max {:.0} us ({} packets; it asks for 100 us)",
            1_000_000 / interval,
            l.min / 1e3,
            l.p50 / 1e3,
            l.p90 / 1e3,
            l.p99 / 1e3,
            l.max / 1e3,
            l.count
        );
    }
    Ok(())
}

type Row = (f64, usize, usize, Percentiles, Percentiles);

/// One ppmd and udp-ingress against a module with `interval_us`, every
/// rate: the rows, and the module's leads over all of them.
fn module_runs(interval_us: i64) -> Result<(Vec<Row>, Percentiles)> {
    let setup = Setup::new(&format!("module{interval_us}"), "")?;
    let module = Arc::new(Mutex::new(SimModule::new(
        interval_us,
        LinkStatistics::WIRED,
    )));
    let pty = {
        let m = module.clone();
        let mut first = true;
        Pty::open_answering(move |now, bytes| {
            if first {
                // The module's UART stamps bytes as they come: its reading
                // thread runs at SCHED_FIFO 70 where it may (below ppmd's
                // 80), so that its stamps are not a busy machine's.
                first = false;
                let param = nix::libc::sched_param { sched_priority: 70 };
                // SAFETY: sets this thread's policy; the struct outlives the call.
                unsafe { nix::libc::sched_setscheduler(0, nix::libc::SCHED_FIFO, &param) };
            }
            m.lock().expect("the module").bytes(now, bytes)
        })?
    };
    let pilot = setup.dir.join("pilot.trace");
    let path = setup.dir.join("ppm.toml");
    let mut config = std::fs::read_to_string(&path)?;
    config.push_str(&format!(
        "[ppm]\nprotocol = \"crsf\"\ncrsf_target = \"module\"\nreceiver = \"betaflight\"\n[ppmd]\noutput = \"serial:{}\"\npilot = \"sim:{}\"\n[pilot]\nswitch_channel = 5\n",
        pty.slave.display(),
        pilot.display()
    ));
    std::fs::write(&path, config)?;
    let (off, flipped, stop) = (
        Arc::new(AtomicBool::new(false)),
        Arc::new(AtomicU64::new(0)),
        Arc::new(AtomicBool::new(false)),
    );
    let radio = {
        let (o, f, s, p) = (off.clone(), flipped.clone(), stop.clone(), pilot.clone());
        std::thread::spawn(move || pilot_radio(&p, &o, &f, &s))
    };
    let ppmd = setup.spawn("ppmd", &[])?;
    let ingress = setup.spawn("udp-ingress", &[])?;
    // Frames flow once the pilot's radio is read and a command came; a
    // second more for the grid to settle on the module's pace.
    let began = now_ns();
    loop {
        paced(setup.port, 10, 50.0, |_| {
            b"[1500, 1500, 1000, 1500]".to_vec()
        })?;
        if !module.lock().expect("the module").frames.is_empty() {
            break;
        }
        if now_ns() - began > 10_000_000_000 {
            bail!(
                "no frame reached the module in 10 s: {}",
                std::fs::read_to_string(setup.dir.join("ppmd.log"))?
            );
        }
    }
    paced(setup.port, 50, 50.0, |_| {
        b"[1500, 1500, 1000, 1500]".to_vec()
    })?;
    let mut rows = Vec::new();
    let mut leads = Vec::new();
    for hz in RATES {
        let count = (SECONDS * hz) as u32;
        let from = now_ns();
        let sent = paced(setup.port, count, hz, |i| {
            let [a, e] = code(i);
            format!("[{a}, {e}, 1000, 1500]").into_bytes()
        })?;
        std::thread::sleep(Duration::from_millis(100));
        let to = now_ns();
        let m = module.lock().expect("the module");
        // Each frame's arrival and the command it names.
        let frames: Vec<(u64, Option<u32>)> = m
            .frames
            .iter()
            .filter(|f| f.0 >= from && f.0 < to)
            .map(|(at, f)| (*at, named(f)))
            .collect();
        let ticks: Vec<(u64, u64)> = m
            .ticks
            .iter()
            .filter(|t| t.0 >= from && t.0 < to)
            .copied()
            .collect();
        leads.extend(ticks.iter().map(|t| t.1 as f64));
        let (mut whole, mut air) = (Vec::new(), Vec::new());
        for (i, &s) in sent.iter().enumerate() {
            let Some(&(at, _)) = frames.iter().find(|f| f.0 >= s && f.1 == Some(i as u32)) else {
                continue;
            };
            whole.push((at - s) as f64);
            // The module's first packet after the frame came.
            if let Some(t) = ticks.iter().find(|t| t.0 >= at) {
                air.push((t.0 - s) as f64);
            }
        }
        let on_line = whole.len();
        rows.push((
            hz,
            sent.len(),
            on_line,
            Percentiles::of(&mut whole),
            Percentiles::of(&mut air),
        ));
    }
    stop.store(true, SeqCst);
    let _ = radio.join();
    ingress.terminate();
    ppmd.terminate();
    drop(pty);
    Ok((rows, Percentiles::of(&mut leads)))
}

/// The command an RC frame to the module names, as Betaflight behind the
/// link reads it.
fn named(frame: &[u8]) -> Option<u32> {
    let rc: &[u8; crsf::RC_FRAME_LEN] = frame.try_into().ok()?;
    let raw = crsf::decode_rc_to(ADDRESS_TRANSMITTER, rc)?;
    let us = |i: usize| ((CrsfReceiver::Betaflight.read_ns(raw[i]) + 500) / 1_000) as u32;
    let (a, e) = (us(0), us(1));
    (a >= 1_000 && e >= 1_000).then(|| (a - 1_000) + (e - 1_000) * 1_000)
}
