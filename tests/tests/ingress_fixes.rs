//! Whole-system checks of udp-ingress fixes, against the real binaries:
//!
//! - a groundstation outside `ingress.status_allow` that sends only its own
//!   HEARTBEAT, once a second and out of phase with ppm's beat, gets ppm's
//!   HEARTBEAT every second (RC_CHANNELS used to spend its credit first),
//!   and never more than 3 times the bytes it sent;
//! - `newest_seq` stays that of the last numbered JSON command after a
//!   MAVLink command (it became `null`);
//! - a JSON key given twice is refused as `duplicate_key` and never flies;
//! - an infinite MAV_CMD_SET_MESSAGE_INTERVAL is taken as 60 s, as the docs
//!   say (it was denied);
//! - bytes before a MAVLink frame are `mavlink_junk` (they were
//!   `invalid_utf8`);
//! - pymavlink without `MAVLINK20=1` signs nothing (MAVLink 1): refused as
//!   `unsigned`, and udp-ingress's log says how to fix it.

use ppm_shared::mavlink;
use ppm_shared::protocol::RejectReason;
use ppm_tests::{python3, read_trace, status, stop_all, Sandbox, Sender};
use std::time::Duration;

fn pymavlink_present() -> bool {
    std::process::Command::new("python3")
        .args(["-c", "import pymavlink"])
        .status()
        .is_ok_and(|s| s.success())
}

/// A groundstation that sends its HEARTBEAT when it connects (which starts
/// ppm's beat), then one a second, each 350 ms after ppm's beat, for 8 s,
/// reading what ppm sends meanwhile. argv: the port. Prints JSON: the times
/// of ppm's HEARTBEATs (s since the first datagram), its RC_CHANNELS, the
/// bytes it received from ppm and the bytes it sent.
const BEAT_LISTENER: &str = r#"
import json, os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
port = int(sys.argv[1])
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % port, source_system=255, source_component=190)
beats, rc, got, sent = [], 0, 0, 0
def beat():
    global sent
    msg = m.mav.heartbeat_encode(6, 8, 0, 0, 4)
    buf = msg.pack(m.mav)
    m.write(buf)
    sent += len(buf)
start = time.time()
beat()
k = 1
while True:
    now = time.time() - start
    if now >= 8.5:
        break
    if k <= 8 and now >= k + 0.35:
        beat()
        k += 1
    r = m.recv_match(blocking=True, timeout=0.01)
    if r is None:
        continue
    got += len(r.get_msgbuf())
    if r.get_type() == "HEARTBEAT":
        beats.append(round(time.time() - start, 3))
    elif r.get_type() == "RC_CHANNELS":
        rc += 1
print(json.dumps({"beats": beats, "rc": rc, "got": got, "sent": sent}))
"#;

/// ppm's HEARTBEAT every second to a remote groundstation that earns
/// little: only its own HEARTBEAT, once a second, 350 ms after ppm's beat.
/// Loopback is taken out of `ingress.status_allow`, so the 3x cap applies
/// as to a remote groundstation. Before RC_CHANNELS kept the HEARTBEAT's
/// bytes, one beat in two was held from the third second on.
#[test]
fn a_remote_groundstation_that_sends_only_its_heartbeat_gets_ppms_every_second() {
    assert!(pymavlink_present(), "pymavlink is needed for this test");
    let sb = Sandbox::new("beats");
    let cfg = sb.config_with_ingress("status_allow = []\n", "");
    let ingress = sb.start_ingress(&cfg, &[]);
    let out = python3(&sb.dir, "", &["-c", BEAT_LISTENER, &sb.port.to_string()]);
    let s = status(sb.addr());
    ingress.terminate();
    let v: serde_json::Value = serde_json::from_str(out.trim()).expect(&out);
    let beats: Vec<f64> = v["beats"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| b.as_f64().unwrap())
        .collect();
    // At once, then at 1, 2, ... 8 s: nine in 8.5 s, none missed.
    assert!(beats.len() >= 9, "{out}");
    assert!(beats[0] < 0.5, "the first at once: {out}");
    for w in beats.windows(2) {
        assert!(w[1] - w[0] < 1.3, "a beat missed: {out}");
    }
    // Within the cap, and RC_CHANNELS from what is left: 42 bytes a
    // second beyond the HEARTBEAT, about three in four seconds.
    let (got, sent) = (v["got"].as_u64().unwrap(), v["sent"].as_u64().unwrap());
    assert!(got <= 3 * sent, "{got} bytes for {sent}: {out}");
    assert!(v["rc"].as_u64().unwrap() >= 3, "{out}");
    assert!(s.mavlink.held > 0, "RC_CHANNELS held: {s:?}");
}

