//! Part 6, SBUS and CRSF against PPM, all following the commands, on the
//! simulated line: send to the moment a receiver has the whole frame that
//! carries each command, and the share of commands that reach the line, at
//! 50, 100, 200, 300, 400 and 500 Hz, and the highest of those rates with
//! at least 99% of the commands on the line.
//!
//! - PPM follow (`ppm.receiver = "any"`): the frame is whole at its last
//!   pulse's rising edge, when EdgeTX has its last channel.
//! - SBUS follow for EdgeTX, Betaflight and ArduPilot (each receiver's
//!   default idle line): the frame is taken as each receiver's framing
//!   takes it from the trace's real edge times (EdgeTX one idle character
//!   after the last byte, the others at the last byte).
//! - CRSF follow for Betaflight, ArduPilot and `any` (at `ppm.crsf_baud`'s
//!   default, 420 000 baud 8N1): the trace's edges read back as UART
//!   characters at that baud, each firmware's [`Framer`] fed them, and an RC
//!   frame the firmware uses is whole when its framing takes it (its last
//!   byte's stop bit). `any` counts a command when every modelled firmware
//!   (Betaflight, iNav, ArduPilot) has it, at the latest of their times.

use super::{paced, Setup};
use anyhow::Result;
use ppm_shared::config::Config;
use ppm_shared::crsf::{self, CrsfReceiver, Framer, Verdict};
use ppm_shared::frame::Level;
use ppm_shared::sbus::SbusReceiver;
use ppm_shared::trace::Trace;
use ppm_shared::wire::{self, WireModel};
use ppm_tools::analysis::Percentiles;
use std::collections::HashMap;
use std::io::BufReader;
use std::time::Duration;

/// Command rates, Hz.
const RATES: [f64; 6] = [50.0, 100.0, 200.0, 300.0, 400.0, 500.0];

/// The share of commands on the line a rate must reach to count as
/// followed, %.
const CLEAN_SHARE: f64 = 99.0;

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

/// Per command, when the first frame carrying it was whole.
fn first_carried(carried: &[(u64, u32)]) -> HashMap<u32, u64> {
    let mut first = HashMap::new();
    for &(at, c) in carried {
        first.entry(c).or_insert(at);
    }
    first
}

