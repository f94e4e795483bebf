//! Commands signed with a key: only signed ones for this output with a new
//! `seq` apply, a copy for another output moves no `seq`; without a key,
//! `to` may be given and must then match.

use super::*;

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
        Outcome::Status(Query::Status),
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
