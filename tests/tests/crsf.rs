//! CRSF through the whole pipeline, with the real binaries: commands in
//! over UDP, RC_CHANNELS_PACKED and LINK_STATISTICS frames out on the
//! simulated line (read back as a 420 000 baud 8N1 UART and each
//! firmware's framing read them) and on a pseudo-terminal (the exact bytes,
//! and the terminal settings ppmd set, read through termios2); the flight
//! controller's telemetry back through the pseudo-terminal to the status
//! reply and to pymavlink as a groundstation.

use ppm_shared::crsf::{self, CrsfReceiver, Framer, LinkStatistics, Verdict};
use ppm_shared::frame::Level;
use ppm_shared::wire::uart::{self, Parity, UartFormat};
use ppm_tests::{at_50hz, python3, read_trace, status, stop_all, Pty, Sandbox, Sender};
use std::time::Duration;

/// CRSF's UART format at the default rate.
const FORMAT: UartFormat = UartFormat {
    baud: 420_000,
    parity: Parity::None,
    stop_bits: 1,
};

/// `[ppm]` for CRSF to `receiver`, following the commands.
fn crsf_config(receiver: &str) -> String {
    format!("[ppm]\nprotocol = \"crsf\"\nreceiver = \"{receiver}\"\ntiming = \"follow\"\n")
}

/// Sends 60 commands at 50 Hz, the k-th with aileron at 1100 + 5 k us,
/// rudder at 1700 and aux12 (the 16th channel) at 1900; returns their
/// aileron values, us.
fn send_60(sb: &Sandbox) -> Vec<u64> {
    let sender = Sender::new(sb.addr());
    let mut sent = Vec::new();
    at_50hz(60, |k| {
        let ail = 1_100 + 5 * k;
        sender.send(format!("{{\"ail\": {ail}, \"rud\": 1700, \"aux12\": 1900}}").as_bytes());
        sent.push(ail);
    });
    std::thread::sleep(Duration::from_millis(100));
    sent
}

/// What `r`'s framing takes from `bytes` (each with the time its stop bit
/// ends): the RC channels it uses, ns, and how many link statistics frames
/// it read.
fn taken(r: CrsfReceiver, bytes: &[(u8, u64)]) -> (Vec<[u64; 16]>, usize) {
    let mut framer = Framer::new(r);
    let (mut rc, mut links) = (Vec::new(), 0);
    for &(b, end) in bytes {
        if let Some(t) = framer.push(b, end) {
            match r.verdict(&t) {
                Verdict::Used { channels_ns } => rc.push(channels_ns),
                Verdict::LinkStatistics(l) => {
                    assert_eq!(l, LinkStatistics::WIRED);
                    links += 1;
                }
                Verdict::Ignored => panic!("{r:?} ignored {:02x?}", t.frame()),
            }
        }
    }
    (rc, links)
}

