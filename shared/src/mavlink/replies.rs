//! Payloads ppm sends back to a groundstation: RC_CHANNELS, and the
//! answers to its requests (PROTOCOL_VERSION, COMMAND_ACK). Payload
//! encoders only, as [`telemetry`](super::telemetry)'s: framing and signing
//! are [`frame`](super::frame)'s and [`Signing`](super::Signing)'s.

/// RC_CHANNELS' payload: `values_us` (at most 18 channels; those past them
/// UINT16_MAX, "unused"), the count, RSSI 255 (unknown), at `time_boot_ms`.
/// No values, a count of 0: no channels are on the line.
pub fn rc_channels_payload(time_boot_ms: u32, values_us: &[u16]) -> [u8; 42] {
    let mut p = [0u8; 42];
    p[..4].copy_from_slice(&time_boot_ms.to_le_bytes());
    for i in 0..18 {
        let v = values_us.get(i).copied().unwrap_or(u16::MAX);
        p[4 + 2 * i..6 + 2 * i].copy_from_slice(&v.to_le_bytes());
    }
    p[40] = values_us.len().min(18) as u8;
    p[41] = u8::MAX;
    p
}

/// PROTOCOL_VERSION's payload: MAVLink 2 (version 200), taking 1 and 2
/// (min 100, max 200), no hashes (zeros).
pub fn protocol_version_payload() -> [u8; 22] {
    let mut p = [0u8; 22];
    p[..2].copy_from_slice(&200u16.to_le_bytes());
    p[2..4].copy_from_slice(&100u16.to_le_bytes());
    p[4..6].copy_from_slice(&200u16.to_le_bytes());
    p
}

/// COMMAND_ACK's payload: `command`'s `result` (a MAV_RESULT), for the
/// sender (system, component) `to`.
pub fn command_ack_payload(command: u16, result: u8, to: (u8, u8)) -> [u8; 10] {
    let c = command.to_le_bytes();
    [c[0], c[1], result, 0, 0, 0, 0, 0, to.0, to.1]
}
