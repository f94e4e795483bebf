//! The capture half of the real-kernel test (a helper module of vm.rs):
//! ppm-capture reads GPIO17 while pull-timed drives it at PPM timing
//! through gpio-sim's pull attribute, and every frame ppm-capture logs is
//! checked against the driver's own record of each write.

use super::read;
use std::path::Path;

/// The channel values pull-timed sends (tests/vm/pipeline-test.sh), in
/// order: all different, so a channel read in the wrong place is off by
/// 100 us or more.
const READBACK_US: [u64; 8] = [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800];

/// How much later than the end of the driver's write the kernel may stamp
/// the edge, ns: none. gpio-sim raises the line's interrupt inside the
/// write (`gpio_sim_apply_pull` -> `irq_set_irqchip_state` -> irq_sim's
/// `irq_work_queue`); irq_sim's work is `IRQ_WORK_INIT_HARD`, run from the
/// self-IPI that x86 sends at once and takes as soon as the write re-enables
/// interrupts, even on PREEMPT_RT; and gpiolib-cdev's primary handler,
/// which takes the timestamp, is requested `IRQF_ONESHOT`, so PREEMPT_RT
/// does not force it into a thread. So the edge is stamped before the write
/// returns: measured 1.8..2.1 us before the reading after it on both
/// kernels (the guest's clock counts instructions, so that does not vary
/// with the host's load). A kernel that stamped later (a deferred
/// irq_work) would fail here, with the stamp and the write in the message.
const STAMP_ALLOWANCE_NS: u64 = 0;

/// One write of pull-timed: the level written, when it was due, and
/// CLOCK_MONOTONIC right before and right after the write (ns).
#[derive(Debug, Clone, Copy)]
struct PullWrite {
    level: u8,
    due: u64,
    before: u64,
    after: u64,
}

/// pull-timed's log: its header's channel values and frame count, and every
/// write.
fn pull_writes(text: &str) -> (Vec<u64>, usize, Vec<PullWrite>) {
    let mut lines = text.lines();
    let header: Vec<&str> = lines
        .next()
        .and_then(|l| l.strip_prefix("# "))
        .unwrap_or_else(|| panic!("no header in pull-timed's log:\n{text}"))
        .split_whitespace()
        .collect();
    let field = |name: &str| {
        let i = header.iter().position(|w| *w == name).unwrap();
        header[i + 1]
    };
    let channels = field("channels_us")
        .split(',')
        .map(|v| v.parse().unwrap())
        .collect();
    let frames = field("frames").parse().unwrap();
    let writes = lines
        .map(|l| {
            let v: Vec<u64> = l.split_whitespace().map(|w| w.parse().unwrap()).collect();
            let [level, due, before, after] = v[..] else {
                panic!("bad line in pull-timed's log: {l}")
            };
            PullWrite {
                level: level as u8,
                due,
                before,
                after,
            }
        })
        .collect();
    (channels, frames, writes)
}

/// ppm-capture's summary line: edges, frames, and the refusals by reason.
fn capture_summary(log: &str) -> (u64, u64, Vec<(String, u64)>) {
    let line = log
        .lines()
        .find(|l| l.starts_with("ppm-capture: ") && l.contains(" edges, "))
        .unwrap_or_else(|| panic!("no summary in ppm-capture's log:\n{log}"));
    let num = |after: &str, before: &str| -> u64 {
        line.split(before)
            .next()
            .unwrap()
            .rsplit(after)
            .next()
            .unwrap()
            .parse()
            .unwrap()
    };
    let edges = num("ppm-capture: ", " edges");
    let frames = num(", ", " frames");
    let refused = line.rsplit("refused: ").next().unwrap();
    let refused = if refused == "none" {
        vec![]
    } else {
        refused
            .split(", ")
            .map(|r| {
                let (name, n) = r.rsplit_once(' ').unwrap();
                (name.to_string(), n.parse().unwrap())
            })
            .collect()
    };
    (edges, frames, refused)
}

