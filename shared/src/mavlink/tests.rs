//! Frames from pymavlink 2.4.50 (`rc_channels_override_send`,
//! `manual_control_send`, `heartbeat_send`, with signing for one) are read
//! back to their fields; the checks refuse each fault by its reason.

use super::*;
use crate::frame::{Channels, FrameModel, PpmSection};
use crate::protocol::{Command, RejectReason};

/// rc_channels_override_send(1, 1, 1100, 1200, ..., 1800), MAVLink 1,
/// from system 255, component 190.
const V1_OVERRIDE: [u8; 26] = [
    0xfe, 0x12, 0x00, 0xff, 0xbe, 0x46, 0x4c, 0x04, 0xb0, 0x04, 0x14, 0x05, 0x78, 0x05, 0xdc, 0x05,
    0x40, 0x06, 0xa4, 0x06, 0x08, 0x07, 0x01, 0x01, 0xae, 0x1d,
];
/// The same in MAVLink 2, with chan9..14 = 1900, 0, 65535, 65534, 0, 0
/// (the rest 0, trimmed).
const V2_OVERRIDE: [u8; 38] = [
    0xfd, 0x1a, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x46, 0x00, 0x00, 0x4c, 0x04, 0xb0, 0x04, 0x14, 0x05,
    0x78, 0x05, 0xdc, 0x05, 0x40, 0x06, 0xa4, 0x06, 0x08, 0x07, 0x01, 0x01, 0x6c, 0x07, 0x00, 0x00,
    0xff, 0xff, 0xfe, 0xff, 0x1d, 0x24,
];
/// rc_channels_override_send(0, 0, 1500, 0, 65535, 0, ...): MAVLink 2
/// trims the payload to its first 6 bytes.
const V2_OVERRIDE_TRIMMED: [u8; 18] = [
    0xfd, 0x06, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x46, 0x00, 0x00, 0xdc, 0x05, 0x00, 0x00, 0xff, 0xff,
    0x0e, 0x03,
];
/// manual_control_send(1, 100, -200, 500, 0, 5), MAVLink 2.
const V2_MANUAL: [u8; 23] = [
    0xfd, 0x0b, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x45, 0x00, 0x00, 0x64, 0x00, 0x38, 0xff, 0xf4, 0x01,
    0x00, 0x00, 0x05, 0x00, 0x01, 0xab, 0x0f,
];
/// The same in MAVLink 1.
const V1_MANUAL: [u8; 19] = [
    0xfe, 0x0b, 0x00, 0xff, 0xbe, 0x45, 0x64, 0x00, 0x38, 0xff, 0xf4, 0x01, 0x00, 0x00, 0x05, 0x00,
    0x01, 0x67, 0xa3,
];
/// heartbeat_send(6 GCS, 8 INVALID, 0, 0, 4), MAVLink 2.
const V2_HEARTBEAT: [u8; 21] = [
    0xfd, 0x09, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x06, 0x08,
    0x00, 0x04, 0x03, 0x3d, 0x48,
];
/// V1_OVERRIDE's command in MAVLink 2, signed (link 3).
const V2_SIGNED: [u8; 43] = [
    0xfd, 0x12, 0x01, 0x00, 0x00, 0xff, 0xbe, 0x46, 0x00, 0x00, 0x4c, 0x04, 0xb0, 0x04, 0x14, 0x05,
    0x78, 0x05, 0xdc, 0x05, 0x40, 0x06, 0xa4, 0x06, 0x08, 0x07, 0x01, 0x01, 0xbb, 0x96, 0x03, 0xe8,
    0x03, 0x00, 0x00, 0x00, 0x00, 0xa4, 0x56, 0x32, 0x3e, 0x76, 0x18,
];
/// param_request_list_send(1, 1), MAVLink 2.
const V2_PARAM_REQUEST_LIST: [u8; 14] = [
    0xfd, 0x02, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x15, 0x00, 0x00, 0x01, 0x01, 0x88, 0xc0,
];
/// request_data_stream_send(1, 1, 0, 4, 1), MAVLink 2.
const V2_REQUEST_DATA_STREAM: [u8; 18] = [
    0xfd, 0x06, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x42, 0x00, 0x00, 0x04, 0x00, 0x01, 0x01, 0x00, 0x01,
    0x79, 0xd1,
];
/// param_value_send(b"PPM_CHANNELS", 8.0, 9 (REAL32), 1, 0) from system 1,
/// component 1, MAVLink 2: what ppm answers a PARAM_REQUEST_LIST with.
pub(crate) const V2_PARAM_VALUE: [u8; 37] = [
    0xfd, 0x19, 0x00, 0x00, 0x00, 0x01, 0x01, 0x16, 0x00, 0x00, 0x00, 0x00, 0x00, 0x41, 0x01, 0x00,
    0x00, 0x00, 0x50, 0x50, 0x4d, 0x5f, 0x43, 0x48, 0x41, 0x4e, 0x4e, 0x45, 0x4c, 0x53, 0x00, 0x00,
    0x00, 0x00, 0x09, 0x34, 0x00,
];

