//! The telemetry reader, on frames written out by hand from the field
//! layouts (their CRCs computed apart from this crate), junk, bad frames and
//! random bytes.

use super::super::telemetry::{Attitude, BaroAltitude, Battery, Gps};
use super::super::*;
use proptest::prelude::*;

/// 16.8 V, 12.3 A, 123456 mAh used, 75 % left.
pub(super) const BATTERY: [u8; 12] = [
    0xC8, 0x0A, 0x08, 0x00, 0xA8, 0x00, 0x7B, 0x01, 0xE2, 0x40, 0x4B, 0xBE,
];
/// 47.3977419 N 8.5455938 E, 36.5 km/h, heading 271.15°, 488 m, 12
/// satellites.
pub(super) const GPS: [u8; 19] = [
    0xC8, 0x11, 0x02, 0x1C, 0x40, 0x52, 0x4B, 0x05, 0x17, 0xF4, 0x42, 0x01, 0x6D, 0x69, 0xEB, 0x05,
    0xD0, 0x0C, 0x3F,
];
/// 33.8688197 S 151.2092955 W, still, -20 m, 5 satellites.
pub(super) const GPS_SOUTH_WEST: [u8; 19] = [
    0xC8, 0x11, 0x02, 0xEB, 0xD0, 0x07, 0x3B, 0xA5, 0xDF, 0x4A, 0xE5, 0x00, 0x00, 0x00, 0x00, 0x03,
    0xD4, 0x05, 0x1F,
];
/// Pitch 0.1234 rad, roll -0.5 rad, yaw 3.1415 rad.
pub(super) const ATTITUDE: [u8; 10] = [0xC8, 0x08, 0x1E, 0x04, 0xD2, 0xEC, 0x78, 0x7A, 0xB7, 0x8C];
/// "ACRO*" (Betaflight: acro, ready to arm).
pub(super) const FLIGHT_MODE: [u8; 10] =
    [0xC8, 0x08, 0x21, 0x41, 0x43, 0x52, 0x4F, 0x2A, 0x00, 0x14];
/// -150 cm/s.
pub(super) const VARIO: [u8; 6] = [0xC8, 0x04, 0x07, 0xFF, 0x6A, 0x34];
/// 10123 packed (12.3 m), vertical speed packed -30.
pub(super) const BARO: [u8; 7] = [0xC8, 0x05, 0x09, 0x27, 0x8B, 0xE2, 0x44];
/// 0x8000 | 3000 packed (3000 m), vertical speed packed 40.
pub(super) const BARO_METRES: [u8; 7] = [0xC8, 0x05, 0x09, 0x8B, 0xB8, 0x28, 0x17];
/// A device ping from the receiver to the flight controller.
pub(super) const PING: [u8; 6] = [0xC8, 0x04, 0x28, 0xEC, 0xC8, 0x5A];

fn read_all(bytes: &[u8]) -> (Vec<Telemetry>, TelemetryCounts) {
    let mut r = TelemetryReader::new();
    let mut out = Vec::new();
    r.feed(bytes, |raw, t| {
        assert!(crc_holds(raw));
        out.push(t);
    });
    (out, *r.counts())
}

