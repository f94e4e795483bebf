//! MAVLink from pymavlink and MAVProxy (from PyPI, clients nobody here
//! wrote) against the real udp-ingress and ppmd: RC_CHANNELS_OVERRIDE in
//! MAVLink 1 and 2 at 50 Hz, MANUAL_CONTROL, a signed frame, commands for
//! another system, ppm's HEARTBEAT and parameter as pymavlink reads them,
//! the README's pymavlink sender, MAVProxy's `rc`; the line carries
//! exactly the commanded values, in order, and nothing of what was
//! refused.

use ppm_shared::protocol::RejectReason;
use ppm_tests::{python3, read_trace, status, stop_all, Sandbox};

/// The sender: each phase sends its message 25 times at 50 Hz (0.5 s).
/// argv: the port. pymavlink writes MAVLink 2 when MAVLINK20 is set before
/// it is imported, and MAVLink 1 for a message sent with `force_mavlink1`.
const SENDER: &str = r#"
import os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil

port = int(sys.argv[1])
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % port, source_system=255, source_component=190)

def phase(send):
    for _ in range(25):
        send()
        time.sleep(0.02)

m.mav.heartbeat_send(6, 8, 0, 0, 4)
# A: MAVLink 1, all eight channels.
phase(lambda: m.mav.rc_channels_override_send(1, 1, 1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800, force_mavlink1=True))
# B: MAVLink 2: chan2 kept, chan5 released, chan9..18 ignored (0) or released (65534).
phase(lambda: m.mav.rc_channels_override_send(1, 1, 1900, 65535, 1250, 1750, 0, 1000, 2000, 1600, 0, 65534, 0, 0, 0, 0, 0, 0, 0, 0))
# Refused: for system 9, and for component 7.
phase(lambda: m.mav.rc_channels_override_send(9, 1, 1111, 1111, 1111, 1111, 1111, 1111, 1111, 1111))
phase(lambda: m.mav.rc_channels_override_send(1, 7, 1111, 1111, 1111, 1111, 1111, 1111, 1111, 1111))
# C: MANUAL_CONTROL to system 0 (any): pitch 500, roll -1000, thrust 250, yaw 0, button 2.
phase(lambda: m.mav.manual_control_send(0, 500, -1000, 250, 0, 2))
# ppm's HEARTBEAT, heard by now (before signing: then pymavlink drops unsigned frames).
beats = []
while True:
    hb = m.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5 if beats else 3)
    if hb is None:
        break
    beats.append(hb)
print(len(beats), sorted(set((b.get_srcSystem(), b.get_srcComponent(), b.type, b.autopilot) for b in beats)))
print(" ".join(str(b.system_status) for b in beats))
# The parameters, as QGroundControl asks for them.
m.mav.param_request_list_send(1, 1)
pv = m.recv_match(type="PARAM_VALUE", blocking=True, timeout=3)
print(pv.param_id, pv.param_value, pv.param_type, pv.param_count, pv.param_index)
# D: signed MAVLink 2 (ppm reads it; it does not check signatures yet).
m.setup_signing(bytes(range(32)), sign_outgoing=True)
phase(lambda: m.mav.rc_channels_override_send(0, 0, 1010, 1020, 1030, 1040, 1050, 1060, 1070, 1080))
print(mavutil.mavlink.WIRE_PROTOCOL_VERSION)
"#;