fn model(extra: &str) -> FrameModel {
    let ppm: PpmSection = toml::from_str(extra).unwrap();
    FrameModel::build(&ppm).unwrap()
}

fn override_of(bytes: &[u8]) -> (Header, RcOverride) {
    match read_frame(bytes).unwrap() {
        (h, Message::RcOverride(o), len) => {
            assert_eq!(len, bytes.len());
            (h, o)
        }
        other => panic!("{other:?}"),
    }
}

fn reason(bytes: &[u8]) -> RejectReason {
    read_datagram(bytes).unwrap_err().reason
}

fn us(c: &Command) -> Vec<f64> {
    c.channels
        .as_ns()
        .iter()
        .map(|&ns| ns as f64 / 1e3)
        .collect()
}

#[test]
fn pymavlink_frames_read_back_to_their_fields() {
    let (h, o) = override_of(&V1_OVERRIDE);
    assert_eq!((h.version, h.sysid, h.compid, h.msgid), (1, 255, 190, 70));
    assert_eq!((o.target_system, o.target_component), (1, 1));
    assert_eq!(
        o.chan[..8],
        [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800]
    );
    assert_eq!(o.chan[8..], [0; 10]);

    let (h, o2) = override_of(&V2_OVERRIDE);
    assert_eq!((h.version, h.signed), (2, false));
    assert_eq!(o2.chan[..8], o.chan[..8]);
    assert_eq!(o2.chan[8..12], [1900, 0, 65535, 65534]);

    let (_, t) = override_of(&V2_OVERRIDE_TRIMMED);
    assert_eq!((t.target_system, t.target_component), (0, 0));
    assert_eq!(t.chan[..3], [1500, 0, 65535]);
    assert!(t.chan[3..].iter().all(|&c| c == 0));

    for bytes in [&V2_MANUAL[..], &V1_MANUAL[..]] {
        let (_, m, _) = read_frame(bytes).unwrap();
        assert_eq!(
            m,
            Message::ManualControl(ManualControl {
                target: 1,
                axes: [100, -200, 500, 0],
                buttons: 5
            })
        );
    }
    assert_eq!(read_frame(&V2_HEARTBEAT).unwrap().1, Message::Heartbeat);
    let d = read_datagram(&V2_PARAM_REQUEST_LIST).unwrap();
    assert_eq!(d.command, None);
    assert_eq!(d.requests.len(), 1);
    assert_eq!(d.requests[0].1, Message::ParamRequestList(1, 1));
    // pymavlink's MAVLink 1 with force_mavlink1 packs the extensions too
    // (38 bytes), as the C library's reader takes.
    let mut whole = V1_OVERRIDE[6..24].to_vec();
    whole.resize(38, 0);
    whole[18..20].copy_from_slice(&1900u16.to_le_bytes());
    let (h, o1) = override_of(&frame(1, (0, 255, 190), &RC_CHANNELS_OVERRIDE, &whole));
    assert_eq!((h.version, o1.chan[8]), (1, 1900));

    let (h, s) = override_of(&V2_SIGNED);
    assert!(h.signed);
    assert_eq!(s, o);
}

#[test]
fn our_frames_are_pymavlinks() {
    let mut payload = vec![];
    for v in [1100u16, 1200, 1300, 1400, 1500, 1600, 1700, 1800] {
        payload.extend_from_slice(&v.to_le_bytes());
    }
    payload.extend_from_slice(&[1, 1]);
    assert_eq!(
        frame(1, (0, 255, 190), &RC_CHANNELS_OVERRIDE, &payload),
        V1_OVERRIDE
    );
    for v in [1900u16, 0, 65535, 65534, 0, 0, 0, 0, 0, 0] {
        payload.extend_from_slice(&v.to_le_bytes());
    }
    assert_eq!(
        frame(2, (0, 255, 190), &RC_CHANNELS_OVERRIDE, &payload),
        V2_OVERRIDE
    );
    let hb = [0, 0, 0, 0, 6, 8, 0, 4, 3];
    assert_eq!(frame(2, (0, 255, 190), &HEARTBEAT, &hb), V2_HEARTBEAT);
}

