//! ppm-watch follows a sim trace as it is written: across a rotation (ppmd
//! renames the file to FILE.1 at `ppmd.trace_max_mb` and starts FILE again)
//! and across a restart (ppmd truncates the file).

use ppm_shared::config::Config;
use ppm_shared::frame::FrameModel;
use ppm_shared::protocol::parse;
use ppm_shared::trace::TraceEdge;
use ppm_tests::Sandbox;
use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

const SECOND: Duration = Duration::from_secs(1);

/// Appends `n` frames carrying `cmd` from `*t` on (after a trace header when
/// the file is empty), moving `*t` past them.
fn append_frames(path: &Path, model: &FrameModel, cmd: &[u8], n: u32, t: &mut u64) {
    let new = std::fs::metadata(path).map_or(true, |m| m.len() == 0);
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .unwrap();
    if new {
        writeln!(f, "# idle_level {}", model.idle_level().as_u8()).unwrap();
        writeln!(f, "# channels {}", model.names().join(",")).unwrap();
    }
    let channels = parse(cmd, model).unwrap().channels;
    for _ in 0..n {
        for e in model.encode(&channels).edges() {
            let edge = TraceEdge {
                scheduled_ns: *t + e.at_ns,
                actual_ns: *t + e.at_ns,
                level: e.level,
            };
            writeln!(f, "{edge}").unwrap();
        }
        *t += model.frame_ns();
    }
}

/// Waits until ppm-watch's output has a line with `text`.
fn wait_for_output(out: &Path, text: &str) {
    let start = Instant::now();
    loop {
        let seen = std::fs::read_to_string(out).unwrap_or_default();
        if seen.lines().any(|l| l.contains(text)) {
            return;
        }
        assert!(
            start.elapsed() < 20 * SECOND,
            "no line with {text:?} in ppm-watch's output:\n{seen}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn watch_follows_a_rotated_and_a_restarted_trace() {
    let sb = Sandbox::new("watch");
    let model = Config::default().validate().unwrap();
    let trace = sb.dir.join("line.trace");
    let mut t = 1_000_000_000u64;
    append_frames(&trace, &model, b"[1100]", 20, &mut t);
    let mut watch = sb.spawn(
        "ppm-watch",
        &[trace.to_str().unwrap(), "--every", "0ms"],
        "watch",
    );
    let out = sb.dir.join("watch.out");
    wait_for_output(&out, "ail  1100.0");

    // Rotated: the last frames of the old file, then the new file.
    append_frames(&trace, &model, b"[1200]", 5, &mut t);
    std::fs::rename(&trace, sb.dir.join("line.trace.1")).unwrap();
    append_frames(&trace, &model, b"[1700]", 20, &mut t);
    wait_for_output(&out, "ail  1700.0");
    let seen = std::fs::read_to_string(&out).unwrap();
    assert!(seen.contains("ail  1200.0"), "the old file's end:\n{seen}");

    // Restarted: ppmd truncates the file and writes its header; frames
    // follow at their pace (ppm-watch sees the file shrink meanwhile).
    std::fs::File::create(&trace).unwrap();
    append_frames(&trace, &model, b"[1900]", 0, &mut t);
    std::thread::sleep(Duration::from_millis(300));
    append_frames(&trace, &model, b"[1900]", 20, &mut t);
    wait_for_output(&out, "ail  1900.0");
    watch.kill();
}

/// `--receiver` decodes as that receiver's firmware does: Betaflight hands
/// a frame on only once 26 frames of one channel count locked it, EdgeTX
/// each frame; the trace's `# receiver` line picks the default.
#[test]
fn watch_decodes_as_the_receiver_asked_for() {
    let sb = Sandbox::new("watch-receiver");
    let model = Config::default().validate().unwrap();
    let path = sb.dir.join("line.trace");
    let mut t = 1_000_000_000;
    append_frames(&path, &model, b"[1100, 1900]", 30, &mut t);
    let frames = |args: &[&str]| -> usize {
        let out = std::process::Command::new(ppm_tests::bin("ppm-watch"))
            .arg(&path)
            .arg("--once")
            .args(args)
            .output()
            .unwrap();
        assert!(out.status.success(), "{out:?}");
        let text = String::from_utf8(out.stdout).unwrap();
        assert!(
            text.lines().all(|l| l.contains("ail  1100.0 ele  1900.0")),
            "{text}"
        );
        text.lines().count()
    };
    // 30 frames: the first has no sync before it; the trainer inputs use
    // the last one's channels as they come.
    assert_eq!(frames(&["--receiver", "edgetx"]), 29);
    assert_eq!(frames(&["--receiver", "opentx"]), 29);
    // Betaflight and ArduPilot hand a frame on at the sync after it.
    assert_eq!(frames(&["--receiver", "betaflight"]), 28 - 26);
    assert_eq!(frames(&["--receiver", "ardupilot"]), 28 - 2);
    assert_eq!(frames(&[]), 29, "edgetx without a # receiver line");
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, format!("# receiver ardupilot\n{text}")).unwrap();
    assert_eq!(frames(&[]), 26);
    let bad = std::process::Command::new(ppm_tests::bin("ppm-watch"))
        .arg(&path)
        .args(["--once", "--receiver", "spektrum"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("spektrum"));
}

/// A frame cut short at a late edge (ppmd writes the pulses before it, then
/// a sync) shows as such: its channels before the cut, and how many of the
/// frame's it has. Whole frames show no mark.
#[test]
fn watch_marks_a_frame_cut_short() {
    let sb = Sandbox::new("watch-cut");
    let model = Config::default().validate().unwrap();
    let path = sb.dir.join("line.trace");
    let mut t = 1_000_000_000;
    append_frames(&path, &model, b"[1100, 1900]", 5, &mut t);
    // The sixth frame's first three pulses only: two channels.
    let channels = parse(b"[1100, 1900]", &model).unwrap().channels;
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .open(&path)
        .unwrap();
    for e in model.encode(&channels).edges().iter().take(6) {
        let at = t + e.at_ns;
        let edge = TraceEdge {
            scheduled_ns: at,
            actual_ns: at,
            level: e.level,
        };
        writeln!(f, "{edge}").unwrap();
    }
    t += model.frame_ns();
    drop(f);
    append_frames(&path, &model, b"[1100, 1900]", 3, &mut t);
    let out = std::process::Command::new(ppm_tests::bin("ppm-watch"))
        .arg(&path)
        .arg("--once")
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    // Of the 9 frames, the first has no sync before it, and the gap after
    // the cut one is too long for a sync (over 19 ms), so the frame after
    // it is not read either: 4 whole, the cut one, 2 whole.
    assert_eq!(lines.len(), 7, "{text}");
    let cut: Vec<&&str> = lines.iter().filter(|l| l.contains("cut short")).collect();
    assert_eq!(cut.len(), 1, "{text}");
    assert!(
        cut[0].contains("ail  1100.0 ele  1900.0  (cut short: 2 of 8 channels)"),
        "{text}"
    );
    assert!(!text.contains("incomplete"), "{text}");
}
