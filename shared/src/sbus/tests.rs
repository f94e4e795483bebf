use super::framing::{
    ARDUPILOT_FRAME_GAP_US, BETAFLIGHT45_FRAME_TIMEOUT_US, BETAFLIGHT_INTERBYTE_TIMEOUT_US,
};
use super::*;
use proptest::prelude::*;

const US: u64 = 1_000;
const EDGETX: SbusReceiver = SbusReceiver::EdgeTx;
const BF2026: SbusReceiver = SbusReceiver::Betaflight2026;
const BF45: SbusReceiver = SbusReceiver::Betaflight45;
const ARDUPILOT: SbusReceiver = SbusReceiver::ArduPilot;

/// Whole microseconds, as ns.
fn us(values: [u64; CHANNELS]) -> [u64; CHANNELS] {
    values.map(|v| v * US)
}

/// Sixteen different commands inside every receiver's range.
const COMMAND_US: [u64; CHANNELS] = [
    1_000, 1_500, 2_000, 988, 1_001, 1_234, 1_499, 1_501, 1_777, 1_999, 2_012, 1_100, 1_250, 1_333,
    1_666, 1_900,
];

fn used(v: Verdict) -> Reading {
    match v {
        Verdict::Used(r) => r,
        other => panic!("not used: {other:?}"),
    }
}

/// `|a - b|`, ns.
fn dist(a: u64, b: u64) -> u64 {
    a.abs_diff(b)
}

/// The largest error [`raw_for`] may leave at a whole microsecond.
fn whole_us_tolerance_ns(r: SbusReceiver) -> u64 {
    match r {
        EDGETX | ARDUPILOT => 0,
        // Half of Betaflight's 0.625 us step, rounded down to whole ns.
        BF2026 | BF45 => 312,
    }
}

#[test]
fn channels_pack_little_endian_from_byte_1() {
    let mut raw = [0u16; CHANNELS];
    raw[0] = 0x7FF;
    raw[1] = 0x001;
    raw[15] = 0x400;
    let f = encode(&raw, Flags::default());
    assert_eq!(f[0], HEADER);
    assert_eq!(f[1], 0xFF);
    // Channel 0's top 3 bits, then channel 1's lowest at bit 3.
    assert_eq!(f[2], 0x07 | 0x08);
    // Channel 15 is bits 165..=175: its top bit is byte 22's bit 7.
    assert_eq!(f[22], 0x80);
    assert!(f[3..22].iter().all(|&b| b == 0));
    assert_eq!(f[FLAGS_INDEX], 0);
    assert_eq!(f[FRAME_LEN - 1], END);
}

#[test]
fn flags_are_the_low_four_bits() {
    let all = Flags {
        ch17: true,
        ch18: true,
        frame_lost: true,
        failsafe: true,
    };
    assert_eq!(all.to_byte(), 0x0F);
    let lost = Flags {
        frame_lost: true,
        ..Flags::default()
    };
    assert_eq!(encode(&[992; CHANNELS], lost)[FLAGS_INDEX], 0x04);
    assert_eq!(
        Flags::from_byte(0xF8),
        Flags {
            failsafe: true,
            ..Flags::default()
        }
    );
}

#[test]
fn encode_clamps_instead_of_wrapping() {
    let mut raw = [0u16; CHANNELS];
    raw[3] = 2_048;
    raw[4] = u16::MAX;
    let got = channels(&encode(&raw, Flags::default()));
    assert_eq!(got[3], RAW_MAX);
    assert_eq!(got[4], RAW_MAX);
    assert_eq!(got[2], 0);
    assert_eq!(got[5], 0);
}

#[test]
fn decode_wants_header_and_end_byte() {
    let good = encode(&[992; CHANNELS], Flags::default());
    assert_eq!(decode(&good), Some(([992; CHANNELS], Flags::default())));
    let mut bad = good;
    bad[0] = 0x0E;
    assert_eq!(decode(&bad), None);
    let mut sbus2 = good;
    sbus2[FRAME_LEN - 1] = 0x04;
    assert_eq!(decode(&sbus2), None);
    assert_eq!(channels(&sbus2), [992; CHANNELS]);
}