#[test]
fn every_fault_has_its_reason() {
    use RejectReason::*;
    // A flipped payload bit, a wrong CRC_EXTRA (the CRC of another layout).
    let mut bad = V2_OVERRIDE;
    bad[12] ^= 1;
    assert_eq!(reason(&bad), MavlinkBadCrc);
    let mut payload = V1_OVERRIDE[6..24].to_vec();
    let mut other = RC_CHANNELS_OVERRIDE;
    other.crc_extra ^= 0x55;
    let wrong_extra = frame(1, (0, 255, 190), &other, &payload);
    assert_eq!(reason(&wrong_extra), MavlinkBadCrc);
    // Cut anywhere: truncated.
    for cut in 1..V2_OVERRIDE.len() {
        assert_eq!(
            reason(&V2_OVERRIDE[..cut]),
            MavlinkTruncated,
            "cut at {cut}"
        );
    }
    for cut in 1..V2_SIGNED.len() {
        assert_eq!(reason(&V2_SIGNED[..cut]), MavlinkTruncated, "cut at {cut}");
    }
    // MAVLink 1 is never trimmed; neither carries more than the message has.
    assert_eq!(
        reason(&frame(
            1,
            (0, 255, 190),
            &RC_CHANNELS_OVERRIDE,
            &payload[..17]
        )),
        MavlinkBadLength
    );
    payload.resize(39, 7);
    for version in [1, 2] {
        assert_eq!(
            reason(&frame(
                version,
                (0, 255, 190),
                &RC_CHANNELS_OVERRIDE,
                &payload
            )),
            MavlinkBadLength
        );
    }
    // Message 4660, in no table (its CRC cannot be checked).
    let mut unknown = V2_REQUEST_DATA_STREAM;
    unknown[7..9].copy_from_slice(&4660u16.to_le_bytes());
    assert_eq!(reason(&unknown), MavlinkUnknownMessage);
    // PARAM_VALUE is ppm's to send, not to take.
    assert_eq!(reason(&V2_PARAM_VALUE), MavlinkUnknownMessage);
    // An incompat flag ppm does not know.
    let mut flagged = V2_OVERRIDE;
    flagged[2] = 0x02;
    assert_eq!(reason(&flagged), BadShape);
    // Junk after, or between, good frames; a good frame does not save it.
    for junk in [&b"\n"[..], b"{\"ch\":[1]}", &[0u8; 3]] {
        let mut d = V1_OVERRIDE.to_vec();
        d.extend_from_slice(junk);
        let r = read_datagram(&d).unwrap_err();
        assert_eq!(r.reason, MavlinkJunk);
        assert!(r.detail.starts_with("after 1 good frame(s)"), "{r}");
        d.extend_from_slice(&V2_OVERRIDE);
        assert_eq!(reason(&d), MavlinkJunk);
    }
    assert!(!is_mavlink(b"[1500]") && !is_mavlink(b"") && is_mavlink(&V1_OVERRIDE));
}

#[test]
fn a_datagram_of_several_frames_gives_its_last_command() {
    let mut d = V2_HEARTBEAT.to_vec();
    d.extend_from_slice(&V2_MANUAL);
    d.extend_from_slice(&V1_OVERRIDE);
    d.extend_from_slice(&V2_HEARTBEAT);
    let r = read_datagram(&d).unwrap();
    assert_eq!(r.frames, 4);
    assert_eq!(r.command.unwrap().0.msgid, 70);
    let r = read_datagram(&V2_HEARTBEAT).unwrap();
    assert_eq!((r.frames, r.command), (1, None));
}

#[test]
fn override_sets_keeps_and_releases_channels() {
    let m = model("order = \"AETR\"\nchannels = 10\n[channel.thr]\ndefault_us = 1000\n");
    let s = Settings::defaults_for(&m);
    let current = Channels::from_ns(&[1_234_000; 10]);
    let (_, o) = override_of(&V2_OVERRIDE);
    let c = command(&Message::RcOverride(o), &m, &s, &current).unwrap();
    // chan9 is set, chan10 (0 on chan9..18) kept.
    assert_eq!(
        us(&c),
        [1100.0, 1200.0, 1300.0, 1400.0, 1500.0, 1600.0, 1700.0, 1800.0, 1900.0, 1234.0]
    );
    assert_eq!((c.seq, c.clamped), (None, 0));
    // chan1 set, chan2 released (0), chan3 kept (UINT16_MAX), chan4..8 released.
    let (_, t) = override_of(&V2_OVERRIDE_TRIMMED);
    let c = command(&Message::RcOverride(t), &m, &s, &current).unwrap();
    let mut want: Vec<f64> = (0..10).map(|i| m.default_ns(i) as f64 / 1e3).collect();
    want[0] = 1500.0;
    want[2] = 1234.0;
    want[8] = 1234.0;
    want[9] = 1234.0;
    assert_eq!(us(&c), want);
    // UINT16_MAX - 1 on chan12 releases a channel the frame does not have:
    // nothing to do; a value there is too many.
    let mut o8 = o;
    o8.chan[8] = 0;
    let m8 = model("");
    let c = command(&Message::RcOverride(o8), &m8, &s, &m8.defaults()).unwrap();
    assert_eq!(us(&c)[7], 1800.0);
    let err = command(&Message::RcOverride(o), &m8, &s, &m8.defaults()).unwrap_err();
    assert_eq!(err.reason, RejectReason::TooManyValues, "{err}");
}

#[test]
fn override_values_are_checked_and_clamped_as_json_values_are() {
    let m = model("");
    let s = Settings::defaults_for(&m);
    let (_, mut o) = override_of(&V1_OVERRIDE);
    o.chan[0] = 2_100;
    o.chan[1] = 600;
    let c = command(&Message::RcOverride(o), &m, &s, &m.defaults()).unwrap();
    assert_eq!(us(&c)[..2], [2000.0, 1000.0]);
    assert_eq!(c.clamped, 2);
    for v in [1, 499, 2_501, 65_533] {
        o.chan[3] = v;
        let err = command(&Message::RcOverride(o), &m, &s, &m.defaults()).unwrap_err();
        assert_eq!(err.reason, RejectReason::OutOfRange, "{v}: {err}");
    }
}