/// The simulated line's trace, read as a 420 000 baud 8N1 UART from the
/// real edge times, is every frame: each firmware takes every RC frame
/// and a LINK_STATISTICS after each, and reads the values as sent, in
/// channel order (AETR: ail, ele, thr, rud), to 1 us.
#[test]
fn crsf_on_the_simulated_line_reads_back_as_8n1_at_420000() {
    let sb = Sandbox::new("crsf-sim");
    let cfg = sb.config(&crsf_config("any"));
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let sent = send_60(&sb);
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let trace = read_trace(&sb.dir.join("line.trace"));
    assert_eq!(trace.protocol, ppm_shared::frame::Protocol::Crsf);
    let edges: Vec<(u64, Level)> = trace.edges.iter().map(|e| (e.actual_ns, e.level)).collect();
    let chars = uart::decode(FORMAT, &edges, Level::High);
    assert!(
        chars.iter().all(|c| c.parity_ok && c.stop_ok),
        "8N1 throughout"
    );
    let frame_len = crsf::RC_FRAME_LEN + LinkStatistics::FRAME_LEN;
    assert_eq!(chars.len() % frame_len, 0, "whole frames");
    let frames = chars.len() / frame_len;
    assert!(frames >= 60, "{frames} frames");
    let bytes: Vec<(u8, u64)> = chars.iter().map(|c| (c.byte, c.end_ns)).collect();
    for r in CrsfReceiver::ALL {
        let (rc, links) = taken(r, &bytes);
        assert_eq!(
            (rc.len(), links),
            (frames, frames),
            "{r:?} takes every frame"
        );
        let mut ail: Vec<u64> = Vec::new();
        for ch in &rc {
            let near = |ns: u64, us: u64| ns.abs_diff(us * 1_000) <= 1_000;
            assert!(near(ch[1], 1_500) && near(ch[2], 1_000), "{r:?} {ch:?}");
            ail.push((ch[0] + 500) / 1_000);
            if near(ch[3], 1_700) {
                assert!(near(ch[15], 1_900), "{r:?} {ch:?}");
            }
        }
        ail.dedup();
        let close =
            ail.len() == sent.len() && ail.iter().zip(&sent).all(|(a, s)| a.abs_diff(*s) <= 1);
        assert!(close, "{r:?}: every command in order: {ail:?} vs {sent:?}");
    }
    // ppm-watch reads the same trace as each firmware does: one line per
    // RC frame, the commands in order; EdgeTX takes no CRSF.
    let trace = sb.dir.join("line.trace");
    let watch = |args: &[&str]| {
        std::process::Command::new(ppm_tests::bin("ppm-watch"))
            .arg(&trace)
            .args(["--once", "--actual"])
            .args(args)
            .output()
            .unwrap()
    };
    for args in [
        &[][..],
        &["--receiver", "betaflight"],
        &["--receiver", "ardupilot"],
    ] {
        let out = watch(args);
        assert!(out.status.success(), "{out:?}");
        let text = String::from_utf8(out.stdout).unwrap();
        assert_eq!(text.lines().count(), frames, "{args:?}: {text}");
        let mut ail: Vec<u64> = text
            .lines()
            .map(|l| {
                let v = l.split_whitespace().skip_while(|w| *w != "ail").nth(1);
                v.and_then(|v| v.parse::<f64>().ok())
                    .expect("an ail value")
                    .round() as u64
            })
            .collect();
        ail.dedup();
        let close =
            ail.len() == sent.len() && ail.iter().zip(&sent).all(|(a, s)| a.abs_diff(*s) <= 1);
        assert!(close, "{args:?}: {ail:?} vs {sent:?}");
    }
    // jitter --trace reads it as 8N1 at 420000, every character good, and
    // Betaflight's framing takes and uses every RC frame (and every link
    // statistics frame).
    let jitter = std::process::Command::new(ppm_tests::bin("jitter"))
        .args([
            "--trace",
            trace.to_str().unwrap(),
            "--receiver",
            "betaflight",
        ])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&jitter.stdout);
    assert!(jitter.status.success(), "{jitter:?}");
    assert!(text.contains("(CRSF, 420000 baud 8N1)"), "{text}");
    assert!(
        text.contains(&format!(
            "characters {} (0 with a parity or stop bit error)",
            chars.len()
        )),
        "{text}"
    );
    assert!(
        text.contains(&format!(
            "betaflight takes {frames} frames of channels and uses {frames}"
        )),
        "{text}"
    );
    let edgetx = watch(&["--receiver", "edgetx"]);
    assert!(!edgetx.status.success());
    assert!(
        String::from_utf8_lossy(&edgetx.stderr).contains("edgetx takes no CRSF"),
        "{edgetx:?}"
    );
}