#[test]
fn pymavlink_flies_the_line_with_exactly_the_commanded_values() {
    if !pymavlink_present() {
        panic!("pymavlink is needed for this test: python3 -m pip install pymavlink");
    }
    let sb = Sandbox::new("mavlink");
    let cfg =
        sb.config("[mavlink]\nbuttons = [\"aux1\", \"aux2\"]\nvehicle_type = \"surface_boat\"\n");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let out = python3(&sb.dir, "", &["-c", SENDER, &sb.port.to_string()]);
    // ppm's HEARTBEATs as pymavlink read them: from system 1, component
    // 1, type SURFACE_BOAT (11, mavlink.vehicle_type), autopilot GENERIC
    // (0); the first at once (the line still
    // silent: STANDBY), then one a second, each with the line's state as
    // ppmd last reported it (STANDBY, ACTIVE or, between the phases,
    // CRITICAL for the failsafe).
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), 4, "{out}");
    let (n, ids) = lines[0].split_once(' ').unwrap();
    // How many is the function: one a second over the 2.5 s of phases and
    // the wait after them, not one per datagram.
    assert!((3..=5).contains(&n.parse::<u32>().unwrap()), "{out}");
    assert_eq!(ids, "[(1, 1, 11, 0)]", "{out}");
    let states: Vec<&str> = lines[1].split(' ').collect();
    assert_eq!(states[0], "3", "{out}");
    assert!(states.iter().all(|s| ["3", "4", "5"].contains(s)), "{out}");
    assert_eq!(lines[2], "PPM_CHANNELS 8.0 9 1 0", "ppm's one parameter");
    assert_eq!(lines[3], "2.0", "the sender's wire version");
    let s = status(sb.addr());
    stop_all(&mut ppmd, &mut [&mut ingress]);

    let d = &s.datagrams;
    assert_eq!(d.received, 6 * 25, "{s:?}");
    assert_eq!(d.rejected.count(RejectReason::WrongOutput), 50, "{s:?}");
    assert_eq!(d.rejected.total(), 50, "{s:?}");
    assert_eq!(d.applied + d.superseded + d.stale, 100, "{s:?}");
    // The sender's HEARTBEAT and its PARAM_REQUEST_LIST.
    assert_eq!(s.mavlink.no_command, 2, "{s:?}");
    // Heard from since the first datagram, 3 s before this status: a
    // HEARTBEAT at once, then one a second, the PARAM_VALUE and
    // RC_CHANNELS; none held (loopback lies in ingress.status_allow).
    let m = &s.mavlink;
    assert_eq!((m.peers, m.held), (1, 0), "{s:?}");
    assert!(m.sent >= 5, "{s:?}");

    // AETR, eight channels, defaults 1500.
    let a = [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800];
    let b = [1900, 1200, 1250, 1750, 1500, 1000, 2000, 1600];
    // x 500 onto ele, y -1000 onto ail, z 250 of 0..1000 onto thr, r 0
    // onto rud; button 2 (aux2) pressed, button 1 (aux1) released; aux3
    // and aux4 kept, but B is a second old by then (the refused phases),
    // past the failsafe: they keep their defaults, not B's values.
    let c = [1000, 1750, 1250, 1500, 1000, 2000, 1500, 1500];
    let signed = [1010, 1020, 1030, 1040, 1050, 1060, 1070, 1080];
    let sent = [a, b, c, signed];
    let frames = read_trace(&trace).decode(false);
    let mut seen = vec![];
    for f in &frames {
        let got = f.channels_us();
        let Some(k) = sent
            .iter()
            .position(|w| got.len() <= 8 && w[..got.len()] == got[..])
        else {
            panic!("a frame at {} carries {got:?}, never sent", f.start_ns);
        };
        // The commands differ on channel 1: every frame that carried it,
        // whole or cut short at a late edge (exact), tells which it was.
        if !got.is_empty() && seen.last() != Some(&k) {
            seen.push(k);
        }
    }
    assert_eq!(seen, [0, 1, 2, 3], "the commands in the order sent");
}

/// A groundstation that flies A, then B, with RC_CHANNELS_OVERRIDE at 50
/// Hz, and reads ppm's RC_CHANNELS: asked for at 10 Hz
/// (MAV_CMD_SET_MESSAGE_INTERVAL) after 0.5 s, stopped
/// (REQUEST_DATA_STREAM) after 2.5 s. argv: the port. Prints JSON: the
/// RC_CHANNELS (chancount, chan1..9) in order, the COMMAND_ACKs (command,
/// result), how many RC_CHANNELS came in the 1.5 s from 0.5 s after the
/// request, and how many before the stop was surely taken.
const RC_READER: &str = r#"
import json, os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
port = int(sys.argv[1])
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % port, source_system=255, source_component=190)
A = (1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800)
B = (1800, 1700, 1600, 1500, 1400, 1300, 1200, 1100)
rc, acks = [], []
def fly(ch, seconds):
    end = time.time() + seconds
    while time.time() < end:
        m.mav.rc_channels_override_send(1, 1, *ch)
        while True:
            r = m.recv_match(blocking=False)
            if r is None:
                break
            if r.get_type() == "RC_CHANNELS":
                rc.append([r.chancount] + [getattr(r, "chan%d_raw" % i) for i in range(1, 10)])
            elif r.get_type() == "COMMAND_ACK":
                acks.append([r.command, r.result])
        time.sleep(0.02)