#[test]
fn targets_must_be_ours_or_zero() {
    let m = model("");
    let s = Settings {
        system_id: 7,
        component_id: 190,
        ..Settings::defaults_for(&m)
    };
    let (_, mut o) = override_of(&V1_OVERRIDE);
    for (sys, comp, ok) in [
        (7, 190, true),
        (0, 0, true),
        (7, 0, true),
        (0, 190, true),
        (1, 190, false),
        (7, 1, false),
    ] {
        (o.target_system, o.target_component) = (sys, comp);
        let r = command(&Message::RcOverride(o), &m, &s, &m.defaults());
        assert_eq!(r.is_ok(), ok, "{sys}/{comp}: {r:?}");
        if let Err(e) = r {
            assert_eq!(e.reason, RejectReason::WrongOutput);
        }
    }
    let (_, manual, _) = read_frame(&V2_MANUAL).unwrap();
    let err = command(&manual, &m, &s, &m.defaults()).unwrap_err();
    assert_eq!(err.reason, RejectReason::WrongOutput);
    assert!(err.detail.contains("target system 1"), "{err}");
}

#[test]
fn manual_control_drives_its_axes_channels() {
    let m = model("");
    let mut s = Settings::defaults_for(&m);
    // AETR: x (pitch) onto ele, y (roll) onto ail, z onto thr, r onto rud.
    assert_eq!(s.axes, [Some(1), Some(0), Some(2), Some(3)]);
    let (_, manual, _) = read_frame(&V2_MANUAL).unwrap();
    let c = command(&manual, &m, &s, &m.defaults()).unwrap();
    // x 100 -> +0.1, y -200 -> -0.2, z 500 of 0..1000 -> the middle, r 0.
    assert_eq!(us(&c)[..5], [1400.0, 1550.0, 1500.0, 1500.0, 1500.0]);
    s.thrust = Thrust::Signed;
    let c = command(&manual, &m, &s, &m.defaults()).unwrap();
    assert_eq!(us(&c)[2], 1750.0);
    // INT16_MAX keeps; beyond ±1000 clamps and counts.
    let current = Channels::from_ns(&[1_111_000; 8]);
    let m2 = Message::ManualControl(ManualControl {
        target: 0,
        axes: [i16::MAX, 1500, -5, -1000],
        buttons: 0,
    });
    s.thrust = Thrust::Positive;
    let c = command(&m2, &m, &s, &current).unwrap();
    assert_eq!(us(&c)[..5], [2000.0, 1111.0, 1000.0, 1000.0, 1111.0]);
    assert_eq!(c.clamped, 2);
    // An axis onto no channel is not used.
    s.axes = [None; 4];
    let c = command(&m2, &m, &s, &current).unwrap();
    assert_eq!(c.channels, current);
}

#[test]
fn buttons_drive_their_channels_to_the_ends() {
    let m = model("[channel.aux2]\nmin_us = 1100\nmax_us = 1900\n");
    let s = Settings {
        buttons: vec![5, 4],
        ..Settings::defaults_for(&m)
    };
    let current = Channels::from_ns(&[1_500_000; 8]);
    // pymavlink's buttons = 5: buttons 1 and 3 pressed.
    let (_, manual, _) = read_frame(&V2_MANUAL).unwrap();
    let c = command(&manual, &m, &s, &current).unwrap();
    assert_eq!(us(&c)[4..], [1000.0, 1900.0, 1500.0, 1500.0]);
    let Message::ManualControl(mut mc) = manual else {
        unreachable!()
    };
    mc.buttons = 1 << 1;
    let c = command(&Message::ManualControl(mc), &m, &s, &current).unwrap();
    assert_eq!(us(&c)[4..6], [2000.0, 1100.0]);
}

#[test]
fn messages_encode_to_what_they_were_read_from() {
    for bytes in [
        &V1_OVERRIDE[..],
        &V2_OVERRIDE,
        &V2_OVERRIDE_TRIMMED,
        &V2_MANUAL,
        &V1_MANUAL,
    ] {
        let (h, m, _) = read_frame(bytes).unwrap();
        let (spec, payload) = m.encode();
        assert_eq!(spec.id, h.msgid);
        let again = frame(h.version, (h.seq, h.sysid, h.compid), spec, &payload);
        if h.version == 2 {
            assert_eq!(again, bytes);
        }
        assert_eq!(read_frame(&again).unwrap().1, m);
    }
    let (_, hb) = Message::Heartbeat.encode();
    assert_eq!(
        frame(2, (0, 255, 190), &HEARTBEAT, &hb)[..16],
        V2_HEARTBEAT[..16]
    );
}

fn test_signing() -> Signing {
    // pymavlink's key in V2_SIGNED: the bytes 0, 1, ..., 31.
    let mut key = [0u8; 32];
    for (i, k) in key.iter_mut().enumerate() {
        *k = i as u8;
    }
    Signing::new(crate::auth::AuthKey::new(key))
}

