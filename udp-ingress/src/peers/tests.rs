//! Tests of the peers: HEARTBEATs, RC_CHANNELS and SERVO_OUTPUT_RAW at
//! their rates, the replies to requests and commands, and the credit each
//! peer earns.

use super::*;

/// A line in MAV_STATE `s` carrying no frame.
fn state(s: u8) -> LineNow<'static> {
    LineNow {
        state: s,
        line: Frame {
            values_us: &[],
            at_us: 0,
        },
        radio: None,
        telemetry: None,
    }
}

/// A groundstation's header: system 255, component 190.
const GCS: Header = Header {
    version: 2,
    seq: 0,
    sysid: 255,
    compid: 190,
    msgid: 76,
    signed: false,
};

fn command_long(target: u8, command: u16, p1: f32, p2: f32) -> Message {
    Message::CommandLong(CommandLong {
        target_system: target,
        target_component: 0,
        command,
        confirmation: 0,
        params: [p1, p2, 0.0, 0.0, 0.0, 0.0, 0.0],
    })
}

/// The message id and payload of frame `f` (MAVLink 1 or 2, unsigned).
fn id_and_payload(f: &[u8]) -> (u8, &[u8]) {
    match f[0] {
        mavlink::STX_V1 => (f[5], &f[6..f.len() - 2]),
        _ => (f[7], &f[10..f.len() - 2]),
    }
}

/// The RC_CHANNELS in `out`: (port, time_boot_ms, chancount, chan1..).
fn rc_channels(out: &[(SocketAddr, Vec<u8>)]) -> Vec<(u16, u32, u8, Vec<u16>)> {
    out.iter()
        .filter(|(_, f)| id_and_payload(f).0 == RC_CHANNELS.id as u8)
        .map(|(a, f)| {
            let mut whole = id_and_payload(f).1.to_vec();
            whole.resize(42, 0);
            let chan = (0..whole[40] as usize)
                .map(|i| u16::from_le_bytes([whole[4 + 2 * i], whole[5 + 2 * i]]))
                .collect();
            let ms = u32::from_le_bytes([whole[0], whole[1], whole[2], whole[3]]);
            (a.port(), ms, whole[40], chan)
        })
        .collect()
}

/// The COMMAND_ACKs in `out`: (port, command, result, target system,
/// target component).
fn acks(out: &[(SocketAddr, Vec<u8>)]) -> Vec<(u16, u16, u8, u8, u8)> {
    out.iter()
        .filter(|(_, f)| id_and_payload(f).0 == COMMAND_ACK.id as u8)
        .map(|(a, f)| {
            let mut p = id_and_payload(f).1.to_vec();
            p.resize(10, 0);
            (a.port(), u16::from_le_bytes([p[0], p[1]]), p[2], p[8], p[9])
        })
        .collect()
}

fn addr(port: u16) -> SocketAddr {
    SocketAddr::from(([192, 0, 2, 1], port))
}

/// The port and MAVLink version of each HEARTBEAT sent.
fn heartbeats(out: &[(SocketAddr, Vec<u8>)]) -> Vec<(u16, u8)> {
    out.iter()
        .map(|(a, f)| {
            let (h, m, len) = mavlink::read_frame(f).expect("a good frame");
            assert_eq!((m, len), (mavlink::Message::Heartbeat, f.len()));
            (a.port(), h.version)
        })
        .collect()
}

#[test]
fn a_peer_gets_a_heartbeat_a_second_in_its_version_while_it_is_heard() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 0);
    let mut out = vec![];
    p.due(t, state(3), None, 0, &mut out);
    assert!(out.is_empty(), "no peer, no heartbeat");
    p.heard(addr(1), 2, 40, false, t);
    p.heard(addr(2), 1, 40, false, t);
    p.due(t, state(4), None, 0, &mut out);
    assert_eq!(heartbeats(&out), [(1, 2), (2, 1)]);
    // From ppm's ids, GENERIC type and autopilot, the line's state.
    let (h, _, _) = mavlink::read_frame(&out[0].1).unwrap();
    assert_eq!((h.sysid, h.compid, h.seq), (1, 1, 0));
    let payload = &out[0].1[10..19];
    assert_eq!(payload, [0, 0, 0, 0, 0, MAV_AUTOPILOT, 0, 4, 3]);
    out.clear();
    p.due(t + Duration::from_millis(999), state(4), None, 0, &mut out);
    assert!(out.is_empty(), "one a second");
    for s in 1..5u64 {
        // Peer 1 keeps talking; peer 2 fell silent at t.
        p.heard(addr(1), 2, 40, false, t + Duration::from_secs(s));
        p.due(t + Duration::from_secs(s), state(4), None, 0, &mut out);
    }
    let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
    assert_eq!(ports, [1, 2, 1, 2, 1, 2, 1, 2], "{out:?}");
    out.clear();
    p.due(t + Duration::from_secs(5), state(4), None, 0, &mut out);
    let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
    assert_eq!(ports, [1], "peer 2 silent for PEER_TIMEOUT");
    assert_eq!(p.known(), 1);
    assert_eq!(p.counters(), ReplyCounters { sent: 11, held: 0 });
}

