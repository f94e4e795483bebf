//! The RC frame, each firmware's scaling and framing, link statistics. The
//! telemetry reader's tests are in `telemetry_tests.rs`, the groundstation's view of it in
//! `report_tests.rs`.

use super::framing::{
    byte_end_ns, ARDUPILOT_FRAME_TIMEOUT_US, BETAFLIGHT_FRAME_TIMEOUT_US, INAV_FRAME_TIMEOUT_US,
};
use super::*;
use crate::sbus;
use proptest::prelude::*;

mod report_tests;
mod telemetry_tests;

const US: u64 = 1_000;
const BF: CrsfReceiver = CrsfReceiver::Betaflight;
const INAV: CrsfReceiver = CrsfReceiver::Inav;
const AP: CrsfReceiver = CrsfReceiver::ArduPilot;

/// Feeds `bytes` back to back from `start_ns` into `f`; the frames taken.
fn feed(f: &mut Framer, bytes: &[u8], start_ns: u64) -> Vec<Taken> {
    bytes
        .iter()
        .enumerate()
        .filter_map(|(i, &b)| f.push(b, byte_end_ns(start_ns, i)))
        .collect()
}

fn used(v: Verdict) -> [u64; CHANNELS] {
    match v {
        Verdict::Used { channels_ns } => channels_ns,
        other => panic!("not used: {other:?}"),
    }
}

#[test]
fn crc8_check_value() {
    assert_eq!(crc8(b"123456789"), 0xBC);
    assert_eq!(crc8(&[]), 0);
    // A frame's CRC is over type and payload: Betaflight's bind command
    // (`crsfRxBind`) ends in the CRC 0xE8.
    let bind = [0xC8, 0x07, 0x32, 0xEC, 0xC8, 0x10, 0x01, 0x9E, 0xE8];
    assert!(crc_holds(&bind));
}

#[test]
fn rc_frame_layout() {
    let f = encode_rc(&[992; CHANNELS]);
    assert_eq!(f.len(), 26);
    assert_eq!(&f[..3], &[0xC8, 24, 0x16]);
    assert!(crc_holds(&f));
    // Packed as SBUS packs its channels, from the payload's first byte.
    let raw: [u16; CHANNELS] = core::array::from_fn(|i| (i as u16 * 131 + 7) & RAW_MAX);
    let crsf = encode_rc(&raw);
    let sb = sbus::encode(&raw, sbus::Flags::default());
    assert_eq!(&crsf[3..25], &sb[1..23]);
    assert_eq!(decode_rc(&crsf), Some(raw));
}

#[test]
fn rc_channels_read_betaflights_test_vectors() {
    // Betaflight `src/test/unit/rx_crsf_unittest.cc`, TestCrsfFrameStatus.
    let mut p = [0u8; RC_PAYLOAD_LEN];
    p[..11].copy_from_slice(&[0xFF, 0xFF, 0, 0, 0x58, 0x01, 0, 0xF0, 0x01, 0x60, 0xE2]);
    assert_eq!(
        &rc_channels(&p)[..9],
        &[0x7FF, 0x1F, 0, 172, 0, 992, 0, 1811, 0]
    );
    // TestCapturedData: a receiver's frame (address 0x00) and what
    // Betaflight reads, truncated to whole us by the test.
    let captured = [
        0x00, 0x18, 0x16, 0xBD, 0x08, 0x9F, 0xF4, 0xAE, 0xF7, 0xBD, 0xEF, 0x7D, 0xEF, 0xFB, 0xAD,
        0xFD, 0x45, 0x2B, 0x5A, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x6C,
    ];
    assert!(crc_holds(&captured));
    p.copy_from_slice(&captured[3..25]);
    let raw = rc_channels(&p);
    assert_eq!(&raw[..4], &[189, 993, 978, 983]);
    let us: Vec<u64> = raw[..4].iter().map(|&r| BF.read_ns(r) / US).collect();
    assert_eq!(us, [999, 1501, 1492, 1495]);
    // Betaflight wants address 0xC8 for RC; iNav takes any.
    let taken = |r| {
        let mut f = Framer::new(r);
        feed(&mut f, &captured, 0)
    };
    assert!(matches!(BF.verdict(&taken(BF)[0]), Verdict::Ignored));
    assert_eq!(used(INAV.verdict(&taken(INAV)[0]))[1], 1_501 * US);
    assert!(taken(AP).is_empty());
}