#[test]
fn pymavlinks_signature_checks_out_once() {
    let mut s = test_signing();
    let (h, _, _) = read_frame(&V2_SIGNED).unwrap();
    // Its timestamp is 1000 (10 ms after 2015 began): a new stream is
    // taken only within a minute of ppm's clock.
    let err = s
        .check(&V2_SIGNED, &h, 1_000 + NEW_STREAM_MAX_LAG + 1)
        .unwrap_err();
    assert_eq!(err.reason, RejectReason::Replay, "{err}");
    let mut s = test_signing();
    s.check(&V2_SIGNED, &h, 1_000).unwrap();
    let err = s.check(&V2_SIGNED, &h, 1_000).unwrap_err();
    assert_eq!(
        err.reason,
        RejectReason::Replay,
        "the same frame again: {err}"
    );
    // Another key, a changed byte: bad_mac.
    let mut other = Signing::new(crate::auth::AuthKey::new([7; 32]));
    assert_eq!(
        other.check(&V2_SIGNED, &h, 0).unwrap_err().reason,
        RejectReason::BadMac
    );
    let mut changed = V2_SIGNED;
    changed[V2_SIGNED.len() - 1] ^= 1;
    assert_eq!(
        test_signing().check(&changed, &h, 0).unwrap_err().reason,
        RejectReason::BadMac
    );
    // Unsigned, and MAVLink 1: unsigned.
    for bytes in [&V2_OVERRIDE[..], &V1_OVERRIDE[..]] {
        let (h, _, _) = read_frame(bytes).unwrap();
        assert_eq!(
            s.check(bytes, &h, 0).unwrap_err().reason,
            RejectReason::Unsigned
        );
    }
}

#[test]
fn signed_frames_read_back_and_check_out_with_growing_timestamps() {
    let mut ours = test_signing();
    let mut theirs = test_signing();
    let now = signing_timestamp(1_800_000_000 * 1_000_000_000);
    let (_, payload) = Message::Heartbeat.encode();
    let mut last = 0;
    for i in 0..3u8 {
        let f = ours.frame((i, 1, 1), &HEARTBEAT, &payload, now);
        let (h, m, len) = read_frame(&f).unwrap();
        assert_eq!((h.signed, m, len), (true, Message::Heartbeat, f.len()));
        theirs.check(&f, &h, now).unwrap();
        let ts = u64::from_le_bytes([f[22], f[23], f[24], f[25], f[26], f[27], 0, 0]);
        assert!(ts > now && ts > last, "{ts}");
        last = ts;
    }
    // Through read_datagram_with: the check refuses the datagram.
    let f = ours.frame((9, 1, 1), &HEARTBEAT, &payload, now);
    let mut replayed = f.clone();
    replayed.extend_from_slice(&f);
    let err = read_datagram_with(&replayed, |b, h| theirs.check(b, h, now)).unwrap_err();
    assert_eq!(err.reason, RejectReason::Replay, "{err}");
}

#[test]
fn after_a_restart_with_the_newest_timestamp_nothing_taken_before_is_taken_again() {
    let mut gcs = test_signing();
    let mut before = test_signing();
    let now = signing_timestamp(1_800_000_000 * 1_000_000_000);
    let (_, payload) = Message::Heartbeat.encode();
    let frames: Vec<Vec<u8>> = (0..4u8)
        .map(|i| gcs.frame((i, 255, 190), &HEARTBEAT, &payload, now))
        .collect();
    assert_eq!(before.newest(), None);
    // The first three were taken before the restart; the fourth was
    // signed then, but not delivered.
    for f in &frames[..3] {
        before.check(f, &read_frame(f).unwrap().0, now).unwrap();
    }
    let floor = before.newest().expect("a timestamp accepted");
    let ts = |f: &[u8]| u64::from_le_bytes([f[22], f[23], f[24], f[25], f[26], f[27], 0, 0]);
    assert_eq!(floor, ts(&frames[2]));
    // Without the floor, a restarted check takes each of them once more.
    let mut forgetful = test_signing();
    assert!(forgetful
        .check(&frames[1], &read_frame(&frames[1]).unwrap().0, now)
        .is_ok());
    // With it, none of them; the undelivered one, newer than any taken,
    // is taken (as a late datagram would be), and after it a frame
    // signed after the restart.
    let mut after = test_signing().with_floor(floor);
    assert_eq!(after.newest(), Some(floor));
    for f in &frames[..3] {
        let e = after.check(f, &read_frame(f).unwrap().0, now).unwrap_err();
        assert_eq!(e.reason, RejectReason::Replay, "{e}");
    }
    after
        .check(&frames[3], &read_frame(&frames[3]).unwrap().0, now)
        .unwrap();
    let next = gcs.frame((4, 255, 190), &HEARTBEAT, &payload, now);
    after
        .check(&next, &read_frame(&next).unwrap().0, now)
        .unwrap();
    assert_eq!(after.newest(), Some(ts(&next)));
    // ppm's own replies go out above the floor.
    let reply = after.frame((0, 1, 1), &HEARTBEAT, &payload, 0);
    assert!(ts(&reply) > floor);
}