fly(A, 0.5)
m.mav.command_long_send(1, 1, 511, 0, 65, 100000, 0, 0, 0, 0, 0)
fly(A, 0.5)
at_10hz = len(rc)
fly(A, 0.5)
fly(B, 1.0)
at_10hz = len(rc) - at_10hz
m.mav.request_data_stream_send(1, 1, 3, 0, 0)
fly(B, 0.5)
before_stop = len(rc)
fly(B, 1.0)
print(json.dumps({"rc": rc, "acks": acks, "at_10hz": at_10hz, "before_stop": before_stop}))
"#;

/// RC_CHANNELS as pymavlink reads them: the values the line carried,
/// frame for frame, at the rate the groundstation asked for, until it
/// stopped them.
#[test]
fn rc_channels_tell_the_groundstation_what_the_line_carried() {
    assert!(pymavlink_present(), "pymavlink is needed for this test");
    let sb = Sandbox::new("mavrc");
    let cfg = sb.config("");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let out = python3(&sb.dir, "", &["-c", RC_READER, &sb.port.to_string()]);
    let s = status(sb.addr());
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let got: serde_json::Value = serde_json::from_str(out.trim()).expect(&out);
    assert_eq!(got["acks"], serde_json::json!([[511, 0]]), "{out}");
    let rc: Vec<Vec<u64>> = serde_json::from_value(got["rc"].clone()).unwrap();
    // Every RC_CHANNELS with channels carries a whole frame as the line
    // carried it (to the microsecond, by the edges' actual times: a frame
    // whose edge was held up carries what the receivers read): A, then
    // B, never A again; chan9 unused.
    let whole: Vec<Vec<u64>> = read_trace(&trace)
        .decode(true)
        .iter()
        .map(|f| f.channels_us())
        .filter(|v| v.len() == 8)
        .collect();
    let a = [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800];
    let b = [1800, 1700, 1600, 1500, 1400, 1300, 1200, 1100];
    let near = |x: &[u64], y: &[u64], by: u64| x.iter().zip(y).all(|(p, q)| p.abs_diff(*q) <= by);
    let mut seen = vec![];
    for r in &rc {
        if r[0] == 0 {
            assert!(
                seen.is_empty(),
                "no channels only before the first frame: {rc:?}"
            );
            assert!(r[1..].iter().all(|&v| v == 65535), "{r:?}");
            continue;
        }
        assert_eq!((r[0], r[9]), (8, 65535), "{r:?}");
        let v = &r[1..9];
        assert!(
            whole.iter().any(|w| near(w, v, 1)),
            "{v:?} was not a whole frame on the line"
        );
        let k = if near(v, &a, 100) {
            0
        } else if near(v, &b, 100) {
            1
        } else {
            panic!("{v:?}")
        };
        if seen.last() != Some(&k) {
            seen.push(k);
        }
    }
    assert_eq!(seen, [0, 1], "{rc:?}");
    // At 10 Hz for 1.5 s (about 15; at the default 4 Hz about 6). How many
    // is the function here, the rate asked for: udp-ingress sends them by
    // its clock, not per frame, so cut-short frames do not thin them out
    // (a stall skips one per 100 ms; 11 leaves room for 0.4 s of those).
    let at_10hz = got["at_10hz"].as_u64().unwrap();
    assert!(at_10hz >= 11, "{at_10hz} RC_CHANNELS in 1.5 s: {out}");
    // Stopped: nothing more once the stop was taken. One before it is what
    // the stop needs to have something to stop (those at 10 Hz were).
    let before_stop = got["before_stop"].as_u64().unwrap() as usize;
    assert_eq!(rc.len(), before_stop, "{out}");
    assert!(before_stop >= 1, "{out}");
    // The status counts the RC_CHANNELS among the replies; the stop and
    // the command are no commands.
    assert!(s.mavlink.sent > rc.len() as u64, "{s:?}");
    assert_eq!(s.mavlink.no_command, 2, "{s:?}");
}

fn pymavlink_present() -> bool {
    std::process::Command::new("python3")
        .args(["-c", "import pymavlink"])
        .status()
        .is_ok_and(|s| s.success())
}

