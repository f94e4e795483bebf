//! Part 6, SBUS against PPM, both following the commands, on the simulated line:
//! send to the moment a receiver has the whole frame that carries each
//! command, and the share of commands that reach the line, at 50, 100, 200
//! and 300 Hz.
//!
//! - PPM follow (`ppm.receiver = "any"`): the frame is whole at its last
//!   pulse's rising edge, when EdgeTX has its last channel.
//! - SBUS follow for EdgeTX, Betaflight and ArduPilot (each receiver's
//!   default idle line): the frame is taken as each receiver's framing
//!   takes it from the trace's real edge times (EdgeTX one idle character
//!   after the last byte, the others at the last byte).

use super::{paced, Setup};
use anyhow::Result;
use ppm_shared::config::Config;
use ppm_shared::sbus::SbusReceiver;
use ppm_shared::trace::Trace;
use ppm_tools::analysis::Percentiles;
use std::io::BufReader;
use std::time::Duration;

/// Command rates, Hz.
const RATES: [f64; 4] = [50.0, 100.0, 200.0, 300.0];

/// What one run measured.
struct Run {
    /// Send to the frame whole at the receiver, ns.
    latency: Percentiles,
    sent: usize,
    /// Commands some frame carried.
    on_line: usize,
    /// Frames on the line, and of those the receiver did not take (SBUS).
    frames: usize,
    lost: usize,
}

impl Run {
    fn share(&self) -> f64 {
        self.on_line as f64 * 100.0 / self.sent.max(1) as f64
    }
}

/// Command `i`'s first two channels: 1000 + i % 1000 and 1000 + i / 1000
/// (us), the others at their defaults.
fn code(i: u32) -> [u32; 2] {
    [1000 + i % 1000, 1000 + (i / 1000) % 1000]
}

/// The command two channel values (us, rounded) name.
fn decode(a: u64, b: u64) -> Option<u32> {
    let (a, b) = (a.checked_sub(1000)?, b.checked_sub(1000)?);
    (a < 1000 && b < 1000).then_some((b * 1000 + a) as u32)
}

/// Latencies and the share on the line, from `sent` and, per command,
/// when a frame carrying it was whole (`carried`: (whole at, command)).
fn measure(sent: &[u64], carried: &[(u64, u32)]) -> Run {
    let mut latency = Vec::new();
    for (i, &s) in sent.iter().enumerate() {
        if let Some(&(at, _)) = carried.iter().find(|&&(_, c)| c == i as u32) {
            latency.push(at.saturating_sub(s) as f64);
        }
    }
    Run {
        on_line: latency.len(),
        latency: Percentiles::of(&mut latency),
        sent: sent.len(),
        frames: carried.len(),
        lost: 0,
    }
}

/// One run: `count` commands at `hz` through udp-ingress and a following
/// ppmd with `[ppm]` lines `ppm`, the trace read back.
fn run(label: &str, ppm: &str, hz: f64, count: u32) -> Result<(Trace, Vec<u64>)> {
    let setup = Setup::new(&format!("sbus-{label}-{hz}"), "")?;
    let cfg = setup.dir.join("ppm.toml");
    let text = std::fs::read_to_string(&cfg)?;
    std::fs::write(&cfg, format!("{text}[ppm]\ntiming = \"follow\"\n{ppm}"))?;
    let trace = setup.dir.join("line.trace");
    let ppmd = setup.spawn("ppmd", &["--output", &format!("sim:{}", trace.display())])?;
    let ingress = setup.spawn("udp-ingress", &[])?;
    let sent = paced(setup.port, count, hz, |i| {
        let [a, b] = code(i);
        format!("[{a}, {b}]").into_bytes()
    })?;
    std::thread::sleep(Duration::from_millis(100));
    ingress.terminate();
    ppmd.terminate();
    let t = Trace::read(BufReader::new(std::fs::File::open(&trace)?))?;
    Ok((t, sent))
}

/// PPM follow: each frame whole at its last pulse's rising edge, as
/// written.
fn ppm_run(hz: f64, count: u32) -> Result<Run> {
    let (t, sent) = run("ppm", "", hz, count)?;
    let written: std::collections::HashMap<u64, u64> = t
        .edges
        .iter()
        .map(|e| (e.scheduled_ns, e.actual_ns))
        .collect();
    let carried: Vec<(u64, u32)> = t
        .decode(false)
        .iter()
        .filter(|f| f.complete && f.channels_us().len() >= 2)
        .filter_map(|f| {
            let c = f.channels_us();
            let last = f.start_ns + f.channels_ns.iter().sum::<u64>();
            let at = written.get(&last).copied().unwrap_or(last);
            Some((at, decode(c[0], c[1])?))
        })
        .collect();
    Ok(measure(&sent, &carried))
}