#[test]
fn decodes_each_frame_exactly() {
    let cases: [(&[u8], Telemetry); 8] = [
        (
            &BATTERY,
            Telemetry::Battery(Battery {
                voltage_dv: 168,
                current_da: 123,
                used_mah: 123_456,
                remaining_pct: 75,
            }),
        ),
        (
            &GPS,
            Telemetry::Gps(Gps {
                latitude_e7: 473_977_419,
                longitude_e7: 85_455_938,
                groundspeed_kmh10: 365,
                heading_cdeg: 27_115,
                altitude_m: 488,
                satellites: 12,
            }),
        ),
        (
            &GPS_SOUTH_WEST,
            Telemetry::Gps(Gps {
                latitude_e7: -338_688_197,
                longitude_e7: -1_512_092_955,
                groundspeed_kmh10: 0,
                heading_cdeg: 0,
                altitude_m: -20,
                satellites: 5,
            }),
        ),
        (
            &ATTITUDE,
            Telemetry::Attitude(Attitude {
                pitch_e4: 1_234,
                roll_e4: -5_000,
                yaw_e4: 31_415,
            }),
        ),
        (
            &VARIO,
            Telemetry::Vario {
                vertical_speed_cms: -150,
            },
        ),
        (
            &BARO,
            Telemetry::BaroAltitude(BaroAltitude {
                altitude_packed: 10_123,
                vertical_speed_packed: -30,
            }),
        ),
        (
            &BARO_METRES,
            Telemetry::BaroAltitude(BaroAltitude {
                altitude_packed: 0x8000 | 3_000,
                vertical_speed_packed: 40,
            }),
        ),
        (
            &LinkStatistics::WIRED.encode(),
            Telemetry::LinkStatistics(LinkStatistics::WIRED),
        ),
    ];
    for (bytes, want) in cases {
        let (got, counts) = read_all(bytes);
        assert_eq!(got, [want], "{bytes:02X?}");
        assert_eq!(counts.frames, 1);
        assert_eq!(counts.frame_bytes, bytes.len() as u64);
    }
    let Telemetry::Battery(b) = read_all(&BATTERY).0[0] else {
        unreachable!()
    };
    assert_eq!((b.voltage_v(), b.current_a()), (16.8, 12.3));
    let Telemetry::Gps(g) = read_all(&GPS).0[0] else {
        unreachable!()
    };
    assert_eq!(
        (g.latitude_deg(), g.longitude_deg()),
        (47.3977419, 8.5455938)
    );
    let Telemetry::Attitude(a) = read_all(&ATTITUDE).0[0] else {
        unreachable!()
    };
    let [pitch, roll, yaw] = a.radians();
    // (Yaw 31415 is pi to four places.)
    assert_eq!((pitch, roll, yaw * 1e4), (0.1234, -0.5, 31_415.0));
    let Telemetry::FlightMode(m) = read_all(&FLIGHT_MODE).0[0] else {
        unreachable!()
    };
    assert_eq!(m.as_str(), Some("ACRO*"));
    let Telemetry::BaroAltitude(b) = read_all(&BARO).0[0] else {
        unreachable!()
    };
    // (exp(30 * 0.026) - 1) * 100 = 118.1 cm/s.
    assert_eq!((b.altitude_dm(), b.vertical_speed_cms()), (123, -118));
    let Telemetry::BaroAltitude(b) = read_all(&BARO_METRES).0[0] else {
        unreachable!()
    };
    assert_eq!((b.altitude_dm(), b.vertical_speed_cms()), (30_000, 183));
}

#[test]
fn counts_by_type() {
    let mut stream = Vec::new();
    for f in [
        &BATTERY[..],
        &GPS,
        &ATTITUDE,
        &FLIGHT_MODE,
        &VARIO,
        &BARO,
        &PING,
    ] {
        stream.extend_from_slice(f);
    }
    // An unknown type (0x7F, ArduPilot's custom telemetry) and a battery
    // frame one byte short.
    let custom = [0xC8, 0x04, 0x7F, 0xF1, 0x00];
    let short_battery = [0xC8, 0x09, 0x08, 0, 0xA8, 0, 0x7B, 0x01, 0xE2, 0x40];
    for f in [&custom[..], &short_battery] {
        let mut f = f.to_vec();
        let n = f.len();
        f.push(crc8(&f[2..n]));
        stream.extend_from_slice(&f);
    }
    let (got, c) = read_all(&stream);
    assert_eq!(got.len(), 6);
    assert_eq!(
        (
            c.battery,
            c.gps,
            c.attitude,
            c.flight_mode,
            c.vario,
            c.baro_altitude
        ),
        (1, 1, 1, 1, 1, 1)
    );
    assert_eq!((c.device, c.other, c.bad_payload), (1, 1, 1));
    assert_eq!(c.frames, 9);
    assert_eq!(c.frame_bytes, stream.len() as u64);
    assert_eq!((c.bad_crc, c.bad_length, c.junk_bytes), (0, 0, 0));
}

#[test]
fn bad_crc_and_bad_length_are_counted_and_skipped() {
    let mut bad_crc = BATTERY;
    bad_crc[5] ^= 0x10;
    let mut stream = bad_crc.to_vec();
    stream.extend_from_slice(&GPS);
    // `len` 0 and 63.
    stream.extend_from_slice(&[0xC8, 0x00, 0xC8, 63]);
    stream.extend_from_slice(&ATTITUDE);
    let (got, c) = read_all(&stream);
    assert_eq!(got.len(), 2);
    assert!(matches!(got[0], Telemetry::Gps(_)));
    assert!(matches!(got[1], Telemetry::Attitude(_)));
    assert_eq!((c.bad_crc, c.bad_length), (1, 2));
    // The bad-CRC frame's other 11 bytes and the byte after each bad length
    // were skipped looking for a start.
    assert_eq!(c.junk_bytes, 13);
}

