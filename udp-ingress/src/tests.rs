//! Tests of the intake: parsing, gates, counters and status replies.

use super::*;
use ppm_shared::config::Config;
use serde_json::json;

fn intake() -> Intake {
    Intake::new(
        "pi",
        Config::default().validate().unwrap(),
        Duration::from_secs(1),
    )
}

fn from() -> SocketAddr {
    "127.0.0.1:9".parse().unwrap()
}

#[test]
fn newest_valid_wins_and_rejects_change_nothing() {
    let mut i = intake();
    let t = Instant::now();
    assert_eq!(i.offer(b"[1100]", from(), 1, 1, t), Outcome::Accepted);
    assert_eq!(i.offer(b"[1200]", from(), 2, 2, t), Outcome::Accepted);
    assert!(matches!(
        i.offer(b"[1300", from(), 3, 3, t),
        Outcome::Rejected(RejectReason::InvalidJson, Some(_))
    ));
    assert!(matches!(
        i.offer(b"[9999]", from(), 4, 4, t),
        Outcome::Rejected(RejectReason::OutOfRange, Some(_))
    ));
    let r = i.take().unwrap();
    assert_eq!(r.command.channels.as_ns()[0], 1_200_000);
    assert_eq!(r.mono_ns, 2);
    assert_eq!(i.take(), None, "published once");
    let c = i.counters();
    assert_eq!(
        (c.received, c.published, c.superseded, c.rejected_total()),
        (4, 1, 1, 2)
    );
}