/// pymavlink 2.4.50's command_long_send(1, 1, 511, 0, 65, 250000, 0, ...)
/// from 255/190, MAVLink 2 (trimmed to 32 bytes: confirmation is 0).
const V2_SET_MESSAGE_INTERVAL: [u8; 44] = [
    0xfd, 0x20, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x4c, 0x00, 0x00, 0x00, 0x00, 0x82, 0x42, 0x00, 0x24,
    0x74, 0x48, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xff, 0x01, 0x01, 0x01, 0x8c, 0x26,
];
/// pymavlink's rc_channels_send(1234, 2, 1100, 1900, 65535 x 16, 255)
/// from 1/1.
const V2_RC_CHANNELS: [u8; 54] = [
    0xfd, 0x2a, 0x00, 0x00, 0x00, 0x01, 0x01, 0x41, 0x00, 0x00, 0xd2, 0x04, 0x00, 0x00, 0x4c, 0x04,
    0x6c, 0x07, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
    0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
    0xff, 0xff, 0x02, 0xff, 0x41, 0xe0,
];
/// pymavlink's command_ack_send(511, 0, 0, 0, 255, 190) from 1/1.
const V2_COMMAND_ACK: [u8; 22] = [
    0xfd, 0x0a, 0x00, 0x00, 0x00, 0x01, 0x01, 0x4d, 0x00, 0x00, 0xff, 0x01, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0xff, 0xbe, 0xa9, 0x60,
];