/// `newest_seq` is that of the last numbered JSON command: a MAVLink
/// command, and a JSON command without `seq`, leave it.
#[test]
fn newest_seq_stays_that_of_the_last_numbered_json_command() {
    let sb = Sandbox::new("newestseq");
    let cfg = sb.config("");
    let ingress = sb.start_ingress(&cfg, &[]);
    let tx = Sender::new(sb.addr());
    tx.send(br#"{"ch": [1100, 1200], "seq": 77}"#);
    let s = status(sb.addr());
    assert_eq!((s.datagrams.applied, s.newest_seq), (1, Some(77)), "{s}");
    let mut payload = [0u8; 38];
    payload[..2].copy_from_slice(&1300u16.to_le_bytes());
    tx.send(&mavlink::frame(
        2,
        (0, 255, 190),
        &mavlink::RC_CHANNELS_OVERRIDE,
        &payload,
    ));
    let s = status(sb.addr());
    assert_eq!(s.datagrams.applied, 2, "{s}");
    assert_eq!(s.newest_seq, Some(77), "after a MAVLink command: {s}");
    tx.send(b"[1400]");
    let s = status(sb.addr());
    assert_eq!((s.datagrams.applied, s.newest_seq), (3, Some(77)), "{s}");
    ingress.terminate();
}

/// A key twice in one object, at the top or inside `norm`, is refused as
/// `duplicate_key`, counted apart, and the line never carries it.
#[test]
fn a_key_given_twice_is_refused_and_never_flies() {
    let sb = Sandbox::new("dupkey");
    let cfg = sb.config("");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let tx = Sender::new(sb.addr());
    let sent: [&[u8]; 3] = [
        br#"{"thr": 1000, "thr": 2000}"#,
        br#"{"ch": [1700], "seq": 1, "seq": 2}"#,
        br#"{"norm": {"ail": 0.2, "ail": -1}, "seq": 3}"#,
    ];
    ppm_tests::at_50hz(30, |n| tx.send(sent[n as usize % 3]));
    std::thread::sleep(Duration::from_millis(300));
    let s = status(sb.addr());
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let d = &s.datagrams;
    assert_eq!(d.rejected.count(RejectReason::DuplicateKey), 30, "{s}");
    assert_eq!((d.rejected.total(), d.applied), (30, 0), "{s}");
    assert_eq!(s.newest_seq, None, "{s}");
    let frames = read_trace(&trace).decode(false);
    assert!(frames.is_empty(), "the line stays silent: {frames:?}");
    assert!(
        ingress
            .log_text()
            .contains("duplicate_key: duplicate key `"),
        "{}",
        ingress.log_text()
    );
}

/// MAV_CMD_SET_MESSAGE_INTERVAL of RC_CHANNELS with an infinite interval:
/// over 60 s, so 60 s (accepted: the RC_CHANNELS already due goes out, then
/// none for a minute); minus infinity is denied and changes nothing. argv:
/// the port. Prints JSON: the COMMAND_ACKs and the RC_CHANNELS of each
/// phase.
const INFINITE_INTERVAL: &str = r#"
import json, os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
port = int(sys.argv[1])
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % port, source_system=255, source_component=190)
def listen(seconds):
    acks, rc = [], 0
    end = time.time() + seconds
    while time.time() < end:
        m.mav.heartbeat_send(6, 8, 0, 0, 4)
        r = m.recv_match(blocking=True, timeout=0.1)
        while r is not None:
            if r.get_type() == "COMMAND_ACK":
                acks.append([r.command, r.result])
            elif r.get_type() == "RC_CHANNELS":
                rc += 1
            r = m.recv_match(blocking=False)
    return acks, rc
before = listen(1.0)
m.mav.command_long_send(1, 1, 511, 0, 65, float("-inf"), 0, 0, 0, 0, 0)
denied = listen(1.5)
m.mav.command_long_send(1, 1, 511, 0, 65, float("inf"), 0, 0, 0, 0, 0)
taken = listen(0.6)
after = listen(2.0)
print(json.dumps({"before": before, "denied": denied, "taken": taken, "after": after}))
"#;

