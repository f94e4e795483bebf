//! Part 5, late edges: follow and grid, with and without a thread of
//! higher SCHED_FIFO priority pinned to ppmd's CPU that busy-loops at random
//! times (`ppm-interfere`'s bursts): frames whole, aborted and glitched,
//! frames whose values as the line carried them differ from the frame log,
//! and the commands that reached the line, by the log and by decoding.

use super::*;
use ppm_shared::framelog::Status;

/// One late-edge run: what ppmd logged and what the line carried.
struct LateRun {
    rows: usize,
    whole: usize,
    aborted: usize,
    glitched: usize,
    /// Frames EdgeTX reads (from the times the edges were written) whose
    /// values differ from the frame log's by more than its 1 us truncation.
    differ: usize,
    /// Largest distance of a value EdgeTX reads from its command, us.
    max_off_us: u64,
    /// Commands found in the frame log and on the line.
    by_log: usize,
    by_line: usize,
    bursts: u64,
}

/// Command `i`'s first two channels, 10 us apart from command to command
/// (so a value read a few us off still names its command); the others are
/// the defaults.
fn late_code(i: u64) -> [u64; 2] {
    [1000 + 10 * (i % 100), 1000 + 10 * ((i / 100) % 100)]
}

/// The command whose [`late_code`] a frame read from the line carries,
/// from its first two values alone (not from the frame log), each to the
/// nearest 10 us.
fn late_decode(values_us: &[u64]) -> Option<u64> {
    let step = |v: u64| {
        (v + 5)
            .checked_sub(1000)
            .map(|d| d / 10)
            .filter(|&d| d < 100)
    };
    Some(step(*values_us.first()?)? + 100 * step(*values_us.get(1)?)?)
}

fn late_run(
    timing: &str,
    interfering: bool,
    bursts: (u64, u64),
    count: u32,
) -> Result<Option<LateRun>> {
    use ppm_shared::receiver::Receiver;
    let setup = Setup::new(&format!("late-{timing}-{interfering}"), "")?;
    let trace = setup.dir.join("line.trace");
    let log = setup.dir.join("frames.jsonl");
    let ppmd = setup.spawn(
        "ppmd",
        &[
            "--output",
            &format!("sim:{}", trace.display()),
            "--frame-log",
            log.to_str().unwrap(),
            "--timing",
            timing,
        ],
    )?;
    let ingress = setup.spawn("udp-ingress", &[])?;
    let stop = Arc::new(AtomicBool::new(false));
    let thread = if interfering {
        // ppmd's defaults: `rt.cpu = "last"`, `rt.priority`.
        let cpu =
            ppm_shared::sched::resolve_rt_cpu(ppm_shared::config::CpuChoice::Last).expect("a CPU");
        let priority = ppm_shared::config::Config::default().rt.priority + 1;
        let plan = ppm_tools::interfere::Plan {
            burst_ns: bursts,
            gap_ns: (5_000_000, 40_000_000),
            seed: now_ns(),
        };
        match ppm_tools::interfere::spawn(cpu, priority, plan, stop.clone()) {
            Ok(t) => Some(t),
            Err(e) => {
                println!("  (no interfering thread: {e:#})");
                return Ok(None);
            }
        }
    } else {
        None
    };
    paced(setup.port, count, 50.0, |i| {
        let [a, b] = late_code(i as u64);
        format!("[{a}, {b}]").into_bytes()
    })?;
    stop.store(true, Relaxed);
    let bursts = thread.map_or(0, |t| t.join().map_or(0, |b| b.len() as u64));
    std::thread::sleep(Duration::from_millis(100));
    ingress.terminate();
    ppmd.terminate();
    let rows = frame_records(&log)?;
    // A command reached the line when a frame carried its first two
    // values (udp-ingress numbers commands from 1, in the order sent).
    let carried = |r: &FrameRow| r.ingress_seq.filter(|_| r.ch_us.len() >= 2);
    let by_log: std::collections::BTreeSet<u64> = rows.iter().filter_map(carried).collect();
    let f = std::fs::File::open(&trace)?;
    let t = ppm_shared::trace::Trace::read(BufReader::new(f))?;
    let read = t.decode_as(Receiver::EdgeTx, true);
    let (mut differ, mut max_off_us) = (0, 0);
    let mut by_line = std::collections::BTreeSet::new();
    for f in &read {
        let v = f.channels_us();
        let row = rows.iter().rev().find(|r| r.mono_ns <= f.start_ns);
        let logged = row.map_or(&[][..], |r| &r.ch_us[..]);
        if logged.len() != v.len()
            || v.iter()
                .zip(logged)
                .any(|(a, b)| (*a as f64 - b).abs() > 1.0)
        {
            differ += 1;
        }
        // udp-ingress numbers commands from 1, in the order sent.
        if let Some(i) = late_decode(&v) {
            by_line.insert(i + 1);
        }
        // The command the row carries (udp-ingress numbers them from 1, in
        // the order sent) and the defaults.
        if let Some(i) = row.and_then(|r| r.ingress_seq) {
            let [a, b] = late_code(i - 1);
            let want = [a, b, 1000, 1500, 1500, 1500, 1500, 1500];
            for (got, w) in v.iter().zip(want) {
                max_off_us = max_off_us.max(got.abs_diff(w));
            }
        }
    }
    Ok(Some(LateRun {
        rows: rows.len(),
        whole: rows.iter().filter(|r| r.status == Status::Whole).count(),
        aborted: rows.iter().filter(|r| r.status == Status::Aborted).count(),
        glitched: rows.iter().filter(|r| r.glitched).count(),
        differ,
        max_off_us,
        by_log: by_log.len(),
        by_line: by_line.len(),
        bursts,
    }))
}