#[test]
fn requests_read_as_pymavlink_wrote_them_and_replies_are_byte_identical() {
    let d = read_datagram(&V2_SET_MESSAGE_INTERVAL).unwrap();
    let (h, m) = d.requests[0];
    assert_eq!((h.sysid, h.compid, d.command), (255, 190, None));
    assert_eq!(
        m,
        Message::CommandLong(CommandLong {
            target_system: 1,
            target_component: 1,
            command: MAV_CMD_SET_MESSAGE_INTERVAL,
            confirmation: 0,
            params: [65.0, 250_000.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        })
    );
    let (spec, payload) = m.encode();
    assert_eq!(
        frame(2, (0, 255, 190), spec, &payload),
        V2_SET_MESSAGE_INTERVAL
    );
    let d = read_datagram(&V2_REQUEST_DATA_STREAM).unwrap();
    let m = d.requests[0].1;
    assert_eq!(
        m,
        Message::RequestDataStream(RequestDataStream {
            target_system: 1,
            target_component: 1,
            stream: MAV_DATA_STREAM_ALL,
            rate_hz: 4,
            start: true,
        })
    );
    let (spec, payload) = m.encode();
    assert_eq!(
        frame(2, (0, 255, 190), spec, &payload),
        V2_REQUEST_DATA_STREAM
    );
    // Both in one datagram, with a command between: every request, in
    // order, and the command.
    let (spec, payload) = Message::Heartbeat.encode();
    let mut two = V2_SET_MESSAGE_INTERVAL.to_vec();
    two.extend_from_slice(&frame(2, (1, 255, 190), spec, &payload));
    two.extend_from_slice(&V2_OVERRIDE);
    two.extend_from_slice(&V2_REQUEST_DATA_STREAM);
    let d = read_datagram(&two).unwrap();
    assert_eq!(d.frames, 4);
    let ids: Vec<u32> = d.requests.iter().map(|(h, _)| h.msgid).collect();
    assert_eq!(ids, [76, 66]);
    assert!(d.command.is_some());

    // What ppm writes is what pymavlink writes.
    let rc = rc_channels_payload(1234, &[1100, 1900]);
    assert_eq!(frame(2, (0, 1, 1), &RC_CHANNELS, &rc), V2_RC_CHANNELS);
    let ack = command_ack_payload(MAV_CMD_SET_MESSAGE_INTERVAL, 0, (255, 190));
    assert_eq!(frame(2, (0, 1, 1), &COMMAND_ACK, &ack), V2_COMMAND_ACK);
    // No channels on the line: a count of 0, every channel unused.
    let none = rc_channels_payload(7, &[]);
    assert_eq!((none[40], none[41]), (0, 255));
    assert!(none[4..40].iter().all(|&b| b == 0xff));
    // RC_CHANNELS and COMMAND_ACK are ppm's to send, not to take.
    let e = read_frame(&V2_RC_CHANNELS).unwrap_err();
    assert_eq!(e.reason, RejectReason::MavlinkUnknownMessage);
}

/// pymavlink's timesync_send(0, 123456789) from 255/190, MAVLink 2.
const V2_TIMESYNC: [u8; 24] = [
    0xfd, 0x0c, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x6f, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x15, 0xcd, 0x5b, 0x07, 0xa0, 0xe4,
];
/// pymavlink's mission_request_list_send(1, 1, 0) from 255/190.
const V2_MISSION_REQUEST_LIST: [u8; 14] = [
    0xfd, 0x02, 0x00, 0x00, 0x00, 0xff, 0xbe, 0x2b, 0x00, 0x00, 0x01, 0x01, 0xa8, 0x90,
];

#[test]
fn what_groundstations_send_any_vehicle_is_read_and_ignored_not_rejected() {
    let mut both = V2_TIMESYNC.to_vec();
    both.extend_from_slice(&V2_MISSION_REQUEST_LIST);
    let d = read_datagram(&both).unwrap();
    let got: Vec<Message> = d.requests.iter().map(|(_, m)| *m).collect();
    assert_eq!(got, [Message::Ignored(111), Message::Ignored(43)]);
    assert_eq!(d.command, None);
    // Checked like the others: a bad CRC, or a length the message cannot
    // have, is a fault.
    let mut bad = V2_TIMESYNC;
    bad[23] ^= 1;
    assert_eq!(
        read_frame(&bad).unwrap_err().reason,
        RejectReason::MavlinkBadCrc
    );
    let long = frame(2, (0, 255, 190), spec(111).unwrap(), &[1; 19]);
    assert_eq!(
        read_frame(&long).unwrap_err().reason,
        RejectReason::MavlinkBadLength
    );
    // No id is in both tables.
    for s in &IGNORED {
        assert_eq!(
            SPECS.iter().filter(|k| k.id == s.id).count(),
            0,
            "{}",
            s.name
        );
        assert!(s.v1_len <= s.max_len);
    }
}

/// pymavlink 2.4's statustext_send(4, b"ppm pi: overridden (instructor has
/// control)", 0, 0) from system 1, component 1, MAVLink 2 (trimmed).
const V2_STATUSTEXT: [u8; 56] = [
    0xfd, 0x2c, 0x00, 0x00, 0x00, 0x01, 0x01, 0xfd, 0x00, 0x00, 0x04, 0x70, 0x70, 0x6d, 0x20, 0x70,
    0x69, 0x3a, 0x20, 0x6f, 0x76, 0x65, 0x72, 0x72, 0x69, 0x64, 0x64, 0x65, 0x6e, 0x20, 0x28, 0x69,
    0x6e, 0x73, 0x74, 0x72, 0x75, 0x63, 0x74, 0x6f, 0x72, 0x20, 0x68, 0x61, 0x73, 0x20, 0x63, 0x6f,
    0x6e, 0x74, 0x72, 0x6f, 0x6c, 0x29, 0x63, 0x4d,
];
/// statustext_send(5, b"ppm pi: following") in MAVLink 1 (the v10
/// dialect: no `id`, no `chunk_seq`).
const V1_STATUSTEXT: [u8; 59] = [
    0xfe, 0x33, 0x00, 0x01, 0x01, 0xfd, 0x05, 0x70, 0x70, 0x6d, 0x20, 0x70, 0x69, 0x3a, 0x20, 0x66,
    0x6f, 0x6c, 0x6c, 0x6f, 0x77, 0x69, 0x6e, 0x67, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x02, 0x93,
];
/// The 69 bytes "ppm quadrotor-left-wing-number-2: overridden (instructor
/// has control)" as pymavlink's statustext_send(4, text[:50], 7, 0) and
/// statustext_send(4, text[50:], 7, 1), MAVLink 2, numbered 0 and 1.
const V2_STATUSTEXT_CHUNKS: [u8; 130] = [
    0xfd, 0x34, 0x00, 0x00, 0x00, 0x01, 0x01, 0xfd, 0x00, 0x00, 0x04, 0x70, 0x70, 0x6d, 0x20, 0x71,
    0x75, 0x61, 0x64, 0x72, 0x6f, 0x74, 0x6f, 0x72, 0x2d, 0x6c, 0x65, 0x66, 0x74, 0x2d, 0x77, 0x69,
    0x6e, 0x67, 0x2d, 0x6e, 0x75, 0x6d, 0x62, 0x65, 0x72, 0x2d, 0x32, 0x3a, 0x20, 0x6f, 0x76, 0x65,
    0x72, 0x72, 0x69, 0x64, 0x64, 0x65, 0x6e, 0x20, 0x28, 0x69, 0x6e, 0x73, 0x74, 0x07, 0x1e, 0xe7,
    0xfd, 0x36, 0x00, 0x00, 0x01, 0x01, 0x01, 0xfd, 0x00, 0x00, 0x04, 0x72, 0x75, 0x63, 0x74, 0x6f,
    0x72, 0x20, 0x68, 0x61, 0x73, 0x20, 0x63, 0x6f, 0x6e, 0x74, 0x72, 0x6f, 0x6c, 0x29, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x07, 0x00, 0x01,
    0x61, 0x4b,
];
/// servo_output_raw_send(5000123, 0, 1100, 1201, 1500, 1900, 1500, 1500,
/// 1500, 1500), MAVLink 2: servo9..16 are 0, trimmed.
const V2_SERVO_OUTPUT_RAW: [u8; 32] = [
    0xfd, 0x14, 0x00, 0x00, 0x00, 0x01, 0x01, 0x24, 0x00, 0x00, 0xbb, 0x4b, 0x4c, 0x00, 0x4c, 0x04,
    0xb1, 0x04, 0xdc, 0x05, 0x6c, 0x07, 0xdc, 0x05, 0xdc, 0x05, 0xdc, 0x05, 0xdc, 0x05, 0x02, 0x75,
];
/// The same with servo9 = 1000 and servo10 = 2000 (extensions).
const V2_SERVO_OUTPUT_RAW_16: [u8; 37] = [
    0xfd, 0x19, 0x00, 0x00, 0x00, 0x01, 0x01, 0x24, 0x00, 0x00, 0xbb, 0x4b, 0x4c, 0x00, 0x4c, 0x04,
    0xb1, 0x04, 0xdc, 0x05, 0x6c, 0x07, 0xdc, 0x05, 0xdc, 0x05, 0xdc, 0x05, 0xdc, 0x05, 0x00, 0xe8,
    0x03, 0xd0, 0x07, 0x11, 0xa7,
];
/// The 8-servo one in MAVLink 1 (the v10 dialect).
const V1_SERVO_OUTPUT_RAW: [u8; 29] = [
    0xfe, 0x15, 0x00, 0x01, 0x01, 0x24, 0xbb, 0x4b, 0x4c, 0x00, 0x4c, 0x04, 0xb1, 0x04, 0xdc, 0x05,
    0x6c, 0x07, 0xdc, 0x05, 0xdc, 0x05, 0xdc, 0x05, 0xdc, 0x05, 0x00, 0xed, 0xfe,
];

/// SERVO_OUTPUT_RAW and STATUSTEXT as ppm writes them are the bytes
/// pymavlink writes (so its CRC_EXTRA, 222 and 83, is pymavlink's), in
/// MAVLink 2 and 1; a long text goes in chunks, as pymavlink's reader
/// joins them.
#[test]
fn servo_output_raw_and_statustext_are_pymavlinks() {
    let us = [1100, 1201, 1500, 1900, 1500, 1500, 1500, 1500];
    let p = servo_output_raw_payload(5_000_123, 0, &us);
    assert_eq!(
        frame(2, (0, 1, 1), &SERVO_OUTPUT_RAW, &p),
        V2_SERVO_OUTPUT_RAW
    );
    let v1 = &p[..SERVO_OUTPUT_RAW.v1_len as usize];
    assert_eq!(
        frame(1, (0, 1, 1), &SERVO_OUTPUT_RAW, v1),
        V1_SERVO_OUTPUT_RAW
    );
    let mut sixteen = us.to_vec();
    sixteen.extend_from_slice(&[1000, 2000]);
    let p = servo_output_raw_payload(5_000_123, 0, &sixteen);
    assert_eq!(
        frame(2, (0, 1, 1), &SERVO_OUTPUT_RAW, &p),
        V2_SERVO_OUTPUT_RAW_16
    );
    // More than 16 values: the first 16.
    let p = servo_output_raw_payload(1, 2, &[1500; 20]);
    assert_eq!(p[20], 2);
    assert_eq!(p[35..37], 1500u16.to_le_bytes());

    let text = "ppm pi: overridden (instructor has control)";
    let p = statustext_payloads(telemetry::MAV_SEVERITY_WARNING, text, 9);
    assert_eq!(p.len(), 1);
    assert_eq!(frame(2, (0, 1, 1), &STATUSTEXT, &p[0]), V2_STATUSTEXT);
    let p = statustext_payloads(telemetry::MAV_SEVERITY_NOTICE, "ppm pi: following", 9);
    let v1 = &p[0][..STATUSTEXT.v1_len as usize];
    assert_eq!(frame(1, (0, 1, 1), &STATUSTEXT, v1), V1_STATUSTEXT);

    let long = "ppm quadrotor-left-wing-number-2: overridden (instructor has control)";
    let p = statustext_payloads(telemetry::MAV_SEVERITY_WARNING, long, 7);
    let frames: Vec<u8> = p
        .iter()
        .enumerate()
        .flat_map(|(seq, p)| frame(2, (seq as u8, 1, 1), &STATUSTEXT, p))
        .collect();
    assert_eq!(frames, V2_STATUSTEXT_CHUNKS);
    // Exactly 100 bytes: two full chunks, then an empty one that ends it;
    // id 0 is taken as 1 (0 says "the only chunk").
    let hundred = "x".repeat(100);
    let p = statustext_payloads(telemetry::MAV_SEVERITY_INFO, &hundred, 0);
    let chunks: Vec<(usize, u16, u8)> = p
        .iter()
        .map(|p| {
            let len = p[1..51].iter().position(|&b| b == 0).unwrap_or(50);
            (len, u16::from_le_bytes([p[51], p[52]]), p[53])
        })
        .collect();
    assert_eq!(chunks, [(50, 1, 0), (50, 1, 1), (0, 1, 2)]);
    // Chunks are bytes: "é" (2 bytes) across two chunks joins whole.
    let accents = format!("{}é{}", "a".repeat(49), "b".repeat(10));
    let p = statustext_payloads(telemetry::MAV_SEVERITY_INFO, &accents, 3);
    let joined: Vec<u8> = p.iter().flat_map(|p| p[1..51].to_vec()).collect();
    let end = joined.iter().position(|&b| b == 0).unwrap();
    assert_eq!(std::str::from_utf8(&joined[..end]), Ok(&accents[..]));
    assert_eq!(p.len(), 2);
    // ppm's to send, not to take.
    for f in [&V2_STATUSTEXT[..], &V2_SERVO_OUTPUT_RAW] {
        let e = read_frame(f).unwrap_err();
        assert_eq!(e.reason, RejectReason::MavlinkUnknownMessage);
    }
}