proptest! {
    #[test]
    fn encode_decode_round_trip(
        raw in proptest::array::uniform16(0u16..=RAW_MAX),
        bits in 0u8..16,
    ) {
        let flags = Flags::from_byte(bits);
        let f = encode(&raw, flags);
        prop_assert_eq!(decode(&f), Some((raw, flags)));
        prop_assert_eq!(f[FLAGS_INDEX], bits);
    }

    #[test]
    fn every_receiver_reads_its_encoding_of_whole_microseconds(
        values in proptest::array::uniform16(1_000u64..=2_000),
        r in proptest::sample::select(SbusReceiver::ALL.to_vec()),
    ) {
        let want = us(values);
        let got = used(r.verdict(&encode_ns(r, &want, Flags::default())));
        for (g, w) in got.channels_ns.iter().zip(want) {
            prop_assert!(dist(*g, w) <= whole_us_tolerance_ns(r), "{:?}: {} for {}", r, g, w);
        }
    }
}

#[test]
fn scaling_as_each_firmware_computes_it() {
    let read = |r: SbusReceiver, raws: &[u16]| -> Vec<u64> {
        raws.iter().map(|&raw| r.read_ns(raw)).collect()
    };
    let marks = [0, 192, 992, 1_792, RAW_MAX];
    assert_eq!(
        read(EDGETX, &marks),
        [880_000, 1_000_000, 1_500_000, 2_000_000, 2_159_000]
    );
    assert_eq!(
        read(BF2026, &marks),
        [880_000, 1_000_000, 1_500_000, 2_000_000, 2_159_375]
    );
    assert_eq!(read(BF45, &marks), read(BF2026, &marks));
    assert_eq!(
        read(ARDUPILOT, &marks),
        [875_000, 995_000, 1_495_000, 1_995_000, 2_154_000]
    );
    assert_eq!(
        read(ARDUPILOT, &[200, 1_000, 1_800]),
        [1_000_000, 1_500_000, 2_000_000]
    );
    // C's division truncates toward zero: 990..=994 read -1, 0, 0, 0, +1.
    assert_eq!(
        read(EDGETX, &[990, 991, 992, 993, 994]),
        [1_499_000, 1_500_000, 1_500_000, 1_500_000, 1_501_000]
    );
    // Betaflight's floats are exact: 993 is 1500.625 us.
    assert_eq!(BF2026.read_ns(993), 1_500_625);
    // Only the low 11 bits are a channel.
    assert_eq!(EDGETX.read_ns(992 | 0x800), 1_500_000);
}

#[test]
fn raw_for_matches_a_search_over_every_raw() {
    let mut targets: Vec<u64> = (800..=2_200).map(|u| u * US).collect();
    for u in (800..=2_200).step_by(7) {
        targets.extend([1, 124, 312, 313, 499, 500, 501, 688, 937, 999].map(|f| u * US + f));
    }
    for r in SbusReceiver::ALL {
        let (lo, hi) = r.range_ns();
        for &t in &targets {
            let best = (0..=RAW_MAX)
                .map(|raw| dist(r.read_ns(raw), t))
                .min()
                .unwrap();
            let raw = raw_for(r, t);
            assert!(raw <= RAW_MAX);
            assert_eq!(dist(r.read_ns(raw), t), best, "{r:?} at {t} ns: raw {raw}");
            if t % US == 0 && (lo..=hi).contains(&t) {
                assert!(best <= whole_us_tolerance_ns(r), "{r:?} at {t} ns");
            }
        }
    }
}

#[test]
fn raw_for_clamps_to_the_range_read() {
    for r in SbusReceiver::ALL {
        let (lo, hi) = r.range_ns();
        assert_eq!(r.read_ns(raw_for(r, 0)), lo, "{r:?}");
        assert_eq!(raw_for(r, u64::MAX), RAW_MAX, "{r:?}");
        assert_eq!(r.read_ns(RAW_MAX), hi, "{r:?}");
    }
}

/// The older, PX4-derived ArduPilot scaling, in single floats as it ran.
fn ardupilot_float_us(raw: u16) -> u64 {
    (raw as f32 * 0.625 + 0.5) as u64 + 874
}

#[test]
fn ardupilot_float_scaling_reads_one_microsecond_lower_on_half_the_raws() {
    for raw in 0..=RAW_MAX {
        let int_us = ARDUPILOT.read_ns(raw) / US;
        let lower = matches!(raw % 8, 0 | 2 | 5 | 7);
        assert_eq!(
            ardupilot_float_us(raw),
            int_us - u64::from(lower),
            "raw {raw}"
        );
    }
    assert_eq!(
        [192, 992, 1_792].map(ardupilot_float_us),
        [994, 1_494, 1_994]
    );
    // The encoder's raws read the same there except at values ending in 4 or 9.
    for u in 875..=2_154 {
        let raw = raw_for(ARDUPILOT, u * US);
        let lower = u64::from(u % 5 == 4);
        assert_eq!(ardupilot_float_us(raw), u - lower, "{u} us, raw {raw}");
    }
}

