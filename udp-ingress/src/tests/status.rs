//! Status queries through the intake: recognised before parsing, counted
//! apart, answered within their size bound, and the reply built from the
//! counters.

use super::*;
use serde_json::{json, Value};

#[test]
fn status_query_is_recognised_before_parsing() {
    for q in [&br#"{"get":"status"}"#[..], br#" { "get" : "status" } "#] {
        assert_eq!(query(q), Some(Ok(Query::Status)), "{q:?}");
    }
    for not_a_query in [
        &b"[1500]"[..],
        br#"{"ail": 1500}"#,
        br#"{"get":"#,
        br#"["get"]"#,
        b"\xff\"get\"",
    ] {
        assert_eq!(query(not_a_query), None, "{not_a_query:?}");
    }
    let detail = |q: &[u8]| match query(q) {
        Some(Err(r)) if r.reason == RejectReason::BadShape => r.detail,
        other => panic!("{q:?}: {other:?}"),
    };
    let d = detail(br#"{"get":"config"}"#);
    assert!(
        d.contains("\"config\"") && d.contains(r#"{"get": "status"}"#),
        "{d}"
    );
    assert!(detail(br#"{"get":1}"#).contains("unknown query 1"));
    assert!(detail(br#"{"get":null}"#).contains("unknown query null"));
    let d = detail(br#"{"get":"status","seq":1}"#);
    assert!(d.contains("`seq`"), "{d}");
    assert!(detail(br#"{"ail":1500,"get":"status"}"#).contains("`ail`"));
    assert_eq!(query(br#"{"get":"telemetry"}"#), Some(Ok(Query::Telemetry)));
    assert!(detail(br#"{"get":"config"}"#).contains(r#"{"get": "telemetry"}"#));
}

#[test]
fn a_telemetry_query_gets_the_member_alone() {
    let mut i = Intake::new(
        "plane",
        Config::default().validate().unwrap(),
        Duration::from_secs(1),
    );
    let t = Instant::now();
    assert_eq!(
        i.offer(br#"{"get": "telemetry"}"#, from(), 1, 1, t),
        Outcome::Status(Query::Telemetry)
    );
    assert_eq!(i.counters().status_requests, 1);
    // An output without telemetry: null.
    assert_eq!(
        i.telemetry_answer(5),
        r#"{"name":"plane","telemetry":null}"#
    );
    // With it, the status reply's member, to the byte.
    let mut i = i.with_telemetry("/dev/ttyAMA0".into());
    let mut s = ppm_shared::ipc::TelemetrySample::default();
    let f = ppm_shared::crsf::frame(0xC8, 0x21, b"ANGL\0");
    let decoded = ppm_shared::crsf::telemetry::decode_frame(&f).unwrap();
    s.take(&f, &decoded, 1_000_000);
    s.published_mono_ns = 1_000_000;
    i.telemetry(s);
    let answer: serde_json::Value = serde_json::from_str(&i.telemetry_answer(2_000_000)).unwrap();
    let reply = wire(&i.status(
        Duration::from_secs(1),
        &ReceiveThread::default(),
        2_000_000,
        None,
    ));
    assert_eq!(answer["telemetry"], reply["telemetry"]);
    assert_eq!(answer["telemetry"]["flight_mode"]["mode"], "ANGL");
    assert_eq!(answer["telemetry"]["state"], "receiving");
}

#[test]
fn status_answers_are_at_most_three_times_the_query_outside_status_allow() {
    let lo: Vec<IpNet> = vec!["127.0.0.0/8".parse().unwrap(), "::1/128".parse().unwrap()];
    let far: IpAddr = "203.0.113.9".parse().unwrap();
    let near: IpAddr = "127.0.0.1".parse().unwrap();
    let mapped: IpAddr = "::ffff:127.0.0.1".parse().unwrap();
    use StatusAnswer::*;
    assert_eq!(status_answer(700, 16, near, &lo), Full);
    assert_eq!(status_answer(700, 16, mapped, &lo), Full);
    assert_eq!(status_answer(700, 16, far, &lo), PadTo(234));
    assert_eq!(status_answer(700, 16, near, &[]), PadTo(234));
    assert_eq!(status_answer(700, 233, far, &lo), PadTo(234));
    assert_eq!(status_answer(700, 234, far, &lo), Full);
    assert_eq!(status_answer(702, 234, far, &lo), Full);
    assert_eq!(pad_to_text(234), r#"{"pad_to":234}"#);
    // Even {"pad_to": N} is more than 3 times a 4-byte datagram.
    assert_eq!(status_answer(700, 4, far, &lo), Nothing);
    assert_eq!(status_answer(700, 5, far, &lo), PadTo(234));
}
#[test]
fn status_query_is_counted_apart_and_changes_nothing() {
    let mut i = intake();
    let t = Instant::now();
    i.offer(br#"{"ch":[1100],"seq":3}"#, from(), 1, 1, t);
    let before = i.counters().clone();
    assert_eq!(
        i.offer(br#"{"get":"status"}"#, from(), 2, 2, t),
        Outcome::Status(Query::Status)
    );
    assert_eq!(
        i.counters(),
        &Counters {
            status_requests: 1,
            ..before
        }
    );
    assert_eq!(i.take().unwrap().command.seq, Some(3), "still the newest");
    assert!(matches!(
        i.offer(br#"{"get":"everything"}"#, from(), 3, 3, t),
        Outcome::Rejected(RejectReason::BadShape, Some(line)) if line.contains("everything")
    ));
    let c = i.counters();
    assert_eq!(
        (c.received, c.rejected_total(), c.status_requests),
        (2, 1, 1)
    );
}

/// `v` with every value as wide as its kind can print: integers
/// u64::MAX, numbers with a fraction the widest a rounded f64 of ours
/// prints (`1.2345678901234567e16`), `null`s that stand for numbers
/// too. Member names and the enum-like strings stay.
/// A status reply as its receiver parses it: the JSON of the text sent.
fn wire(reply: &StatusReply) -> Value {
    serde_json::from_str(&reply.to_json()).expect("a reply is JSON")
}

fn widest(v: &mut Value) {
    match v {
        Value::Number(n) if n.is_f64() => *v = json!(1.234_567_890_123_456_7e16_f64),
        Value::Number(_) => *v = json!(u64::MAX),
        Value::Array(a) => a.iter_mut().for_each(widest),
        Value::Object(m) => m.values_mut().for_each(widest),
        _ => {}
    }
}

/// The largest status reply there can be: the real builder, with a
/// name of 64 characters, a command with a `seq`, a pinned receive
/// thread, a ppmd snapshot in the longest state and timing, and then
/// every number at its widest (so a counter added to the reply is
/// counted here too). It fits in STATUS_REPLY_MAX_LEN, and the padded
/// query of ppm's tools earns it from any source.
#[test]
fn the_largest_reply_fits_the_documented_bound() {
    use ppm_shared::protocol::{STATUS_QUERY_PADDED_LEN, STATUS_REPLY_MAX_LEN};
    let name = "n".repeat(64);
    ppm_shared::config::validate_name(&name).unwrap();
    let mut i = Intake::new(
        &name,
        Config::default().validate().unwrap(),
        Duration::from_secs(1),
    );
    let t = Instant::now();
    i.offer(br#"{"ch":[900],"seq":7}"#, from(), 1, 1, t);
    let rt = ReceiveThread {
        busy_poll: true,
        priority: 0, // "other", longer than "fifo"
        cpu: Some(1),
        degraded: false,
    };
    let mut snap = snapshot(10);
    snap.state = LineState::Failsafe as u32;
    snap.timing = 1;
    snap.degraded = 0;
    let mut reply = wire(&i.status(Duration::from_secs(1), &rt, 20, Some(&snap)));
    assert_eq!(reply["ppmd"]["state"], "failsafe");
    assert_eq!(reply["ppmd"]["timing"], "follow");
    for key in ["newest_seq", "newest_command_age_ms"] {
        assert!(!reply[key].is_null(), "{key}");
    }
    // A read-back of 16 channels, every reason refused.
    reply["readback"] = serde_json::to_value(ppm_shared::status::ReadbackStatus {
        state: "overridden".into(),
        input: format!("gpio:{}:{}", "c".repeat(40), "l".repeat(40)),
        since_ms: Some(1.5),
        changes: 1,
        edges: 1,
        frames: 1,
        matched: 1,
        mismatched: 1,
        refused: ppm_shared::capture::CaptureCounts::default()
            .reasons()
            .iter()
            .map(|(r, _)| (r.to_string(), 1))
            .collect(),
        ch_us: vec![1500.5; 16],
        max_diff_us: Some(1.5),
        age_ms: 1.5,
    })
    .unwrap();
    widest(&mut reply);
    let text = reply.to_string();
    assert!(
        text.len() <= STATUS_REPLY_MAX_LEN,
        "the largest reply is {} bytes, over STATUS_REPLY_MAX_LEN ({STATUS_REPLY_MAX_LEN}): raise it (and the docs): {text}",
        text.len()
    );
    assert_eq!(
        status_answer(
            STATUS_REPLY_MAX_LEN,
            STATUS_QUERY_PADDED_LEN,
            "192.0.2.1".parse().unwrap(),
            &[]
        ),
        StatusAnswer::Full
    );
    // Room for more counters: two more, at their widest, still fit.
    let two_more = r#","stale_commands_and_so_on":18446744073709551615"#.len() * 2;
    assert!(
        text.len() + two_more <= STATUS_REPLY_MAX_LEN,
        "{} bytes",
        text.len()
    );
    // A CRSF serial output has telemetry instead (never both: a read-back
    // needs PPM): every kind, a flight mode of 60 quotes (each escaped in
    // JSON, no NUL), a port path of 64 characters.
    reply.as_object_mut().unwrap().remove("readback");
    reply["telemetry"] = serde_json::to_value(widest_telemetry()).unwrap();
    widest(&mut reply);
    let text = reply.to_string();
    assert!(
        text.len() + two_more <= STATUS_REPLY_MAX_LEN,
        "the largest reply with telemetry is {} bytes: {text}",
        text.len()
    );
}

/// The telemetry member with every kind, its text at its longest.
fn widest_telemetry() -> ppm_shared::crsf::report::TelemetryStatus {
    use ppm_shared::crsf::{LinkStatistics, TelemetryReader};
    let frame = |kind: u8, payload: &[u8]| ppm_shared::crsf::frame(0xC8, kind, payload);
    let mut s = ppm_shared::ipc::TelemetrySample::default();
    let mut r = TelemetryReader::new();
    let mut link = LinkStatistics::WIRED.encode().to_vec();
    link[0] = 0xC8;
    for f in [
        frame(0x08, &[0x80; 8]),
        frame(0x02, &[0x80; 15]),
        frame(0x1E, &[0x80; 6]),
        frame(0x21, &[b'"'; 60]),
        frame(0x07, &[0x80; 2]),
        frame(0x09, &[0x12, 0x34, 0x80]),
        link,
    ] {
        r.feed(&f, |raw, t| s.take(raw, &t, 1));
    }
    s.counts = r.counts().to_array();
    s.published_mono_ns = 1;
    let t = ppm_shared::crsf::report::TelemetryStatus::of(&s, &"/dev/tty".repeat(8), 2);
    assert!(
        t.link_statistics.is_some() && t.baro_altitude.is_some(),
        "{t:?}"
    );
    assert_eq!(t.flight_mode.as_ref().unwrap().mode.len(), 60);
    t
}

fn snapshot(mono_ns: u64) -> TimingSnapshot {
    let mut s = TimingSnapshot {
        mono_ns,
        frames: 400,
        overruns: 1,
        late_frames: 2,
        aborted_frames: 4,
        glitched_frames: 5,
        failsafe_entries: 3,
        degraded: 1,
        state: 1,
        ..TimingSnapshot::default()
    };
    s.total.p50 = 31;
    s.total.p99 = 1_250;
    s.total.max = 17_000_400;
    s
}

#[test]
fn status_reply_is_built_from_the_counters() {
    let mut i = intake();
    let t = Instant::now();
    let at = |ms: u64| 10_000_000_000 + ms * 1_000_000;
    let plain = ReceiveThread::default();
    let empty = wire(&i.status(Duration::from_millis(1500), &plain, at(10), None));
    assert_eq!(
        empty["receiver"],
        json!({"wait": "epoll", "policy": "other", "priority": 0, "cpu": null, "degraded": false})
    );
    assert_eq!(empty["newest_command_age_ms"], Value::Null);
    assert_eq!(empty["newest_seq"], Value::Null);
    assert_eq!(
        (&empty["ppmd"], &empty["ppmd_stale"]),
        (&Value::Null, &json!(false))
    );

    i.offer(br#"{"ch":[900,2100],"seq":7}"#, from(), at(100), 1, t);
    i.take();
    i.offer(br#"{"ch":[1200],"seq":6}"#, from(), at(101), 1, t);
    i.offer(br#"{"ch":[1200],"seq":8}"#, from(), at(102), 1, t);
    i.offer(b"[1300]", from(), at(103), 1, t);
    i.offer(b"[1300", from(), at(104), 1, t);
    i.offer(b"{}", from(), at(105), 1, t);
    i.offer(br#"{"get":"status"}"#, from(), at(106), 1, t);
    i.take();
    i.status_dropped();
    let now = at(110) + 400;
    let rt = ReceiveThread {
        busy_poll: true,
        priority: 70,
        cpu: Some(1),
        degraded: true,
    };
    let typed = i.status(
        Duration::from_millis(2_345_678),
        &rt,
        now,
        Some(&snapshot(now - 250_000_000)),
    );
    let reply = wire(&typed);
    assert_eq!(
        reply,
        json!({
            "name": "pi",
            "uptime_s": 2345.678,
            "receiver": {"wait": "busy_poll", "policy": "fifo", "priority": 70, "cpu": 1, "degraded": true},
            "datagrams": {
                "received": 6,
                "applied": 2,
                "rejected": {
                    "invalid_utf8": 0,
                    "invalid_json": 1,
                    "not_a_number": 0,
                    "out_of_range": 0,
                    "too_many_values": 0,
                    "unknown_channel": 0,
                    "bad_shape": 1,
                    "duplicate_key": 0,
                    "unsigned": 0,
                    "bad_mac": 0,
                    "no_seq": 0,
                    "replay": 0,
                    "not_allowed": 0,
                    "wrong_output": 0,
                    "no_to": 0,
                    "mavlink_junk": 0,
                    "mavlink_truncated": 0,
                    "mavlink_bad_length": 0,
                    "mavlink_bad_crc": 0,
                    "mavlink_unknown_message": 0,
                },
                "clamped": 1,
                "clamped_values": 2,
                "stale": 1,
                "seq_resets": 0,
                "superseded": 1,
            },
            "status_requests": 1,
            "status_dropped": 1,
            "status_short": 0,
            "mavlink": {"no_command": 0, "ignored": 0, "peers": 0, "sent": 0, "held": 0},
            "newest_command_age_ms": 7.0,
            // Of the newest command that had one: [1300] has none.
            "newest_seq": 8,
            "publish_latency_us": {"count": 0, "p50": 0.0, "p99": 0.0, "max": 0.0},
            "ppmd": {
                "state": "active",
                "timing": "grid",
                "frames": 400,
                "repeats": 0,
                "edge_error_us": {"p50": 0.031, "p99": 1.25, "max": 17000.4},
                "overruns": 1,
                "late_frames": 2,
                "aborted_frames": 4,
                "glitched_frames": 5,
                "mismatched_commands": 0,
                "expired_commands": 0,
                "log_errors": 0,
                "failsafe_entries": 3,
                "degraded": true,
                "snapshot_age_ms": 250.0,
            },
            "ppmd_stale": false,
        })
    );
    assert!(reply.to_string().len() < 1_200, "one small datagram");
    // The text as udp-ingress sent it before the reply had a type: its
    // keys sorted at every level, numbers as serde_json writes an f64.
    assert_eq!(
        typed.to_json(),
        r#"{"datagrams":{"applied":2,"clamped":1,"clamped_values":2,"received":6,"rejected":{"bad_mac":0,"bad_shape":1,"duplicate_key":0,"invalid_json":1,"invalid_utf8":0,"mavlink_bad_crc":0,"mavlink_bad_length":0,"mavlink_junk":0,"mavlink_truncated":0,"mavlink_unknown_message":0,"no_seq":0,"no_to":0,"not_a_number":0,"not_allowed":0,"out_of_range":0,"replay":0,"too_many_values":0,"unknown_channel":0,"unsigned":0,"wrong_output":0},"seq_resets":0,"stale":1,"superseded":1},"mavlink":{"held":0,"ignored":0,"no_command":0,"peers":0,"sent":0},"name":"pi","newest_command_age_ms":7.0,"newest_seq":8,"ppmd":{"aborted_frames":4,"degraded":true,"edge_error_us":{"max":17000.4,"p50":0.031,"p99":1.25},"expired_commands":0,"failsafe_entries":3,"frames":400,"glitched_frames":5,"late_frames":2,"log_errors":0,"mismatched_commands":0,"overruns":1,"repeats":0,"snapshot_age_ms":250.0,"state":"active","timing":"grid"},"ppmd_stale":false,"publish_latency_us":{"count":0,"max":0.0,"p50":0.0,"p99":0.0},"receiver":{"cpu":1,"degraded":true,"policy":"fifo","priority":70,"wait":"busy_poll"},"status_dropped":1,"status_requests":1,"status_short":0,"uptime_s":2345.678}"#
    );

    let old = snapshot(now - PPMD_STALE_AFTER_NS - 1);
    let reply = wire(&i.status(Duration::ZERO, &plain, now, Some(&old)));
    assert_eq!(
        (&reply["ppmd"], &reply["ppmd_stale"]),
        (&Value::Null, &json!(true))
    );
    let at_limit = snapshot(now - PPMD_STALE_AFTER_NS);
    let reply = wire(&i.status(Duration::ZERO, &plain, now, Some(&at_limit)));
    assert_eq!(reply["ppmd"]["snapshot_age_ms"], json!(3000.0));
}
