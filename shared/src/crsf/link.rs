//! LINK_STATISTICS (0x14): what a receiver tells the flight controller
//! about the radio link, ten bytes to address 0xC8.
//!
//! What the firmware do with it:
//!
//! - Betaflight (`rx/crsf.c`, `handleCrsfLinkStatisticsFrame`): only at
//!   address 0xC8 with `len` 12; RSSI from the active antenna's dBm, scaled
//!   from -130..0 dBm to 0..100 %; link quality (the OSD's LQ) from the
//!   uplink LQ; RF mode and TX power (an index into 0, 10, 25, 100, 500,
//!   1000, 2000, 250, 50 mW) for the OSD; SNR. Without one for 250 ms
//!   (`CRSF_LINK_STATUS_UPDATE_TIMEOUT_US`) it sets RSSI and LQ to 0.
//! - iNav (`rx/crsf.c`, `crsfFrameStatus`): uplink RSSI, LQ, SNR, RF mode,
//!   TX power and antenna into `rxLinkStatistics`; an RSSI percentage from
//!   the dBm only while LQ is above 0.
//! - ArduPilot (`AP_RCProtocol_CRSF.cpp`, `process_link_stats_frame`):
//!   RSSI 255 for under 50 dBm, 0 for over 120, linear between (or LQ x 2.5
//!   with `RC_OPTIONS` "use LQ as RSSI"); LQ as link quality; RF mode picks
//!   the link rate it reports and paces its telemetry by. It counts any good
//!   frame, RC frames included, as the receiver being there
//!   (`is_rx_active`, 150 ms).

use super::{crc8, ADDRESS_FLIGHT_CONTROLLER, TYPE_LINK_STATISTICS};

/// The link statistics payload (field order and units of the TBS
/// specification; Betaflight `crsfLinkStatistics_t`, ArduPilot
/// `LinkStatisticsFrame`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct LinkStatistics {
    /// Uplink RSSI of antenna 1, dBm x -1.
    pub uplink_rssi_ant1: u8,
    /// Uplink RSSI of antenna 2, dBm x -1.
    pub uplink_rssi_ant2: u8,
    /// Uplink link quality (packet success rate), %.
    pub uplink_link_quality: u8,
    /// Uplink signal-to-noise ratio, dB.
    pub uplink_snr: i8,
    /// The diversity antenna in use: 0 antenna 1, 1 antenna 2.
    pub active_antenna: u8,
    /// RF mode: Crossfire 0 = 4 Hz, 1 = 50 Hz, 2 = 150 Hz (ExpressLRS numbers
    /// its own).
    pub rf_mode: u8,
    /// Uplink TX power: an index into 0, 10, 25, 100, 500, 1000, 2000, 250,
    /// 50 mW.
    pub uplink_tx_power: u8,
    /// Downlink RSSI, dBm x -1.
    pub downlink_rssi: u8,
    /// Downlink link quality, %.
    pub downlink_link_quality: u8,
    /// Downlink signal-to-noise ratio, dB.
    pub downlink_snr: i8,
}

impl LinkStatistics {
    /// Payload bytes.
    pub const PAYLOAD_LEN: usize = 10;
    /// Bytes of the frame on the wire.
    pub const FRAME_LEN: usize = Self::PAYLOAD_LEN + 4;

    /// What ppm sends for its wired link, which has no radio to measure: a
    /// perfect link every firmware shows as full.
    ///
    /// - RSSI 0 dBm on both antennas, antenna 1: Betaflight scales it to
    ///   100 %, ArduPilot to 255 (anything under 50 dBm), iNav to 99 %.
    /// - LQ 100 % both ways: the number all three show as link quality.
    /// - SNR 20 dB: the top of Betaflight's range (`CRSF_SNR_MAX`).
    /// - RF mode 2 (Crossfire 150 Hz): ArduPilot reports a 150 Hz link and
    ///   paces its telemetry for it, not for 4 Hz (mode 0).
    /// - TX power index 0 (0 mW): no radio transmits.
    pub const WIRED: LinkStatistics = LinkStatistics {
        uplink_rssi_ant1: 0,
        uplink_rssi_ant2: 0,
        uplink_link_quality: 100,
        uplink_snr: 20,
        active_antenna: 0,
        rf_mode: 2,
        uplink_tx_power: 0,
        downlink_rssi: 0,
        downlink_link_quality: 100,
        downlink_snr: 20,
    };

    /// The payload's ten bytes.
    pub fn payload(&self) -> [u8; Self::PAYLOAD_LEN] {
        [
            self.uplink_rssi_ant1,
            self.uplink_rssi_ant2,
            self.uplink_link_quality,
            self.uplink_snr as u8,
            self.active_antenna,
            self.rf_mode,
            self.uplink_tx_power,
            self.downlink_rssi,
            self.downlink_link_quality,
            self.downlink_snr as u8,
        ]
    }

    /// The statistics in a payload.
    pub fn from_payload(p: &[u8; Self::PAYLOAD_LEN]) -> LinkStatistics {
        LinkStatistics {
            uplink_rssi_ant1: p[0],
            uplink_rssi_ant2: p[1],
            uplink_link_quality: p[2],
            uplink_snr: p[3] as i8,
            active_antenna: p[4],
            rf_mode: p[5],
            uplink_tx_power: p[6],
            downlink_rssi: p[7],
            downlink_link_quality: p[8],
            downlink_snr: p[9] as i8,
        }
    }

    /// The frame to the flight controller: 0xC8, `len` 12, 0x14, the
    /// payload, the CRC.
    pub fn encode(&self) -> [u8; Self::FRAME_LEN] {
        let mut out = [0u8; Self::FRAME_LEN];
        out[0] = ADDRESS_FLIGHT_CONTROLLER;
        out[1] = (Self::PAYLOAD_LEN + 2) as u8;
        out[2] = TYPE_LINK_STATISTICS;
        out[3..3 + Self::PAYLOAD_LEN].copy_from_slice(&self.payload());
        out[Self::FRAME_LEN - 1] = crc8(&out[2..Self::FRAME_LEN - 1]);
        out
    }

    /// Betaflight's RSSI for these statistics, 0..=1023 (`RSSI_MAX_VALUE`):
    /// the active antenna's dBm scaled from -130..0 to 0..1023 in floats
    /// (`scaleRangeCrsfRssi`, `DEFINE_SCALE_FN`), truncated by `setRssi`'s
    /// `uint16_t`.
    pub fn betaflight_rssi(&self) -> u16 {
        let dbm = -f32::from(self.active_rssi());
        let factor = 1023.0f32 / 130.0;
        (dbm * factor + 130.0 * factor) as u16
    }

    /// ArduPilot's RSSI for these statistics, 0..=255
    /// (`process_link_stats_frame` without "LQ as RSSI").
    pub fn ardupilot_rssi(&self) -> u8 {
        let dbm = self.active_rssi();
        match dbm {
            0..50 => 255,
            121.. => 0,
            _ => ((1.0f32 - (f32::from(dbm) - 50.0) / 70.0) * 255.0).round() as u8,
        }
    }

    /// The active antenna's uplink RSSI, dBm x -1.
    fn active_rssi(&self) -> u8 {
        if self.active_antenna == 0 {
            self.uplink_rssi_ant1
        } else {
            self.uplink_rssi_ant2
        }
    }
}
