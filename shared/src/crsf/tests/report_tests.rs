//! Telemetry as the groundstation gets it: the status member's values from
//! the frames of `telemetry_tests.rs`, the sample's round trip, and the
//! MAVLink messages byte for byte as pymavlink 2.4.50 packs them
//! (`MAVLink_sys_status_message(...).pack(mav)`, system 1, component 1,
//! sequence 0, MAVLink 2).

use super::super::report::{self, TelemetryStatus};
use super::super::sample::TelemetrySample;
use super::super::telemetry::{decode_frame, KINDS, KIND_NAMES};
use super::super::*;
use super::telemetry_tests::{ATTITUDE, BARO, BATTERY, FLIGHT_MODE, GPS, PING, VARIO};
use crate::mavlink;

/// SYS_STATUS: 16 800 mV, 1230 cA, 75 %.
const V2_SYS_STATUS: [u8; 43] = [
    0xFD, 0x1F, 0x00, 0x00, 0x00, 0x01, 0x01, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xA0, 0x41, 0xCE, 0x04, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x4B, 0xA5, 0xAB,
];
/// ATTITUDE at 5123 ms: roll -0.5, pitch 0.1234, yaw 3.1415 rad.
const V2_ATTITUDE: [u8; 28] = [
    0xFD, 0x10, 0x00, 0x00, 0x00, 0x01, 0x01, 0x1E, 0x00, 0x00, 0x03, 0x14, 0x00, 0x00, 0x00, 0x00,
    0x00, 0xBF, 0x24, 0xB9, 0xFC, 0x3D, 0x56, 0x0E, 0x49, 0x40, 0x00, 0xEA,
];
/// GPS_RAW_INT at 5 123 000 us: 473977419, 85455938, 488 000 mm, eph and
/// epv 65535, 1014 cm/s, 27115 cdeg, 3D fix, 12 satellites.
const V2_GPS_RAW_INT: [u8; 42] = [
    0xFD, 0x1E, 0x00, 0x00, 0x00, 0x01, 0x01, 0x18, 0x00, 0x00, 0xB8, 0x2B, 0x4E, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x4B, 0x52, 0x40, 0x1C, 0x42, 0xF4, 0x17, 0x05, 0x40, 0x72, 0x07, 0x00, 0xFF, 0xFF,
    0xFF, 0xFF, 0xF6, 0x03, 0xEB, 0x69, 0x03, 0x0C, 0x8E, 0x22,
];

/// A sample holding `frames`, each read at `at_ns`, published at
/// `published_ns`, counted as a reader counts them.
fn sample(frames: &[&[u8]], at_ns: u64, published_ns: u64) -> TelemetrySample {
    let mut s = TelemetrySample::default();
    let mut r = TelemetryReader::new();
    for f in frames {
        r.feed(f, |raw, t| s.take(raw, &t, at_ns));
    }
    s.counts = r.counts().to_array();
    s.published_mono_ns = published_ns;
    s
}

#[test]
fn counts_round_trip_in_their_named_order() {
    let mut a = [0u64; TelemetryCounts::LEN];
    for (i, v) in a.iter_mut().enumerate() {
        *v = 1_000 + i as u64;
    }
    let c = TelemetryCounts::from_array(a);
    assert_eq!(c.to_array(), a);
    assert_eq!((c.frames, c.junk_bytes, c.bad_crc), (1_000, 1_015, 1_013));
    assert_eq!(TelemetryCounts::NAMES[13], "bad_crc");
    let kinds: Vec<usize> = [
        BATTERY.as_slice(),
        &GPS,
        &ATTITUDE,
        &FLIGHT_MODE,
        &VARIO,
        &BARO,
    ]
    .iter()
    .map(|f| decode_frame(f).expect("decodes").kind())
    .collect();
    assert_eq!(kinds, [0, 1, 2, 3, 4, 5]);
    assert_eq!(KIND_NAMES[report::GPS], "gps");
    assert_eq!(decode_frame(&PING), None, "a ping is not decoded");
}

