//! MAVLink datagrams through the intake: commands take the JSON path's
//! checks and counters and leave `newest_seq`, RC_CHANNELS carry the line,
//! junk before a frame is `mavlink_junk`, and an unsigned MAVLink 1 frame
//! with a key says how to send MAVLink 2.

use super::*;

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