#[test]
fn encode_clamps_instead_of_wrapping() {
    let mut raw = [0u16; CHANNELS];
    raw[3] = 2_048;
    raw[4] = u16::MAX;
    let got = decode_rc(&encode_rc(&raw)).unwrap();
    assert_eq!((got[2], got[3], got[4], got[5]), (0, RAW_MAX, RAW_MAX, 0));
}

#[test]
fn scaling_as_each_firmware_computes_it() {
    let read = |r: CrsfReceiver| -> Vec<u64> {
        [0, 172, 992, 1_811, RAW_MAX]
            .iter()
            .map(|&raw| r.read_ns(raw))
            .collect()
    };
    // 0.62477120195241 * raw + 881: 881, 988.4606, 1500.7730, 2012.4606,
    // 2159.9067 us.
    assert_eq!(
        read(BF),
        [881_000, 988_461, 1_500_773, 2_012_461, 2_159_907]
    );
    // raw * 1024 / 1639 + 881, truncated.
    assert_eq!(
        read(INAV),
        [881_000, 988_000, 1_500_000, 2_012_000, 2_159_000]
    );
    // raw * 5 / 8 + 880, truncated.
    assert_eq!(
        read(AP),
        [880_000, 987_000, 1_500_000, 2_011_000, 2_159_000]
    );
    // ArduPilot's newer form, (raw - 992) * 5 / 8 + 1500 in u32 cast to u16,
    // reads the same for every raw.
    for raw in 0..=RAW_MAX {
        let newer = (u32::from(raw).wrapping_sub(992).wrapping_mul(5) / 8).wrapping_add(1_500);
        assert_eq!(u64::from(newer as u16) * US, AP.read_ns(raw), "raw {raw}");
    }
    // Only the low 11 bits are a channel.
    assert_eq!(INAV.read_ns(992 | 0x800), 1_500_000);
}

#[test]
fn raw_for_matches_a_search_over_every_raw() {
    let mut targets: Vec<u64> = (800..=2_250).map(|u| u * US).collect();
    for u in (800..=2_250).step_by(7) {
        targets.extend([1, 124, 312, 313, 499, 500, 501, 688, 937, 999].map(|f| u * US + f));
    }
    targets.extend([0, u64::MAX]);
    for r in CrsfReceiver::ALL {
        let (lo, hi) = r.range_ns();
        for &t in &targets {
            let best = (0..=RAW_MAX)
                .map(|raw| r.read_ns(raw).abs_diff(t))
                .min()
                .unwrap();
            let raw = raw_for(r, t);
            assert!(raw <= RAW_MAX);
            assert_eq!(
                r.read_ns(raw).abs_diff(t),
                best,
                "{r:?} at {t} ns: raw {raw}"
            );
            if t % US == 0 && (lo..=hi).contains(&t) {
                assert!(best <= r.whole_us_error_ns(), "{r:?} at {t} ns");
            }
        }
    }
}

#[test]
fn encoded_for_one_firmware_the_others_read_close() {
    // The largest error, ns, of each firmware (Betaflight, iNav, ArduPilot)
    // at whole microseconds 881..=2159, encoded for each and for all.
    let worst = |raw_of: &dyn Fn(u64) -> u16| -> Vec<u64> {
        CrsfReceiver::ALL
            .iter()
            .map(|r| {
                (881..=2_159)
                    .map(|us| r.read_ns(raw_of(us * US)).abs_diff(us * US))
                    .max()
                    .unwrap()
            })
            .collect()
    };
    assert_eq!(worst(&|ns| raw_for(BF, ns)), [312, 1_000, 2_000]);
    assert_eq!(worst(&|ns| raw_for(INAV, ns)), [999, 0, 1_000]);
    assert_eq!(worst(&|ns| raw_for(AP, ns)), [1_499, 1_000, 0]);
    assert_eq!(worst(&raw_for_any), [999, 0, 1_000]);
}