/// ppmd sets the pseudo-terminal to raw 420 000 baud 8N1 (read through
/// termios2 from another descriptor) and writes whole frames: an RC frame
/// (address 0xC8, type 0x16, CRC holding, the values Betaflight reads as
/// sent, in channel order), then LINK_STATISTICS.
#[test]
fn crsf_on_a_serial_port_is_rc_frames_and_link_statistics() {
    let sb = Sandbox::new("crsf-pty");
    let pty = Pty::open().expect("a pseudo-terminal");
    let cfg = sb.config(&crsf_config("betaflight"));
    let output = format!("serial:{}", pty.slave.display());
    let cfg_s = cfg.to_str().unwrap();
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg_s, "--output", &output], "ppmd");
    ppmd.wait_for_log("commands from", Duration::from_secs(20));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let settings = ppmd::line::serial::SerialLine::settings_of(&pty.slave).expect("TCGETS2");
    let sent = send_60(&sb);
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let chunks = pty.finish();
    assert_eq!((settings.ispeed, settings.ospeed), (420_000, 420_000));
    assert_eq!(
        (settings.data_bits, settings.stop_bits, settings.parity),
        (8, 1, Parity::None)
    );
    assert!(settings.raw && !settings.flow_control, "{settings:?}");
    let bytes: Vec<u8> = chunks.iter().flat_map(|c| c.1.clone()).collect();
    let frame_len = crsf::RC_FRAME_LEN + LinkStatistics::FRAME_LEN;
    assert_eq!(bytes.len() % frame_len, 0, "whole frames only");
    let r = CrsfReceiver::Betaflight;
    let mut ail = Vec::new();
    for f in bytes.chunks(frame_len) {
        let (rc, link) = f.split_at(crsf::RC_FRAME_LEN);
        assert_eq!(link, LinkStatistics::WIRED.encode(), "link statistics");
        assert!(crsf::crc_holds(link));
        let raw = crsf::decode_rc(rc.try_into().unwrap()).expect("0xC8, 0x16, CRC");
        // Betaflight's scaling, to half its 0.625 us step.
        let read = |i: usize| r.read_ns(raw[i]);
        assert!(
            read(2).abs_diff(1_000_000) <= 313,
            "throttle at its default"
        );
        assert!(
            read(1).abs_diff(1_500_000) <= 313,
            "elevator at its default"
        );
        assert!(read(15).abs_diff(1_900_000) <= 313 || read(3).abs_diff(1_500_000) <= 313);
        ail.push((read(0) + 500) / 1_000);
    }
    ail.dedup();
    assert_eq!(ail, sent, "every command, in order");
}

/// A CRSF frame from the flight controller: `kind`, `payload`, its CRC.
fn fc_frame(kind: u8, payload: &[u8]) -> Vec<u8> {
    crsf::frame(crsf::ADDRESS_FLIGHT_CONTROLLER, kind, payload)
}

/// The groundstation: pymavlink sends its HEARTBEAT every 0.2 s for 4 s
/// and prints every SYS_STATUS, ATTITUDE, GPS_RAW_INT and STATUSTEXT it
/// gets from ppm, one JSON object a line. argv: the port.
const GROUNDSTATION: &str = r#"
import json, os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % int(sys.argv[1]), source_system=255, source_component=190)
end = time.time() + 4
beat = 0
while time.time() < end:
    if time.time() >= beat:
        m.mav.heartbeat_send(6, 8, 0, 0, 4)
        beat = time.time() + 0.2
    msg = m.recv_match(type=["SYS_STATUS", "ATTITUDE", "GPS_RAW_INT", "STATUSTEXT"], blocking=True, timeout=0.05)
    if msg is not None:
        d = msg.to_dict()
        d["sys"] = msg.get_srcSystem()
        print(json.dumps(d), flush=True)
"#;