#[test]
fn a_peer_gets_at_most_three_times_what_it_sent_unless_exempt() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 0);
    let mut out = vec![];
    // One forged 10-byte datagram earns 30 bytes: one MAVLink 2
    // HEARTBEAT (21 bytes), not two.
    p.heard(addr(1), 2, 10, false, t);
    p.heard(addr(2), 2, 10, true, t);
    for s in 0..4u64 {
        p.due(
            t + Duration::from_millis(1_000 * s),
            state(3),
            None,
            0,
            &mut out,
        );
    }
    let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
    assert_eq!(ports, [1, 2, 2, 2, 2]);
    assert_eq!(p.counters(), ReplyCounters { sent: 5, held: 3 });
    let sent: usize = out
        .iter()
        .filter(|(a, _)| a.port() == 1)
        .map(|(_, f)| f.len())
        .sum();
    assert!(sent <= 10 * REPLY_MAX_RATIO);
}

/// pymavlink 2.4.50's param_value_send(b"PPM_CHANNELS", 8.0, 9, 1, 0)
/// from system 1, component 1, MAVLink 2.
const PYMAVLINK_PARAM_VALUE: [u8; 37] = [
    0xfd, 0x19, 0x00, 0x00, 0x00, 0x01, 0x01, 0x16, 0x00, 0x00, 0x00, 0x00, 0x00, 0x41, 0x01, 0x00,
    0x00, 0x00, 0x50, 0x50, 0x4d, 0x5f, 0x43, 0x48, 0x41, 0x4e, 0x4e, 0x45, 0x4c, 0x53, 0x00, 0x00,
    0x00, 0x00, 0x09, 0x34, 0x00,
];

#[test]
fn a_request_for_the_parameters_gets_ppms_one_parameter() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 0);
    let mut out = vec![];
    p.request(addr(1), &GCS, &Message::ParamRequestList(1, 1));
    p.due(t, state(3), None, 0, &mut out);
    assert!(out.is_empty(), "only a peer is answered");
    p.heard(addr(1), 2, 14, false, t);
    p.request(addr(1), &GCS, &Message::ParamRequestList(1, 1));
    p.due(t, state(3), None, 0, &mut out);
    // The PARAM_VALUE (numbered 0) first; the HEARTBEAT is held: the
    // 14-byte request earned 42 bytes, the PARAM_VALUE took 37.
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].1, PYMAVLINK_PARAM_VALUE);
    assert_eq!(p.counters(), ReplyCounters { sent: 1, held: 1 });
    // Once per request.
    out.clear();
    p.heard(addr(1), 2, 14, false, t + Duration::from_secs(1));
    p.due(t + Duration::from_secs(1), state(3), None, 0, &mut out);
    assert_eq!(out.len(), 1);
    assert_eq!(
        mavlink::read_frame(&out[0].1).unwrap().1,
        mavlink::Message::Heartbeat
    );
}

#[test]
fn the_line_state_is_the_heartbeats_system_status() {
    use ppm_shared::line::LineState;
    assert_eq!(mav_state(None), 3);
    assert_eq!(mav_state(Some(LineState::Silent)), 3);
    assert_eq!(mav_state(Some(LineState::Active)), 4);
    assert_eq!(mav_state(Some(LineState::Failsafe)), 5);
}

#[test]
fn the_peer_heard_longest_ago_makes_room() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 0);
    for i in 0..=MAX_PEERS as u16 {
        p.heard(addr(i), 2, 100, false, t + Duration::from_millis(i as u64));
    }
    let mut out = vec![];
    p.due(t + Duration::from_millis(10), state(3), None, 0, &mut out);
    let mut ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
    ports.sort();
    assert_eq!(ports, (1..=MAX_PEERS as u16).collect::<Vec<_>>());
}