#[test]
fn frames_back_to_back_are_all_taken() {
    let mut stream = Vec::new();
    let mut want = Vec::new();
    for k in 0..20u64 {
        let ns: [u64; CHANNELS] =
            core::array::from_fn(|i| (1_000 + (37 * k + 50 * i as u64) % 1_000) * US);
        want.push(ns);
        stream.extend_from_slice(&encode_ns(AP, &ns));
        if k % 4 == 0 {
            stream.extend_from_slice(&LinkStatistics::WIRED.encode());
        }
    }
    for r in CrsfReceiver::ALL {
        let mut f = Framer::new(r);
        let taken = feed(&mut f, &stream, 5_000_000);
        let rc: Vec<_> = taken
            .iter()
            .filter_map(|t| match r.verdict(t) {
                Verdict::Used { channels_ns } => Some(channels_ns),
                _ => None,
            })
            .collect();
        assert_eq!(rc.len(), want.len(), "{r:?}");
        let links = taken
            .iter()
            .filter(|t| r.verdict(t) == Verdict::LinkStatistics(LinkStatistics::WIRED))
            .count();
        assert_eq!(links, 5, "{r:?}");
        if r == AP {
            assert_eq!(rc, want);
        }
    }
}

#[test]
fn every_firmware_resynchronises_after_junk() {
    // Junk, then frames every 4 ms: each firmware takes every frame from the
    // second on.
    let junk: Vec<u8> = (0..40u8).map(|i| i.wrapping_mul(97) ^ 0x5A).collect();
    let frame = encode_rc(&[992; CHANNELS]);
    for r in CrsfReceiver::ALL {
        let mut f = Framer::new(r);
        let t0 = 1_000_000;
        let mut n = feed(&mut f, &junk, t0).len();
        assert_eq!(n, 0, "{r:?} took junk");
        for k in 1..=10 {
            n += feed(&mut f, &frame, t0 + k * 4_000_000).len();
        }
        assert!(n >= 9, "{r:?}: {n} frames");
    }
}

#[test]
fn a_frame_slower_than_the_timeout_is_lost() {
    let frame = encode_rc(&[992; CHANNELS]);
    for (r, timeout_us) in [
        (BF, BETAFLIGHT_FRAME_TIMEOUT_US),
        (INAV, INAV_FRAME_TIMEOUT_US),
        (AP, ARDUPILOT_FRAME_TIMEOUT_US),
    ] {
        // Bytes spread so the last comes 1 us past the timeout.
        let step = (timeout_us + 1) * US / 25;
        let mut f = Framer::new(r);
        let late: Vec<_> = (0..26)
            .filter_map(|i| f.push(frame[i], 10_000_000 + i as u64 * step))
            .collect();
        assert!(late.is_empty(), "{r:?}");
        let mut f = Framer::new(r);
        let step = (timeout_us - 1) * US / 25;
        let on_time: Vec<_> = (0..26)
            .filter_map(|i| f.push(frame[i], 10_000_000 + i as u64 * step))
            .collect();
        assert_eq!(on_time.len(), 1, "{r:?}");
    }
}

#[test]
fn each_firmware_checks_what_its_code_checks() {
    let good = encode_rc(&[992; CHANNELS]);
    let take = |r: CrsfReceiver, bytes: &[u8]| {
        let mut f = Framer::new(r);
        feed(&mut f, bytes, 0)
    };
    // Another address: Betaflight frames it and ignores it, iNav uses it,
    // ArduPilot's framing drops it.
    let mut to_module = good;
    to_module[0] = ADDRESS_TRANSMITTER;
    assert_eq!(BF.verdict(&take(BF, &to_module)[0]), Verdict::Ignored);
    assert!(matches!(
        INAV.verdict(&take(INAV, &to_module)[0]),
        Verdict::Used { .. }
    ));
    assert!(take(AP, &to_module).is_empty());
    // A bad CRC: nobody.
    let mut bad = good;
    bad[10] ^= 1;
    for r in CrsfReceiver::ALL {
        assert!(take(r, &bad).is_empty(), "{r:?}");
    }
    // `len` 63: Betaflight drops it at the third byte, iNav at the fourth,
    // ArduPilot skips it; the good frame right after is taken by all.
    // (Betaflight, framing from the fourth byte on, needs the line quiet for
    // its 1748 us before it finds the next frame's start.)
    for r in CrsfReceiver::ALL {
        let mut f = Framer::new(r);
        assert!(feed(&mut f, &[0xC8, 63, 0x16, 0x00], 0).is_empty());
        assert_eq!(feed(&mut f, &good, 3_000_000).len(), 1, "{r:?}");
    }
    // iNav compares an RC frame's CRC with the byte after 22 payload bytes:
    // a longer frame whose 26th byte is that CRC is taken there only.
    let mut long = [0u8; 28];
    long[..26].copy_from_slice(&good);
    long[1] = 26;
    // The CRC covers the byte it is compared with: find one that is its own.
    let fixed = (0..=255u8).flat_map(|tail| (0..=255u8).map(move |x| (tail, x)));
    let (tail, x) = fixed
        .into_iter()
        .find(|&(tail, x)| {
            let mut l = long;
            (l[25], l[26]) = (x, tail);
            crc8(&l[2..27]) == x
        })
        .unwrap();
    (long[25], long[26]) = (x, tail);
    long[27] = !crc8(&long[2..27]);
    assert_eq!(take(INAV, &long).len(), 1);
    assert!(take(BF, &long).is_empty());
    assert!(take(AP, &long).is_empty());
}