/// What the flight controller sends on its TX line reaches the
/// groundstation: ppmd reads it from the pseudo-terminal (junk, a frame
/// with a bad CRC and one cut short among the good ones), the status
/// reply has the exact values and every bad frame counted by reason, and
/// pymavlink reads SYS_STATUS, ATTITUDE, GPS_RAW_INT and the flight mode's
/// STATUSTEXT with the same values.
#[test]
fn telemetry_from_the_flight_controller_reaches_the_groundstation() {
    assert!(
        std::process::Command::new("python3")
            .args(["-c", "import pymavlink"])
            .status()
            .is_ok_and(|s| s.success()),
        "pymavlink is needed for this test: python3 -m pip install pymavlink"
    );
    let sb = Sandbox::new("crsf-telemetry");
    let pty = Pty::open().expect("a pseudo-terminal");
    // Both read the output from the file, as under systemd: udp-ingress
    // learns there that the output has telemetry.
    let output = format!("serial:{}", pty.slave.display());
    let cfg = sb.config(&format!(
        "[ppmd]\noutput = \"{output}\"\n{}",
        crsf_config("betaflight")
    ));
    let cfg_s = cfg.to_str().unwrap();
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg_s], "ppmd");
    ppmd.wait_for_log("telemetry: reading", Duration::from_secs(20));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    ingress.wait_for_log(
        "telemetry from the flight controller",
        Duration::from_secs(20),
    );
    // 16.8 V, 12.3 A, 1234 mAh, 75 %; roll -0.5, pitch 0.1234, yaw 3.1415
    // rad; 47.3977419 N 8.5455938 E, 36.5 km/h, 271.15 deg, 488 m, 12
    // satellites; "ANGL".
    let battery = fc_frame(0x08, &[0x00, 0xA8, 0x00, 0x7B, 0x00, 0x04, 0xD2, 0x4B]);
    let attitude = fc_frame(0x1E, &[0x04, 0xD2, 0xEC, 0x78, 0x7A, 0xB7]);
    let gps = fc_frame(
        0x02,
        &[
            0x1C, 0x40, 0x52, 0x4B, 0x05, 0x17, 0xF4, 0x42, 0x01, 0x6D, 0x69, 0xEB, 0x05, 0xD0,
            0x0C,
        ],
    );
    let mode = fc_frame(0x21, b"ANGL\0");
    let mut bad_crc = battery.clone();
    *bad_crc.last_mut().unwrap() ^= 0xFF;
    let dir = sb.dir.clone();
    let port = sb.addr().port().to_string();
    let gcs = std::thread::spawn(move || python3(&dir, "", &["-c", GROUNDSTATION, &port]));
    std::thread::sleep(Duration::from_millis(500));
    // 40 rounds, 50 ms apart: each its frames back to back, as a flight
    // controller sends them between two RC frames.
    let rounds = 40;
    for _ in 0..rounds {
        let mut burst = vec![0x00, 0x55];
        for f in [&battery, &attitude, &gps, &mode, &bad_crc] {
            burst.extend_from_slice(f);
        }
        pty.send(&burst).expect("writing to the pty");
        std::thread::sleep(Duration::from_millis(50));
    }
    // A frame cut short: the line then pauses.
    pty.send(&attitude[..5]).expect("writing to the pty");
    let lines = gcs.join().expect("the groundstation");
    std::thread::sleep(Duration::from_millis(300));
    let st = status(sb.addr());
    // The Python package's telemetry query: the same member.
    let asked = python3(
        &sb.dir,
        ppm_tests::PYTHON_PACKAGE,
        &[
            "-c",
            "import json, sys, ppm; print(json.dumps(ppm.Sender(sys.argv[1]).telemetry()))",
            &sb.addr().to_string(),
        ],
    );
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let _ = pty.finish();
    let asked: serde_json::Value = serde_json::from_str(&asked).expect("JSON");
    assert_eq!(asked["battery"]["voltage_v"], 16.8, "{asked}");
    assert_eq!(asked["flight_mode"]["mode"], "ANGL", "{asked}");
    assert_eq!(asked["frames"], 4 * rounds, "{asked}");

    let t = st.telemetry.expect("a telemetry member");
    assert_eq!(t.port, pty_path(&output));
    assert_eq!(t.frames, 4 * rounds, "{t:?}");
    assert_eq!(t.bad["bad_crc"], rounds, "{t:?}");
    assert_eq!(t.bad["truncated"], 1, "{t:?}");
    // Junk: the two leading bytes of each round, and the bad frames'
    // bytes after their first.
    assert_eq!(
        t.junk_bytes,
        rounds * (2 + battery.len() as u64 - 1) + 4,
        "{t:?}"
    );
    let b = t.battery.expect("battery");
    assert_eq!(
        (b.voltage_v, b.current_a, b.used_mah, b.remaining_pct),
        (16.8, 12.3, 1234, 75)
    );
    let a = t.attitude.expect("attitude");
    assert_eq!(
        (a.roll_rad, a.pitch_rad, a.yaw_rad),
        (-0.5, 0.1234, 31_415.0 / 10_000.0)
    );
    let g = t.gps.expect("gps");
    assert_eq!(
        (
            g.lat_deg,
            g.lon_deg,
            g.altitude_m,
            g.groundspeed_kmh,
            g.heading_deg,
            g.satellites
        ),
        (47.3977419, 8.5455938, 488, 36.5, 271.15, 12)
    );
    assert_eq!(t.flight_mode.expect("mode").mode, "ANGL");

    let msgs: Vec<serde_json::Value> = lines
        .lines()
        .map(|l| serde_json::from_str(l).expect("a JSON line"))
        .collect();
    let of = |kind: &str| -> Vec<&serde_json::Value> {
        msgs.iter().filter(|m| m["mavpackettype"] == kind).collect()
    };
    let sys = of("SYS_STATUS");
    assert!(sys.len() >= 5, "{} SYS_STATUS in 2 s", sys.len());
    for m in &sys {
        assert_eq!(
            (
                &m["voltage_battery"],
                &m["current_battery"],
                &m["battery_remaining"]
            ),
            (&16800.into(), &1230.into(), &75.into())
        );
        assert_eq!(m["sys"], 1);
    }
    let att = of("ATTITUDE");
    assert!(att.len() >= 5, "{} ATTITUDE", att.len());
    for m in &att {
        let f = |k: &str| m[k].as_f64().unwrap();
        assert_eq!(
            (f("roll"), f("pitch"), f("yaw")),
            (
                -0.5,
                0.1234f32 as f64,
                (31_415.0f64 / 10_000.0) as f32 as f64
            )
        );
    }
    let gps_msgs = of("GPS_RAW_INT");
    assert!(gps_msgs.len() >= 5, "{} GPS_RAW_INT", gps_msgs.len());
    for m in &gps_msgs {
        let v = |k: &str| m[k].as_i64().unwrap();
        assert_eq!(
            [
                v("lat"),
                v("lon"),
                v("alt"),
                v("vel"),
                v("cog"),
                v("fix_type"),
                v("satellites_visible")
            ],
            [473977419, 85455938, 488_000, 1014, 27115, 3, 12]
        );
    }
    // At most ten of a kind a second: 40 frames of each in 2 s, 20 sent
    // at most (and one more at the edges).
    assert!(
        sys.len() <= 21 && att.len() <= 21,
        "{} {}",
        sys.len(),
        att.len()
    );
    let texts: Vec<&str> = of("STATUSTEXT")
        .iter()
        .map(|m| m["text"].as_str().unwrap())
        .collect();
    let want = format!("ppm {}: flight mode ANGL", sb.name);
    assert_eq!(texts.iter().filter(|t| **t == want).count(), 1, "{texts:?}");
}