#[test]
fn rc_channels_carry_the_line_at_the_default_rate_or_the_one_asked_for() {
    let t = Instant::now();
    let ms = Duration::from_millis;
    let mut p = Peers::new(1, 1, 8, 4);
    let values = [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800];
    let line = LineNow {
        state: 4,
        line: Frame {
            values_us: &values,
            at_us: 12_345_000,
        },
        radio: None,
        telemetry: None,
    };
    p.heard(addr(1), 2, 4_000, false, t);
    p.heard(addr(2), 2, 4_000, false, t);
    let mut out = vec![];
    // Every 10 ms for a second: 4 each at the default 4 Hz (at once,
    // then every 250 ms), exact values, count 8.
    for k in 0..100 {
        p.due(t + ms(10 * k), line, None, 0, &mut out);
    }
    let rc = rc_channels(&out);
    assert_eq!(rc.len(), 8, "{rc:?}");
    assert!(rc
        .iter()
        .all(|(_, ms, n, c)| (*ms, *n, &c[..]) == (12_345, 8, &values[..])));
    // Peer 1 asks for 10 Hz (100000 us); peer 2 for none (-1).
    p.request(addr(1), &GCS, &command_long(1, 511, 65.0, 100_000.0));
    p.request(addr(2), &GCS, &command_long(0, 511, 65.0, -1.0));
    out.clear();
    let t1 = t + ms(1_000);
    for s in [1, 2] {
        p.heard(addr(s), 2, 4_000, false, t1);
    }
    for k in 0..100 {
        p.due(t1 + ms(10 * k), line, None, 0, &mut out);
    }
    let ports: Vec<u16> = rc_channels(&out).iter().map(|r| r.0).collect();
    assert_eq!(ports, [1; 10], "10 Hz to peer 1, none to peer 2");
    assert_eq!(
        acks(&out),
        [
            (1, 511, MAV_RESULT_ACCEPTED, 255, 190),
            (2, 511, 0, 255, 190)
        ]
    );
    // 50 Hz is more than ppmd reports: 10 Hz. 0 is the default again;
    // REQUEST_DATA_STREAM (all streams) at 2 Hz, then stopped.
    let rate = |p: &mut Peers, m: &Message, t: Instant| -> usize {
        p.heard(addr(1), 2, 4_000, false, t);
        p.request(addr(1), &GCS, m);
        let mut out = vec![];
        for k in 0..100 {
            p.due(t + ms(10 * k), line, None, 0, &mut out);
        }
        rc_channels(&out).len()
    };
    let stream = |start, rate_hz| {
        Message::RequestDataStream(mavlink::RequestDataStream {
            target_system: 1,
            target_component: 1,
            stream: mavlink::MAV_DATA_STREAM_ALL,
            rate_hz,
            start,
        })
    };
    let s = |n: u64| t + Duration::from_secs(n);
    assert_eq!(
        rate(&mut p, &command_long(1, 511, 65.0, 20_000.0), s(2)),
        10
    );
    assert_eq!(rate(&mut p, &command_long(1, 511, 65.0, 0.0), s(3)), 4);
    assert_eq!(rate(&mut p, &stream(true, 2), s(4)), 2);
    assert_eq!(rate(&mut p, &stream(false, 2), s(5)), 0);
    // Another stream (MAV_DATA_STREAM_POSITION, 6) changes nothing.
    let position = Message::RequestDataStream(mavlink::RequestDataStream {
        stream: 6,
        ..match stream(true, 10) {
            Message::RequestDataStream(r) => r,
            _ => unreachable!(),
        }
    });
    assert_eq!(rate(&mut p, &position, s(6)), 0);
    // One now, on request, whatever the rate.
    assert_eq!(rate(&mut p, &command_long(1, 512, 65.0, 0.0), s(7)), 1);
}

