//! Reading what a flight controller sends back on its TX line: a streaming
//! parser of any bytes that resynchronises after junk, a bad length or a bad
//! CRC, counts every frame it drops by reason, and decodes the telemetry
//! frames Betaflight, iNav and ArduPilot send.
//!
//! Field layouts and scalings (big-endian; read from Betaflight
//! `src/main/telemetry/crsf.c` and ArduPilot
//! `libraries/AP_RCTelemetry/AP_CRSF_Telem.cpp`, which write them):
//!
//! | type | payload | written by |
//! | --- | --- | --- |
//! | 0x02 GPS | lat, lon i32 deg x 1e7; ground speed u16 km/h x 10; heading u16 deg x 100; altitude u16 m + 1000; satellites u8 | `crsfFrameGps`, `calc_gps` |
//! | 0x07 vario | vertical speed i16 cm/s | `crsfFrameVarioSensor` |
//! | 0x08 battery | voltage u16 V x 10; current u16 A x 10; used capacity u24 mAh; remaining u8 % | `crsfFrameBatterySensor`, `calc_battery` |
//! | 0x09 barometric altitude | altitude u16 packed (below); vertical speed i8 packed | `crsfFrameAltitude` |
//! | 0x14 link statistics | [`LinkStatistics`] | receivers |
//! | 0x1E attitude | pitch, roll, yaw i16 rad x 10 000 | `crsfFrameAttitude`, `calc_attitude` |
//! | 0x21 flight mode | text, NUL-terminated | `crsfFrameFlightMode`, `calc_flight_mode` |
//!
//! Device ping (0x28) and device information (0x29) are counted and not
//! decoded; a transmitter module's timing correction (0x3A) is counted as
//! `other` and kept for [`TelemetryReader::take_timing`]; other types are counted as `other`. A payload longer than its
//! layout is read (the specification lets frames grow); a shorter one is
//! counted as `bad_payload`.
//!
//! The reader keeps one frame's bytes in a fixed buffer and allocates
//! nothing: every byte goes into a good frame, is dropped as the first byte
//! of a bad one (`bad_length`, `bad_crc`, `truncated`), is skipped while
//! hunting for a frame's first byte (`junk_bytes`), or waits in the buffer.

use super::link::LinkStatistics;
use super::{
    crc8, ADDRESS_FLIGHT_CONTROLLER, ADDRESS_RADIO_TRANSMITTER, ADDRESS_RECEIVER,
    ADDRESS_TRANSMITTER, MAX_FRAME_LEN, MAX_LEN_FIELD, MIN_LEN_FIELD, TYPE_ATTITUDE,
    TYPE_BARO_ALTITUDE, TYPE_BATTERY, TYPE_DEVICE_INFO, TYPE_DEVICE_PING, TYPE_FLIGHT_MODE,
    TYPE_GPS, TYPE_LINK_STATISTICS, TYPE_VARIO,
};

/// The bytes a frame may start with: the addresses of the devices on a CRSF
/// bus (a flight controller starts all of its frames with 0xC8).
pub const FRAME_STARTS: [u8; 4] = [
    ADDRESS_FLIGHT_CONTROLLER,
    ADDRESS_RADIO_TRANSMITTER,
    ADDRESS_RECEIVER,
    ADDRESS_TRANSMITTER,
];

/// The longest payload: [`MAX_FRAME_LEN`] less address, length, type and
/// CRC.
pub const MAX_PAYLOAD_LEN: usize = MAX_FRAME_LEN - 4;

/// Battery sensor (0x08).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Battery {
    /// Voltage, 0.1 V (Betaflight: the pack's, or the average cell's with
    /// `report_cell_voltage`).
    pub voltage_dv: u16,
    /// Current, 0.1 A.
    pub current_da: u16,
    /// Capacity used, mAh (24 bits).
    pub used_mah: u32,
    /// Capacity remaining, %.
    pub remaining_pct: u8,
}

impl Battery {
    /// Voltage, V.
    pub fn voltage_v(&self) -> f64 {
        f64::from(self.voltage_dv) / 10.0
    }