/// The pymavlink sender of the README's "From a MAVLink groundstation",
/// run as written (aimed at this test's port): the line carries its
/// throttle ramp, in order, with the other channels as it sent them.
#[test]
fn readme_pymavlink_sender_flies_the_line() {
    assert!(pymavlink_present(), "pymavlink is needed for this test");
    let code = ppm_tests::python_block("README.md", "### From a MAVLink groundstation");
    let sb = Sandbox::new("mavreadme");
    let code = code.replace("192.168.1.20:5005", &format!("127.0.0.1:{}", sb.port));
    assert!(
        code.contains(&sb.port.to_string()),
        "the block sends to 192.168.1.20:5005"
    );
    let cfg = sb.config("");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    python3(&sb.dir, "", &["-c", &code]);
    stop_all(&mut ppmd, &mut [&mut ingress]);
    // Every frame, whole or cut short at a late edge, carries the sent
    // values; each that carried the throttle (whole, or cut short after
    // it), the ramp in order.
    let frames = read_trace(&trace).decode(false);
    let mut thr = vec![];
    for f in &frames {
        let ch = f.channels_us();
        let want = [
            1500,
            1500,
            ch.get(2).copied().unwrap_or(0),
            1500,
            1500,
            1500,
            1500,
            1500,
        ];
        assert_eq!(ch[..], want[..ch.len()], "a frame at {}", f.start_ns);
        if ch.len() >= 3 {
            thr.push(ch[2]);
        }
    }
    // Two frames are the least a ramp shows in.
    assert!(thr.len() >= 2, "{} frames carried the throttle", thr.len());
    assert!(thr.windows(2).all(|w| w[1] >= w[0]), "{thr:?}");
    assert!(
        thr.iter().all(|t| (1000..=1498).contains(t) && t % 2 == 0),
        "{thr:?}"
    );
    assert!(thr.last().unwrap() - thr[0] > 250, "{thr:?}");
}

