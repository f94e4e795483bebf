//! CRSF telemetry as the groundstation gets it: the status reply's
//! `telemetry` member ([`TelemetryStatus`], built from ppmd's newest
//! [`TelemetrySample`]). The MAVLink messages that carry the same values
//! are [`crate::mavlink::telemetry`]'s (`crsf_sys_status`, ...).
//!
//! The units are the frames' (see [`super::telemetry`]) turned into SI or
//! the usual display units without rounding: a value shown is the value the
//! flight controller sent.

use super::sample::TelemetrySample;
use super::telemetry::{Telemetry, KINDS};
use super::LinkStatistics;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// A telemetry sample older than this (ppmd publishes one at least every
/// tenth of a second) is `stale`: ppmd stopped, or hangs.
pub const STALE_AFTER_NS: u64 = 1_000_000_000;

/// No good frame for this long and the flight controller is `silent`.
pub const SILENT_AFTER_NS: u64 = 1_000_000_000;

/// Kind indexes ([`Telemetry::kind`]).
pub const BATTERY: usize = 0;
/// GPS.
pub const GPS: usize = 1;
/// Attitude.
pub const ATTITUDE: usize = 2;
/// Flight mode.
pub const FLIGHT_MODE: usize = 3;
/// Vario.
pub const VARIO: usize = 4;
/// Barometric altitude.
pub const BARO_ALTITUDE: usize = 5;
/// Link statistics.
pub const LINK_STATISTICS: usize = 6;

/// The `telemetry` member of a status reply (and the answer to
/// `{"get": "telemetry"}`): what the flight controller sends back on a CRSF
/// output's serial port (see docs/crsf.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TelemetryStatus {
    /// `receiving` (a good frame within the last second), `silent` (none:
    /// is the flight controller's TX wired to the board's RX, and its
    /// telemetry on?), or `stale` (ppmd has published nothing for a
    /// second).
    pub state: String,
    /// The tty read.
    pub port: String,
    /// Age of ppmd's newest telemetry sample, ms.
    pub age_ms: f64,
    /// Good frames (CRC holds) of every type.
    pub frames: u64,
    /// Frames dropped or not decoded, by reason: `bad_crc`, `bad_length`,
    /// `truncated` (cut by a pause in the line), `bad_payload` (too short
    /// for its type).
    pub bad: BTreeMap<String, u64>,
    /// Bytes skipped between frames.
    pub junk_bytes: u64,
    /// Good frames of types not decoded (device ping and information too).
    pub other: u64,
    /// Battery (0x08); `null` until one came.
    pub battery: Option<BatteryStatus>,
    /// Attitude (0x1E).
    pub attitude: Option<AttitudeStatus>,
    /// GPS (0x02).
    pub gps: Option<GpsStatus>,
    /// Flight mode (0x21).
    pub flight_mode: Option<FlightModeStatus>,
    /// Vario (0x07).
    pub vario: Option<VarioStatus>,
    /// Barometric altitude (0x09).
    pub baro_altitude: Option<BaroStatus>,
    /// Link statistics (0x14), as a receiver or module sends them.
    pub link_statistics: Option<LinkStatus>,
}

/// Battery.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BatteryStatus {
    /// Voltage, V.
    pub voltage_v: f64,
    /// Current, A.
    pub current_a: f64,
    /// Capacity used, mAh.
    pub used_mah: u32,
    /// Capacity remaining, %.
    pub remaining_pct: u8,
    /// Age, ms.
    pub age_ms: f64,
}

/// Attitude, radians.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AttitudeStatus {
    /// Roll.
    pub roll_rad: f64,
    /// Pitch.
    pub pitch_rad: f64,
    /// Yaw.
    pub yaw_rad: f64,
    /// Age, ms.
    pub age_ms: f64,
}

/// GPS.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GpsStatus {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude, m.
    pub altitude_m: i32,
    /// Ground speed, km/h.
    pub groundspeed_kmh: f64,
    /// Course over ground, degrees.
    pub heading_deg: f64,
    /// Satellites in use.
    pub satellites: u8,
    /// Age, ms.
    pub age_ms: f64,
}

/// Flight mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FlightModeStatus {
    /// The text, printable ASCII (every other byte shown as `?`: the
    /// firmware send ASCII, and a control byte has no place in a display).
    pub mode: String,
    /// Age, ms.
    pub age_ms: f64,
}

/// Vario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VarioStatus {
    /// Vertical speed, m/s, up positive.
    pub vertical_speed_ms: f64,
    /// Age, ms.
    pub age_ms: f64,
}

/// Barometric altitude.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BaroStatus {
    /// Altitude, m.
    pub altitude_m: f64,
    /// Vertical speed, m/s (unpacked from its logarithmic byte).
    pub vertical_speed_ms: f64,
    /// Age, ms.
    pub age_ms: f64,
}

/// Link statistics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LinkStatus {
    /// Uplink RSSI of the active antenna, dBm.
    pub rssi_dbm: i32,
    /// Uplink link quality, %.
    pub link_quality: u8,
    /// Uplink signal-to-noise ratio, dB.
    pub snr_db: i8,
    /// RF mode.
    pub rf_mode: u8,
    /// Downlink link quality, %.
    pub downlink_link_quality: u8,
    /// Age, ms.
    pub age_ms: f64,
}

