//! What ppm tells a groundstation beside its HEARTBEAT and RC_CHANNELS:
//! SERVO_OUTPUT_RAW (36), the values on ppm's line, and STATUSTEXT (253),
//! a line of text such as a read-back state change ("ppm pi: overridden
//! (instructor has control)").
//!
//! Payload encoders only, as [`super::rc_channels_payload`]: framing,
//! numbering and signing are [`super::frame`]'s and [`super::Signing`]'s.
//! CRC_EXTRA values were computed from each message's fields in the common
//! dialect and match pymavlink's; the tests compare whole frames with
//! pymavlink's.

use super::Spec;
use crate::crsf::telemetry::{Attitude, Battery, Gps};

/// `SERVO_OUTPUT_RAW`: what ppm's line carried (ArduPilot sends its outputs
/// in it). servo9..16 are MAVLink 2 extensions.
pub const SERVO_OUTPUT_RAW: Spec = Spec {
    id: 36,
    name: "SERVO_OUTPUT_RAW",
    crc_extra: 222,
    v1_len: 21,
    max_len: 37,
};

/// `STATUSTEXT`: severity and up to [`STATUSTEXT_LEN`] bytes of text; `id`
/// and `chunk_seq` (MAVLink 2 extensions) join the chunks of a longer one.
pub const STATUSTEXT: Spec = Spec {
    id: 253,
    name: "STATUSTEXT",
    crc_extra: 83,
    v1_len: 51,
    max_len: 54,
};

/// The most text bytes one STATUSTEXT carries.
pub const STATUSTEXT_LEN: usize = 50;

/// MAV_SEVERITY_WARNING: something to act on, not yet an error.
pub const MAV_SEVERITY_WARNING: u8 = 4;
/// MAV_SEVERITY_NOTICE: normal but significant.
pub const MAV_SEVERITY_NOTICE: u8 = 5;
/// MAV_SEVERITY_INFO: for information.
pub const MAV_SEVERITY_INFO: u8 = 6;

/// SERVO_OUTPUT_RAW's payload: `values_us` on servo1.. (at most 16; those
/// past them 0, "not used", as ArduPilot sends an output it does not
/// drive), output `port`, at `time_usec` (us since boot, wrapping at 2^32 as
/// ArduPilot's does).
pub fn servo_output_raw_payload(time_usec: u32, port: u8, values_us: &[u16]) -> [u8; 37] {
    let mut p = [0u8; 37];
    p[..4].copy_from_slice(&time_usec.to_le_bytes());
    let servo = |i: usize| values_us.get(i).copied().unwrap_or(0).to_le_bytes();
    for i in 0..8 {
        p[4 + 2 * i..6 + 2 * i].copy_from_slice(&servo(i));
    }
    p[20] = port;
    for i in 8..16 {
        p[21 + 2 * (i - 8)..23 + 2 * (i - 8)].copy_from_slice(&servo(i));
    }
    p
}

/// STATUSTEXT payloads of `text` at `severity` (a MAV_SEVERITY): one, with
/// `id` 0, when it fits in [`STATUSTEXT_LEN`] bytes; otherwise chunks of
/// exactly that many bytes numbered by `chunk_seq` 0, 1, ... under `id`
/// (not 0), the last shorter, so that it holds a NUL (an empty chunk
/// follows one that ends exactly at the limit): the common dialect's
/// reader joins the chunks' bytes up to that NUL. A chunk may so end inside
/// a character of a non-ASCII text; the joined text is whole. A MAVLink 1
/// frame carries no `id` and `chunk_seq`: its reader shows each chunk as a
/// line. At most 256 chunks.
pub fn statustext_payloads(severity: u8, text: &str, id: u16) -> Vec<[u8; 54]> {
    let payload = |chunk: &[u8], id: u16, seq: u8| {
        let mut p = [0u8; 54];
        p[0] = severity;
        p[1..1 + chunk.len()].copy_from_slice(chunk);
        p[51..53].copy_from_slice(&id.to_le_bytes());
        p[53] = seq;
        p
    };
    let bytes = &text.as_bytes()[..text.len().min(256 * STATUSTEXT_LEN - 1)];
    if bytes.len() <= STATUSTEXT_LEN {
        return vec![payload(bytes, 0, 0)];
    }
    let id = id.max(1);
    let mut chunks: Vec<&[u8]> = bytes.chunks(STATUSTEXT_LEN).collect();
    if bytes.len().is_multiple_of(STATUSTEXT_LEN) {
        chunks.push(&[]);
    }
    chunks
        .iter()
        .enumerate()
        .map(|(seq, c)| payload(c, id, seq as u8))
        .collect()
}

/// `SYS_STATUS`: the battery of a vehicle whose flight controller sends
/// CRSF telemetry. The sensor words (MAVLink 2 extensions too) are 0.
pub const SYS_STATUS: Spec = Spec {
    id: 1,
    name: "SYS_STATUS",
    crc_extra: 124,
    v1_len: 31,
    max_len: 43,
};

/// `ATTITUDE`: roll, pitch and yaw, rad (rates unknown: 0).
pub const ATTITUDE: Spec = Spec {
    id: 30,
    name: "ATTITUDE",
    crc_extra: 39,
    v1_len: 28,
    max_len: 28,
};