/// SBUS follow for `receiver` (its default idle line): each frame as its
/// framing takes it from the real edge times.
fn sbus_run(receiver: &str, hz: f64, count: u32) -> Result<Run> {
    let ppm = format!("protocol = \"sbus\"\nreceiver = \"{receiver}\"\n");
    let (t, sent) = run(receiver, &ppm, hz, count)?;
    let model = Config::parse(&format!("[ppm]\n{ppm}"))?.validate()?;
    let r = model.sbus().expect("an SBUS model").encode_for();
    let taken = t.sbus_taken(r, true);
    let carried: Vec<(u64, u32)> = taken
        .iter()
        .filter_map(|k| {
            let v = model.sbus_reads(&k.frame);
            decode((v[0] + 500) / 1_000, (v[1] + 500) / 1_000).map(|c| (k.at_ns, c))
        })
        .collect();
    let on_wire = t.sbus_characters(true).len() / ppm_shared::sbus::FRAME_LEN;
    Ok(Run {
        frames: on_wire,
        lost: on_wire.saturating_sub(taken.len()),
        ..measure(&sent, &carried)
    })
}

/// The idle line `receiver` gets by default, us, and so the highest rate
/// its frames can follow.
fn top_rate(receiver: &str) -> Result<(f64, f64)> {
    let model = Config::parse(&format!(
        "[ppm]\nprotocol = \"sbus\"\nreceiver = \"{receiver}\"\n"
    ))?
    .validate()?;
    let gap_us = model.follow_sync_ns().0 as f64 / 1e3;
    Ok((gap_us, 1e6 / (3_000.0 + gap_us)))
}

pub fn sbus(count_at_50: u32) -> Result<()> {
    println!(
        "== 6. SBUS against PPM, follow timing, simulated line: send to the frame carrying each command whole at the receiver, and the share of commands on the line ({count_at_50} commands at 50 Hz, as many seconds' worth at each rate)"
    );
    println!(
        "{:<22} {:>5} {:>6} {:>8} {:>8} {:>8} {:>8} {:>12}",
        "output", "Hz", "sent", "on line", "p50 ms", "p99 ms", "max ms", "frames lost"
    );
    let mut table: Vec<(String, Vec<Run>)> = Vec::new();
    let outputs: [(&str, Option<&str>); 4] = [
        ("ppm (any)", None),
        ("sbus edgetx", Some("edgetx")),
        ("sbus betaflight", Some("betaflight")),
        ("sbus ardupilot", Some("ardupilot")),
    ];
    for (label, receiver) in outputs {
        let mut runs = Vec::new();
        for hz in RATES {
            let count = (count_at_50 as f64 * hz / 50.0) as u32;
            let r = match receiver {
                None => ppm_run(hz, count)?,
                Some(rx) => sbus_run(rx, hz, count)?,
            };
            let l = &r.latency;
            println!(
                "{label:<22} {hz:>5} {:>6} {:>7.1}% {:>8.3} {:>8.3} {:>8.3} {:>12}",
                r.sent,
                r.share(),
                l.p50 / 1e6,
                l.p99 / 1e6,
                l.max / 1e6,
                format!("{}/{}", r.lost, r.frames)
            );
            runs.push(r);
        }
        table.push((label.to_string(), runs));
    }
    let ppm = &table[0].1;
    for (label, runs) in &table[1..] {
        let ratios: Vec<String> = runs
            .iter()
            .zip(ppm)
            .zip(RATES)
            .map(|((s, p), hz)| {
                format!(
                    "{hz} Hz p50 {:.1}x p99 {:.1}x",
                    p.latency.p50 / s.latency.p50.max(1.0),
                    p.latency.p99 / s.latency.p99.max(1.0)
                )
            })
            .collect();
        println!("  PPM / {label}: {}", ratios.join(", "));
    }
    for (label, rx) in [
        ("edgetx", SbusReceiver::EdgeTx),
        ("betaflight", SbusReceiver::Betaflight2026),
        ("ardupilot", SbusReceiver::ArduPilot),
    ] {
        let (gap, top) = top_rate(label)?;
        let runs = &table
            .iter()
            .find(|t| t.0.ends_with(label))
            .expect("a row")
            .1;
        let clean = RATES
            .iter()
            .zip(runs)
            .filter(|(_, r)| r.share() >= 99.0)
            .map(|(hz, _)| *hz)
            .fold(0.0, f64::max);
        println!(
            "  {} ({:?}): idle line {gap} us, so at most one frame every {:.2} ms ({top:.0} Hz); highest rate measured with >= 99% on the line: {clean} Hz",
            label,
            rx,
            (3_000.0 + gap) / 1e3
        );
    }
    println!("(PPM: whole at its last pulse's rising edge; SBUS: taken by the receiver's framing, EdgeTX one idle character (120 us) after the last byte; frames lost: on the line but not taken by the receiver's framing, of all frames on the line (PPM: frames read))");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_name_their_command_and_measure_finds_them() {
        for i in [0, 1, 999, 1000, 12_345, 999_999] {
            let [a, b] = code(i);
            assert_eq!(decode(a as u64, b as u64), Some(i));
        }
        assert_eq!(decode(999, 1000), None);
        assert_eq!(decode(2000, 1000), None);
        let r = measure(&[100, 200, 300], &[(1_100, 0), (1_300, 2), (1_400, 2)]);
        assert_eq!((r.sent, r.on_line), (3, 2));
        assert_eq!(r.latency.max, 1_000.0);
    }
}