/// `frame` writes what the flight controller writes: the hand-written
/// frames (their CRCs computed apart from this crate), byte for byte.
#[test]
fn frames_are_built_as_flight_controllers_write_them() {
    for f in [&BATTERY[..], &GPS, &ATTITUDE, &FLIGHT_MODE, &VARIO, &BARO] {
        assert_eq!(frame(f[0], f[2], &f[3..f.len() - 1]), f);
    }
}

#[test]
fn the_sample_keeps_the_newest_frame_of_each_kind() {
    let s = sample(
        &[&BATTERY, &GPS, &ATTITUDE, &FLIGHT_MODE, &VARIO, &BARO],
        7,
        9,
    );
    for k in 0..KINDS - 1 {
        let (at, t) = s.newest(k).expect("kept");
        assert_eq!((at, t.kind()), (7, k));
    }
    assert_eq!(s.newest(report::LINK_STATISTICS), None);
    assert_eq!(s.newest(KINDS), None, "no such kind");
    assert_eq!(s.counts().frames, 6);
    // A shorter frame of a kind replaces a longer one whole.
    let mut s = sample(&[&FLIGHT_MODE], 1, 1);
    let framed = frame(ADDRESS_FLIGHT_CONTROLLER, TYPE_FLIGHT_MODE, b"A\0");
    let t = decode_frame(&framed).expect("a one-letter mode");
    s.take(&framed, &t, 2);
    let Some((2, Telemetry::FlightMode(f))) = s.newest(report::FLIGHT_MODE) else {
        panic!("replaced")
    };
    assert_eq!(f.as_str(), Some("A"));
}

#[test]
fn the_status_member_has_the_values_sent() {
    let s = sample(
        &[
            &BATTERY,
            &GPS,
            &ATTITUDE,
            &FLIGHT_MODE,
            &VARIO,
            &BARO,
            &PING,
            &[0x00, 0x55],
        ],
        1_000_000_000,
        1_050_000_000,
    );
    let st = TelemetryStatus::of(&s, "/dev/ttyAMA0", 1_100_000_000);
    assert_eq!(st.state, "receiving");
    assert_eq!((st.frames, st.junk_bytes, st.other), (7, 2, 1));
    assert_eq!(st.age_ms, 50.0);
    let b = st.battery.as_ref().expect("battery");
    assert_eq!(
        (
            b.voltage_v,
            b.current_a,
            b.used_mah,
            b.remaining_pct,
            b.age_ms
        ),
        (16.8, 12.3, 123_456, 75, 100.0)
    );
    let g = st.gps.as_ref().expect("gps");
    assert_eq!(
        (
            g.lat_deg,
            g.lon_deg,
            g.altitude_m,
            g.groundspeed_kmh,
            g.heading_deg,
            g.satellites
        ),
        (47.3977419, 8.5455938, 488, 36.5, 271.15, 12)
    );
    let a = st.attitude.as_ref().expect("attitude");
    assert_eq!(
        (a.roll_rad, a.pitch_rad, a.yaw_rad),
        (-0.5, 0.1234, 31_415.0 / 10_000.0)
    );
    assert_eq!(
        st.flight_mode.as_ref().map(|f| f.mode.as_str()),
        Some("ACRO*")
    );
    assert_eq!(st.vario.as_ref().map(|v| v.vertical_speed_ms), Some(-1.5));
    let baro = st.baro_altitude.as_ref().expect("baro");
    assert_eq!(baro.altitude_m, 12.3);
    assert!(st.link_statistics.is_none());
    // Its JSON reads back to itself.
    let back: TelemetryStatus = serde_json::from_str(&serde_json::to_string(&st).unwrap()).unwrap();
    assert_eq!(back, st);
    // A second later with nothing new: silent; ppmd gone: stale.
    let later = sample(&[&BATTERY], 1_000_000_000, 2_500_000_000);
    assert_eq!(
        TelemetryStatus::of(&later, "p", 2_500_000_000).state,
        "silent"
    );
    assert_eq!(
        TelemetryStatus::of(&later, "p", 3_600_000_000).state,
        "stale"
    );
    assert_eq!(
        TelemetryStatus::of(&TelemetrySample::default(), "p", 5).state,
        "stale"
    );
}

