//! Tests of the read-back as udp-ingress reports it: the status reply's
//! `readback` member, the JSON events, and what MAVLink peers get
//! (STATUSTEXT, RC_CHANNELS of the radio, SERVO_OUTPUT_RAW of the line).
//! The receive loop's part (it sees a change while no datagram comes) is
//! tested in `server.rs`.

use super::*;
use crate::peers::{self, Peers};
use crate::{Intake, Outcome, ReceiveThread};
use ppm_shared::capture::ReadbackState::{self, Following, NoInput, Overridden};
use ppm_shared::config::Config;
use ppm_shared::ipc::LineSample;
use ppm_shared::mavlink::{self, HEARTBEAT, RC_CHANNELS, SERVO_OUTPUT_RAW, STATUSTEXT};
use serde_json::{json, Value};
use std::time::{Duration, Instant};

const S: u64 = 1_000_000_000;
const MS: u64 = 1_000_000;
const INPUT: &str = "sim:/run/ppm/radio.trace";

fn intake() -> Intake {
    Intake::new(
        "pi",
        Config::default().validate().unwrap(),
        Duration::from_secs(1),
    )
    .with_readback(INPUT.into())
}

fn addr(s: &str) -> SocketAddr {
    s.parse().unwrap()
}

/// A read-back sample published at `at`, in `state` after `changes`
/// changes (the last at `changed`), its newest frame begun 2 ms before.
pub(crate) fn sample(at: u64, state: ReadbackState, changes: u64, changed: u64) -> ReadbackSample {
    let mut values_ns = [0; MAX_CHANNELS];
    values_ns[..4].copy_from_slice(&[1_100_400, 1_499_600, 1_900_000, 1_500_000]);
    ReadbackSample {
        published_mono_ns: at,
        state: state as u32,
        channels: 4,
        changes,
        changed_mono_ns: changed,
        edges: 1_234,
        frames: 250,
        matched: 240,
        mismatched: 10,
        refused: [1, 2, 3, 4, 5, 6, 7, 8],
        start_mono_ns: at - 2 * MS,
        values_ns,
        max_diff_ns: 12_345,
        reserved: 0,
    }
}

/// The `readback` member of `i`'s status reply at `now`, as sent.
fn readback_member(i: &Intake, uptime: Duration, now: u64) -> Value {
    let reply = i.status(uptime, &ReceiveThread::default(), now, None);
    let v: Value = serde_json::from_str(&reply.to_json()).unwrap();
    v["readback"].clone()
}

#[test]
fn the_status_reply_carries_the_newest_readback_and_says_stale_when_ppmd_is_quiet() {
    let mut i = intake();
    // Before any sample: stale, nothing read, waited as long as udp-ingress ran.
    assert_eq!(
        readback_member(&i, Duration::from_millis(1_500), 10 * S),
        json!({
            "state": "stale",
            "input": INPUT,
            "since_ms": null,
            "changes": 0,
            "edges": 0,
            "frames": 0,
            "matched": 0,
            "mismatched": 0,
            "refused": {"lost_events": 0, "lost_frames": 0, "runts": 0, "noise": 0,
                        "out_of_window": 0, "too_many_channels": 0, "wrong_count": 0, "unsynced": 0},
            "ch_us": [],
            "max_diff_us": 0.0,
            "age_ms": 1500.0,
        })
    );
    i.readback(sample(10 * S, Following, 3, 9 * S));
    let at = 10 * S + 250 * MS + 400;
    assert_eq!(
        readback_member(&i, Duration::ZERO, at),
        json!({
            "state": "following",
            "input": INPUT,
            "since_ms": 1250.0,
            "changes": 3,
            "edges": 1234,
            "frames": 250,
            "matched": 240,
            "mismatched": 10,
            "refused": {"lost_events": 1, "lost_frames": 2, "runts": 3, "noise": 4,
                        "out_of_window": 5, "too_many_channels": 6, "wrong_count": 7, "unsynced": 8},
            "ch_us": [1100.4, 1499.6, 1900.0, 1500.0],
            "max_diff_us": 12.345,
            "age_ms": 250.0,
        })
    );
    // 1 s old is still fresh; older is stale, the counts kept.
    let r = readback_member(&i, Duration::ZERO, 11 * S);
    assert_eq!(
        (&r["state"], &r["age_ms"]),
        (&json!("following"), &json!(1000.0))
    );
    let r = readback_member(&i, Duration::ZERO, 11 * S + 1);
    assert_eq!((&r["state"], &r["frames"]), (&json!("stale"), &json!(250)));
    // A code this build does not know.
    let mut odd = sample(12 * S, Following, 4, 12 * S);
    odd.state = 9;
    i.readback(odd);
    assert_eq!(
        readback_member(&i, Duration::ZERO, 12 * S)["state"],
        "unknown"
    );
    // No change yet: no since_ms.
    let mut i = intake();
    i.readback(sample(10 * S, NoInput, 0, 0));
    assert_eq!(
        readback_member(&i, Duration::ZERO, 10 * S)["since_ms"],
        Value::Null
    );

    // Without a read-back the reply has no `readback` member at all.
    let plain = Intake::new(
        "pi",
        Config::default().validate().unwrap(),
        Duration::from_secs(1),
    );
    let text = plain
        .status(Duration::ZERO, &ReceiveThread::default(), S, None)
        .to_json();
    assert!(!text.contains("readback"), "{text}");
}