/// MAVProxy (from PyPI), headless, its `rc` command: RC_CHANNELS_OVERRIDE
/// at 10 Hz with the channels it was not given at 0 (released). The line
/// carries exactly what it set, the defaults elsewhere; what else MAVProxy
/// sends (parameter downloads over FTP, ...) is counted as ignored, never
/// applied or refused.
#[test]
fn mavproxy_rc_flies_the_line() {
    let present = std::process::Command::new("python3")
        .args(["-c", "import MAVProxy.mavproxy"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        present,
        "MAVProxy is needed for this test: python3 -m pip install --no-deps MAVProxy (and pymavlink, pyserial)"
    );
    let sb = Sandbox::new("mavproxy");
    let cfg = sb.config("");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let mut mavproxy = std::process::Command::new("python3")
        .args([
            "-m",
            "MAVProxy.mavproxy",
            &format!("--master=udpout:127.0.0.1:{}", sb.port),
            "--daemon",
            "--nowait",
            "--non-interactive",
            "--cmd",
            "rc 3 1200; rc 1 1600",
        ])
        .current_dir(&sb.dir)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("starting MAVProxy");
    std::thread::sleep(std::time::Duration::from_secs(4));
    let s = status(sb.addr());
    let _ = mavproxy.kill();
    let _ = mavproxy.wait();
    stop_all(&mut ppmd, &mut [&mut ingress]);

    // About 10 overrides a second for the seconds it ran (its start takes
    // some of them, more on a loaded machine): one taken in is the least,
    // the line below says which.
    let d = &s.datagrams;
    assert!(d.applied + d.superseded >= 1, "{s:?}");
    // What else it sends (FILE_TRANSFER_PROTOCOL, ...) is read and
    // ignored: nothing is refused.
    assert_eq!(d.rejected.total(), 0, "{s:?}");
    assert!(s.mavlink.ignored > 0, "{s:?}");
    assert_eq!(s.mavlink.peers, 1, "{s:?}");
    // `rc 3 1200` first, then `rc 1 1600` as well: the line carries the
    // one, then the other, and nothing else.
    let steps = [
        [1500, 1500, 1200, 1500, 1500, 1500, 1500, 1500],
        [1600, 1500, 1200, 1500, 1500, 1500, 1500, 1500],
    ];
    let frames = read_trace(&trace).decode(false);
    let mut at = 0;
    for f in &frames {
        let ch = f.channels_us();
        let k = (at..steps.len())
            .find(|&k| steps[k][..ch.len()] == ch[..])
            .unwrap_or_else(|| panic!("a frame at {} carries {ch:?}", f.start_ns));
        // The steps differ on channel 1: every frame that carried it, whole
        // or cut short at a late edge (exact), tells which it was.
        if !ch.is_empty() {
            at = k;
        }
    }
    // One frame carrying both is all this needs (how many a loaded machine
    // cuts short is its business).
    assert_eq!(at, 1, "the last frame carries both");
}

/// MAVLink 2 signing with pymavlink: only frames signed with
/// `mavlink.key_file`'s key fly; unsigned ones are `unsigned`, another
/// key's `bad_mac`, a frame sent again `replay`; ppm's replies are signed
/// so that pymavlink, signing too, takes them.
#[test]
fn signed_mavlink_flies_and_nothing_else_does() {
    use std::os::unix::fs::PermissionsExt;
    assert!(pymavlink_present(), "pymavlink is needed for this test");
    let sb = Sandbox::new("mavsign");
    let key = sb.dir.join("mav.key");
    // The key MAVProxy's `signing setup ppm-test` makes: SHA-256 of the
    // passphrase.
    let hex = "27c0e8df855cbe39ceeff58ef0e792c51d522483501c81d223c87a4abe643881";
    std::fs::write(&key, hex).unwrap();
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
    let cfg = sb.config(&format!("[mavlink]\nkey_file = \"{}\"\n", key.display()));
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let script = r#"
import os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
port, key = int(sys.argv[1]), bytes.fromhex(sys.argv[2])
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % port, source_system=255, source_component=190)
def phase(n, *ch):
    for _ in range(n):
        m.mav.rc_channels_override_send(1, 1, *ch)
        time.sleep(0.02)
phase(10, 1900, 1900, 1900, 1900, 1900, 1900, 1900, 1900)      # unsigned
m.setup_signing(key, sign_outgoing=True)
phase(25, 1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800)      # signed
m.setup_signing(bytes(32), sign_outgoing=True)
phase(10, 1900, 1900, 1900, 1900, 1900, 1900, 1900, 1900)      # another key
m.setup_signing(key, sign_outgoing=True)
phase(25, 1800, 1700, 1600, 1500, 1400, 1300, 1200, 1100)      # signed
m.write(m.mav.rc_channels_override_encode(1, 1, 1900, 1900, 1900, 1900, 1900, 1900, 1900, 1900).pack(m.mav))
last = m.mav.rc_channels_override_encode(1, 1, 1800, 1700, 1600, 1500, 1400, 1300, 1200, 1100).pack(m.mav)
m.write(last)
m.write(last)                                                   # sent again
hb = m.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
print(hb is not None and hb.get_signed(), hb is not None and hb.get_srcSystem())
"#;
    let out = python3(&sb.dir, "", &["-c", script, &sb.port.to_string(), hex]);
    let s = status(sb.addr());
    stop_all(&mut ppmd, &mut [&mut ingress]);
    assert_eq!(
        out.trim(),
        "True 1",
        "pymavlink took a signed HEARTBEAT from ppm: {out}"
    );
    let d = &s.datagrams;
    assert_eq!(d.rejected.count(RejectReason::Unsigned), 10, "{s:?}");
    assert_eq!(d.rejected.count(RejectReason::BadMac), 10, "{s:?}");
    assert_eq!(d.rejected.count(RejectReason::Replay), 1, "{s:?}");
    assert_eq!(d.rejected.total(), 21, "{s:?}");
    assert_eq!(d.applied + d.superseded, 52, "{s:?}");
    let a = [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800];
    let c = [1800, 1700, 1600, 1500, 1400, 1300, 1200, 1100];
    // The hand-packed 1900s were signed with the key: they fly (a frame or
    // two), then the last command.
    let d2 = [1900; 8];
    let frames = read_trace(&trace).decode(false);
    let mut seen = vec![];
    for f in &frames {
        let ch = f.channels_us();
        let k = [a, c, d2]
            .iter()
            .position(|w| w[..ch.len()] == ch[..])
            .unwrap_or_else(|| panic!("a frame at {} carries {ch:?}", f.start_ns));
        // They differ on channel 1: every frame that carried it, whole or
        // cut short at a late edge (exact), tells which it was.
        if !ch.is_empty() && seen.last() != Some(&k) {
            seen.push(k);
        }
    }
    assert_eq!(seen.first(), Some(&0), "{seen:?}");
    assert_eq!(seen.get(1), Some(&1), "{seen:?}");
    assert!(!seen.contains(&2) || seen.ends_with(&[2, 1]), "{seen:?}");
}