/// The tty of a `serial:` output.
fn pty_path(output: &str) -> String {
    output.trim_start_matches("serial:").to_owned()
}

/// Nothing the flight controller sends can reach the line: while 256 KiB
/// of random bytes pour in on the tty's receive side, ppmd writes every
/// command, in order, as whole frames, and the telemetry reader counts the
/// junk.
#[test]
fn a_flood_on_the_receive_side_changes_nothing_on_the_line() {
    let sb = Sandbox::new("crsf-flood");
    let pty = std::sync::Arc::new(Pty::open().expect("a pseudo-terminal"));
    let output = format!("serial:{}", pty.slave.display());
    let cfg = sb.config(&format!(
        "[ppmd]\noutput = \"{output}\"\n{}",
        crsf_config("betaflight")
    ));
    let cfg_s = cfg.to_str().unwrap();
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg_s], "ppmd");
    ppmd.wait_for_log("telemetry: reading", Duration::from_secs(20));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let flood = {
        let pty = pty.clone();
        std::thread::spawn(move || {
            // xorshift: no two runs alike, nothing to seed.
            let mut x = ppm_shared::time::now_ns() | 1;
            let mut sent = 0;
            while sent < 256 * 1024 {
                let chunk: Vec<u8> = (0..1024)
                    .map(|_| {
                        x ^= x << 13;
                        x ^= x >> 7;
                        x ^= x << 17;
                        x as u8
                    })
                    .collect();
                pty.send(&chunk).expect("writing to the pty");
                sent += chunk.len();
            }
        })
    };
    let sent = send_60(&sb);
    flood.join().expect("the flood");
    std::thread::sleep(Duration::from_millis(300));
    let st = status(sb.addr());
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let pty = std::sync::Arc::try_unwrap(pty).unwrap_or_else(|_| panic!("the pty is shared"));
    let chunks = pty.finish();
    let bytes: Vec<u8> = chunks.iter().flat_map(|c| c.1.clone()).collect();
    let frame_len = crsf::RC_FRAME_LEN + LinkStatistics::FRAME_LEN;
    assert_eq!(bytes.len() % frame_len, 0, "whole frames only");
    let r = CrsfReceiver::Betaflight;
    let mut ail: Vec<u64> = bytes
        .chunks(frame_len)
        .map(|f| {
            let raw = crsf::decode_rc(f[..crsf::RC_FRAME_LEN].try_into().unwrap()).expect("CRC");
            (r.read_ns(raw[0]) + 500) / 1_000
        })
        .collect();
    ail.dedup();
    assert_eq!(ail, sent, "every command, in order");
    let t = st.telemetry.expect("a telemetry member");
    let dropped: u64 = t.bad.values().sum();
    assert!(t.junk_bytes + dropped > 100_000, "{t:?}");
    assert!(
        ppmd.log_text().contains(" 0 write errors"),
        "{}",
        ppmd.log_text()
    );
}