#[test]
fn link_statistics_frame() {
    let f = LinkStatistics::WIRED.encode();
    assert_eq!(
        f,
        [0xC8, 0x0C, 0x14, 0, 0, 100, 20, 0, 2, 0, 0, 100, 20, 0x98]
    );
    assert_eq!(LinkStatistics::WIRED.betaflight_rssi(), 1023);
    assert_eq!(LinkStatistics::WIRED.ardupilot_rssi(), 255);
    let weak = LinkStatistics {
        uplink_rssi_ant2: 85,
        active_antenna: 1,
        ..LinkStatistics::WIRED
    };
    // -85 dBm: (1 - 35 / 70) * 255 = 127.5, rounded; 45 * 1023 / 130.
    assert_eq!(weak.ardupilot_rssi(), 128);
    assert_eq!(weak.betaflight_rssi(), 354);
    for r in CrsfReceiver::ALL {
        let mut fr = Framer::new(r);
        let taken = feed(&mut fr, &f, 0);
        assert_eq!(
            r.verdict(&taken[0]),
            Verdict::LinkStatistics(LinkStatistics::WIRED)
        );
    }
}

proptest! {
    #[test]
    fn every_frame_ppm_writes_reads_exactly_in_each_firmware(
        us in proptest::array::uniform16(881u64..=2_159),
        frac in proptest::array::uniform16(0u64..1_000),
        enc in proptest::sample::select(CrsfReceiver::ALL.to_vec()),
        start_ns in 0u64..1_000_000_000,
    ) {
        let whole = us.map(|u| u * US);
        let any: [u64; CHANNELS] = core::array::from_fn(|i| whole[i] + frac[i]);
        for want in [whole, any] {
            let frame = encode_ns(enc, &want);
            let raw = decode_rc(&frame).unwrap();
            for r in CrsfReceiver::ALL {
                let mut f = Framer::new(r);
                let taken: Vec<_> = on_wire(&frame, start_ns)
                    .iter()
                    .filter_map(|&(b, t)| f.push(b, t))
                    .collect();
                prop_assert_eq!(taken.len(), 1, "{:?}", r);
                let got = used(r.verdict(&taken[0]));
                for (i, (&g, &w)) in got.iter().zip(&want).enumerate() {
                    prop_assert_eq!(g, r.read_ns(raw[i]));
                    if r == enc {
                        // What raw_for promises: the nearest the firmware
                        // reads, exact at whole us (Betaflight: half a step).
                        let best = (0..=RAW_MAX).map(|x| r.read_ns(x).abs_diff(w)).min().unwrap();
                        prop_assert_eq!(g.abs_diff(w), best);
                        if w % US == 0 {
                            prop_assert!(g.abs_diff(w) <= r.whole_us_error_ns());
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn framers_never_panic_and_take_only_good_crcs(
        bytes in proptest::collection::vec(any::<u8>(), 0..600),
        gaps in proptest::collection::vec(0u64..3_000_000, 0..600),
    ) {
        for r in CrsfReceiver::ALL {
            let mut f = Framer::new(r);
            let mut t = 0u64;
            for (i, &b) in bytes.iter().enumerate() {
                t += 23_810 + gaps.get(i).copied().unwrap_or(0) % 100_000;
                if let Some(taken) = f.push(b, t) {
                    prop_assert!(taken.len >= 4 && taken.len <= MAX_FRAME_LEN);
                    let _ = r.verdict(&taken);
                    if r != INAV {
                        prop_assert!(crc_holds(taken.frame()));
                    }
                }
            }
        }
    }
}