    /// Current, A.
    pub fn current_a(&self) -> f64 {
        f64::from(self.current_da) / 10.0
    }
}

/// GPS (0x02).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Gps {
    /// Latitude, degrees x 10^7.
    pub latitude_e7: i32,
    /// Longitude, degrees x 10^7.
    pub longitude_e7: i32,
    /// Ground speed, km/h x 10 (Betaflight writes cm/s x 36 / 100; ArduPilot
    /// writes m/s x 100000 / 3600, which this field reads 0.77 times as fast).
    pub groundspeed_kmh10: u16,
    /// Course over ground, degrees x 100.
    pub heading_cdeg: u16,
    /// Altitude, m (the field is m + 1000; Betaflight clamps the field to
    /// 0..=5000, ArduPilot the altitude to 0..=5000 m).
    pub altitude_m: i32,
    /// Satellites in use.
    pub satellites: u8,
}

impl Gps {
    /// Latitude, degrees.
    pub fn latitude_deg(&self) -> f64 {
        f64::from(self.latitude_e7) / 1e7
    }

    /// Longitude, degrees.
    pub fn longitude_deg(&self) -> f64 {
        f64::from(self.longitude_e7) / 1e7
    }
}

/// Attitude (0x1E), radians x 10 000, each within ±pi (Betaflight wraps
/// decidegrees to ±180°; ArduPilot wraps and clamps to ±31415).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Attitude {
    /// Pitch.
    pub pitch_e4: i16,
    /// Roll.
    pub roll_e4: i16,
    /// Yaw.
    pub yaw_e4: i16,
}

impl Attitude {
    /// Pitch, roll and yaw, radians.
    pub fn radians(&self) -> [f64; 3] {
        [self.pitch_e4, self.roll_e4, self.yaw_e4].map(|v| f64::from(v) / 10_000.0)
    }
}

/// Flight mode (0x21): the text before the first NUL (all of the payload if
/// it has none).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FlightMode {
    text: [u8; MAX_PAYLOAD_LEN],
    len: u8,
}

impl FlightMode {
    /// The text's bytes.
    pub fn as_bytes(&self) -> &[u8] {
        &self.text[..usize::from(self.len)]
    }

    /// The text, when it is UTF-8.
    pub fn as_str(&self) -> Option<&str> {
        std::str::from_utf8(self.as_bytes()).ok()
    }
}

/// Barometric altitude (0x09), as Betaflight packs it
/// (`calcAltitudePacked`, `calcVerticalSpeedPacked`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct BaroAltitude {
    /// The altitude field: top bit clear, decimetres + 10 000; set, metres
    /// in the low 15 bits.
    pub altitude_packed: u16,
    /// The vertical speed, packed logarithmically
    /// ([`BaroAltitude::vertical_speed_cms`]).
    pub vertical_speed_packed: i8,
}

impl BaroAltitude {
    /// The altitude, dm: `packed - 10000` when the top bit is clear, the low
    /// 15 bits x 10 when it is set.
    pub fn altitude_dm(&self) -> i32 {
        let v = i32::from(self.altitude_packed);
        if v & 0x8000 == 0 {
            v - 10_000
        } else {
            (v & 0x7FFF) * 10
        }
    }

    /// The vertical speed, cm/s, unpacked as Betaflight's comment says:
    /// `(exp(|v| x 0.026) - 1) x 100`, signed, rounded.
    pub fn vertical_speed_cms(&self) -> i32 {
        let v = f64::from(self.vertical_speed_packed);
        let magnitude = ((v.abs() * 0.026).exp() - 1.0) * 100.0;
        (magnitude.round() as i32) * if v < 0.0 { -1 } else { 1 }
    }
}

/// A decoded telemetry frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Telemetry {
    /// 0x08.
    Battery(Battery),
    /// 0x02.
    Gps(Gps),
    /// 0x1E.
    Attitude(Attitude),
    /// 0x21.
    FlightMode(FlightMode),
    /// 0x07: vertical speed, cm/s.
    Vario {
        /// Vertical speed, cm/s, up positive.
        vertical_speed_cms: i16,
    },
    /// 0x09.
    BaroAltitude(BaroAltitude),
    /// 0x14.
    LinkStatistics(LinkStatistics),
}