pub(super) fn late(cli: &Cli) -> Result<()> {
    println!(
        "== 5. late edges: {} commands at 50 Hz; with interference, a thread of higher SCHED_FIFO priority on ppmd's CPU busy for {}..{} us every 5..40 ms (as ppm-interfere does)",
        cli.late_count,
        cli.late_burst_us.0 / 1_000,
        cli.late_burst_us.1 / 1_000
    );
    println!(
        "{:<8} {:<12} {:>6} {:>6} {:>8} {:>9} {:>7} {:>8} {:>9} {:>9}",
        "timing",
        "interference",
        "frames",
        "whole",
        "aborted",
        "glitched",
        "differ",
        "off us",
        "cmds log",
        "cmds line"
    );
    for timing in ["grid", "follow"] {
        for interfering in [false, true] {
            let Some(r) = late_run(timing, interfering, cli.late_burst_us, cli.late_count)? else {
                continue;
            };
            println!(
                "{timing:<8} {:<12} {:>6} {:>6} {:>8} {:>9} {:>7} {:>8} {:>9} {:>9}",
                if interfering {
                    format!("{} bursts", r.bursts)
                } else {
                    "none".into()
                },
                r.rows,
                r.whole,
                r.aborted,
                r.glitched,
                r.differ,
                r.max_off_us,
                format!("{}/{}", r.by_log, cli.late_count),
                format!("{}/{}", r.by_line, cli.late_count),
            );
        }
    }
    println!(
        "(differ: frames EdgeTX reads from the times the edges were written whose values differ from the frame log's by more than 1 us; off us: the largest distance of a value EdgeTX reads from its command; cmds: commands found in the frame log and on the line, decoded as EdgeTX does)"
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every command's values name it again when read up to 4 us off, and
    /// values outside the code name none.
    #[test]
    fn late_codes_read_a_few_us_off_name_their_command() {
        for i in 0..10_000 {
            let [a, b] = late_code(i);
            for (da, db) in [(0, 0), (4, 0), (0, 4), (4, 4)] {
                assert_eq!(late_decode(&[a + da, b + db, 1000]), Some(i), "{i}");
                assert_eq!(late_decode(&[a - da, b - db]), Some(i), "{i}");
            }
        }
        assert_eq!(late_decode(&[1500]), None);
        assert_eq!(late_decode(&[994, 1000]), None);
        assert_eq!(late_decode(&[1000, 1995]), None);
    }
}