/// `GPS_RAW_INT`: position, speed, course and satellites. The MAVLink 2
/// extensions (ellipsoid altitude, accuracies, yaw) are 0, "unknown".
pub const GPS_RAW_INT: Spec = Spec {
    id: 24,
    name: "GPS_RAW_INT",
    crc_extra: 24,
    v1_len: 30,
    max_len: 52,
};

/// GPS_FIX_TYPE_NO_FIX.
pub const GPS_FIX_TYPE_NO_FIX: u8 = 1;
/// GPS_FIX_TYPE_3D_FIX.
pub const GPS_FIX_TYPE_3D_FIX: u8 = 3;

/// SYS_STATUS' payload: battery voltage, mV (`u16::MAX`: unknown),
/// current, cA (-1: unknown), remaining, % (-1: unknown); every other field
/// 0.
pub fn sys_status_payload(voltage_mv: u16, current_ca: i16, remaining_pct: i8) -> [u8; 43] {
    let mut p = [0u8; 43];
    p[14..16].copy_from_slice(&voltage_mv.to_le_bytes());
    p[16..18].copy_from_slice(&current_ca.to_le_bytes());
    p[30] = remaining_pct as u8;
    p
}

/// ATTITUDE's payload: `roll`, `pitch`, `yaw` (rad) at `time_boot_ms`,
/// rates 0.
pub fn attitude_payload(time_boot_ms: u32, roll: f32, pitch: f32, yaw: f32) -> [u8; 28] {
    let mut p = [0u8; 28];
    p[..4].copy_from_slice(&time_boot_ms.to_le_bytes());
    for (i, v) in [roll, pitch, yaw].into_iter().enumerate() {
        p[4 + 4 * i..8 + 4 * i].copy_from_slice(&v.to_le_bytes());
    }
    p
}

/// GPS_RAW_INT's fields that ppm knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GpsRawInt {
    /// us since boot.
    pub time_usec: u64,
    /// Latitude, degrees x 10^7.
    pub lat: i32,
    /// Longitude, degrees x 10^7.
    pub lon: i32,
    /// Altitude (MSL), mm.
    pub alt_mm: i32,
    /// Ground speed, cm/s.
    pub vel_cms: u16,
    /// Course over ground, degrees x 100.
    pub cog_cdeg: u16,
    /// GPS_FIX_TYPE.
    pub fix_type: u8,
    /// Satellites visible.
    pub satellites: u8,
}

/// GPS_RAW_INT's payload: `g`, with eph and epv `u16::MAX` (unknown) and
/// the extensions 0.
pub fn gps_raw_int_payload(g: &GpsRawInt) -> [u8; 52] {
    let mut p = [0u8; 52];
    p[..8].copy_from_slice(&g.time_usec.to_le_bytes());
    p[8..12].copy_from_slice(&g.lat.to_le_bytes());
    p[12..16].copy_from_slice(&g.lon.to_le_bytes());
    p[16..20].copy_from_slice(&g.alt_mm.to_le_bytes());
    p[20..22].copy_from_slice(&u16::MAX.to_le_bytes());
    p[22..24].copy_from_slice(&u16::MAX.to_le_bytes());
    p[24..26].copy_from_slice(&g.vel_cms.to_le_bytes());
    p[26..28].copy_from_slice(&g.cog_cdeg.to_le_bytes());
    p[28] = g.fix_type;
    p[29] = g.satellites;
    p
}

/// SYS_STATUS' payload for battery `b`: voltage in mV (0.1 V x 100),
/// current in cA (0.1 A x 10, at most `i16::MAX`), remaining (at most
/// 100 %).
pub fn crsf_sys_status(b: &Battery) -> [u8; 43] {
    let mv = (u32::from(b.voltage_dv) * 100).min(u32::from(u16::MAX - 1)) as u16;
    let ca = (u32::from(b.current_da) * 10).min(i16::MAX as u32) as i16;
    sys_status_payload(mv, ca, b.remaining_pct.min(100) as i8)
}

/// ATTITUDE's payload for `a`, read at `at_ns` (CLOCK_MONOTONIC: its
/// `time_boot_ms`, as RC_CHANNELS').
pub fn crsf_attitude(a: &Attitude, at_ns: u64) -> [u8; 28] {
    let [pitch, roll, yaw] = a.radians().map(|v| v as f32);
    attitude_payload((at_ns / 1_000_000) as u32, roll, pitch, yaw)
}

/// GPS_RAW_INT's payload for `g`, read at `at_ns`. CRSF carries no fix
/// type: a frame with satellites is called a 3D fix, one with none no fix
/// (the satellites are the only sign of one the frame has). Ground speed turns from km/h x 10 to cm/s
/// (x 100 / 36, rounded; at most 65534, as `u16::MAX` is "unknown").
pub fn crsf_gps_raw_int(g: &Gps, at_ns: u64) -> [u8; 52] {
    gps_raw_int_payload(&GpsRawInt {
        time_usec: at_ns / 1_000,
        lat: g.latitude_e7,
        lon: g.longitude_e7,
        alt_mm: g.altitude_m.saturating_mul(1_000),
        vel_cms: ((u32::from(g.groundspeed_kmh10) * 100 + 18) / 36).min(u32::from(u16::MAX - 1))
            as u16,
        cog_cdeg: g.heading_cdeg,
        fix_type: if g.satellites > 0 {
            GPS_FIX_TYPE_3D_FIX
        } else {
            GPS_FIX_TYPE_NO_FIX
        },
        satellites: g.satellites,
    })
}