/// ppm-capture read GPIO17 (requested as an input with both edges and
/// kernel timestamps) while pull-timed drove it through gpio-sim's pull
/// attribute on its own clock, recording CLOCK_MONOTONIC right before and
/// right after each write. Every frame ppm-capture logged is one pull-timed
/// sent, whole and in order: each leading edge the kernel stamped lies in
/// the window of the write that made it (from `before` to `after` plus
/// [`STAMP_ALLOWANCE_NS`]), so each channel period read lies within the
/// driver's measured bounds (`before[k+1] - after[k]` to `after[k+1] -
/// before[k]`, widened by the allowance) and within the driver's lateness
/// plus the allowance of the value intended. All frames sent but at most
/// three are logged; nothing is refused but what came before the first
/// sync.
pub(crate) fn check_readback(out: &Path, flavor: &str) {
    let what = format!("ppm-capture on the {flavor} kernel");
    let (channels, sent, writes) = pull_writes(&read(out, "readback_pull.txt"));
    assert_eq!(channels, READBACK_US, "{what}: pull-timed's channels");
    let leads: Vec<PullWrite> = writes.iter().copied().filter(|w| w.level == 1).collect();
    let per_frame = channels.len() + 1;
    // A lead-in pulse, the frames' pulses, a closing pulse.
    assert_eq!(leads.len(), 1 + sent * per_frame + 1, "{what}: pulses sent");

    let log = read(out, "readback_capture.log");
    let (edges, summary_frames, refused) = capture_summary(&log);
    assert_eq!(
        edges,
        writes.len() as u64,
        "{what}: every write is one edge: {log}"
    );
    for (reason, n) in &refused {
        assert!(
            reason == "unsynced" || reason == "wrong_count",
            "{what}: {n} refused as {reason}: {log}"
        );
    }

    let rows: Vec<serde_json::Value> = read(out, "readback_frames.jsonl")
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len() as u64, summary_frames, "{what}: {log}");
    assert!(
        rows.len() + 3 >= sent,
        "{what}: {} frames logged of {sent} sent: {log}",
        rows.len()
    );

    let allowance = STAMP_ALLOWANCE_NS;
    let mut seen = vec![false; sent];
    // Reported: the driver's write windows and lateness, the stamps' place
    // in the windows, the periods read against the values intended.
    let write_ns = writes.iter().map(|w| w.after - w.before).max().unwrap();
    let late_ns = writes.iter().map(|w| w.after - w.due).max().unwrap();
    // The driver kept to its schedule closely enough that a channel read
    // within its lateness of the value intended is that channel (the values
    // are 100 us apart).
    assert!(
        late_ns < 40_000,
        "{what}: a write of pull-timed ended {late_ns} ns after its due time"
    );
    let (mut stamp_after_max, mut stamp_after_min) = (i64::MIN, i64::MAX);
    let mut off_intended_ns = 0u64;
    let mut off_measured_ns = 0i64;
    for (r, row) in rows.iter().enumerate() {
        assert_eq!(row["type"], "read", "{what}: row {r}: {row}");
        let ch: Vec<u64> = row["ch_us"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| (v.as_f64().unwrap() * 1e3).round() as u64)
            .collect();
        assert_eq!(ch.len(), channels.len(), "{what}: row {r}: {row}");
        // The leading edges as the kernel stamped them: the frame's start,
        // each channel's end, the end of the sync after it.
        let mut stamps = vec![row["mono_ns"].as_u64().unwrap()];
        for c in &ch {
            stamps.push(stamps.last().unwrap() + c);
        }
        stamps.push(row["end_mono_ns"].as_u64().unwrap());
        let j = leads
            .iter()
            .position(|w| w.before <= stamps[0] && stamps[0] <= w.after + allowance)
            .unwrap_or_else(|| {
                panic!(
                    "{what}: row {r} starts at {}, in no write: {row}",
                    stamps[0]
                )
            });
        assert!(
            j >= 1 && (j - 1) % per_frame == 0 && j + per_frame < leads.len(),
            "{what}: row {r} starts at pulse {j}, not at a frame's start: {row}"
        );
        let frame = (j - 1) / per_frame;
        assert!(!seen[frame], "{what}: frame {frame} logged twice");
        seen[frame] = true;
        for (i, (&got, &want_us)) in ch.iter().zip(&channels).enumerate() {
            let (a, b) = (leads[j + i], leads[j + i + 1]);
            let want = want_us * 1_000;
            assert_eq!(b.due - a.due, want, "{what}: pull-timed's schedule");
            // The driver's own bounds of the period it made, and its
            // lateness (a write starts at or after its due time).
            let (lo, hi) = (b.before - a.after, b.after - a.before);
            assert!(
                lo.saturating_sub(allowance) <= got && got <= hi + allowance,
                "{what}: frame {frame} channel {}: {got} ns read, the driver made {lo}..{hi} ns: {ch:?}",
                i + 1
            );
            let jitter = (a.after - a.due).max(b.after - b.due);
            assert!(
                got.abs_diff(want) <= jitter + allowance,
                "{what}: frame {frame} channel {}: {got} ns read, {want} ns sent (driver late by up to {jitter} ns): {ch:?}",
                i + 1
            );
            off_intended_ns = off_intended_ns.max(got.abs_diff(want));
            // Against the driver's period measured at the writes' ends.
            let measured = (b.after - a.after) as i64;
            if (got as i64 - measured).abs() > off_measured_ns.abs() {
                off_measured_ns = got as i64 - measured;
            }
        }
        // Each leading edge was stamped while the write that made it ran
        // (this bounds the periods above).
        for (i, &s) in stamps.iter().enumerate() {
            let w = leads[j + i];
            assert!(
                w.before <= s && s <= w.after + allowance,
                "{what}: frame {frame}: leading edge {i} stamped at {s}, written {}..{}: {row}",
                w.before,
                w.after
            );
            stamp_after_max = stamp_after_max.max(s as i64 - w.after as i64);
            stamp_after_min = stamp_after_min.min(s as i64 - w.after as i64);
        }
    }
    eprintln!(
        "{what} (reported): {} of {sent} frames logged, refused {refused:?}; driver: longest write {:.1} us, latest write end {:.1} us after due; kernel stamps {:.1}..{:.1} us after the write's end; periods read at most {:.1} us from intended, {:.1} us from the driver's (write end to write end)",
        rows.len(),
        write_ns as f64 / 1e3,
        late_ns as f64 / 1e3,
        stamp_after_min as f64 / 1e3,
        stamp_after_max as f64 / 1e3,
        off_intended_ns as f64 / 1e3,
        off_measured_ns as f64 / 1e3,
    );
}