#[test]
fn an_infinite_message_interval_is_a_minute() {
    assert!(pymavlink_present(), "pymavlink is needed for this test");
    let sb = Sandbox::new("interval");
    let cfg = sb.config("");
    let ingress = sb.start_ingress(&cfg, &[]);
    let out = python3(
        &sb.dir,
        "",
        &["-c", INFINITE_INTERVAL, &sb.port.to_string()],
    );
    ingress.terminate();
    let v: serde_json::Value = serde_json::from_str(out.trim()).expect(&out);
    // The default 4 Hz before, and after the denied -inf.
    assert!(v["before"][1].as_u64().unwrap() >= 2, "{out}");
    assert_eq!(v["denied"][0], serde_json::json!([[511, 2]]), "{out}");
    assert!(v["denied"][1].as_u64().unwrap() >= 2, "{out}");
    // Infinity: accepted; the one already due, then none for a minute.
    assert_eq!(v["taken"][0], serde_json::json!([[511, 0]]), "{out}");
    assert_eq!(v["after"], serde_json::json!([[], 0]), "{out}");
}

/// Bytes before a good MAVLink frame are `mavlink_junk`, as bytes between
/// or after frames are; not UTF-8 without a good frame stays `invalid_utf8`.
#[test]
fn junk_before_a_mavlink_frame_is_mavlink_junk() {
    let sb = Sandbox::new("junk");
    let cfg = sb.config("");
    let ingress = sb.start_ingress(&cfg, &[]);
    let tx = Sender::new(sb.addr());
    let hb = mavlink::frame(
        2,
        (0, 255, 190),
        &mavlink::HEARTBEAT,
        &[0, 0, 0, 0, 6, 8, 0, 4, 3],
    );
    tx.send(&[&b"\r\n"[..], &hb].concat());
    tx.send(&[&hb[..], b"\r\n"].concat());
    tx.send(b"\xff\xfe[1500]");
    let s = status(sb.addr());
    ingress.terminate();
    let r = &s.datagrams.rejected;
    assert_eq!(r.count(RejectReason::MavlinkJunk), 2, "{s}");
    assert_eq!(r.count(RejectReason::InvalidUtf8), 1, "{s}");
    assert_eq!(s.mavlink.peers, 0, "no peer made: {s}");
}

/// pymavlink signing as the docs showed it, without `MAVLINK20=1`: its
/// frames are MAVLink 1, refused as `unsigned`, and udp-ingress's log says
/// to send MAVLink 2 and how (the same script with it set flies: see
/// mavlink.rs).
#[test]
fn pymavlink_without_mavlink20_is_unsigned_and_the_log_says_why() {
    assert!(pymavlink_present(), "pymavlink is needed for this test");
    let sb = Sandbox::new("mav1sign");
    let hex = "27c0e8df855cbe39ceeff58ef0e792c51d522483501c81d223c87a4abe643881";
    let key = sb.write_file("mav.key", hex, 0o600);
    let cfg = sb.config(&format!("[mavlink]\nkey_file = \"{}\"\n", key.display()));
    let ingress = sb.start_ingress(&cfg, &[]);
    let script = r#"
import os, sys, time
os.environ.pop("MAVLINK20", None)
from pymavlink import mavutil
port, key = int(sys.argv[1]), bytes.fromhex(sys.argv[2])
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % port, source_system=255)
m.setup_signing(key, sign_outgoing=True)
for i in range(10):
    m.mav.rc_channels_override_send(1, 1, 1500, 1500, 1200, 1500, 0, 0, 0, 0)
    time.sleep(0.02)
print(mavutil.mavlink.WIRE_PROTOCOL_VERSION)
"#;
    let out = python3(&sb.dir, "", &["-c", script, &sb.port.to_string(), hex]);
    let s = status(sb.addr());
    let log = ingress.log_text();
    ingress.terminate();
    assert_eq!(out.trim(), "1.0", "pymavlink wrote MAVLink 1: {out}");
    let d = &s.datagrams;
    assert_eq!(d.rejected.count(RejectReason::Unsigned), 10, "{s}");
    assert_eq!((d.rejected.total(), d.applied), (10, 0), "{s}");
    assert!(
        log.contains("a MAVLink 1 frame")
            && log.contains("only MAVLink 2 carries a signature")
            && log.contains("MAVLINK20=1"),
        "{log}"
    );
}