#[test]
fn bad_frames_are_counted_by_reason() {
    let mut bad_crc = BATTERY;
    bad_crc[5] ^= 1;
    let s = sample(&[&bad_crc, &[0xC8, 0x50], &ATTITUDE], 1, 1);
    let st = TelemetryStatus::of(&s, "p", 1);
    assert_eq!(st.frames, 1);
    assert_eq!(st.bad["bad_crc"], 1);
    assert_eq!(st.bad["bad_length"], 1);
    assert!(st.battery.is_none() && st.attitude.is_some());
}

#[test]
fn mavlink_messages_are_pymavlinks() {
    let decoded = |f: &[u8]| decode_frame(f).expect("decodes");
    let Telemetry::Battery(b) = decoded(&BATTERY) else {
        panic!()
    };
    let Telemetry::Attitude(a) = decoded(&ATTITUDE) else {
        panic!()
    };
    let Telemetry::Gps(g) = decoded(&GPS) else {
        panic!()
    };
    let at_ns = 5_123_000_999;
    let frame = |spec, payload: &[u8]| mavlink::frame(2, (0, 1, 1), spec, payload);
    assert_eq!(
        frame(
            &mavlink::SYS_STATUS,
            &crate::mavlink::telemetry::crsf_sys_status(&b)
        ),
        V2_SYS_STATUS
    );
    assert_eq!(
        frame(
            &mavlink::ATTITUDE,
            &crate::mavlink::telemetry::crsf_attitude(&a, at_ns)
        ),
        V2_ATTITUDE
    );
    assert_eq!(
        frame(
            &mavlink::GPS_RAW_INT,
            &crate::mavlink::telemetry::crsf_gps_raw_int(&g, at_ns)
        ),
        V2_GPS_RAW_INT
    );
    // Every one reads back through ppm's own MAVLink parser's checks.
    for f in [
        frame(
            &mavlink::SYS_STATUS,
            &crate::mavlink::telemetry::crsf_sys_status(&b),
        ),
        frame(
            &mavlink::GPS_RAW_INT,
            &crate::mavlink::telemetry::crsf_gps_raw_int(&g, at_ns),
        ),
    ] {
        assert_eq!(f.len(), usize::from(f[1]) + 12);
    }
}

#[test]
fn mavlink_values_clamp_instead_of_wrapping() {
    let b = telemetry::Battery {
        voltage_dv: u16::MAX,
        current_da: u16::MAX,
        used_mah: 0,
        remaining_pct: 255,
    };
    let p = crate::mavlink::telemetry::crsf_sys_status(&b);
    assert_eq!(u16::from_le_bytes([p[14], p[15]]), u16::MAX - 1);
    assert_eq!(i16::from_le_bytes([p[16], p[17]]), i16::MAX);
    assert_eq!(p[30], 100);
    let g = telemetry::Gps {
        latitude_e7: 0,
        longitude_e7: 0,
        groundspeed_kmh10: u16::MAX,
        heading_cdeg: 0,
        altitude_m: -1_000,
        satellites: 0,
    };
    let p = crate::mavlink::telemetry::crsf_gps_raw_int(&g, 0);
    assert_eq!(
        i32::from_le_bytes(p[16..20].try_into().unwrap()),
        -1_000_000
    );
    assert_eq!(
        u16::from_le_bytes([p[24], p[25]]),
        u16::MAX - 1,
        "6553.5 km/h is more than the field holds"
    );
    assert_eq!(p[28], mavlink::telemetry::GPS_FIX_TYPE_NO_FIX);
}