/// check_readback on made-up runs shaped like the real ones (writes 4 us
/// long, each edge stamped 1.9 us before the write's end): it passes the
/// true record, and fails a frame with two channels swapped, a channel
/// 5 us off, frames missing and a refusal other than at the start.
#[test]
fn readback_check_fails_wrong_frames() {
    type Rows = Vec<(u64, Vec<u64>, u64)>;
    let run = |name: &str, refused: &str, mutate: &dyn Fn(&mut Rows)| {
        let sent = 6;
        let (frame_ns, pulse_ns) = (22_500_000u64, 300_000u64);
        let sync_ns = frame_ns - READBACK_US.iter().sum::<u64>() * 1_000;
        let t0 = 1_000_000_000u64;
        let mut leads = vec![t0 - sync_ns];
        for f in 0..sent {
            leads.push(t0 + f * frame_ns);
            for c in READBACK_US {
                leads.push(leads.last().unwrap() + c * 1_000);
            }
        }
        leads.push(t0 + sent * frame_ns);
        let mut pull = format!(
            "# channels_us {} pulse_us 300 frame_us 22500 frames {sent}\n",
            READBACK_US.map(|c| c.to_string()).join(",")
        );
        for &due in &leads {
            for (level, at) in [(1, due), (0, due + pulse_ns)] {
                pull += &format!("{level} {at} {} {}\n", at + 170, at + 4_200);
            }
        }
        let stamp = |k: usize| leads[k] + 4_200 - 1_900;
        let mut rows: Rows = (0..sent as usize)
            .map(|f| {
                let j = 1 + f * 9;
                let ch = (0..8).map(|i| stamp(j + i + 1) - stamp(j + i)).collect();
                (stamp(j), ch, stamp(j + 9))
            })
            .collect();
        mutate(&mut rows);
        let dir =
            std::env::temp_dir().join(format!("ppm-vm-readback-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("readback_pull.txt"), pull).unwrap();
        let jsonl: String = rows
            .iter()
            .map(|(start, ch, end)| {
                let ch: Vec<f64> = ch.iter().map(|&n| n as f64 / 1e3).collect();
                format!(
                    "{}\n",
                    serde_json::json!({"type": "read", "mono_ns": start, "end_mono_ns": end, "ch_us": ch})
                )
            })
            .collect();
        std::fs::write(dir.join("readback_frames.jsonl"), jsonl).unwrap();
        std::fs::write(
            dir.join("readback_capture.log"),
            format!(
                "ppm-capture: reading GPIO17\nppm-capture: {} edges, {} frames, idle level low, 8 channels; refused: {refused}\n",
                leads.len() * 2,
                rows.len()
            ),
        )
        .unwrap();
        let ok = std::panic::catch_unwind(|| check_readback(&dir, name)).is_ok();
        std::fs::remove_dir_all(&dir).unwrap();
        ok
    };
    assert!(run("true", "unsynced 3", &|_| {}));
    assert!(!run("swapped", "none", &|r| r[2].1.swap(3, 4)));
    assert!(!run("off", "none", &|r| r[4].1[6] += 5_000));
    assert!(!run("missing", "none", &|r| r.truncate(2)));
    assert!(!run("refused", "noise 1", &|_| {}));
}