/// SERVO_OUTPUT_RAW: the line's values (RC_CHANNELS the radio's, with
/// a read-back) at the default rate, its own interval, or one asked
/// for; REQUEST_DATA_STREAM sets both.
#[test]
fn servo_output_raw_carries_the_line_at_its_own_rate() {
    let t = Instant::now();
    let ms = Duration::from_millis;
    let mut p = Peers::new(1, 1, 8, 4);
    let values = [1100, 1200, 1300, 1400];
    let radio = [1900, 1900];
    let line = LineNow {
        state: 4,
        line: Frame {
            values_us: &values,
            at_us: 5_000_123,
        },
        radio: Some(Frame {
            values_us: &radio,
            at_us: 6_000_000,
        }),
        telemetry: None,
    };
    let second = |p: &mut Peers, from: Instant| {
        p.heard(addr(1), 2, 4_000, false, from);
        let mut out = vec![];
        for k in 0..100 {
            p.due(from + ms(10 * k), line, None, 0, &mut out);
        }
        out
    };
    let servo = |out: &[(SocketAddr, Vec<u8>)]| -> Vec<(u32, u8, Vec<u16>)> {
        out.iter()
            .filter(|(_, f)| id_and_payload(f).0 == SERVO_OUTPUT_RAW.id as u8)
            .map(|(_, f)| {
                let mut w = id_and_payload(f).1.to_vec();
                w.resize(37, 0);
                let u = |at: usize| u16::from_le_bytes([w[at], w[at + 1]]);
                let mut s: Vec<u16> = (0..8).map(|i| u(4 + 2 * i)).collect();
                s.extend((0..8).map(|i| u(21 + 2 * i)));
                (u32::from_le_bytes([w[0], w[1], w[2], w[3]]), w[20], s)
            })
            .collect()
    };
    let out = second(&mut p, t);
    let mut want = values.to_vec();
    want.resize(16, 0);
    assert_eq!(servo(&out), vec![(5_000_123, 0, want); 4]);
    let rc = rc_channels(&out);
    assert_eq!(rc.len(), 4);
    assert_eq!(rc[0], (1, 6_000, 2, vec![1900, 1900]), "the radio's");
    // Its own interval: 10 Hz; RC_CHANNELS keep theirs.
    p.request(addr(1), &GCS, &command_long(1, 511, 36.0, 100_000.0));
    let out = second(&mut p, t + ms(1_000));
    assert_eq!(acks(&out), [(1, 511, MAV_RESULT_ACCEPTED, 255, 190)]);
    assert_eq!((servo(&out).len(), rc_channels(&out).len()), (10, 4));
    // None, and one asked for.
    p.request(addr(1), &GCS, &command_long(1, 511, 36.0, -1.0));
    assert_eq!(servo(&second(&mut p, t + ms(2_000))).len(), 0);
    p.request(addr(1), &GCS, &command_long(1, 512, 36.0, 0.0));
    assert_eq!(servo(&second(&mut p, t + ms(3_000))).len(), 1);
    // REQUEST_DATA_STREAM of the RC channels: both at 2 Hz.
    let stream = Message::RequestDataStream(mavlink::RequestDataStream {
        target_system: 1,
        target_component: 1,
        stream: mavlink::MAV_DATA_STREAM_RC_CHANNELS,
        rate_hz: 2,
        start: true,
    });
    p.request(addr(1), &GCS, &stream);
    let out = second(&mut p, t + ms(4_000));
    assert_eq!((servo(&out).len(), rc_channels(&out).len()), (2, 2));
}

#[test]
fn no_frame_on_the_line_is_a_count_of_zero() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 10);
    p.heard(addr(1), 2, 1_000, false, t);
    let mut out = vec![];
    p.due(t, state(3), None, 0, &mut out);
    let rc = rc_channels(&out);
    assert_eq!(rc, [(1, 0, 0, vec![])]);
    // Every channel UINT16_MAX (unused), RSSI 255 (unknown): the
    // MAVLink 2 frame keeps them all.
    let f = &out.iter().find(|(_, f)| f[7] == 65).unwrap().1;
    assert_eq!(f[1], 42);
    assert!(f[14..50].iter().all(|&b| b == 0xff));
    assert_eq!((f[50], f[51]), (0, 255));
}

#[test]
fn commands_are_acknowledged_for_this_system_only() {
    let t = Instant::now();
    let mut p = Peers::new(7, 1, 8, 0);
    p.heard(addr(1), 1, 4_000, false, t);
    // MAV_CMD_REQUEST_MESSAGE of AUTOPILOT_VERSION (148): not sent by
    // ppm, denied; MAV_CMD_COMPONENT_ARM_DISARM (400): unsupported;
    // one for system 8: not answered.
    p.request(addr(1), &GCS, &command_long(7, 512, 148.0, 0.0));
    p.request(addr(1), &GCS, &command_long(0, 400, 1.0, 0.0));
    p.request(addr(1), &GCS, &command_long(8, 400, 1.0, 0.0));
    p.request(addr(1), &GCS, &command_long(7, 511, 0.0, 1e6));
    let mut out = vec![];
    p.due(t, state(3), None, 0, &mut out);
    // In MAVLink 1, without the extension fields (the target).
    assert_eq!(
        acks(&out),
        [
            (1, 512, MAV_RESULT_DENIED, 0, 0),
            (1, 400, MAV_RESULT_UNSUPPORTED, 0, 0),
            (1, 511, MAV_RESULT_DENIED, 0, 0),
        ]
    );
    // 3 bytes.
    let (_, f) = out.iter().find(|(_, f)| f[5] == 77).unwrap();
    assert_eq!((f[0], f[1]), (mavlink::STX_V1, 3));
    assert!(mavlink::read_frame(f).is_err(), "ppm's to send, not take");
    // A request from a source that is not a peer is not answered.
    p.request(addr(9), &GCS, &command_long(7, 400, 1.0, 0.0));
    out.clear();
    p.due(t, state(3), None, 0, &mut out);
    assert!(acks(&out).is_empty());
}