/// A restarted udp-ingress takes no signed MAVLink frame it took before:
/// the newest signing timestamp accepted is kept in
/// `mavlink.timestamp_file`. pymavlink signs 20 commands (A), of which the
/// last 10 are captured; after the restart those 10, sent again as they
/// were, are `replay`, and 20 newly signed ones (B) fly.
#[test]
fn a_restarted_ingress_takes_no_signed_frame_twice() {
    use nix::sys::signal::Signal;
    assert!(pymavlink_present(), "pymavlink is needed for this test");
    let sb = Sandbox::new("mavrestart");
    let hex = "27c0e8df855cbe39ceeff58ef0e792c51d522483501c81d223c87a4abe643881";
    let key = sb.write_file("mav.key", hex, 0o600);
    let cfg = sb.config(&format!("[mavlink]\nkey_file = \"{}\"\n", key.display()));
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let sign = r#"
import os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
port, key, v = int(sys.argv[1]), bytes.fromhex(sys.argv[2]), int(sys.argv[3])
m = mavutil.mavlink_connection("udpout:127.0.0.1:%d" % port, source_system=255, source_component=190)
m.setup_signing(key, sign_outgoing=True)
sent = []
for _ in range(20):
    buf = m.mav.rc_channels_override_encode(1, 1, v, v, v, v, v, v, v, v).pack(m.mav)
    m.write(buf)
    sent.append(buf.hex())
    time.sleep(0.02)
print(" ".join(sent[10:]))
"#;
    let port = sb.port.to_string();
    let captured = python3(&sb.dir, "", &["-c", sign, &port, hex, "1100"]);
    let first = status(sb.addr());
    assert!(
        ingress
            .signal_and_wait(Signal::SIGINT, std::time::Duration::from_secs(10))
            .success(),
        "{}",
        ingress.log_text()
    );
    // By default beside the shared memory, named after the output.
    let kept = std::fs::read_dir(sb.dir.join("ipc"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "mavlink_timestamp"))
        .map(|p| std::fs::read_to_string(p).unwrap())
        .expect("the timestamp file");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    assert!(
        ingress.log_text().contains(&format!(
            "signing timestamps {} and below refused",
            kept.trim().trim_start_matches('0')
        )),
        "{}",
        ingress.log_text()
    );
    let resend = r#"
import socket, sys, time
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
for h in sys.argv[2].split():
    s.sendto(bytes.fromhex(h), ("127.0.0.1", int(sys.argv[1])))
    time.sleep(0.02)
"#;
    python3(&sb.dir, "", &["-c", resend, &port, captured.trim()]);
    python3(&sb.dir, "", &["-c", sign, &port, hex, "1900"]);
    let s = status(sb.addr());
    stop_all(&mut ppmd, &mut [&mut ingress]);
    assert_eq!(
        first.datagrams.applied + first.datagrams.superseded,
        20,
        "{first:?}"
    );
    let d = &s.datagrams;
    assert_eq!(d.rejected.count(RejectReason::Replay), 10, "{s:?}");
    assert_eq!(d.rejected.total(), 10, "{s:?}");
    assert_eq!(d.applied + d.superseded, 20, "{s:?}");
    // The line: A, then (after the failsafe) B, never A again.
    let mut seen = vec![];
    for f in read_trace(&trace).decode(false) {
        let ch = f.channels_us();
        let k = [1100, 1500, 1900]
            .iter()
            .position(|&v| ch.iter().all(|&c| c == v))
            .unwrap_or_else(|| panic!("a frame at {} carries {ch:?}", f.start_ns));
        // Every frame that carried a channel, whole or cut short at a late
        // edge (exact), tells which it was.
        if !ch.is_empty() && k != 1 && seen.last() != Some(&k) {
            seen.push(k);
        }
    }
    assert_eq!(seen, [0, 2], "A, then B");
}
