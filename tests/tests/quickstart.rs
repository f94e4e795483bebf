//! The quick start's line (`sim-spi`): each PPM frame handed to the
//! simulated line whole at its start and timed by the line's own clock, as
//! an SPI output sends it. Every frame it carries is whole and exactly the
//! command, by the edges' actual times, whatever the timing thread does
//! inside a frame; the frame log and ppm-watch say the same; and the
//! configuration refuses it where an SPI output would not work.

use ppm_shared::framelog::{self, Status};
use ppm_tests::{at_50hz, bin, read_trace, stop_all, Sandbox, Sender};
use std::process::Command;

#[test]
fn the_quick_starts_line_carries_whole_frames_of_the_command() {
    let sb = Sandbox::new("quickstart");
    // The quick start's own settings: follow timing, the default guard.
    let cfg = sb.config("[ppm]\ntiming = \"follow\"\nlate_edge_guard_us = 3\n");
    let trace = sb.dir.join("line.trace");
    let log = sb.dir.join("frames.jsonl");
    let output = format!("sim-spi:{}", trace.display());
    let cfg_s = cfg.to_str().unwrap();
    let mut ppmd = sb.spawn(
        "ppmd",
        &[
            "--config",
            cfg_s,
            "--output",
            &output,
            "--frame-log",
            log.to_str().unwrap(),
        ],
        "ppmd",
    );
    ppmd.wait_for_log(
        "timed by the line's own clock",
        std::time::Duration::from_secs(30),
    );
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let sender = Sender::new(sb.addr());
    at_50hz(50, |_| sender.send(b"[1000, 1200, 1700, 2000]"));
    stop_all(&mut ppmd, &mut [&mut ingress]);

    let want: Vec<u64> = vec![1000, 1200, 1700, 2000, 1500, 1500, 1500, 1500];
    // By the edges' actual times: what a receiver read.
    let frames = read_trace(&trace).decode(true);
    // One whole frame proves the command flew; every frame is whole and
    // carries exactly it.
    assert!(!frames.is_empty(), "no frame");
    for f in &frames {
        assert_eq!(f.channels_us(), want, "frame at {}", f.start_ns);
    }
    // The frame log: every frame whole, with the command's values exactly.
    let rows = framelog::read_frames(&log).unwrap_or_else(|e| panic!("{e}"));
    assert!(!rows.is_empty());
    for r in &rows {
        assert_eq!(r.status, Status::Whole, "{r:?}");
        let ch: Vec<u64> = r.ch_us.iter().map(|&v| v as u64).collect();
        assert_eq!(ch, want, "{r:?}");
    }
    // ppm-watch shows no frame cut short.
    let out = Command::new(bin("ppm-watch"))
        .arg(&trace)
        .arg("--once")
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(!text.is_empty());
    assert!(!text.contains("cut short"), "{text}");
}

#[test]
fn sim_spi_is_refused_where_spi_would_not_work() {
    let sb = Sandbox::new("quickstart-refused");
    for (extra, key, says) in [
        (
            "[ppm]\nidle_level = \"high\"\n",
            "ppm.idle_level",
            "simulates an SPI output",
        ),
        (
            "[ppm]\nprotocol = \"sbus\"\n",
            "ppmd.output",
            "already takes each frame whole",
        ),
    ] {
        let cfg = sb.config(extra);
        let out = Command::new(bin("ppmd"))
            .args([
                "--config",
                cfg.to_str().unwrap(),
                "--output",
                "sim-spi:x.trace",
            ])
            .current_dir(&sb.dir)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{extra}: {err}");
        assert!(err.contains(key) && err.contains(says), "{extra}: {err}");
        assert!(!sb.dir.join("x.trace").exists(), "{extra}");
    }
}