#[test]
fn a_groundstation_that_sends_only_its_heartbeat_keeps_getting_ppms() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 4);
    let values = [1500; 8];
    let line = LineNow {
        state: 4,
        line: Frame {
            values_us: &values,
            at_us: 0,
        },
        radio: None,
        telemetry: None,
    };
    let mut out = vec![];
    // Its 21-byte HEARTBEAT each second earns 63 bytes: ppm's HEARTBEAT
    // (21) every second, RC_CHANNELS (54) with what is left, before
    // SERVO_OUTPUT_RAW.
    for k in 0..1_000u64 {
        let now = t + Duration::from_millis(10 * k);
        if k % 100 == 0 {
            p.heard(addr(1), 2, 21, false, now);
        }
        p.due(now, line, None, 0, &mut out);
    }
    let beats = out.iter().filter(|(_, f)| f[7] == 0).count();
    assert_eq!(beats, 10, "one a second");
    let rc = rc_channels(&out).len();
    assert!((5..=10).contains(&rc), "{rc} RC_CHANNELS");
    // SERVO_OUTPUT_RAW take only what is left beyond the next
    // RC_CHANNELS: here, nothing.
    assert_eq!(out.iter().filter(|(_, f)| f[7] == 36).count(), 0);
    let sent: usize = out.iter().map(|(_, f)| f.len()).sum();
    assert!(sent <= 10 * 63, "{sent} bytes");
    // Its frames are numbered 0, 1, 2, ... without a gap, whatever
    // was held.
    let seqs: Vec<u8> = out.iter().map(|(_, f)| f[4]).collect();
    assert_eq!(seqs, (0..seqs.len() as u8).collect::<Vec<_>>());
    assert!(p.counters().held > 0);
}

/// How a groundstation's own HEARTBEAT a second comes against ppm's
/// beat, in the phase test below.
#[derive(Debug, Clone, Copy)]
enum Clock {
    /// Every 1000 ms exactly.
    Exact,
    /// Every 1000 ms, each up to 200 ms early or late (a second may
    /// bring none of them, the next two: one HEARTBEAT kept back is
    /// not enough then).
    Jitter,
    /// Every 997 ms: its phase slides 60 ms in 20 s.
    Drift,
}

/// A groundstation that sends only its own HEARTBEAT, once a second (as
/// QGroundControl may, joystick off), whatever the phase of its
/// datagrams against ppm's beat (set by another groundstation heard
/// first), 0 to 995 ms in 5 ms steps, sent exactly, with jitter or
/// drifting, in MAVLink 1, 2 and signed: ppm's HEARTBEAT every second
/// for 20 s, RC_CHANNELS from what is left, and never more than 3 times
/// the bytes it sent. Simulated time, 1 ms steps: `due` runs every 20 ms
/// (the receive loop's poll timeout) and after each of its datagrams,
/// as the server drains, then settles. (Before RC_CHANNELS kept the
/// HEARTBEAT's bytes, 11 HEARTBEATs came in 20 s at some phases.)
#[test]
fn a_heartbeat_every_second_whatever_the_phase_of_the_peers_own() {
    let values = [1500; 8];
    let line = LineNow {
        state: 4,
        line: Frame {
            values_us: &values,
            at_us: 0,
        },
        radio: None,
        telemetry: None,
    };
    let ms = |n: u64| Duration::from_millis(n);
    let mut worst_rc = usize::MAX;
    for (version, signed) in [(2u8, false), (1, false), (2, true)] {
        // The groundstation's HEARTBEAT, as it sends it.
        let own = match (version, signed) {
            (1, _) => 17,
            (_, false) => 21,
            (_, true) => 34,
        };
        for clock in [Clock::Exact, Clock::Jitter, Clock::Drift] {
            for offset in (0..1_000u64).step_by(10) {
                let t = Instant::now();
                let mut p = Peers::new(1, 1, 8, 4);
                let mut signing =
                    signed.then(|| mavlink::Signing::new(ppm_shared::auth::AuthKey::new([7; 32])));
                // Its first datagram, when it connects, starts ppm's
                // beat (a HEARTBEAT at once, then one a second); its
                // own timer then sends at `offset` into each second.
                let mut lcg = offset * 2_654_435_761 + 1;
                let sends: Vec<u64> = std::iter::once(0)
                    .chain((1..=21u64).map(|k| match clock {
                        Clock::Exact => offset + 1_000 * k,
                        Clock::Drift => offset + 997 * k,
                        Clock::Jitter => {
                            lcg = lcg.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                            offset + 1_000 * k + 200 - (lcg >> 33) % 401
                        }
                    }))
                    .collect();
                let last = 20_000;
                let (mut earned, mut got) = (0usize, 0usize);
                let mut beats = vec![];
                let mut rc = 0;
                let mut next = 0;
                for now_ms in 0..=last {
                    let now = t + ms(now_ms);
                    let mut wake = now_ms % 20 == 0;
                    while next < sends.len() && sends[next] == now_ms {
                        p.heard(addr(1), version, own, false, now);
                        earned += own;
                        next += 1;
                        wake = true;
                    }
                    if !wake {
                        continue;
                    }
                    let mut out = vec![];
                    p.due(now, line, signing.as_mut(), now_ms, &mut out);
                    for (_, f) in out.iter().filter(|(a, _)| a.port() == 1) {
                        let (v, s, id) = frame_kind(f);
                        assert_eq!((v, s), (if signed { 2 } else { version }, signed));
                        got += f.len();
                        match id {
                            0 => beats.push(now_ms),
                            65 => rc += 1,
                            36 => {}
                            other => panic!("message {other}"),
                        }
                    }
                    let what = format!("{version} {signed} {clock:?} at {offset} ms");
                    assert!(
                        got <= REPLY_MAX_RATIO * earned,
                        "{what}: {got} bytes for {earned} at {now_ms} ms"
                    );
                }
                let what = format!("MAVLink {version}, signed {signed}, {clock:?}, at {offset} ms: beats {beats:?}");
                // One a second, none missed, for 20 s.
                let want: Vec<u64> = (0..=20).map(|s| s * 1_000).collect();
                assert_eq!(beats, want, "{what}");
                worst_rc = worst_rc.min(rc);
            }
        }
    }
    // What is left beyond the HEARTBEAT buys RC_CHANNELS: at least 42
    // bytes a second (MAVLink 1: 51 earned, 17 for the HEARTBEAT), 0.68
    // RC_CHANNELS (50 bytes in MAVLink 1) a second.
    assert!(worst_rc >= 11, "{worst_rc} RC_CHANNELS in 20 s");
}