/// Latencies and the share on the line, from `sent` and, per command,
/// when a frame carrying it was whole (`carried`: (whole at, command)).
fn measure(sent: &[u64], carried: &[(u64, u32)]) -> Run {
    let first = first_carried(carried);
    let mut latency = Vec::new();
    for (i, &s) in sent.iter().enumerate() {
        if let Some(&at) = first.get(&(i as u32)) {
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

/// What several receivers carried together: each command every one of
/// them carried, at the latest of the times each first had it, in that
/// order.
fn worst_of(each: &[Vec<(u64, u32)>]) -> Vec<(u64, u32)> {
    let Some((head, rest)) = each.split_first() else {
        return Vec::new();
    };
    let rest: Vec<HashMap<u32, u64>> = rest.iter().map(|c| first_carried(c)).collect();
    let mut out: Vec<(u64, u32)> = first_carried(head)
        .into_iter()
        .filter_map(|(c, at)| {
            rest.iter()
                .try_fold(at, |t, r| r.get(&c).map(|&a| t.max(a)))
                .map(|t| (t, c))
        })
        .collect();
    out.sort_unstable();
    out
}

/// The highest of `rates` whose share on the line is at least
/// [`CLEAN_SHARE`] (0 when none is).
fn highest_clean(rates: &[f64], shares: &[f64]) -> f64 {
    rates
        .iter()
        .zip(shares)
        .filter(|(_, &s)| s >= CLEAN_SHARE)
        .map(|(hz, _)| *hz)
        .fold(0.0, f64::max)
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

/// CRSF follow encoded for `receiver` (at the default baud): the trace's
/// characters at that baud, framed by each firmware it covers; a command is
/// carried when every one of them used an RC frame carrying it.
fn crsf_run(receiver: &str, hz: f64, count: u32) -> Result<Run> {
    let ppm = format!("protocol = \"crsf\"\nreceiver = \"{receiver}\"\n");
    let (t, sent) = run(&format!("crsf-{receiver}"), &ppm, hz, count)?;
    let model = Config::parse(&format!("[ppm]\n{ppm}"))?.validate()?;
    let WireModel::Crsf(c) = *model.wire() else {
        anyhow::bail!("not a CRSF model");
    };
    let edges: Vec<(u64, Level)> = t.edges.iter().map(|e| (e.actual_ns, e.level)).collect();
    let chars = wire::uart::decode(c.uart(), &edges, Level::High);
    let mut used = usize::MAX;
    let each: Vec<Vec<(u64, u32)>> = c
        .encode_for()
        .receivers()
        .iter()
        .map(|&rx| {
            let read = c.encode_for().reads_as();
            let carried = crsf_carried(rx, read, chars.iter().map(|c| (c.byte, c.end_ns)));
            used = used.min(carried.len());
            carried
        })
        .collect();
    let on_wire = chars.len() / wire::crsf::FRAME_LEN;
    Ok(Run {
        frames: on_wire,
        lost: on_wire.saturating_sub(used),
        ..measure(&sent, &worst_of(&each))
    })
}

/// The RC frames `rx`'s framing takes from `bytes` (each with its stop
/// bit's end, ns) and uses: (taken at, the command its values name, or
/// `u32::MAX` for values that name none). The values are named as `read`
/// reads them, the firmware they were encoded for (under `any`, iNav, which
/// reads them exactly; Betaflight and ArduPilot read them within 1 us, too
/// close for commands 1 us apart).
fn crsf_carried(
    rx: CrsfReceiver,
    read: CrsfReceiver,
    bytes: impl Iterator<Item = (u8, u64)>,
) -> Vec<(u64, u32)> {
    let mut framer = Framer::new(rx);
    bytes
        .filter_map(|(b, end)| framer.push(b, end))
        .filter_map(|k| match rx.verdict(&k) {
            Verdict::Used { .. } => {
                let mut payload = [0u8; crsf::RC_PAYLOAD_LEN];
                payload.copy_from_slice(&k.bytes[3..3 + crsf::RC_PAYLOAD_LEN]);
                let v = crsf::rc_channels(&payload).map(|raw| read.read_ns(raw));
                let c = decode((v[0] + 500) / 1_000, (v[1] + 500) / 1_000);
                Some((k.at_ns, c.unwrap_or(u32::MAX)))
            }
            _ => None,
        })
        .collect()
}

/// CRSF encoded for `receiver`: its frame on the wire and its least idle
/// line under follow, us, and so the highest rate its frames can follow.
fn crsf_top_rate(receiver: &str) -> Result<(f64, f64, f64)> {
    let model = Config::parse(&format!(
        "[ppm]\nprotocol = \"crsf\"\nreceiver = \"{receiver}\"\n"
    ))?
    .validate()?;
    let frame_us = model.wire().frame_wire_ns() as f64 / 1e3;
    let gap_us = model.follow_sync_ns().0 as f64 / 1e3;
    Ok((frame_us, gap_us, 1e6 / (frame_us + gap_us)))
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
        "== 6. SBUS and CRSF against PPM, follow timing, simulated line: send to the frame carrying each command whole at the receiver, and the share of commands on the line ({count_at_50} commands at 50 Hz, as many seconds' worth at each rate)"
    );
    println!(
        "{:<22} {:>5} {:>6} {:>8} {:>8} {:>8} {:>8} {:>12}",
        "output", "Hz", "sent", "on line", "p50 ms", "p99 ms", "max ms", "frames lost"
    );
    let mut table: Vec<(String, Vec<Run>)> = Vec::new();
    let outputs: [(&str, &str, &str); 7] = [
        ("ppm (any)", "ppm", "any"),
        ("sbus edgetx", "sbus", "edgetx"),
        ("sbus betaflight", "sbus", "betaflight"),
        ("sbus ardupilot", "sbus", "ardupilot"),
        ("crsf betaflight", "crsf", "betaflight"),
        ("crsf ardupilot", "crsf", "ardupilot"),
        ("crsf any", "crsf", "any"),
    ];
    for (label, protocol, receiver) in outputs {
        let mut runs = Vec::new();
        for hz in RATES {
            let count = (count_at_50 as f64 * hz / 50.0) as u32;
            let r = match protocol {
                "ppm" => ppm_run(hz, count)?,
                "sbus" => sbus_run(receiver, hz, count)?,
                _ => crsf_run(receiver, hz, count)?,
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
        let shares: Vec<f64> = runs.iter().map(Run::share).collect();
        let clean = highest_clean(&RATES, &shares);
        println!(
            "  sbus {} ({:?}): idle line {gap} us, so at most one frame every {:.2} ms ({top:.0} Hz); highest rate measured with >= 99% on the line: {clean} Hz",
            label,
            rx,
            (3_000.0 + gap) / 1e3
        );
    }
    for label in ["betaflight", "ardupilot", "any"] {
        let (frame, gap, top) = crsf_top_rate(label)?;
        let runs = &table
            .iter()
            .find(|t| t.0 == format!("crsf {label}"))
            .expect("a row")
            .1;
        let shares: Vec<f64> = runs.iter().map(Run::share).collect();
        let clean = highest_clean(&RATES, &shares);
        println!(
            "  crsf {label}: frame {frame:.0} us (RC frame and link statistics), idle line {gap} us, so at most one frame every {:.2} ms ({top:.0} Hz); highest rate measured with >= 99% on the line: {clean} Hz",
            (frame + gap) / 1e3
        );
    }
    let shares: Vec<f64> = table[0].1.iter().map(Run::share).collect();
    println!(
        "  ppm (any): highest rate measured with >= 99% on the line: {} Hz",
        highest_clean(&RATES, &shares)
    );
    println!("(PPM: whole at its last pulse's rising edge; SBUS: taken by the receiver's framing, EdgeTX one idle character (120 us) after the last byte; CRSF: the RC frame taken by each firmware's framing at its last byte, `any` when Betaflight, iNav and ArduPilot all have it; frames lost: on the line but not taken by the receiver's framing, of all frames on the line (PPM: frames read; CRSF: RC frames, the worst firmware))");
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

    #[test]
    fn worst_of_keeps_commands_every_receiver_had_at_the_latest_time() {
        let a = vec![(10, 0), (20, 1), (30, 1), (40, 2)];
        let b = vec![(12, 0), (25, 1), (50, 3)];
        assert_eq!(worst_of(&[a.clone(), b]), vec![(12, 0), (25, 1)]);
        assert_eq!(worst_of(&[a]), vec![(10, 0), (20, 1), (40, 2)]);
        assert!(worst_of(&[]).is_empty());
    }

    #[test]
    fn highest_clean_is_the_top_rate_at_99_percent() {
        let rates = [50.0, 100.0, 200.0, 300.0];
        assert_eq!(highest_clean(&rates, &[100.0, 99.0, 98.9, 99.5]), 300.0);
        assert_eq!(highest_clean(&rates, &[100.0, 99.0, 50.0, 20.0]), 100.0);
        assert_eq!(highest_clean(&rates, &[90.0, 50.0, 20.0, 10.0]), 0.0);
    }

    #[test]
    fn crsf_frames_on_the_wire_name_their_command_for_each_firmware() {
        let model = Config::parse("[ppm]\nprotocol = \"crsf\"\nreceiver = \"any\"\n")
            .unwrap()
            .validate()
            .unwrap();
        let WireModel::Crsf(c) = *model.wire() else {
            panic!("a CRSF model");
        };
        let mut bytes = Vec::new();
        let mut start = 1_000_000_000;
        for i in [7u32, 1_234] {
            let mut ns = [1_500_000u64; ppm_shared::MAX_CHANNELS];
            let [a, b] = code(i);
            ns[0] = u64::from(a) * 1_000;
            ns[1] = u64::from(b) * 1_000;
            let mut out = [0u8; wire::MAX_FRAME_BYTES];
            let n = model.wire().encode_bytes(&ns, false, &mut out);
            let f = c.uart();
            let e: Vec<_> = wire::uart::edges(f, &out[..n], start, Level::High).collect();
            let chars = wire::uart::decode(f, &e, Level::High);
            bytes.extend(chars.iter().map(|c| (c.byte, c.end_ns)));
            start += 4_000_000;
        }
        for rx in CrsfReceiver::ALL {
            let got: Vec<u32> = crsf_carried(rx, CrsfReceiver::Inav, bytes.iter().copied())
                .iter()
                .map(|k| k.1)
                .collect();
            assert_eq!(got, [7, 1_234], "{rx:?}");
        }
    }
}