#[test]
fn every_receiver_reads_a_frame_made_for_it() {
    let want = us(COMMAND_US);
    for r in SbusReceiver::ALL {
        let got = used(r.verdict(&encode_ns(r, &want, Flags::default())));
        for (g, w) in got.channels_ns.iter().zip(want) {
            assert!(
                dist(*g, w) <= whole_us_tolerance_ns(r),
                "{r:?}: {g} for {w}"
            );
        }
        if r == EDGETX || r == ARDUPILOT {
            assert_eq!(got.channels_ns, want, "{r:?}");
        }
    }
}

#[test]
fn offsets_between_receivers() {
    let read_as = |made_for: SbusReceiver, reader: SbusReceiver, at_us: u64| {
        let f = encode_ns(made_for, &[at_us * US; CHANNELS], Flags::default());
        used(reader.verdict(&f)).channels_ns[0]
    };
    for at in [1_000, 1_500, 2_000] {
        // EdgeTX and Betaflight pick the same raws at these values.
        assert_eq!(read_as(EDGETX, BF2026, at), at * US);
        assert_eq!(read_as(BF2026, EDGETX, at), at * US);
        assert_eq!(read_as(EDGETX, ARDUPILOT, at), (at - 5) * US);
        assert_eq!(read_as(BF45, ARDUPILOT, at), (at - 5) * US);
        assert_eq!(
            read_as(ARDUPILOT, EDGETX, at),
            (at + 5) * US + if at == 1_000 { US } else { 0 }
        );
        assert_eq!(read_as(ARDUPILOT, BF2026, at), (at + 5) * US + 625);
    }
    // Between the marks EdgeTX's truncation toward zero and Betaflight's
    // eighths differ by under 1 us.
    assert_eq!(read_as(EDGETX, BF2026, 1_234), 1_233_750);
    assert_eq!(read_as(EDGETX, BF2026, 1_001), 1_000_625);
    assert_eq!(read_as(EDGETX, BF2026, 1_999), 1_999_375);
    assert_eq!(read_as(BF2026, EDGETX, 1_234), 1_234_000);
}

#[test]
fn flags_and_end_byte_per_receiver() {
    let frame = |flags: Flags, end: u8| {
        let mut f = encode(&[992; CHANNELS], flags);
        f[FRAME_LEN - 1] = end;
        f
    };
    let plain = Flags::default();
    let failsafe = Flags {
        failsafe: true,
        ..plain
    };
    let lost = Flags {
        frame_lost: true,
        ..plain
    };
    let ch17 = Flags {
        ch17: true,
        ..plain
    };
    let mut wrong_header = frame(plain, END);
    wrong_header[0] = 0x8F;
    for r in SbusReceiver::ALL {
        assert_eq!(r.verdict(&wrong_header), Verdict::Invalid, "{r:?}");
    }

    assert_eq!(EDGETX.verdict(&frame(failsafe, END)), Verdict::NoSignal);
    assert_eq!(EDGETX.verdict(&frame(lost, END)), Verdict::NoSignal);
    assert_eq!(EDGETX.verdict(&frame(plain, 0x04)), Verdict::Invalid);
    assert_eq!(used(EDGETX.verdict(&frame(ch17, END))).digital_ns, None);
    assert_eq!(EDGETX.digital_ns(true), None);

    for bf in [BF2026, BF45] {
        assert_eq!(bf.verdict(&frame(failsafe, END)), Verdict::NoSignal);
        assert_eq!(bf.verdict(&frame(lost, END)), Verdict::NoSignal);
        let sbus2 = used(bf.verdict(&frame(plain, 0x04)));
        assert_eq!(sbus2.channels_ns, [1_500_000; CHANNELS]);
        // Raw 1812 and 173.
        assert_eq!(
            used(bf.verdict(&frame(ch17, 0xC3))).digital_ns,
            Some([2_012_500, 988_125])
        );
    }

    assert_eq!(ARDUPILOT.verdict(&frame(failsafe, END)), Verdict::Failsafe);
    let both = Flags {
        failsafe: true,
        frame_lost: true,
        ..plain
    };
    assert_eq!(ARDUPILOT.verdict(&frame(both, END)), Verdict::Failsafe);
    assert_eq!(
        used(ARDUPILOT.verdict(&frame(lost, END))).channels_ns,
        [1_495_000; CHANNELS]
    );
    assert_eq!(
        used(ARDUPILOT.verdict(&frame(plain, 0x23))).channels_ns[0],
        1_495_000
    );
    assert_eq!(used(ARDUPILOT.verdict(&frame(ch17, END))).digital_ns, None);
    assert_eq!(ARDUPILOT.digital_ns(true), Some(1_998_000));
    assert_eq!(ARDUPILOT.digital_ns(false), Some(998_000));
}