/// One event per change, to the sender of the newest accepted JSON
/// command (a MAVLink command does not make its sender the target), none
/// for a sample that changes nothing, none for the first sample seen.
#[test]
fn each_change_sends_one_event_to_the_newest_json_sender() {
    let mut i = intake();
    let t = Instant::now();
    let (a, b, gcs) = (
        addr("192.0.2.1:4000"),
        addr("192.0.2.2:4001"),
        addr("192.0.2.3:14550"),
    );
    let cmd = br#"{"ch":[1500,1500,1500,1500],"seq":1}"#;
    assert_eq!(i.offer(cmd, a, 1, 1, t), Outcome::Accepted);
    // 36 bytes each earn 108: four, enough for the three events below
    // (104 to 114 bytes each).
    for seq in [2, 3, 4, 5] {
        let cmd = format!(r#"{{"ch":[1500,1500,1500,1500],"seq":{seq}}}"#);
        assert_eq!(i.offer(cmd.as_bytes(), b, 2, 2, t), Outcome::Accepted);
    }
    let over = crate::tests::rc_override(2, &[1500]);
    assert_eq!(i.offer(&over, gcs, 3, 3, t), Outcome::Accepted);
    // No target before the first sample: nothing to tell, and no change.
    assert_eq!(i.readback(sample(10 * S, NoInput, 0, 0)), None);
    let mut more = sample(10 * S + 100 * MS, NoInput, 0, 0);
    more.frames += 5;
    assert_eq!(i.readback(more), None, "no change");
    let (change, event) = i
        .readback(sample(11 * S, Following, 1, 10 * S + 980 * MS))
        .expect("a change");
    assert_eq!(change.from, NoInput as u32);
    assert_eq!(
        event,
        Some((
            b,
            r#"{"changed_mono_ns":10980000000,"changes":1,"event":"readback","from":"no_input","name":"pi","state":"following"}"#
                .to_string()
        ))
    );
    assert_eq!(
        i.readback(sample(11 * S + 20 * MS, Following, 1, 10 * S + 980 * MS)),
        None
    );
    // Two changes between two samples read (following, overridden,
    // following, overridden): one event, its counter says 3.
    let (_, event) = i.readback(sample(12 * S, Overridden, 3, 12 * S)).unwrap();
    assert_eq!(
        event.unwrap().1,
        r#"{"changed_mono_ns":12000000000,"changes":3,"event":"readback","from":"following","name":"pi","state":"overridden"}"#
    );
    // ppmd restarted: its counter starts again.
    let (_, event) = i.readback(sample(20 * S, NoInput, 0, 0)).unwrap();
    assert_eq!(
        event.unwrap().1,
        r#"{"changed_mono_ns":0,"changes":0,"event":"readback","from":"overridden","name":"pi","state":"no_input"}"#
    );
    let c = i.readback_state().unwrap().counters();
    assert_eq!(c, EventCounters { sent: 3, held: 0 });
}

/// A sender earns 3 times the bytes of its accepted commands, as MAVLink
/// peers do: a forged command cannot aim more at its victim. One in
/// `ingress.status_allow` needs no credit.
#[test]
fn events_are_earned_by_the_senders_commands_unless_it_lies_in_status_allow() {
    let t = Instant::now();
    let from = addr("192.0.2.1:4000");
    let text_len = event_text(
        "pi",
        &Change {
            from: 0,
            sample: sample(11 * S, Following, 1, 11 * S),
        },
    )
    .len();
    assert_eq!(text_len, 112);
    for (exempt, want) in [(false, None), (true, Some(from))] {
        let nets = if exempt {
            vec!["192.0.2.0/24".parse().unwrap()]
        } else {
            vec![]
        };
        let mut i = intake().with_status_allow(nets);
        // 6 bytes earn 18.
        assert_eq!(i.offer(b"[1500]", from, 1, 1, t), Outcome::Accepted);
        i.readback(sample(10 * S, NoInput, 0, 0));
        let (_, event) = i.readback(sample(11 * S, Following, 1, 11 * S)).unwrap();
        assert_eq!(event.map(|(to, _)| to), want, "exempt {exempt}");
    }
    // 38 bytes earn 114: one event of 112 bytes, and 2 left (the next is
    // 114).
    let mut i = intake();
    let cmd = br#"{"ch":[1500,1500,1500,1500],"seq":100}"#;
    assert_eq!(cmd.len(), 38);
    i.offer(cmd, from, 1, 1, t);
    i.readback(sample(10 * S, NoInput, 0, 0));
    assert!(i
        .readback(sample(11 * S, Following, 1, 11 * S))
        .unwrap()
        .1
        .is_some());
    assert!(i
        .readback(sample(12 * S, Overridden, 2, 12 * S))
        .unwrap()
        .1
        .is_none());
    assert_eq!(
        i.readback_state().unwrap().counters(),
        EventCounters { sent: 1, held: 1 }
    );
    // A socket that could not send it: held.
    i.readback_event_not_sent();
    assert_eq!(
        i.readback_state().unwrap().counters(),
        EventCounters { sent: 0, held: 2 }
    );
}

/// A MAVLink 2 frame's message id and payload, zero-extended to the
/// message's whole length (unsigned frames).
pub(crate) fn decode(f: &[u8]) -> (u32, Vec<u8>) {
    assert_eq!(f[0], mavlink::STX_V2, "{f:?}");
    let id = u32::from_le_bytes([f[7], f[8], f[9], 0]);
    let spec = mavlink::spec(id).expect("a message ppm knows");
    let mut p = f[10..f.len() - 2].to_vec();
    assert_eq!(
        mavlink::frame_crc(spec, &f[1..f.len() - 2]).to_le_bytes(),
        f[f.len() - 2..],
        "its CRC"
    );
    p.resize(spec.max_len as usize, 0);
    (id, p)
}

fn u16_at(p: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([p[at], p[at + 1]])
}

/// STATUSTEXT: severity, text (to its NUL), id, chunk_seq.
pub(crate) fn statustext(p: &[u8]) -> (u8, String, u16, u8) {
    let text = &p[1..51];
    let end = text.iter().position(|&b| b == 0).unwrap_or(50);
    (
        p[0],
        String::from_utf8(text[..end].to_vec()).unwrap(),
        u16_at(p, 51),
        p[53],
    )
}

/// RC_CHANNELS: time_boot_ms, chancount, chan1..chan(count), and whether
/// every channel past them is UINT16_MAX.
pub(crate) fn rc_channels(p: &[u8]) -> (u32, u8, Vec<u16>, bool) {
    let n = p[40] as usize;
    let chan: Vec<u16> = (0..18).map(|i| u16_at(p, 4 + 2 * i)).collect();
    (
        u32::from_le_bytes([p[0], p[1], p[2], p[3]]),
        p[40],
        chan[..n].to_vec(),
        chan[n..].iter().all(|&c| c == u16::MAX),
    )
}

/// SERVO_OUTPUT_RAW: time_usec, port, servo1..16.
pub(crate) fn servo_output_raw(p: &[u8]) -> (u32, u8, Vec<u16>) {
    let mut servo: Vec<u16> = (0..8).map(|i| u16_at(p, 4 + 2 * i)).collect();
    servo.extend((0..8).map(|i| u16_at(p, 21 + 2 * i)));
    (u32::from_le_bytes([p[0], p[1], p[2], p[3]]), p[20], servo)
}

/// The messages in `out` to `to`, decoded, in order.
fn to_peer(out: &[(SocketAddr, Vec<u8>)], to: SocketAddr) -> Vec<(u32, Vec<u8>)> {
    out.iter()
        .filter(|(a, _)| *a == to)
        .map(|(_, f)| decode(f))
        .collect()
}

fn line_sample(start: u64) -> LineSample {
    let mut values_ns = [0; MAX_CHANNELS];
    values_ns[..4].copy_from_slice(&[1_000_000, 1_250_400, 1_750_600, 2_000_000]);
    LineSample {
        frame: 7,
        start_mono_ns: start,
        channels: 4,
        state: 1,
        values_ns,
    }
}

/// With a read-back, a MAVLink peer gets a STATUSTEXT for each change (at
/// once, in order), RC_CHANNELS carrying what the radio transmits and
/// SERVO_OUTPUT_RAW what the line carries, each decoded to its fields.
#[test]
fn mavlink_peers_get_each_change_as_statustext_and_the_radio_in_rc_channels() {
    let t = Instant::now();
    let gcs = addr("192.0.2.3:14550");
    let mut i = intake().with_status_allow(vec!["192.0.2.0/24".parse().unwrap()]);
    let hb = mavlink::frame(2, (0, 255, 190), &HEARTBEAT, &[0, 0, 0, 0, 6, 8, 0, 4, 3]);
    assert_eq!(i.offer(&hb, gcs, 1, 1, t), Outcome::NoCommand);
    let now = 10 * S;
    let line = line_sample(now - 5 * MS);
    let due = |i: &mut Intake, at: Instant, mono: u64| {
        let mut out = vec![];
        i.mavlink_due((at, mono, 0), (None, Some(&line)), &mut out);
        to_peer(&out, gcs)
    };
    i.readback(sample(now, NoInput, 0, 0));
    let got = due(&mut i, t, now);
    let ids: Vec<u32> = got.iter().map(|(id, _)| *id).collect();
    assert_eq!(
        ids,
        [HEARTBEAT.id, RC_CHANNELS.id, SERVO_OUTPUT_RAW.id],
        "no change yet"
    );
    // RC_CHANNELS: the radio's frame (begun 2 ms before `now`), to the us.
    assert_eq!(
        rc_channels(&got[1].1),
        (9_998, 4, vec![1100, 1500, 1900, 1500], true)
    );
    // SERVO_OUTPUT_RAW: the line's (begun 5 ms before), port 0, 0 past it.
    let mut servo = vec![1000, 1250, 1751, 2000];
    servo.resize(16, 0);
    assert_eq!(
        servo_output_raw(&got[2].1),
        (((now - 5 * MS) / 1_000) as u32, 0, servo.clone())
    );

    // Three changes: three STATUSTEXTs at the next due, in order, before
    // anything else; then none.
    let ms = Duration::from_millis;
    i.readback(sample(now + 10 * MS, Following, 1, now + 10 * MS));
    i.readback(sample(now + 20 * MS, Overridden, 2, now + 20 * MS));
    i.readback(sample(now + 30 * MS, NoInput, 3, now + 30 * MS));
    let got = due(&mut i, t + ms(30), now + 30 * MS);
    let texts: Vec<(u8, String, u16, u8)> = got
        .iter()
        .filter(|(id, _)| *id == STATUSTEXT.id)
        .map(|(_, p)| statustext(p))
        .collect();
    assert_eq!(
        texts,
        [
            (5, "ppm pi: following".to_string(), 0, 0),
            (
                4,
                "ppm pi: overridden (instructor has control)".to_string(),
                0,
                0
            ),
            (4, "ppm pi: no read-back input".to_string(), 0, 0),
        ]
    );
    assert_eq!(got.len(), 3, "the streams are not due yet");
    i.readback(sample(now + 40 * MS, NoInput, 3, now + 30 * MS));
    assert!(due(&mut i, t + ms(40), now + 40 * MS).is_empty());

    // A radio frame begun more than 300 ms ago: RC_CHANNELS say no
    // channels; SERVO_OUTPUT_RAW still carries the line's.
    let later = now + 250 * MS;
    let old = sample(later, NoInput, 3, now + 30 * MS);
    let mut old = ReadbackSample {
        start_mono_ns: later - 301 * MS,
        ..old
    };
    i.readback(old);
    let got = due(&mut i, t + ms(250), later);
    let rc = got.iter().find(|(id, _)| *id == RC_CHANNELS.id).unwrap();
    assert_eq!(rc_channels(&rc.1), ((later / MS) as u32, 0, vec![], true));
    let servo_now = got
        .iter()
        .find(|(id, _)| *id == SERVO_OUTPUT_RAW.id)
        .unwrap();
    assert_eq!(servo_output_raw(&servo_now.1).2, servo);
    // Nor does one with no channels.
    old.start_mono_ns = later + 100 * MS;
    old.channels = 0;
    i.readback(old);
    let got = due(&mut i, t + ms(500), later + 250 * MS);
    let rc = got.iter().find(|(id, _)| *id == RC_CHANNELS.id).unwrap();
    assert_eq!(rc_channels(&rc.1).1, 0);
}

/// Without a read-back, RC_CHANNELS carry the line as before, and
/// SERVO_OUTPUT_RAW the same values; no STATUSTEXT.
#[test]
fn without_a_readback_rc_channels_and_servo_output_raw_both_carry_the_line() {
    let t = Instant::now();
    let gcs = addr("192.0.2.3:14550");
    let mut i = Intake::new(
        "pi",
        Config::default().validate().unwrap(),
        Duration::from_secs(1),
    )
    .with_status_allow(vec!["192.0.2.0/24".parse().unwrap()]);
    let hb = mavlink::frame(2, (0, 255, 190), &HEARTBEAT, &[0, 0, 0, 0, 6, 8, 0, 4, 3]);
    i.offer(&hb, gcs, 1, 1, t);
    assert_eq!(i.readback(sample(10 * S, Following, 1, 10 * S)), None);
    let line = line_sample(10 * S - 5 * MS);
    let mut out = vec![];
    i.mavlink_due((t, 10 * S, 0), (None, Some(&line)), &mut out);
    let got = to_peer(&out, gcs);
    let ids: Vec<u32> = got.iter().map(|(id, _)| *id).collect();
    assert_eq!(ids, [HEARTBEAT.id, RC_CHANNELS.id, SERVO_OUTPUT_RAW.id]);
    assert_eq!(
        rc_channels(&got[1].1),
        (9_995, 4, vec![1000, 1250, 1751, 2000], true)
    );
    assert_eq!(
        servo_output_raw(&got[2].1).2[..5],
        [1000, 1250, 1751, 2000, 0]
    );
}

/// A STATUSTEXT a peer has not earned waits (not counted as held) until
/// it has, leaving one HEARTBEAT's worth; a long one goes in chunks; more
/// than TEXTS_KEPT waiting, the oldest make room.
#[test]
fn a_statustext_not_earned_waits_for_the_credit() {
    let t = Instant::now();
    let gcs = addr("192.0.2.3:14550");
    let none = peers::LineNow {
        state: 3,
        line: peers::Frame {
            values_us: &[],
            at_us: 0,
        },
        radio: None,
        telemetry: None,
    };
    let mut p = Peers::new(1, 1, 8, 0);
    // 21 bytes earn 63: the HEARTBEAT (21) at once, 42 left.
    p.heard(gcs, 2, 21, false, t);
    p.announce(4, "ppm pi: overridden (instructor has control)");
    let mut out = vec![];
    p.due(t, none, None, 0, &mut out);
    let ids: Vec<u32> = to_peer(&out, gcs).iter().map(|(id, _)| *id).collect();
    assert_eq!(ids, [HEARTBEAT.id]);
    assert_eq!(p.counters(), peers::ReplyCounters { sent: 1, held: 0 });
    // 42 + 63 = 105: the STATUSTEXT (56) with a HEARTBEAT (21) left.
    p.heard(gcs, 2, 21, false, t);
    out.clear();
    p.due(t, none, None, 0, &mut out);
    let got = to_peer(&out, gcs);
    assert_eq!(got.len(), 1);
    assert_eq!(
        statustext(&got[0].1),
        (
            4,
            "ppm pi: overridden (instructor has control)".into(),
            0,
            0
        )
    );
    assert_eq!(out[0].1.len(), 56);
    // A long name: two chunks under one id.
    let mut p = Peers::new(1, 1, 8, 0);
    p.heard(gcs, 2, 1_000, false, t);
    let long = format!("ppm {}: following", "n".repeat(64));
    p.announce(5, &long);
    p.announce(5, &long);
    out.clear();
    p.due(t, none, None, 0, &mut out);
    let chunks: Vec<(u8, String, u16, u8)> = to_peer(&out, gcs)
        .iter()
        .filter(|(id, _)| *id == STATUSTEXT.id)
        .map(|(_, p)| statustext(p))
        .collect();
    let (first, second) = long.split_at(50);
    assert_eq!(
        chunks,
        [
            (5, first.to_string(), 1, 0),
            (5, second.to_string(), 1, 1),
            (5, first.to_string(), 2, 0),
            (5, second.to_string(), 2, 1),
        ]
    );
    // A peer that earns nothing more keeps TEXTS_KEPT chunks; the oldest
    // make room, counted as held (with its HEARTBEAT: 6 bytes earn 18).
    let mut p = Peers::new(1, 1, 8, 0);
    p.heard(gcs, 2, 6, false, t);
    for _ in 0..peers::TEXTS_KEPT + 2 {
        p.announce(5, "ppm pi: following");
    }
    out.clear();
    p.due(t, none, None, 0, &mut out);
    assert!(out.is_empty());
    assert_eq!(p.counters(), peers::ReplyCounters { sent: 0, held: 3 });
}

/// A pilot's radio's changes say who flies, at the read-back's severities;
/// a read-back's keep their words.
#[test]
fn a_pilots_radio_says_who_flies() {
    let change = |state: ReadbackState| Change {
        from: 0,
        sample: sample(S, state, 1, S),
    };
    let pilot = Readback::pilot("gpio:GPIO17".into());
    let radio = Readback::new("gpio:GPIO17".into());
    assert_eq!(
        pilot.statustext("plane", &change(Following)),
        (5, "ppm plane: the groundstation has control".into())
    );
    assert_eq!(
        pilot.statustext("plane", &change(Overridden)),
        (4, "ppm plane: the pilot has control".into())
    );
    assert_eq!(
        pilot.statustext("plane", &change(NoInput)),
        (4, "ppm plane: no pilot's radio, no command goes out".into())
    );
    assert_eq!(
        radio.statustext("plane", &change(Overridden)),
        (4, "ppm plane: overridden (instructor has control)".into())
    );
}