/// A frame's MAVLink version, whether it is signed, and its message.
fn frame_kind(f: &[u8]) -> (u8, bool, u32) {
    match f[0] {
        mavlink::STX_V1 => (1, false, f[5] as u32),
        _ => (
            2,
            f[2] & mavlink::IFLAG_SIGNED != 0,
            u32::from_le_bytes([f[7], f[8], f[9], 0]),
        ),
    }
}

/// An RC_CHANNELS asked for (MAV_CMD_REQUEST_MESSAGE) is an answer,
/// earned by its request: it needs no HEARTBEATs' bytes left over, as
/// those of the stream do.
#[test]
fn an_rc_channels_asked_for_is_earned_by_its_request() {
    let t = Instant::now();
    let values = [1500; 8];
    let line = LineNow {
        state: 4,
        line: Frame {
            values_us: &values,
            at_us: 0,
        },
        radio: None,
        telemetry: None,
    };
    let mut p = Peers::new(1, 1, 8, 0);
    // A MAVLink 2 COMMAND_LONG (trimmed) is 43 bytes: it earns 129, the
    // COMMAND_ACK (22), ppm's first HEARTBEAT (21) and the RC_CHANNELS
    // (54) take 97; 42 more kept would be 139.
    let request = command_long(1, 512, 65.0, 0.0);
    let (_, payload) = request.encode();
    let len = mavlink::frame(2, (0, 255, 190), &mavlink::COMMAND_LONG, &payload).len();
    assert_eq!(len, 43);
    p.heard(addr(1), 2, len, false, t);
    p.request(addr(1), &GCS, &request);
    let mut out = vec![];
    p.due(t, line, None, 0, &mut out);
    assert_eq!(acks(&out), [(1, 512, MAV_RESULT_ACCEPTED, 255, 190)]);
    assert_eq!(rc_channels(&out).len(), 1, "{out:?}");
    assert_eq!(p.counters(), ReplyCounters { sent: 3, held: 0 });
}

#[test]
fn heartbeat_len_is_the_heartbeats() {
    let mut s = mavlink::Signing::new(ppm_shared::auth::AuthKey::new([7; 32]));
    let payload = [0, 0, 0, 0, 0, MAV_AUTOPILOT, 0, 4, 3];
    for version in [1, 2] {
        let f = mavlink::frame(version, (0, 1, 1), &HEARTBEAT, &payload);
        assert_eq!(heartbeat_len(version, false), f.len());
        let f = s.frame((0, 1, 1), &HEARTBEAT, &payload, 1);
        assert_eq!(heartbeat_len(version, true), f.len());
        let rc = mavlink::rc_channels_payload(1, &[]);
        let f = mavlink::frame(version, (0, 1, 1), &RC_CHANNELS, &rc);
        assert_eq!(rc_channels_len(version, false), f.len());
        let f = s.frame((0, 1, 1), &RC_CHANNELS, &rc, 1);
        assert_eq!(rc_channels_len(version, true), f.len());
    }
}

