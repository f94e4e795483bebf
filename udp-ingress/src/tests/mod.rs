//! Tests of the intake: parsing, gates, counters and status replies.
//!
//! - here: newest wins, the `seq` gate, clamps, the allowlist, the reject
//!   log, and datagrams classified by their parsed keys.
//! - `status.rs`: status queries and the replies built from the counters.
//! - `signed.rs`: commands signed with a key, and `to`.
//! - `mavlink_datagrams.rs`: MAVLink datagrams through the intake.

use super::*;
use ppm_shared::config::Config;

mod mavlink_datagrams;
mod signed;
mod status;

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
        Outcome::Status(Query::Status)
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
        Outcome::Status(Query::Status)
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