/// The kinds of telemetry decoded ([`Telemetry::kind`]).
pub const KINDS: usize = 7;

/// The names of the kinds, in [`Telemetry::kind`]'s order (the status
/// reply's keys).
pub const KIND_NAMES: [&str; KINDS] = [
    "battery",
    "gps",
    "attitude",
    "flight_mode",
    "vario",
    "baro_altitude",
    "link_statistics",
];

impl Telemetry {
    /// Its kind: an index into [`KIND_NAMES`].
    pub fn kind(&self) -> usize {
        match self {
            Telemetry::Battery(_) => 0,
            Telemetry::Gps(_) => 1,
            Telemetry::Attitude(_) => 2,
            Telemetry::FlightMode(_) => 3,
            Telemetry::Vario { .. } => 4,
            Telemetry::BaroAltitude(_) => 5,
            Telemetry::LinkStatistics(_) => 6,
        }
    }
}

/// What one good frame (address to CRC, as [`TelemetryReader::feed`] hands
/// it on) decodes to, if it is of a type decoded.
pub fn decode_frame(frame: &[u8]) -> Option<Telemetry> {
    let mut reader = TelemetryReader::new();
    let mut out = None;
    reader.feed(frame, |_, t| out = Some(t));
    out
}

/// What the reader has seen, by kind; every count only grows.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct TelemetryCounts {
    /// Frames whose CRC held, of every type.
    pub frames: u64,
    /// Bytes in those frames.
    pub frame_bytes: u64,
    /// Battery frames decoded.
    pub battery: u64,
    /// GPS frames decoded.
    pub gps: u64,
    /// Attitude frames decoded.
    pub attitude: u64,
    /// Flight mode frames decoded.
    pub flight_mode: u64,
    /// Vario frames decoded.
    pub vario: u64,
    /// Barometric altitude frames decoded.
    pub baro_altitude: u64,
    /// Link statistics frames decoded.
    pub link_statistics: u64,
    /// Device ping and device information frames (not decoded).
    pub device: u64,
    /// Frames of other types (not decoded).
    pub other: u64,
    /// Frames of a decoded type whose payload was too short (not decoded).
    pub bad_payload: u64,
    /// Frames dropped for a length field outside 2..=62.
    pub bad_length: u64,
    /// Frames dropped for a CRC that did not hold.
    pub bad_crc: u64,
    /// Partial frames dropped at a gap in the line ([`TelemetryReader::gap`]).
    pub truncated: u64,
    /// Bytes skipped while looking for a frame's first byte.
    pub junk_bytes: u64,
}

impl TelemetryCounts {
    /// How many counts there are.
    pub const LEN: usize = 16;

    /// Their names, in [`TelemetryCounts::to_array`]'s order.
    pub const NAMES: [&'static str; TelemetryCounts::LEN] = [
        "frames",
        "frame_bytes",
        "battery",
        "gps",
        "attitude",
        "flight_mode",
        "vario",
        "baro_altitude",
        "link_statistics",
        "device",
        "other",
        "bad_payload",
        "bad_length",
        "bad_crc",
        "truncated",
        "junk_bytes",
    ];

    /// The counts, in [`TelemetryCounts::NAMES`]' order.
    pub fn to_array(&self) -> [u64; TelemetryCounts::LEN] {
        [
            self.frames,
            self.frame_bytes,
            self.battery,
            self.gps,
            self.attitude,
            self.flight_mode,
            self.vario,
            self.baro_altitude,
            self.link_statistics,
            self.device,
            self.other,
            self.bad_payload,
            self.bad_length,
            self.bad_crc,
            self.truncated,
            self.junk_bytes,
        ]
    }