/// A flight mode's text as shown (status replies, STATUSTEXT): printable
/// ASCII, every other byte `?` (the firmware send ASCII; a control byte
/// from the port has no place in a display or a log).
pub fn printable(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|&c| {
            if c == b' ' || c.is_ascii_graphic() {
                c as char
            } else {
                '?'
            }
        })
        .collect()
}

/// ms between `then` and `now` (ns), never negative.
fn ms(now_ns: u64, then_ns: u64) -> f64 {
    now_ns.saturating_sub(then_ns) as f64 / 1e6
}

impl TelemetryStatus {
    /// The member for sample `s` of the tty `port`, at `now_ns`
    /// (CLOCK_MONOTONIC); a sample never published (all zeros) is
    /// `stale`.
    pub fn of(s: &TelemetrySample, port: &str, now_ns: u64) -> TelemetryStatus {
        let c = s.counts();
        let newest = (0..KINDS)
            .filter_map(|k| s.newest(k))
            .map(|(at, _)| at)
            .max();
        let state = if s.published_mono_ns == 0
            || now_ns.saturating_sub(s.published_mono_ns) > STALE_AFTER_NS
        {
            "stale"
        } else if newest.is_some_and(|at| now_ns.saturating_sub(at) <= SILENT_AFTER_NS) {
            "receiving"
        } else {
            "silent"
        };
        let mut out = TelemetryStatus {
            state: state.to_owned(),
            port: port.to_owned(),
            age_ms: ms(now_ns, s.published_mono_ns),
            frames: c.frames,
            bad: [
                ("bad_crc", c.bad_crc),
                ("bad_length", c.bad_length),
                ("truncated", c.truncated),
                ("bad_payload", c.bad_payload),
            ]
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v))
            .collect(),
            junk_bytes: c.junk_bytes,
            other: c.other + c.device,
            battery: None,
            attitude: None,
            gps: None,
            flight_mode: None,
            vario: None,
            baro_altitude: None,
            link_statistics: None,
        };
        for k in 0..KINDS {
            let Some((at, t)) = s.newest(k) else {
                continue;
            };
            let age_ms = ms(now_ns, at);
            match t {
                Telemetry::Battery(b) => {
                    out.battery = Some(BatteryStatus {
                        voltage_v: b.voltage_v(),
                        current_a: b.current_a(),
                        used_mah: b.used_mah,
                        remaining_pct: b.remaining_pct,
                        age_ms,
                    })
                }
                Telemetry::Attitude(a) => {
                    let [pitch, roll, yaw] = a.radians();
                    out.attitude = Some(AttitudeStatus {
                        roll_rad: roll,
                        pitch_rad: pitch,
                        yaw_rad: yaw,
                        age_ms,
                    })
                }
                Telemetry::Gps(g) => {
                    out.gps = Some(GpsStatus {
                        lat_deg: g.latitude_deg(),
                        lon_deg: g.longitude_deg(),
                        altitude_m: g.altitude_m,
                        groundspeed_kmh: f64::from(g.groundspeed_kmh10) / 10.0,
                        heading_deg: f64::from(g.heading_cdeg) / 100.0,
                        satellites: g.satellites,
                        age_ms,
                    })
                }
                Telemetry::FlightMode(f) => {
                    out.flight_mode = Some(FlightModeStatus {
                        mode: printable(f.as_bytes()),
                        age_ms,
                    })
                }
                Telemetry::Vario { vertical_speed_cms } => {
                    out.vario = Some(VarioStatus {
                        vertical_speed_ms: f64::from(vertical_speed_cms) / 100.0,
                        age_ms,
                    })
                }
                Telemetry::BaroAltitude(b) => {
                    out.baro_altitude = Some(BaroStatus {
                        altitude_m: f64::from(b.altitude_dm()) / 10.0,
                        vertical_speed_ms: f64::from(b.vertical_speed_cms()) / 100.0,
                        age_ms,
                    })
                }
                Telemetry::LinkStatistics(l) => out.link_statistics = Some(link_status(&l, age_ms)),
            }
        }
        out
    }

    /// The member's text alone, keys sorted as in status replies, for the
    /// answer to `{"get": "telemetry"}`: `{"name": ..., "telemetry": ...}`.
    pub fn answer_json(&self, name: &str) -> String {
        serde_json::json!({ "name": name, "telemetry": self }).to_string()
    }
}

fn link_status(l: &LinkStatistics, age_ms: f64) -> LinkStatus {
    let rssi = if l.active_antenna == 0 {
        l.uplink_rssi_ant1
    } else {
        l.uplink_rssi_ant2
    };
    LinkStatus {
        rssi_dbm: -i32::from(rssi),
        link_quality: l.uplink_link_quality,
        snr_db: l.uplink_snr,
        rf_mode: l.rf_mode,
        downlink_link_quality: l.downlink_link_quality,
        age_ms,
    }
}
