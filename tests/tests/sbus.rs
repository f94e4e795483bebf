//! SBUS through the whole pipeline, with the real binaries: commands in
//! over UDP, SBUS frames out on the simulated line (read back as each
//! receiver's UART and framing read it) and on a pseudo-terminal (the
//! exact bytes a UART would send, and the terminal settings ppmd set).

use ppm_shared::sbus::{self, SbusReceiver, Verdict};
use ppm_tests::{at_50hz, read_trace, stop_all, Pty, Sandbox, Sender};
use std::time::Duration;

/// `[ppm]` for SBUS to `receiver`, following the commands.
fn sbus_config(receiver: &str) -> String {
    format!("[ppm]\nprotocol = \"sbus\"\nreceiver = \"{receiver}\"\ntiming = \"follow\"\n")
}

/// Sends 100 commands at 50 Hz, the k-th with aileron at 1100 + 5 k us and
/// aux12 (the 16th channel) at 1900; returns their aileron values, us.
fn send_100(sb: &Sandbox) -> Vec<u64> {
    let sender = Sender::new(sb.addr());
    let mut sent = Vec::new();
    at_50hz(100, |k| {
        let ail = 1_100 + 5 * k;
        sender.send(format!("{{\"ail\": {ail}, \"aux12\": 1900}}").as_bytes());
        sent.push(ail);
    });
    std::thread::sleep(Duration::from_millis(100));
    sent
}

/// Every command reaches the line, in order, and every modelled receiver
/// of `any` takes every frame from the trace's real edge times and reads
/// each value as sent (EdgeTX, whose scaling `any` encodes for, to the
/// microsecond).
#[test]
fn sbus_on_the_simulated_line_reaches_every_receiver() {
    let sb = Sandbox::new("sbus-sim");
    let cfg = sb.config(&sbus_config("any"));
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let sent = send_100(&sb);
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let trace = read_trace(&sb.dir.join("line.trace"));
    assert_eq!(trace.protocol, ppm_shared::frame::Protocol::Sbus);
    let chars = trace.sbus_characters(true);
    assert!(
        chars.iter().all(|c| c.parity_ok && c.stop_ok),
        "8E2 throughout"
    );
    assert_eq!(chars.len() % sbus::FRAME_LEN, 0);
    let frames = chars.len() / sbus::FRAME_LEN;
    for r in SbusReceiver::ALL {
        let taken = trace.sbus_taken(r, true);
        assert_eq!(taken.len(), frames, "{r:?} takes every frame");
        let mut read_ail = Vec::new();
        for t in &taken {
            let Verdict::Used(reading) = r.verdict(&t.frame) else {
                panic!("{r:?}: {:?}", r.verdict(&t.frame));
            };
            let ns = reading.channels_ns;
            let want_aux12 = 1_900_000;
            let off = match r {
                SbusReceiver::EdgeTx => 0..=0,
                SbusReceiver::ArduPilot => 4_375..=6_625,
                _ => 0..=625,
            };
            assert!(
                off.contains(&want_aux12.max(ns[15]).abs_diff(want_aux12.min(ns[15]))),
                "{r:?}: aux12 {}",
                ns[15]
            );
            read_ail.push(ns[0]);
        }
        if r == SbusReceiver::EdgeTx {
            // Each command once, in order, exact; repeats of the last.
            let mut seen: Vec<u64> = read_ail.iter().map(|ns| ns / 1_000).collect();
            seen.dedup();
            assert_eq!(seen, sent, "every command on the line, in order");
        }
    }
    let log = ppmd.log_text();
    assert!(log.contains("SBUS encoded for edgetx"), "{log}");
    // The tools read the same trace as SBUS.
    let trace_path = sb.dir.join("line.trace");
    let run = |bin: &str, args: &[&str]| {
        let out = std::process::Command::new(ppm_tests::bin(bin))
            .args(args)
            .arg(&trace_path)
            .output()
            .unwrap();
        assert!(out.status.success(), "{bin}: {out:?}");
        String::from_utf8(out.stdout).unwrap()
    };
    let jitter = run("jitter", &["--trace"]);
    assert!(
        jitter.contains(&format!(
            "characters {} (0 with a parity or stop bit error)",
            chars.len()
        )) && jitter.contains(&format!("edgetx takes {frames} frames")),
        "{jitter}"
    );
    let watch = run("ppm-watch", &["--once", "--actual"]);
    let rows: Vec<&str> = watch.lines().collect();
    assert_eq!(rows.len(), frames, "{watch}");
    assert!(rows.iter().all(|r| r.contains("aux12  1900.0")), "{watch}");
}

/// On a pseudo-terminal: ppmd sets it raw at 100 000 baud with 2 stop bits
/// (a pty keeps no parity) and writes whole 25-byte frames carrying the
/// commands, encoded for Betaflight.
#[test]
fn sbus_on_a_serial_port_is_whole_frames_of_the_exact_bytes() {
    let sb = Sandbox::new("sbus-pty");
    let pty = Pty::open().expect("a pseudo-terminal");
    let cfg = sb.config(&sbus_config("betaflight"));
    let output = format!("serial:{}", pty.slave.display());
    let cfg_s = cfg.to_str().unwrap();
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg_s, "--output", &output], "ppmd");
    ppmd.wait_for_log("commands from", Duration::from_secs(20));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    // The settings ppmd left on the port, read through another descriptor.
    let settings = ppmd::line::serial::SerialLine::settings_of(&pty.slave).expect("TCGETS2");
    let sent = send_100(&sb);
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let chunks = pty.finish();
    assert_eq!((settings.ispeed, settings.ospeed), (100_000, 100_000));
    assert_eq!((settings.data_bits, settings.stop_bits), (8, 2));
    assert!(settings.raw && !settings.flow_control, "{settings:?}");
    let bytes: Vec<u8> = chunks.iter().flat_map(|c| c.1.clone()).collect();
    assert_eq!(bytes.len() % sbus::FRAME_LEN, 0, "whole frames only");
    let mut ail = Vec::new();
    for f in bytes.chunks(sbus::FRAME_LEN) {
        let frame: [u8; sbus::FRAME_LEN] = f.try_into().unwrap();
        let (raw, flags) = sbus::decode(&frame).expect("header and end byte");
        assert_eq!(flags, sbus::Flags::default());
        let r = SbusReceiver::Betaflight2026;
        // Betaflight's scaling, to its 0.625 us step.
        assert!(r.read_ns(raw[15]).abs_diff(1_900_000) <= 312);
        assert!(
            r.read_ns(raw[2]).abs_diff(1_000_000) <= 312,
            "throttle at its default"
        );
        ail.push((r.read_ns(raw[0]) + 500) / 1_000);
    }
    ail.dedup();
    assert_eq!(ail, sent, "every command, in order");
}