    /// The counts of [`TelemetryCounts::to_array`]'s `a`.
    pub fn from_array(a: [u64; TelemetryCounts::LEN]) -> TelemetryCounts {
        let [frames, frame_bytes, battery, gps, attitude, flight_mode, vario, baro_altitude, link_statistics, device, other, bad_payload, bad_length, bad_crc, truncated, junk_bytes] =
            a;
        TelemetryCounts {
            frames,
            frame_bytes,
            battery,
            gps,
            attitude,
            flight_mode,
            vario,
            baro_altitude,
            link_statistics,
            device,
            other,
            bad_payload,
            bad_length,
            bad_crc,
            truncated,
            junk_bytes,
        }
    }

    /// Frames dropped, of every reason (`bad_payload` frames are counted
    /// in `frames` too).
    pub fn dropped(&self) -> u64 {
        self.bad_length + self.bad_crc + self.truncated
    }
}

/// A streaming reader of telemetry frames; see the [module](self).
#[derive(Debug, Clone)]
pub struct TelemetryReader {
    buf: [u8; MAX_FRAME_LEN],
    /// Bytes buffered: a frame in progress.
    n: usize,
    counts: TelemetryCounts,
    /// The newest timing correction a transmitter module sent, not yet
    /// taken ([`TelemetryReader::take_timing`]).
    timing: Option<super::module::Correction>,
}

impl Default for TelemetryReader {
    fn default() -> Self {
        Self::new()
    }
}

impl TelemetryReader {
    /// A reader that has seen nothing.
    pub fn new() -> TelemetryReader {
        TelemetryReader {
            buf: [0; MAX_FRAME_LEN],
            n: 0,
            counts: TelemetryCounts::default(),
            timing: None,
        }
    }

    /// The newest timing correction (0x3A, sub-type 0x10) a transmitter
    /// module sent since the last call, if any. Such frames are counted
    /// as `other`; they carry no telemetry.
    pub fn take_timing(&mut self) -> Option<super::module::Correction> {
        self.timing.take()
    }

    /// What it has seen so far.
    pub fn counts(&self) -> &TelemetryCounts {
        &self.counts
    }

    /// Bytes waiting in the buffer, a frame not yet whole.
    pub fn buffered(&self) -> usize {
        self.n
    }

    /// Reads `bytes`, calling `on` with each good frame's bytes (address to
    /// CRC) and what it decodes to, for the types decoded.
    pub fn feed(&mut self, bytes: &[u8], mut on: impl FnMut(&[u8], Telemetry)) {
        for &b in bytes {
            self.push(b, &mut on);
        }
    }

    /// Reads one byte; see [`TelemetryReader::feed`].
    pub fn push(&mut self, byte: u8, on: &mut impl FnMut(&[u8], Telemetry)) {
        if self.n == 0 && !FRAME_STARTS.contains(&byte) {
            self.counts.junk_bytes += 1;
            return;
        }
        self.buf[self.n] = byte;
        self.n += 1;
        self.scan(on);
    }

    /// The line has been quiet long enough that no frame continues across
    /// the quiet (a read timeout): the buffered partial frame is dropped as
    /// `truncated`, and any whole frame inside it is still read.
    pub fn gap(&mut self, mut on: impl FnMut(&[u8], Telemetry)) {
        while self.n > 0 {
            self.counts.truncated += 1;
            self.skip();
            self.scan(&mut on);
        }
    }

    /// Takes every whole frame at the buffer's start, dropping bad ones,
    /// until what remains is the start of a frame.
    fn scan(&mut self, on: &mut impl FnMut(&[u8], Telemetry)) {
        while self.n >= 2 {
            let len = self.buf[1];
            if !(MIN_LEN_FIELD..=MAX_LEN_FIELD).contains(&len) {
                self.counts.bad_length += 1;
                self.skip();
                continue;
            }
            let full = usize::from(len) + 2;
            if self.n < full {
                return;
            }
            if crc8(&self.buf[2..full - 1]) != self.buf[full - 1] {
                self.counts.bad_crc += 1;
                self.skip();
                continue;
            }
            self.counts.frames += 1;
            self.counts.frame_bytes += full as u64;
            if let Some(t) = self.decode(full) {
                on(&self.buf[..full], t);
            }
            self.buf.copy_within(full..self.n, 0);
            self.n -= full;
        }
    }