#[test]
fn resynchronises_after_junk() {
    // Junk with start-like bytes in it, a frame cut short, then good frames.
    let mut stream = vec![0x00, 0xFF, 0xC8, 0x30, 0x55, 0xEE, 0x02, 0x99, 0xEA];
    stream.extend_from_slice(&GPS[..9]);
    for _ in 0..3 {
        stream.extend_from_slice(&BATTERY);
        stream.extend_from_slice(&FLIGHT_MODE);
    }
    let (got, c) = read_all(&stream);
    let batteries = got
        .iter()
        .filter(|t| matches!(t, Telemetry::Battery(_)))
        .count();
    let modes = got
        .iter()
        .filter(|t| matches!(t, Telemetry::FlightMode(_)))
        .count();
    assert_eq!((batteries, modes), (3, 3));
    assert!(c.bad_crc + c.bad_length >= 1);
}

#[test]
fn frames_inside_a_bad_one_are_found() {
    // A start byte whose length (59) swallows the next frames: when its CRC
    // fails, the frames inside it are read.
    let mut stream = vec![0xC8, 59];
    for _ in 0..4 {
        stream.extend_from_slice(&BATTERY);
    }
    stream.extend_from_slice(&ATTITUDE);
    stream.extend_from_slice(&ATTITUDE);
    let (got, c) = read_all(&stream);
    assert_eq!(got.len(), 6, "{c:?}");
    assert_eq!(c.bad_crc, 1);
}

#[test]
fn a_gap_drops_a_partial_frame() {
    let mut r = TelemetryReader::new();
    let mut n = 0;
    r.feed(&GPS[..7], |_, _| n += 1);
    assert_eq!(r.buffered(), 7);
    r.gap(|_, _| n += 1);
    assert_eq!((r.buffered(), r.counts().truncated), (0, 1));
    r.feed(&GPS, |_, _| n += 1);
    assert_eq!(n, 1);
}

#[test]
fn split_anywhere_reads_the_same() {
    let mut stream = Vec::new();
    for f in [&BATTERY[..], &GPS, &ATTITUDE, &FLIGHT_MODE, &VARIO, &BARO] {
        stream.extend_from_slice(f);
    }
    let (whole, counts) = read_all(&stream);
    for cut in 0..stream.len() {
        let mut r = TelemetryReader::new();
        let mut got = Vec::new();
        r.feed(&stream[..cut], |_, t| got.push(t));
        r.feed(&stream[cut..], |_, t| got.push(t));
        assert_eq!(got, whole, "cut at {cut}");
        assert_eq!(*r.counts(), counts);
    }
}

proptest! {
    #[test]
    fn random_bytes_never_panic_nor_yield_a_bad_crc(
        bytes in proptest::collection::vec(any::<u8>(), 0..2_000),
        sprinkle in proptest::collection::vec((0usize..2_000, 0usize..6), 0..20),
        cut in 0usize..2_000,
    ) {
        // Random bytes with good frames sprinkled in.
        let good: [&[u8]; 6] = [&BATTERY, &GPS, &ATTITUDE, &FLIGHT_MODE, &VARIO, &BARO];
        let mut stream = bytes.clone();
        for &(at, which) in &sprinkle {
            let at = at.min(stream.len());
            stream.splice(at..at, good[which].iter().copied());
        }
        let mut r = TelemetryReader::new();
        let mut seen = 0u64;
        let mut check = |raw: &[u8], _t: Telemetry| {
            assert!(crc_holds(raw), "{raw:02X?}");
            assert!(stream.windows(raw.len()).any(|w| w == raw));
            seen += 1;
        };
        let cut = cut.min(stream.len());
        r.feed(&stream[..cut], &mut check);
        r.feed(&stream[cut..], &mut check);
        let c = *r.counts();
        // Every byte is in a good frame, dropped, skipped or waiting.
        prop_assert_eq!(
            stream.len() as u64,
            c.frame_bytes + c.bad_crc + c.bad_length + c.truncated + c.junk_bytes
                + r.buffered() as u64
        );
        let decoded = c.battery + c.gps + c.attitude + c.flight_mode + c.vario
            + c.baro_altitude + c.link_statistics;
        prop_assert_eq!(seen, decoded);
        prop_assert_eq!(c.frames, decoded + c.device + c.other + c.bad_payload);
        r.gap(|raw, _| assert!(crc_holds(raw)));
        prop_assert_eq!(r.buffered(), 0);
    }
}