#[test]
fn any_interval_a_peer_asks_for_is_taken_or_denied_never_a_fault() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 4);
    for (param2, result) in [
        (f32::NAN, MAV_RESULT_DENIED),
        (f32::NEG_INFINITY, MAV_RESULT_DENIED),
        (f32::INFINITY, MAV_RESULT_ACCEPTED),
        (-2.0, MAV_RESULT_DENIED),
        (f32::MAX, MAV_RESULT_ACCEPTED),
        (1e30, MAV_RESULT_ACCEPTED),
        (1.0, MAV_RESULT_ACCEPTED),
    ] {
        p.heard(addr(1), 2, 4_000, false, t);
        p.request(addr(1), &GCS, &command_long(1, 511, 65.0, param2));
        let mut out = vec![];
        p.due(t, state(3), None, 0, &mut out);
        assert_eq!(acks(&out), [(1, 511, result, 255, 190)], "{param2}");
    }
    // The last asked for 1 us: 10 Hz at most (counted over the second
    // second). f32::MAX before it: every 60 s.
    let mut out = vec![];
    for k in 1..=200 {
        if k == 101 {
            out.clear();
        }
        let now = t + Duration::from_millis(10 * k);
        p.due(now, state(3), None, 0, &mut out);
    }
    assert_eq!(rc_channels(&out).len(), 10);
    p.request(addr(1), &GCS, &command_long(1, 511, 65.0, f32::MAX));
    let mut out = vec![];
    let later = t + Duration::from_secs(2);
    p.heard(addr(1), 2, 4_000, false, later);
    for k in 0..300 {
        p.due(
            later + Duration::from_millis(10 * k),
            state(3),
            None,
            0,
            &mut out,
        );
    }
    assert_eq!(rc_channels(&out).len(), 1, "one, then a minute later");
}

/// An infinite interval is over 60 s: taken as 60 s, as the docs say
/// of any interval over it (and as ArduPilot takes it), not denied. -1
/// stops them; minus infinity and NaN are denied and change nothing.
#[test]
fn an_infinite_interval_is_a_minute() {
    let t = Instant::now();
    let ms = Duration::from_millis;
    let mut p = Peers::new(1, 1, 8, 4);
    p.heard(addr(1), 2, 4_000, false, t);
    let mut out = vec![];
    p.due(t, state(3), None, 0, &mut out);
    assert_eq!(rc_channels(&out).len(), 1, "the first at once");
    for (param2, result) in [
        (f32::INFINITY, MAV_RESULT_ACCEPTED),
        (f32::NEG_INFINITY, MAV_RESULT_DENIED),
        (f32::NAN, MAV_RESULT_DENIED),
    ] {
        p.request(addr(1), &GCS, &command_long(1, 511, 65.0, param2));
        let mut out = vec![];
        p.due(t + ms(1), state(3), None, 0, &mut out);
        assert_eq!(acks(&out), [(1, 511, result, 255, 190)], "{param2}");
    }
    // The next one due (at 250 ms, the default 4 Hz) goes out, then
    // one a minute: 3 in 3 minutes.
    let mut out = vec![];
    for k in 1..=18_000u64 {
        let now = t + ms(10 * k);
        if k % 400 == 0 {
            p.heard(addr(1), 2, 4_000, false, now);
        }
        p.due(now, state(3), None, 0, &mut out);
    }
    assert_eq!(rc_channels(&out).len(), 3, "at 0.25, 60.25 and 120.25 s");
}

#[test]
fn a_request_for_the_protocol_version_gets_mavlink_2() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 0);
    // A MAVLink 1 peer: PROTOCOL_VERSION still goes out in MAVLink 2.
    p.heard(addr(1), 1, 4_000, false, t);
    p.request(addr(1), &GCS, &command_long(1, 512, 300.0, 0.0));
    p.request(addr(1), &GCS, &command_long(1, 519, 0.0, 0.0));
    let mut out = vec![];
    p.due(t, state(3), None, 0, &mut out);
    assert_eq!(
        acks(&out),
        [
            (1, 512, MAV_RESULT_ACCEPTED, 0, 0),
            (1, 519, MAV_RESULT_ACCEPTED, 0, 0)
        ]
    );
    let v: Vec<&Vec<u8>> = out
        .iter()
        .map(|(_, f)| f)
        .filter(|f| f[0] == mavlink::STX_V2 && f[7..10] == [0x2c, 0x01, 0])
        .collect();
    assert_eq!(v.len(), 1, "one, for both requests");
    let mut payload = v[0][10..v[0].len() - 2].to_vec();
    payload.resize(22, 0);
    assert_eq!(payload, mavlink::protocol_version_payload());
    assert_eq!(payload[..6], [200, 0, 100, 0, 200, 0]);
    let crc = mavlink::frame_crc(&PROTOCOL_VERSION, &v[0][1..v[0].len() - 2]);
    assert_eq!(v[0][v[0].len() - 2..], crc.to_le_bytes());
}