// Framing.

/// Frames whose bytes after the header hold no header byte, so a receiver
/// hunting for one can only find the real ones.
fn test_frames(n: usize) -> Vec<[u8; FRAME_LEN]> {
    (0..n)
        .map(|i| {
            let mut ch = us(COMMAND_US);
            ch[0] = (1_100 + 10 * i as u64) * US;
            let f = encode_ns(EDGETX, &ch, Flags::default());
            assert!(!f[1..].contains(&HEADER), "frame {i}: {f:?}");
            f
        })
        .collect()
}

/// Feeds `frames` sent back to back with `gap_ns` of idle line between them
/// (and, with `inner` = (frame, byte index, idle ns), that idle after that
/// byte), then a long idle line; returns what `r` takes.
fn stream(
    r: SbusReceiver,
    frames: &[[u8; FRAME_LEN]],
    gap_ns: u64,
    inner: Option<(usize, usize, u64)>,
) -> Vec<Taken> {
    let mut framer = Framer::new(r);
    let mut taken = Vec::new();
    let mut t = 50_000 * US + 123;
    for (i, f) in frames.iter().enumerate() {
        for (j, &b) in f.iter().enumerate() {
            t += BYTE_NS;
            taken.extend(framer.push(b, t));
            if let Some((_, _, idle)) = inner.filter(|&(fi, bj, _)| (fi, bj) == (i, j)) {
                t += idle;
            }
        }
        t += gap_ns;
    }
    taken.extend(framer.idle(t + 1_000 * US));
    taken
}

/// The ends of each frame's last byte when `n` frames are sent from the
/// stream's start with `gap_ns` between them.
fn last_byte_ends(n: usize, gap_ns: u64) -> Vec<u64> {
    (0..n as u64)
        .map(|i| 50_000 * US + 123 + (i + 1) * FRAME_WIRE_NS + i * gap_ns)
        .collect()
}

#[test]
fn min_gaps_follow_from_the_rules() {
    assert_eq!(EDGETX.min_gap_ns(), 120 * US);
    assert_eq!(BF2026.min_gap_ns(), 481 * US);
    assert_eq!(BF45.min_gap_ns(), 501 * US);
    assert_eq!(ARDUPILOT.min_gap_ns(), 1_880 * US);
    assert_eq!(
        BETAFLIGHT_INTERBYTE_TIMEOUT_US * US,
        BF2026.min_gap_ns() + BYTE_NS - US
    );
    assert_eq!(
        BETAFLIGHT45_FRAME_TIMEOUT_US * US,
        BF45.min_gap_ns() + FRAME_WIRE_NS - US
    );
    assert_eq!(
        ARDUPILOT_FRAME_GAP_US * US,
        ARDUPILOT.min_gap_ns() + BYTE_NS
    );
}

#[test]
fn back_to_back_frames_with_the_gap_each_needs_are_all_taken() {
    let frames = test_frames(6);
    for r in SbusReceiver::ALL {
        let gap = r.min_gap_ns();
        let taken = stream(r, &frames, gap, None);
        let got: Vec<_> = taken.iter().map(|t| t.frame).collect();
        assert_eq!(got, frames, "{r:?}");
        let late = if r == EDGETX { BYTE_NS } else { 0 };
        let at: Vec<_> = taken.iter().map(|t| t.at_ns).collect();
        let want: Vec<_> = last_byte_ends(6, gap).iter().map(|e| e + late).collect();
        assert_eq!(at, want, "{r:?}");
    }
}

#[test]
fn a_gap_one_microsecond_short_loses_what_each_rule_says() {
    let frames = test_frames(6);
    let taken = |r: SbusReceiver| -> Vec<[u8; FRAME_LEN]> {
        stream(r, &frames, r.min_gap_ns() - US, None)
            .iter()
            .map(|t| t.frame)
            .collect()
    };
    // No idle between frames: 150 bytes at the one idle, none taken.
    assert_eq!(taken(EDGETX), Vec::<[u8; FRAME_LEN]>::new());
    // Never a long enough gap again: bytes after the first frame ignored.
    assert_eq!(taken(BF2026), frames[..1]);
    assert_eq!(taken(ARDUPILOT), frames[..1]);
    // Each second header is exactly 3500 us after the one before: its
    // frame is ignored, and the next header is 7000 us on.
    assert_eq!(taken(BF45), [frames[0], frames[2], frames[4]]);
}