    /// Drops the first byte, and the bytes after it up to the next byte a
    /// frame may start with.
    fn skip(&mut self) {
        match self.buf[1..self.n]
            .iter()
            .position(|b| FRAME_STARTS.contains(b))
        {
            Some(i) => {
                self.counts.junk_bytes += i as u64;
                self.buf.copy_within(i + 1..self.n, 0);
                self.n -= i + 1;
            }
            None => {
                self.counts.junk_bytes += (self.n - 1) as u64;
                self.n = 0;
            }
        }
    }

    /// The telemetry in the good frame of `full` bytes at the buffer's
    /// start, counted by type.
    fn decode(&mut self, full: usize) -> Option<Telemetry> {
        let kind = self.buf[2];
        let p = &self.buf[3..full - 1];
        let c = &mut self.counts;
        let (count, need): (&mut u64, usize) = match kind {
            TYPE_BATTERY => (&mut c.battery, 8),
            TYPE_GPS => (&mut c.gps, 15),
            TYPE_ATTITUDE => (&mut c.attitude, 6),
            TYPE_FLIGHT_MODE => (&mut c.flight_mode, 0),
            TYPE_VARIO => (&mut c.vario, 2),
            TYPE_BARO_ALTITUDE => (&mut c.baro_altitude, 3),
            TYPE_LINK_STATISTICS => (&mut c.link_statistics, LinkStatistics::PAYLOAD_LEN),
            TYPE_DEVICE_PING | TYPE_DEVICE_INFO => {
                c.device += 1;
                return None;
            }
            super::module::TYPE_HANDSET => {
                c.other += 1;
                if let Some(t) = super::module::Correction::from_payload(p) {
                    self.timing = Some(t);
                }
                return None;
            }
            _ => {
                c.other += 1;
                return None;
            }
        };
        if p.len() < need {
            c.bad_payload += 1;
            return None;
        }
        *count += 1;
        let u16_at = |i: usize| u16::from_be_bytes([p[i], p[i + 1]]);
        let i16_at = |i: usize| i16::from_be_bytes([p[i], p[i + 1]]);
        let i32_at = |i: usize| i32::from_be_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]);
        Some(match kind {
            TYPE_BATTERY => Telemetry::Battery(Battery {
                voltage_dv: u16_at(0),
                current_da: u16_at(2),
                used_mah: u32::from_be_bytes([0, p[4], p[5], p[6]]),
                remaining_pct: p[7],
            }),
            TYPE_GPS => Telemetry::Gps(Gps {
                latitude_e7: i32_at(0),
                longitude_e7: i32_at(4),
                groundspeed_kmh10: u16_at(8),
                heading_cdeg: u16_at(10),
                altitude_m: i32::from(u16_at(12)) - 1_000,
                satellites: p[14],
            }),
            TYPE_ATTITUDE => Telemetry::Attitude(Attitude {
                pitch_e4: i16_at(0),
                roll_e4: i16_at(2),
                yaw_e4: i16_at(4),
            }),
            TYPE_FLIGHT_MODE => {
                let len = p.iter().position(|&b| b == 0).unwrap_or(p.len());
                let mut text = [0u8; MAX_PAYLOAD_LEN];
                text[..len].copy_from_slice(&p[..len]);
                Telemetry::FlightMode(FlightMode {
                    text,
                    len: len as u8,
                })
            }
            TYPE_VARIO => Telemetry::Vario {
                vertical_speed_cms: i16_at(0),
            },
            TYPE_BARO_ALTITUDE => Telemetry::BaroAltitude(BaroAltitude {
                altitude_packed: u16_at(0),
                vertical_speed_packed: p[2] as i8,
            }),
            _ => {
                let mut payload = [0u8; LinkStatistics::PAYLOAD_LEN];
                payload.copy_from_slice(&p[..LinkStatistics::PAYLOAD_LEN]);
                Telemetry::LinkStatistics(LinkStatistics::from_payload(&payload))
            }
        })
    }
}
