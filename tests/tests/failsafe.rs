//! What ppmd sends when commands stop (and before the first one), with the
//! real binaries: silence within `after_ms` plus one frame, `hold`,
//! `default`, and `startup = "default"`.

use nix::sys::signal::Signal;
use ppm_shared::time::now_ns;
use ppm_tests::{carries, channel_of_frames, read_trace, Proc, Sandbox, Sender};
use std::time::Duration;

const FRAME_NS: u64 = 22_500_000;
const SECOND: Duration = Duration::from_secs(1);

fn start(sb: &Sandbox, failsafe: &str) -> (Proc, Proc) {
    let cfg = sb.config(&format!("[failsafe]\n{failsafe}"));
    (
        sb.start_ppmd(&cfg, "line.trace"),
        sb.start_ingress(&cfg, &[]),
    )
}

/// Sends `cmd` at 50 Hz for `n` datagrams; returns the time of the last send.
fn send(sb: &Sandbox, cmd: &[u8], n: u32) -> u64 {
    let s = Sender::new(sb.addr());
    let mut last = 0;
    for _ in 0..n {
        s.send(cmd);
        last = now_ns();
        std::thread::sleep(Duration::from_millis(20));
    }
    last
}

#[test]
fn silence_comes_within_after_ms_and_one_frame() {
    let sb = Sandbox::new("fs-silence");
    let (mut ppmd, _ingress) = start(&sb, "after_ms = 200\naction = 'silence'");
    let last_sent = send(&sb, b"[1300]", 40);
    std::thread::sleep(Duration::from_millis(800));
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let trace = read_trace(&sb.dir.join("line.trace"));
    let last_edge = trace.edges.last().expect("edges").actual_ns;
    // The command was received a little after it was sent; the bound is the
    // send time plus after_ms plus one frame (plus a 2 ms allowance for the
    // datagram's trip to ppmd).
    let bound = last_sent + 200_000_000 + FRAME_NS + 2_000_000;
    assert!(
        last_edge <= bound,
        "pulses went on {:.1} ms after the last command",
        (last_edge - last_sent) as f64 / 1e6
    );
    assert!(
        last_edge >= last_sent + 200_000_000 - FRAME_NS,
        "stopped early"
    );
    assert!(ppmd.log_text().contains("no fresh command: line silent"));
}

#[test]
fn hold_repeats_the_last_command() {
    let sb = Sandbox::new("fs-hold");
    let (mut ppmd, _ingress) = start(&sb, "after_ms = 100\naction = 'hold'");
    let last_sent = send(&sb, b"[1300, 1400]", 25);
    std::thread::sleep(Duration::from_millis(800));
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    // Every frame, whole or cut short at a late edge (then with the
    // channels before it).
    let frames = read_trace(&sb.dir.join("line.trace")).decode(false);
    let after: Vec<_> = frames
        .iter()
        .filter(|f| f.start_ns > last_sent + 300_000_000)
        .collect();
    assert!(frames.iter().all(|f| carries(f, &[1300, 1400])));
    // Well past after_ms (silence would have ended the line by then), one
    // frame carrying both channels shows the hold (how many a loaded
    // machine cuts short is its business).
    assert!(
        after.iter().any(|f| f.channels_us().len() >= 2),
        "{} frames after the command, none held it",
        after.len()
    );
    assert!(ppmd.log_text().contains("emitting failsafe frames"));
}

#[test]
fn default_action_sends_the_defaults() {
    let sb = Sandbox::new("fs-default");
    let (mut ppmd, _ingress) = start(&sb, "after_ms = 100\naction = 'default'");
    let last_sent = send(&sb, b"[1300, 1400, 1800]", 25);
    std::thread::sleep(Duration::from_millis(800));
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let frames = read_trace(&sb.dir.join("line.trace")).decode(false);
    let (before, after): (Vec<_>, Vec<_>) = frames
        .iter()
        .partition(|f| f.start_ns < last_sent + 100_000_000);
    assert!(before.iter().all(|f| carries(f, &[1300, 1400, 1800])));
    let late: Vec<_> = after
        .iter()
        .filter(|f| f.start_ns > last_sent + 100_000_000 + 2 * FRAME_NS)
        .collect();
    // One frame carrying the defaults up to the throttle shows the action
    // (how many a loaded machine cuts short is its business).
    assert!(
        late.iter().any(|f| f.channels_us().len() >= 3),
        "{} frames after the failsafe, none with the throttle",
        late.len()
    );
    for f in late {
        // Throttle (channel 3) defaults to its minimum.
        assert!(
            carries(f, &[1500, 1500, 1000, 1500, 1500, 1500, 1500, 1500]),
            "{:?}",
            f.channels_us()
        );
    }
}

#[test]
fn startup_default_sends_defaults_before_the_first_command() {
    let sb = Sandbox::new("fs-startup");
    let (mut ppmd, _ingress) = start(&sb, "startup = 'default'");
    std::thread::sleep(Duration::from_millis(500));
    let first_sent = now_ns();
    send(&sb, b"[1100]", 25);
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let frames = read_trace(&sb.dir.join("line.trace")).decode(false);
    let early: Vec<_> = frames.iter().filter(|f| f.start_ns < first_sent).collect();
    // One frame before the first command carrying the defaults up to the
    // throttle shows the startup (how many a loaded machine cuts short is
    // its business).
    assert!(
        early.iter().any(|f| f.channels_us().len() >= 3),
        "{} frames before the first command, none with the throttle",
        early.len()
    );
    assert!(early.iter().all(|f| carries(f, &[1500, 1500, 1000])));
    assert!(frames
        .iter()
        .any(|f| f.channels_us().first() == Some(&1100)));
}