#[test]
fn a_gap_inside_a_frame() {
    let frames = test_frames(3);
    // (receiver, idle after byte 10 of frame 1, taken)
    let cases = [
        (EDGETX, 119 * US, true),
        (EDGETX, 120 * US, false),
        (BF2026, 480 * US, true),
        (BF2026, 481 * US, false),
        // The last byte 3500 us after the header, then 3501.
        (BF45, 620 * US, true),
        (BF45, 621 * US, false),
        (ARDUPILOT, 1_879 * US, true),
        (ARDUPILOT, 1_880 * US, false),
    ];
    for (r, inner, kept) in cases {
        let taken: Vec<_> = stream(r, &frames, r.min_gap_ns(), Some((1, 10, inner)))
            .iter()
            .map(|t| t.frame)
            .collect();
        let want = if kept {
            frames.clone()
        } else {
            vec![frames[0], frames[2]]
        };
        assert_eq!(taken, want, "{r:?}, {inner} ns inside");
    }
}

#[test]
fn edgetx_takes_a_frame_after_one_idle_character() {
    let f = test_frames(1)[0];
    let mut framer = Framer::new(EDGETX);
    for (b, end) in on_wire(&f, 0) {
        assert_eq!(framer.push(b, end), None);
    }
    assert_eq!(framer.idle(FRAME_WIRE_NS + BYTE_NS - 1), None);
    assert_eq!(
        framer.idle(FRAME_WIRE_NS + BYTE_NS),
        Some(Taken {
            at_ns: FRAME_WIRE_NS + BYTE_NS,
            frame: f
        })
    );
    // One idle interrupt per idle line.
    assert_eq!(framer.idle(FRAME_WIRE_NS + 10 * BYTE_NS), None);
    // 24 or 26 bytes at the idle: cleared.
    for n in [24, 26] {
        let mut framer = Framer::new(EDGETX);
        for i in 0..n {
            framer.push(f[i % FRAME_LEN], (i as u64 + 1) * BYTE_NS);
        }
        assert_eq!(framer.idle(u64::MAX / 2), None, "{n} bytes");
    }
}

#[test]
fn betaflight_and_ardupilot_hunt_for_the_header() {
    let f = test_frames(1)[0];
    for r in [BF2026, BF45, ARDUPILOT] {
        let mut framer = Framer::new(r);
        // Junk right before the header, as after a byte lost on the line.
        for (i, b) in [0x00u8, 0x55, 0xAA].into_iter().enumerate() {
            assert_eq!(framer.push(b, (i as u64 + 1) * BYTE_NS), None);
        }
        let start = 3 * BYTE_NS;
        let taken: Vec<_> = on_wire(&f, start)
            .into_iter()
            .filter_map(|(b, e)| framer.push(b, e))
            .collect();
        // ArduPilot wants its gap before the header too.
        let want = if r == ARDUPILOT {
            vec![]
        } else {
            vec![Taken {
                at_ns: start + FRAME_WIRE_NS,
                frame: f,
            }]
        };
        assert_eq!(taken, want, "{r:?}");
    }
}

proptest! {
    #[test]
    fn frames_sent_with_at_least_the_gap_are_read_exactly(
        values in proptest::array::uniform16(1_000u64..=2_000),
        r in proptest::sample::select(SbusReceiver::ALL.to_vec()),
        extra_ns in 0u64..5_000_000,
    ) {
        let want = us(values);
        let f = encode_ns(r, &want, Flags::default());
        let mut framer = Framer::new(r);
        let mut start = 10_000 * US;
        let mut read = 0;
        for _ in 0..3 {
            let mut got: Vec<Taken> = on_wire(&f, start)
                .into_iter()
                .filter_map(|(b, e)| framer.push(b, e))
                .collect();
            start += FRAME_WIRE_NS + r.min_gap_ns() + extra_ns;
            got.extend(framer.idle(start));
            for t in got {
                let reading = used(r.verdict(&t.frame));
                for (g, w) in reading.channels_ns.iter().zip(want) {
                    prop_assert!(dist(*g, w) <= whole_us_tolerance_ns(r));
                }
                read += 1;
            }
        }
        prop_assert_eq!(read, 3, "{:?}", r);
    }
}
