//! `ppm-capture`, the real binary: it follows a trace in the simulated
//! line's format while it grows, logs every whole frame exactly (values to
//! the ns, times on the trace's clock), says what it refused, and stops
//! with a clear message on an input this machine does not have.

use ppm_tests::bin;
use std::io::Write;
use std::process::{Command, Stdio};
use std::time::Duration;

/// One PPM frame of `us` channels starting at `start` with 300 us pulses
/// (idle low), as trace lines: a pulse before each channel and one after
/// the last.
fn frame(start: u64, us: &[u64]) -> String {
    let mut out = String::new();
    let mut t = start;
    for &v in us.iter().chain(std::iter::once(&0)) {
        out.push_str(&format!("{t} {t} 1\n{} {} 0\n", t + 300_000, t + 300_000));
        t += v * 1_000;
    }
    out
}

#[test]
fn ppm_capture_logs_every_whole_frame_of_a_growing_trace() {
    let dir = tempdir("capture");
    let trace = dir.join("pilot.trace");
    let log = dir.join("pilot.jsonl");
    std::fs::write(&trace, "# idle_level 0\n").unwrap();
    let child = Command::new(bin("ppm-capture"))
        .args([
            "--input",
            &format!("sim:{}", trace.display()),
            "--log",
            log.to_str().unwrap(),
            "--duration",
            "3s",
            "--quiet",
            "--idle-level",
            "low",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // 20 frames of 22.5 ms, each with its own values, written in pieces
    // while ppm-capture reads; a runt spoils frame 10.
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .open(&trace)
        .unwrap();
    let mut start = 1_000_000_000u64;
    let mut sent = vec![];
    for i in 0..20u64 {
        let us: Vec<u64> = (0..6).map(|c| 1_000 + 100 * c + i).collect();
        let mut text = frame(start, &us);
        if i == 10 {
            // A 10 us spike in the middle of channel 3.
            let t = start + (us[0] + us[1] + 500) * 1_000;
            text.push_str(&format!("{t} {t} 1\n{} {} 0\n", t + 10_000, t + 10_000));
            let mut lines: Vec<&str> = text.lines().collect();
            lines.sort_by_key(|l| l.split(' ').next().unwrap().parse::<u64>().unwrap());
            text = lines.join("\n") + "\n";
        }
        let (a, b) = text.split_at(text.len() / 2);
        f.write_all(a.as_bytes()).unwrap();
        f.flush().unwrap();
        std::thread::sleep(Duration::from_millis(5));
        f.write_all(b.as_bytes()).unwrap();
        f.flush().unwrap();
        sent.push((start, us));
        start += 22_500_000;
    }
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let rows: Vec<serde_json::Value> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    // The first frame has no timed sync before it; the next two lock the
    // count; frame 10 has a runt; the last has no sync after it.
    let want: Vec<&(u64, Vec<u64>)> = sent
        .iter()
        .enumerate()
        .filter(|(i, _)| *i >= 3 && *i != 10 && *i != 19)
        .map(|(_, s)| s)
        .collect();
    assert_eq!(rows.len(), want.len(), "{rows:?}");
    for (row, (start, us)) in rows.iter().zip(want) {
        assert_eq!(row["type"], "read");
        assert_eq!(row["mono_ns"].as_u64(), Some(*start));
        let ch: Vec<f64> = us.iter().map(|&u| u as f64).collect();
        assert_eq!(row["ch_us"], serde_json::json!(ch), "{row}");
        assert_eq!(row["match"], serde_json::Value::Null);
    }
    assert!(
        err.contains("idle level low, 6 channels; refused: runts 1,"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn ppm_capture_names_an_input_this_machine_does_not_have() {
    let out = Command::new(bin("ppm-capture"))
        .args(["--input", "gpio:nochip:3", "--duration", "1s"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(78), "{err}");
    assert!(err.contains("input gpio:nochip:3"), "{err}");
    let out = Command::new(bin("ppm-capture"))
        .args(["--input", "spi:/dev/spidev0.0"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("`spi:/dev/spidev0.0` is not an input"),
        "{err}"
    );
    // A bad option is a usage error: status 2, naming it.
    for (args, says) in [
        (["--channels", "17"], "17 is not in 1..=16"),
        (["--idle-level", "mid"], "possible values: low, high"),
    ] {
        let out = Command::new(bin("ppm-capture"))
            .args(["--input", "sim:/nonexistent"])
            .args(args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{err}");
        assert!(err.contains(says), "{err}");
    }
}

fn tempdir(label: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("ppm-test-{label}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}