/// udp-ingress left running with another channel model than ppmd's (here
/// AETR against ppmd's TAER, where `{"norm": {"thr": -1}}`, zero throttle,
/// would be 1500 us on channel 1, throttle under TAER: half throttle) puts
/// nothing on the line: ppmd refuses its commands, counts them, says so in
/// its log and the status reply. Restarted with ppmd's configuration, the
/// same command flies, zero throttle on channel 1.
#[test]
fn commands_made_under_another_channel_model_are_refused() {
    let sb = Sandbox::new("fs-model");
    let ppmd_cfg = sb.dir.join("ppmd.toml");
    std::fs::copy(sb.config("[ppm]\norder = 'TAER'"), &ppmd_cfg).unwrap();
    let ingress_cfg = sb.config("");
    let mut ppmd = sb.start_ppmd(&ppmd_cfg, "line.trace");
    let mut ingress = sb.start_ingress(&ingress_cfg, &[]);
    let zero_throttle = br#"{"norm": {"thr": -1}}"#;
    send(&sb, zero_throttle, 60);
    // ppmd publishes its snapshot once a second.
    std::thread::sleep(Duration::from_millis(1_200));
    let reply = ppm_tests::status(sb.addr());
    let p = reply.ppmd.as_ref().expect("ppmd's timing");
    // Refused and counted: one shows it (ppmd takes only the newest command
    // when it decides a frame, so how many of the 60 it met is the
    // machine's); nothing flew.
    assert!(p.mismatched_commands >= 1, "{reply}");
    assert_eq!(p.state, "silent", "{reply}");
    assert_eq!(p.frames, 0, "{reply}");
    ppmd.wait_for_log(
        "refused: udp-ingress made them under another channel model",
        10 * SECOND,
    );
    let status = std::process::Command::new(ppm_tests::bin("ppm-status"))
        .args(["--to", &sb.addr().to_string()])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&status.stdout);
    assert!(text.contains("commands REFUSED"), "{text}");
    assert!(ingress
        .signal_and_wait(Signal::SIGTERM, 10 * SECOND)
        .success());

    // The ingress restarted with ppmd's configuration.
    let _ingress = sb.start_ingress(&ppmd_cfg, &[]);
    send(&sb, zero_throttle, 40);
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let frames = read_trace(&sb.dir.join("line.trace")).decode(false);
    // The command flies now: one frame carrying its first channel shows it.
    assert!(
        frames.iter().any(|f| !f.channels_us().is_empty()),
        "{} frames, none with a channel",
        frames.len()
    );
    for f in &frames {
        assert!(
            carries(f, &[1000, 1500, 1500, 1500]),
            "TAER: throttle first, at its minimum: {:?}",
            f.channels_us()
        );
    }
}

/// Logs are never worth the line: with its HdrHistogram log and its frame
/// log on a device that refuses every write, ppmd keeps emitting, says so
/// while running (log line, `log_errors` in the status reply) and exits 0
/// with its summary at SIGTERM.
#[test]
fn logs_that_cannot_be_written_do_not_stop_the_line() {
    let sb = Sandbox::new("fs-logs");
    let cfg = sb.config("[ppmd]\nframe_log = \"/dev/full\"");
    let cfg_s = cfg.to_str().unwrap();
    let trace = format!("sim:{}", sb.dir.join("line.trace").display());
    let mut ppmd = sb.spawn(
        "ppmd",
        &[
            "--config",
            cfg_s,
            "--output",
            &trace,
            "--hdr-log",
            "/dev/full",
        ],
        "ppmd",
    );
    ppmd.wait_for_log("commands from", 30 * SECOND);
    let _ingress = sb.start_ingress(&cfg, &[]);
    send(&sb, b"[1300]", 100);
    let reply = ppm_tests::status(sb.addr());
    let p = reply.ppmd.as_ref().expect("ppmd's timing");
    assert!(p.log_errors > 0, "{reply}");
    assert_eq!(p.state, "active", "{reply}");
    ppmd.wait_for_log("HdrHistogram log: cannot write", 10 * SECOND);
    ppmd.wait_for_log("frame log: cannot write", 10 * SECOND);
    assert!(
        ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success(),
        "{}",
        ppmd.log_text()
    );
    let log = ppmd.log_text();
    assert!(log.contains("stopped"), "the summary: {log}");
    assert!(log.contains("rows could not be written"), "{log}");
    // The line carried the command, and nothing else: one frame carrying
    // it shows the line went on (the reply above said active after the
    // errors; how many frames a loaded machine cuts short is its business).
    let ch1 = channel_of_frames(&read_trace(&sb.dir.join("line.trace")), 0);
    assert!(!ch1.is_empty(), "the command never flew");
    assert!(ch1.iter().all(|&v| v == 1300), "{ch1:?}");
}