/// A CRSF frame from the flight controller: `kind`, `payload`, its CRC.
fn crsf_frame(kind: u8, payload: &[u8]) -> Vec<u8> {
    ppm_shared::crsf::frame(ppm_shared::crsf::ADDRESS_FLIGHT_CONTROLLER, kind, payload)
}

/// A telemetry sample holding `frames`, read at `at_ns`, counted as
/// ppmd's reader counts them.
fn telemetry_sample(frames: &[Vec<u8>], at_ns: u64) -> TelemetrySample {
    let mut s = TelemetrySample::default();
    let mut r = ppm_shared::crsf::TelemetryReader::new();
    for f in frames {
        r.feed(f, |raw, t| s.take(raw, &t, at_ns));
    }
    s.counts = r.counts().to_array();
    s.published_mono_ns = at_ns;
    s
}

/// The ids of the frames in `out`, in order.
fn ids(out: &[(SocketAddr, Vec<u8>)]) -> Vec<u8> {
    out.iter().map(|(_, f)| id_and_payload(f).0).collect()
}

#[test]
fn telemetry_goes_to_peers_once_per_new_frame_at_most_ten_a_second() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 0);
    p.heard(addr(1), 2, 4_000, false, t);
    let battery = crsf_frame(0x08, &[0x00, 0xA8, 0x00, 0x7B, 0x01, 0xE2, 0x40, 0x4B]);
    let attitude = crsf_frame(0x1E, &[0x04, 0xD2, 0xEC, 0x78, 0x7A, 0xB7]);
    let mode = crsf_frame(0x21, b"ANGL\0");
    let mut line = state(4);
    let mut out = vec![];
    let s1 = telemetry_sample(
        &[battery.clone(), attitude.clone(), mode.clone()],
        7_000_000,
    );
    line.telemetry = Some(&s1);
    p.due(t, line, None, 0, &mut out);
    // A HEARTBEAT first, then SYS_STATUS and ATTITUDE; the flight mode is
    // no MAVLink message of its own (a STATUSTEXT when it changes).
    assert_eq!(ids(&out), [0, 1, 30]);
    let sys = id_and_payload(&out[1].1).1.to_vec();
    assert_eq!(u16::from_le_bytes([sys[14], sys[15]]), 16_800, "mV");
    let att = id_and_payload(&out[2].1).1.to_vec();
    assert_eq!(u32::from_le_bytes(att[..4].try_into().unwrap()), 7, "ms");
    assert_eq!(
        f32::from_le_bytes(att[4..8].try_into().unwrap()),
        -0.5,
        "roll"
    );
    // The same sample again, or nothing new: nothing more.
    out.clear();
    for k in 1..30 {
        p.due(t + Duration::from_millis(10 * k), line, None, 0, &mut out);
    }
    assert!(out.is_empty(), "{:?}", ids(&out));
    // A second attitude frame (the battery's count unchanged): only
    // ATTITUDE goes.
    let s2 = telemetry_sample(
        &[battery.clone(), attitude.clone(), attitude.clone()],
        8_000_000,
    );
    line.telemetry = Some(&s2);
    p.due(t + Duration::from_millis(350), line, None, 0, &mut out);
    assert_eq!(ids(&out), [30], "only the kind that moved");
    out.clear();
    let s3 = telemetry_sample(
        &[battery, attitude.clone(), attitude.clone(), attitude],
        9_000_000,
    );
    line.telemetry = Some(&s3);
    p.due(t + Duration::from_millis(400), line, None, 0, &mut out);
    assert!(
        out.is_empty(),
        "a third, within 100 ms of the last ATTITUDE"
    );
    p.due(t + Duration::from_millis(450), line, None, 0, &mut out);
    assert_eq!(ids(&out), [30]);
}

#[test]
fn telemetry_is_earned_like_rc_channels() {
    let t = Instant::now();
    let mut p = Peers::new(1, 1, 8, 0);
    // 21 bytes earn 63: ppm's HEARTBEAT (21) and two kept, nothing more.
    p.heard(addr(1), 2, 21, false, t);
    let s = telemetry_sample(
        &[crsf_frame(
            0x08,
            &[0x00, 0xA8, 0x00, 0x7B, 0x01, 0xE2, 0x40, 0x4B],
        )],
        1,
    );
    let mut line = state(4);
    line.telemetry = Some(&s);
    let mut out = vec![];
    p.due(t, line, None, 0, &mut out);
    assert_eq!(ids(&out), [0], "the HEARTBEAT only");
    assert_eq!(p.counters().held, 1, "SYS_STATUS held");
    // An exempt peer gets it.
    let mut p = Peers::new(1, 1, 8, 0);
    p.heard(addr(2), 2, 21, true, t);
    out.clear();
    p.due(t, line, None, 0, &mut out);
    assert_eq!(ids(&out), [0, 1]);
}