#[test]
fn stale_seq_is_dropped_across_wakeups() {
    let mut i = intake();
    let t = Instant::now();
    assert_eq!(
        i.offer(br#"{"ch":[1100],"seq":5}"#, from(), 1, 1, t),
        Outcome::Accepted
    );
    i.take();
    assert_eq!(
        i.offer(br#"{"ch":[1200],"seq":5}"#, from(), 2, 2, t),
        Outcome::Stale
    );
    assert_eq!(
        i.offer(br#"{"ch":[1200],"seq":4}"#, from(), 3, 3, t),
        Outcome::Stale
    );
    assert_eq!(i.take(), None);
    assert_eq!(
        i.offer(br#"{"ch":[1300],"seq":6}"#, from(), 4, 4, t),
        Outcome::Accepted
    );
    assert_eq!(i.take().unwrap().command.seq, Some(6));
    assert_eq!(i.counters().stale, 2);
}

/// One unsigned datagram with the largest `seq` used to make every
/// numbered command stale until the ingress restarted. Now the gate
/// forgets once nothing was accepted for the failsafe's interval.
#[test]
fn without_a_key_one_huge_seq_locks_out_for_the_failsafe_interval_at_most() {
    let after = Duration::from_millis(200);
    let ms = Duration::from_millis;
    let mut i = intake().forget_seq_after(after);
    let t = Instant::now();
    let mut offer = |d: &[u8], at: Duration| i.offer(d, from(), 1, 1, t + at);
    assert_eq!(offer(br#"{"ch":[1100],"seq":5}"#, ms(0)), Outcome::Accepted);
    let huge = br#"{"ch":[1900],"seq":18446744073709551615}"#;
    assert_eq!(offer(huge, ms(10)), Outcome::Accepted);
    // The sender's next commands, every 20 ms: stale until 200 ms after
    // the last accepted one, then applied, and counted from there.
    for n in 0..9u64 {
        let d = format!(r#"{{"ch":[1200],"seq":{}}}"#, 6 + n);
        assert_eq!(offer(d.as_bytes(), ms(30 + 20 * n)), Outcome::Stale, "{n}");
    }
    assert_eq!(
        offer(br#"{"ch":[1200],"seq":15}"#, ms(210)),
        Outcome::Accepted
    );
    assert_eq!(
        offer(br#"{"ch":[1200],"seq":16}"#, ms(230)),
        Outcome::Accepted
    );
    assert_eq!(offer(br#"{"ch":[1200],"seq":15}"#, ms(240)), Outcome::Stale);
    // Commands without a seq keep the line fresh: the gate holds.
    assert_eq!(offer(br#"{"ch":[1300]}"#, ms(400)), Outcome::Accepted);
    assert_eq!(offer(br#"{"ch":[1300],"seq":1}"#, ms(590)), Outcome::Stale);
    assert_eq!(
        offer(br#"{"ch":[1300],"seq":1}"#, ms(600)),
        Outcome::Accepted
    );
    let c = i.counters();
    assert_eq!((c.stale, c.seq_resets), (11, 2));
    assert!(c.summary().contains("(seq resets 2)"), "{}", c.summary());
}

/// With a key the gate never forgets, however long the quiet.
#[test]
fn with_a_key_the_seq_gate_never_forgets() {
    let k = key();
    let mut i = intake()
        .forget_seq_after(Duration::from_millis(200))
        .with_auth(k.clone(), None);
    let t = Instant::now();
    let d = k
        .envelope(r#"{"ch":[1100],"seq":5,"to":"pi"}"#)
        .into_bytes();
    assert_eq!(i.offer(&d, from(), 1, 1, t), Outcome::Accepted);
    let later = t + Duration::from_secs(3600);
    assert_eq!(
        reason(i.offer(&d, from(), 1, 1, later)),
        RejectReason::Replay
    );
    let older = k
        .envelope(r#"{"ch":[1100],"seq":4,"to":"pi"}"#)
        .into_bytes();
    assert_eq!(
        reason(i.offer(&older, from(), 1, 1, later)),
        RejectReason::Replay
    );
    assert_eq!(i.counters().seq_resets, 0);
}

#[test]
fn clamps_are_counted() {
    let mut i = intake();
    i.offer(b"[900, 2100, 1500]", from(), 1, 1, Instant::now());
    assert_eq!(
        (i.counters().clamped_commands, i.counters().clamped_values),
        (1, 2)
    );
    assert!(i.counters().summary().contains("clamped 1 (values 2)"));
}

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

/// JSON is classified by its parsed keys: escaped spellings of `get`,
/// `msg` and `mac` behave as the plain ones (they were taken for
/// commands: `unknown_channel`, `unsigned`).
#[test]
fn escaped_keys_are_the_keys_they_spell() {
    assert_eq!(query(br#"{"\u0067et":"status"}"#), Some(Ok(Query::Status)));
    assert_eq!(
        query(br#"{"g\u0065t":"st\u0061tus"}"#),
        Some(Ok(Query::Status))
    );
    let mut i = intake();
    let t = Instant::now();
    assert_eq!(
        i.offer(br#"{"\u0067et":"status"}"#, from(), 1, 1, t),
        Outcome::Status
    );
    assert_eq!(i.counters().status_requests, 1);
    assert_eq!(i.counters().received, 0);

    let k = key();
    let mut i = intake().with_auth(k.clone(), None);
    let msg = r#"{"ch":[1100],"seq":7,"to":"pi"}"#;
    let escaped = format!(
        r#"{{"\u006dsg": {msg:?}, "m\u0061c": "{}"}}"#,
        k.sign(msg.as_bytes())
    );
    assert_eq!(
        i.offer(escaped.as_bytes(), from(), 1, 1, t),
        Outcome::Accepted,
        "{escaped}"
    );
    assert_eq!(i.take().unwrap().command.channels.as_ns()[0], 1_100_000);
    // The same with a MAC of other bytes is a forgery, not unsigned.
    let forged = escaped.replace(r#"\"ch\""#, r#"\"c\\u0068\""#);
    assert_ne!(forged, escaped);
    assert_eq!(
        reason(i.offer(forged.as_bytes(), from(), 1, 1, t)),
        RejectReason::BadMac
    );
}

#[test]
fn status_query_is_counted_apart_and_changes_nothing() {
    let mut i = intake();
    let t = Instant::now();
    i.offer(br#"{"ch":[1100],"seq":3}"#, from(), 1, 1, t);
    let before = i.counters().clone();
    assert_eq!(
        i.offer(br#"{"get":"status"}"#, from(), 2, 2, t),
        Outcome::Status
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
        max_diff_us: 1.5,
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

fn key() -> AuthKey {
    AuthKey::new(*b"0123456789abcdef0123456789abcdef")
}

fn reason(o: Outcome) -> RejectReason {
    match o {
        Outcome::Rejected(r, _) => r,
        other => panic!("not rejected: {other:?}"),
    }
}

#[test]
fn with_a_key_only_signed_commands_with_a_new_seq_apply() {
    use RejectReason::*;
    let k = key();
    let mut i = intake().with_auth(k.clone(), Some(100));
    let t = Instant::now();
    // Signed for this output: `to` added to the object forms.
    let signed = |msg: &str| {
        let msg = match msg.strip_suffix('}') {
            Some(head) => format!(r#"{head},"to":"pi"}}"#),
            None => msg.to_owned(),
        };
        k.envelope(&msg).into_bytes()
    };
    let mut offer = |d: &[u8]| i.offer(d, from(), 1, 1, t);
    // The floor from before a restart: 100 and below are replays.
    assert_eq!(reason(offer(&signed(r#"{"ch":[1900],"seq":100}"#))), Replay);
    assert_eq!(
        offer(&signed(r#"{"ch":[1100],"seq":101}"#)),
        Outcome::Accepted
    );
    let good = signed(r#"{"ch":[1200],"seq":102}"#);
    assert_eq!(offer(&good), Outcome::Accepted);
    assert_eq!(reason(offer(&good)), Replay, "the same datagram again");
    assert_eq!(reason(offer(br#"{"ch":[1900],"seq":200}"#)), Unsigned);
    assert_eq!(reason(offer(b"[1900]")), Unsigned);
    assert_eq!(
        reason(offer(br#"{"yaw":1}"#)),
        Unsigned,
        "unsigned before anything else"
    );
    assert_eq!(reason(offer(b"[1900")), InvalidJson);
    assert_eq!(reason(offer(b"\xff")), InvalidUtf8);
    let other_key = AuthKey::new([9; 32]);
    assert_eq!(
        reason(offer(
            other_key.envelope(r#"{"ch":[1900],"seq":300}"#).as_bytes()
        )),
        BadMac
    );
    let text = String::from_utf8(signed(r#"{"ch":[1200],"seq":400}"#)).unwrap();
    let tampered_msg = text.replace("1200", "1900");
    assert_eq!(reason(offer(tampered_msg.as_bytes())), BadMac);
    let mac_at = text.find("\"mac\":\"").unwrap() + 7;
    let mut tampered_mac = text.clone().into_bytes();
    tampered_mac[mac_at] = if tampered_mac[mac_at] == b'a' {
        b'b'
    } else {
        b'a'
    };
    assert_eq!(reason(offer(&tampered_mac)), BadMac);
    assert_eq!(reason(offer(&signed(r#"{"ch":[1900]}"#))), NoSeq);
    assert_eq!(
        reason(offer(&signed("[1900]"))),
        NoTo,
        "an array names no output"
    );
    assert_eq!(
        reason(offer(&signed(r#"{"ch":[9000],"seq":500}"#))),
        OutOfRange
    );
    assert_eq!(reason(offer(br#"{"msg":"[1500]"}"#)), BadShape);
    assert_eq!(
        offer(br#"{"get":"status"}"#),
        Outcome::Status,
        "unsigned, read-only"
    );
    assert_eq!(i.last_seq(), Some(102));
    let r = i.take().unwrap();
    assert_eq!(
        (r.command.seq, r.command.channels.as_ns()[0]),
        (Some(102), 1_200_000)
    );
    let c = i.counters();
    let n = |r: RejectReason| c.rejected[r.index()];
    assert_eq!(
        (
            n(Replay),
            n(Unsigned),
            n(BadMac),
            n(NoSeq),
            n(BadShape),
            n(NoTo)
        ),
        (2, 3, 3, 1, 1, 1)
    );
    assert_eq!(
        (c.received, c.published, c.superseded, c.stale),
        (16, 1, 1, 0)
    );
    assert_eq!(
        c.received,
        c.published + c.superseded + c.stale + c.rejected_total()
    );
}

/// The report: two outputs share a key; a listener copies the plane's
/// signed commands (with higher `seq`s) to the rover's port. The rover
/// refuses them as `wrong_output` before its `seq` gate sees them, so
/// its own commands keep applying (no `replay`).
#[test]
fn a_signed_command_for_another_output_is_refused_and_moves_no_seq() {
    use RejectReason::*;
    let k = key();
    let rover_model = Config::parse("[ppm]\norder = 'TAER'\nchannels = 6")
        .unwrap()
        .validate()
        .unwrap();
    let mut rover =
        Intake::new("rover", rover_model, Duration::from_secs(1)).with_auth(k.clone(), None);
    let t = Instant::now();
    let mut offer = |d: String| rover.offer(d.as_bytes(), from(), 1, 1, t);
    let own = |seq: u64| k.envelope(&format!(r#"{{"thr":1000,"seq":{seq},"to":"rover"}}"#));
    let plane = |seq: u64| k.envelope(&format!(r#"{{"thr":1800,"seq":{seq},"to":"plane"}}"#));
    assert_eq!(offer(own(10)), Outcome::Accepted);
    // Copies of the plane's commands, far ahead in seq.
    for seq in [1_000, 1_001, u64::MAX] {
        assert_eq!(reason(offer(plane(seq))), WrongOutput);
    }
    // And an old sender's command that names no output.
    let unaddressed = k.envelope(r#"{"thr":1800,"seq":2000}"#);
    assert_eq!(reason(offer(unaddressed)), NoTo);
    // The plane's channel names need not exist here: still wrong_output.
    assert_eq!(
        reason(offer(
            k.envelope(r#"{"aux7":1800,"seq":3000,"to":"plane"}"#)
        )),
        WrongOutput
    );
    // The rover's own next commands apply: the copies moved nothing.
    assert_eq!(offer(own(11)), Outcome::Accepted);
    assert_eq!(offer(own(12)), Outcome::Accepted);
    assert_eq!(reason(offer(own(12))), Replay, "a real replay still is one");
    assert_eq!(rover.last_seq(), Some(12));
    let r = rover.take().unwrap();
    assert_eq!(
        (r.command.seq, r.command.channels.as_ns()[0]),
        (Some(12), 1_000_000)
    );
    let c = rover.counters();
    let n = |r: RejectReason| c.rejected[r.index()];
    assert_eq!((n(WrongOutput), n(NoTo), n(Replay)), (4, 1, 1));
    assert_eq!(c.rejected_total(), 6);
    let s = rover.status(Duration::ZERO, &ReceiveThread::default(), 0, None);
    assert_eq!(s.name, "rover");
    assert_eq!(s.datagrams.rejected.count(WrongOutput), 4);
    assert_eq!(s.datagrams.rejected.count(NoTo), 1);
}

proptest::proptest! {
    /// Any interleaving of the rover's own signed commands (any seq,
    /// repeats and reorderings included) with copies of another
    /// output's, under the same key: every copy is `wrong_output` and
    /// moves nothing; the rover's own are taken exactly when their seq
    /// is above the last one taken, else `replay`.
    #[test]
    fn copies_for_another_output_never_apply_nor_move_the_seq(
        stream in proptest::collection::vec(
            (proptest::bool::ANY, 0u64..40, 1_000u32..=2_000),
            1..60,
        ),
    ) {
        use proptest::prop_assert_eq;
        let k = key();
        let mut rover = intake().with_auth(k.clone(), None);
        let t = Instant::now();
        let (mut last, mut copies) = (None::<u64>, 0);
        for (own, seq, v) in stream {
            let to = if own { "pi" } else { "plane" };
            let d = k.envelope(&format!(r#"{{"ch":[{v}],"seq":{seq},"to":"{to}"}}"#));
            let out = rover.offer(d.as_bytes(), from(), 1, 1, t);
            if !own {
                copies += 1;
                prop_assert_eq!(reason(out), RejectReason::WrongOutput);
            } else if last.is_none_or(|l| seq > l) {
                prop_assert_eq!(out, Outcome::Accepted);
                last = Some(seq);
                let taken = rover.take().expect("the command taken");
                prop_assert_eq!(taken.command.channels.as_ns()[0], v * 1_000);
            } else {
                prop_assert_eq!(reason(out), RejectReason::Replay);
            }
            prop_assert_eq!(rover.last_seq(), last);
        }
        let c = rover.counters();
        prop_assert_eq!(c.rejected[RejectReason::WrongOutput.index()], copies);
    }
}

/// After the floor of a restart too: a copy for another output does not
/// move the gate, and is told apart from a replay.
#[test]
fn a_copy_for_another_output_below_the_floor_is_wrong_output_not_replay() {
    let k = key();
    let mut i = intake().with_auth(k.clone(), Some(100));
    let t = Instant::now();
    let copy = k.envelope(r#"{"ch":[1900],"seq":50,"to":"other"}"#);
    assert_eq!(
        reason(i.offer(copy.as_bytes(), from(), 1, 1, t)),
        RejectReason::WrongOutput
    );
    assert_eq!(i.last_seq(), Some(100));
    let own = k.envelope(r#"{"ch":[1100],"seq":101,"to":"pi"}"#);
    assert_eq!(i.offer(own.as_bytes(), from(), 1, 1, t), Outcome::Accepted);
}

/// Unsigned commands need no `to`; one that names another output is
/// refused as `wrong_output` (a groundstation aimed at the wrong port).
#[test]
fn without_a_key_to_may_be_given_and_must_then_match() {
    let mut i = intake();
    let t = Instant::now();
    let mut offer = |d: &[u8]| i.offer(d, from(), 1, 1, t);
    assert_eq!(offer(br#"{"ch":[1100],"seq":1}"#), Outcome::Accepted);
    assert_eq!(
        offer(br#"{"ch":[1200],"seq":2,"to":"pi"}"#),
        Outcome::Accepted
    );
    match offer(br#"{"ch":[1900],"seq":3,"to":"rover"}"#) {
        Outcome::Rejected(RejectReason::WrongOutput, Some(line)) => {
            assert!(line.contains("for output `rover`, this is `pi`"), "{line}")
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(i.last_seq(), Some(2));
    assert_eq!(i.take().unwrap().command.channels.as_ns()[0], 1_200_000);
}

#[test]
fn without_a_key_signed_datagrams_are_bad_shape() {
    let mut i = intake();
    let d = key().envelope(r#"{"ch":[1100],"seq":1}"#);
    match i.offer(d.as_bytes(), from(), 1, 1, Instant::now()) {
        Outcome::Rejected(RejectReason::BadShape, Some(line)) => {
            assert!(
                line.contains("signed datagram but no auth key configured"),
                "{line}"
            )
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(i.last_seq(), None);
}

#[test]
fn allowlist_matches_blocks() {
    let nets: Vec<IpNet> = ["10.0.0.0/24", "127.0.0.2/32", "fd00::/8"]
        .iter()
        .map(|s| s.parse().unwrap())
        .collect();
    let ok = |ip: &str| allowed(&nets, ip.parse().unwrap());
    assert!(ok("10.0.0.0") && ok("10.0.0.255") && ok("127.0.0.2") && ok("fd12::1"));
    assert!(!ok("10.0.1.0") && !ok("127.0.0.1") && !ok("::1") && !ok("fe80::1"));
    assert!(ok("::ffff:10.0.0.7"), "IPv4 on a dual-stack socket");
    assert!(!ok("::ffff:10.0.1.7"));
    assert!(
        allowed(&[], "192.0.2.1".parse().unwrap()),
        "empty: any source"
    );
}

#[test]
fn other_sources_are_dropped_before_parsing_and_logged_rate_limited() {
    let mut i = intake().with_allowlist(vec!["127.0.0.2/32".parse().unwrap()]);
    let t = Instant::now();
    let outsider: SocketAddr = "127.0.0.1:4000".parse().unwrap();
    let insider: SocketAddr = "127.0.0.2:4000".parse().unwrap();
    let mut lines = 0;
    for k in 0..5 {
        match i.offer(br#"{"get":"status"}"#, outsider, 1, 1, t) {
            Outcome::Rejected(RejectReason::NotAllowed, line) => {
                lines += line.is_some() as u32;
                if k == 0 {
                    assert!(line.unwrap().contains("127.0.0.1 is not in ingress.allow"));
                }
            }
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(lines, 1, "one log line per interval");
    assert_eq!(i.offer(b"[1100]", insider, 1, 1, t), Outcome::Accepted);
    assert_eq!(
        i.offer(br#"{"get":"status"}"#, insider, 1, 1, t),
        Outcome::Status
    );
    let c = i.counters();
    assert_eq!(
        (
            c.received,
            c.rejected[RejectReason::NotAllowed.index()],
            c.status_requests
        ),
        (6, 5, 1)
    );
}

#[test]
fn reject_log_is_rate_limited_per_reason() {
    let mut l = RejectLog::new(Duration::from_secs(1));
    let t = Instant::now();
    assert_eq!(l.note(RejectReason::InvalidJson, t), Some(0));
    assert_eq!(
        l.note(RejectReason::InvalidJson, t + Duration::from_millis(10)),
        None
    );
    assert_eq!(
        l.note(RejectReason::InvalidJson, t + Duration::from_millis(20)),
        None
    );
    assert_eq!(
        l.note(RejectReason::BadShape, t + Duration::from_millis(30)),
        Some(0)
    );
    assert_eq!(
        l.note(RejectReason::InvalidJson, t + Duration::from_millis(1001)),
        Some(2)
    );
}

/// An RC_CHANNELS_OVERRIDE frame for any target: `chan` on chan1.., the
/// other channels of chan1..8 released (0), chan9..18 ignored.
pub(crate) fn rc_override(version: u8, chan: &[u16]) -> Vec<u8> {
    let mut payload = vec![];
    for i in 0..18 {
        let v = chan.get(i).copied().unwrap_or(0);
        payload.extend_from_slice(&v.to_le_bytes());
        if i == 7 {
            payload.extend_from_slice(&[0, 0]);
        }
    }
    if version == 1 {
        payload.truncate(18);
    }
    mavlink::frame(
        version,
        (0, 255, 190),
        &mavlink::RC_CHANNELS_OVERRIDE,
        &payload,
    )
}

#[test]
fn mavlink_commands_take_the_json_path() {
    let mut i = intake().forget_seq_after(Duration::from_millis(200));
    let t = Instant::now();
    let ch = |i: &mut Intake| -> Vec<u32> {
        let r = i.take().expect("a command");
        r.command
            .channels
            .as_ns()
            .iter()
            .map(|ns| ns / 1_000)
            .collect()
    };
    assert_eq!(
        i.offer(&rc_override(1, &[1100, 1200, 1300, 1400]), from(), 1, 1, t),
        Outcome::Accepted
    );
    assert_eq!(ch(&mut i), [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500]);
    // UINT16_MAX keeps the fresh command's value; 0 releases to the default.
    let keep = rc_override(2, &[u16::MAX, 0, 1700, u16::MAX, 1800]);
    assert_eq!(i.offer(&keep, from(), 2, 2, t), Outcome::Accepted);
    assert_eq!(ch(&mut i), [1100, 1500, 1700, 1400, 1800, 1500, 1500, 1500]);
    // Past the failsafe's after_ms, "keep" keeps the defaults instead.
    let later = t + Duration::from_millis(250);
    assert_eq!(i.offer(&keep, from(), 3, 3, later), Outcome::Accepted);
    assert_eq!(ch(&mut i), [1500, 1500, 1700, 1500, 1800, 1500, 1500, 1500]);
    // HEARTBEATs alone are no command, and are not received datagrams.
    let hb = mavlink::frame(
        2,
        (0, 255, 190),
        &mavlink::HEARTBEAT,
        &[0, 0, 0, 0, 6, 8, 0, 4, 3],
    );
    assert_eq!(i.offer(&hb, from(), 4, 4, later), Outcome::NoCommand);
    assert_eq!(i.take(), None);
    // Faults are counted by reason and change nothing.
    let mut bad = rc_override(2, &[1000]);
    let n = bad.len();
    bad[n - 1] ^= 0xFF;
    for (d, reason) in [
        (bad, RejectReason::MavlinkBadCrc),
        (
            rc_override(2, &[1000])[..9].to_vec(),
            RejectReason::MavlinkTruncated,
        ),
        (rc_override(1, &[400]), RejectReason::OutOfRange),
        (
            [&rc_override(1, &[1000])[..], b"x"].concat(),
            RejectReason::MavlinkJunk,
        ),
    ] {
        assert!(
            matches!(i.offer(&d, from(), 5, 5, later), Outcome::Rejected(r, _) if r == reason),
            "{reason:?}"
        );
    }
    assert_eq!(i.take(), None);
    let c = i.counters().clone();
    assert_eq!((c.received, c.published, c.rejected_total()), (7, 3, 4));
    assert_eq!(c.mavlink_no_command, 1);
    for r in [
        RejectReason::MavlinkBadCrc,
        RejectReason::MavlinkTruncated,
        RejectReason::OutOfRange,
        RejectReason::MavlinkJunk,
    ] {
        assert_eq!(c.rejected[r.index()], 1, "{r:?}");
    }
}

#[test]
fn with_a_key_mavlink_commands_are_unsigned() {
    let mut i = intake().with_auth(key(), None);
    let t = Instant::now();
    assert!(matches!(
        i.offer(&rc_override(2, &[1000]), from(), 1, 1, t),
        Outcome::Rejected(RejectReason::Unsigned, _)
    ));
    assert_eq!(i.take(), None);
}

#[test]
fn rc_channels_report_the_newest_frame_on_the_line_while_it_is_fresh() {
    use ppm_shared::ipc::LineSample;
    let mut i = intake();
    let t = Instant::now();
    let hb = mavlink::frame(
        2,
        (0, 255, 190),
        &mavlink::HEARTBEAT,
        &[0, 0, 0, 0, 6, 8, 0, 4, 3],
    );
    // Three of them earn a HEARTBEAT and an RC_CHANNELS.
    for _ in 0..3 {
        assert_eq!(i.offer(&hb, from(), 1, 1, t), Outcome::NoCommand);
    }
    let mut values_ns = [0; ppm_shared::frame::MAX_CHANNELS];
    values_ns[..3].copy_from_slice(&[1_100_400, 1_200_600, 1_499_500]);
    let line = LineSample {
        frame: 9,
        start_mono_ns: 5_000_000_000,
        channels: 3,
        state: 1,
        values_ns,
    };
    // The RC_CHANNELS' time_boot_ms, chancount and first channels, of the
    // replies due at CLOCK_MONOTONIC `mono`.
    let rc = |i: &mut Intake, mono: u64, at: Instant| -> (u32, u8, [u16; 4]) {
        let mut out = vec![];
        i.mavlink_due((at, mono, 0), (None, Some(&line)), &mut out);
        let f = &out
            .iter()
            .find(|(_, f)| f[7] == 65)
            .expect("an RC_CHANNELS")
            .1;
        let mut p = f[10..f.len() - 2].to_vec();
        p.resize(42, 0);
        let u = |k: usize| u16::from_le_bytes([p[4 + 2 * k], p[5 + 2 * k]]);
        let ms = u32::from_le_bytes([p[0], p[1], p[2], p[3]]);
        (ms, p[40], [u(0), u(1), u(2), u(3)])
    };
    // To the microsecond, at the frame's start; UINT16_MAX past its
    // channels.
    assert_eq!(
        rc(&mut i, 5_300_000_000, t),
        (5_000, 3, [1100, 1201, 1500, u16::MAX])
    );
    // A frame that started more than 300 ms ago: no channels now (the
    // peer's next HEARTBEATs earned the reply).
    let later = t + Duration::from_millis(250);
    for _ in 0..3 {
        assert_eq!(i.offer(&hb, from(), 2, 2, later), Outcome::NoCommand);
    }
    assert_eq!(rc(&mut i, 5_300_000_001, later), (5_300, 0, [u16::MAX; 4]));
}

/// `newest_seq` is the `seq` of the newest command applied that had one,
/// as docs/protocol.md says: a MAVLink command (which has none) leaves it,
/// and so does a JSON command without one. It used to become `null` after
/// one MAVLink command.
#[test]
fn newest_seq_stays_that_of_the_last_numbered_command() {
    let mut i = intake();
    let t = Instant::now();
    let seq = |i: &Intake| {
        i.status(Duration::ZERO, &ReceiveThread::default(), 1, None)
            .newest_seq
    };
    assert_eq!(seq(&i), None, "none before the first");
    i.offer(br#"{"ch":[1100],"seq":41}"#, from(), 1, 1, t);
    assert_eq!(seq(&i), Some(41));
    assert_eq!(
        i.offer(&rc_override(2, &[1200]), from(), 2, 2, t),
        Outcome::Accepted
    );
    assert_eq!(seq(&i), Some(41), "after a MAVLink command");
    assert_eq!(i.offer(b"[1300]", from(), 3, 3, t), Outcome::Accepted);
    assert_eq!(seq(&i), Some(41), "after a JSON command without seq");
    // A stale command is not applied: it changes nothing either.
    assert_eq!(
        i.offer(br#"{"ch":[1300],"seq":40}"#, from(), 4, 4, t),
        Outcome::Stale
    );
    assert_eq!(seq(&i), Some(41));
    i.offer(br#"{"ch":[1400],"seq":42}"#, from(), 5, 5, t);
    assert_eq!(seq(&i), Some(42));
    // With a key, the floor of a restart is no command's: null until one.
    let i = intake().with_auth(key(), Some(1_000));
    assert_eq!(seq(&i), None);
}

/// The same key twice in one object, at the top or nested, is refused as
/// `duplicate_key` and changes nothing; with a key too, in the signed
/// envelope (two `msg`) as in the command it signs, and an unsigned command
/// with a key twice is `duplicate_key`, not `unsigned`.
#[test]
fn a_key_given_twice_is_refused_and_counted_apart() {
    let mut i = intake();
    let t = Instant::now();
    assert_eq!(
        i.offer(br#"{"ch":[1100],"seq":5}"#, from(), 1, 1, t),
        Outcome::Accepted
    );
    i.take();
    for d in [
        &br#"{"thr": 1000, "thr": 2000}"#[..],
        br#"{"ch": [1200], "seq": 6, "seq": 7}"#,
        br#"{"norm": {"thr": -1, "thr": 1}, "seq": 8}"#,
        br#"{"get": "status", "get": "status"}"#,
    ] {
        // One log line a second per reason: each a second apart.
        let at = t + Duration::from_secs(1 + i.counters().rejected_total());
        let o = i.offer(d, from(), 2, 2, at);
        let Outcome::Rejected(RejectReason::DuplicateKey, Some(line)) = &o else {
            panic!("{}: {o:?}", String::from_utf8_lossy(d));
        };
        assert!(line.contains("duplicate_key: duplicate key `"), "{line}");
    }
    assert_eq!(i.take(), None, "nothing applied");
    let c = i.counters();
    assert_eq!(c.rejected[RejectReason::DuplicateKey.index()], 4);
    assert_eq!((c.rejected_total(), c.status_requests), (4, 0));
    assert_eq!(i.last_seq(), Some(5), "the seq gate did not move");

    let k = key();
    let mut i = intake().with_auth(k.clone(), None);
    let cmd = r#"{"ch":[1100],"seq":9,"to":"pi"}"#;
    let signed = k.envelope(cmd);
    let twice = format!(
        r#"{{"msg":{},"mac":"{}","msg":{}}}"#,
        serde_json::to_string(r#"{"ch":[2000],"seq":9,"to":"pi"}"#).unwrap(),
        k.sign(cmd.as_bytes()),
        serde_json::to_string(cmd).unwrap()
    );
    assert_eq!(
        reason(i.offer(twice.as_bytes(), from(), 1, 1, t)),
        RejectReason::DuplicateKey
    );
    let dup = r#"{"ch":[1100],"seq":9,"seq":10,"to":"pi"}"#;
    let inner = k.envelope(dup);
    assert_eq!(
        reason(i.offer(inner.as_bytes(), from(), 1, 1, t)),
        RejectReason::DuplicateKey
    );
    assert_eq!(
        reason(i.offer(dup.as_bytes(), from(), 1, 1, t)),
        RejectReason::DuplicateKey
    );
    assert_eq!(i.take(), None);
    assert_eq!(i.last_seq(), None);
    assert_eq!(
        i.offer(signed.as_bytes(), from(), 1, 1, t),
        Outcome::Accepted
    );
}

/// Bytes before a MAVLink frame are `mavlink_junk`, as docs/protocol.md
/// says (and as bytes between or after frames are), not `invalid_utf8`;
/// bytes that are not UTF-8 and hold no good frame stay `invalid_utf8`.
#[test]
fn junk_before_a_mavlink_frame_is_mavlink_junk() {
    let mut i = intake();
    let t = Instant::now();
    let hb = mavlink::frame(
        2,
        (0, 255, 190),
        &mavlink::HEARTBEAT,
        &[0, 0, 0, 0, 6, 8, 0, 4, 3],
    );
    for d in [
        [&b"xx"[..], &rc_override(2, &[1000])].concat(),
        [&b"\n"[..], &rc_override(1, &[1000])].concat(),
        [&[0u8, 0xFD, 0xFE][..], &hb].concat(),
        [&[0xFFu8][..], &hb, &rc_override(2, &[1000])].concat(),
    ] {
        let at = t + Duration::from_secs(i.counters().rejected_total());
        let o = i.offer(&d, from(), 1, 1, at);
        let Outcome::Rejected(RejectReason::MavlinkJunk, Some(line)) = &o else {
            panic!("{d:?}: {o:?}");
        };
        assert!(line.contains("before a MAVLink"), "{line}");
    }
    assert_eq!(i.take(), None);
    assert_eq!(i.peers.known(), 0, "no peer made");
    let mut bad_crc = hb.clone();
    bad_crc[12] ^= 1;
    // Not UTF-8, no good frame: invalid_utf8, however many start bytes.
    for d in [
        b"\xff\xfe[1500]".to_vec(),
        [&b"x"[..], &bad_crc].concat(),
        [&b"x"[..], &[0xFD; 65_000]].concat(),
        [&b"x"[..], &[0xFE; 65_000]].concat(),
        [&b"x"[..], &[0xFE; mavlink::JUNK_SCAN_MAX_STARTS], &hb].concat(),
    ] {
        let started = Instant::now();
        assert_eq!(
            reason(i.offer(&d, from(), 1, 1, t)),
            RejectReason::InvalidUtf8,
            "{:?}",
            &d[..d.len().min(20)]
        );
        assert!(started.elapsed() < Duration::from_millis(50));
    }
    let c = i.counters();
    assert_eq!(c.rejected[RejectReason::MavlinkJunk.index()], 4);
    assert_eq!(c.rejected[RejectReason::InvalidUtf8.index()], 5);
}

/// With `mavlink.key_file`, a MAVLink 1 frame is `unsigned`, and the log
/// line says why and how to fix it: MAVLink 2, which pymavlink writes only
/// with MAVLINK20=1 set before it is imported.
#[test]
fn an_unsigned_mavlink_1_frame_says_how_to_send_mavlink_2() {
    let mut i = intake().with_mavlink_signing(key(), None);
    let t = Instant::now();
    let o = i.offer(&rc_override(1, &[1000]), from(), 1, 1, t);
    let Outcome::Rejected(RejectReason::Unsigned, Some(line)) = &o else {
        panic!("{o:?}");
    };
    assert!(
        line.contains("only MAVLink 2 carries a signature")
            && line.contains("MAVLINK20=1")
            && line.contains("before it is imported"),
        "{line}"
    );
    // MAVLink 2 without a signature: how to sign.
    let o = i.offer(
        &rc_override(2, &[1000]),
        from(),
        2,
        2,
        t + Duration::from_secs(1),
    );
    let Outcome::Rejected(RejectReason::Unsigned, Some(line)) = &o else {
        panic!("{o:?}");
    };
    assert!(
        line.contains("unsigned MAVLink 2") && line.contains("setup_signing"),
        "{line}"
    );
}
