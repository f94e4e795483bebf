//! CRSF (Crossfire, also spoken by ExpressLRS): the frame, the RC channels
//! frame a receiver hands a flight controller, the link statistics that make
//! the flight controller show a link, what flight controllers send back, and
//! RC input as Betaflight, iNav and ArduPilot frame and read it, each
//! modelled on its firmware's decoder (the file and function are named on
//! each [`CrsfReceiver`] and each rule's constant).
//!
//! A frame is `address | len | type | payload | crc`: `len` counts type,
//! payload and CRC (2..=62), the CRC is CRC-8 with polynomial 0xD5 over type
//! and payload ([`crc8`]), multi-byte fields are big-endian, except the
//! channels of RC_CHANNELS_PACKED (0x16): 16 values of 11 bits packed least
//! significant bit first (as SBUS packs them), 22 bytes, 26 bytes in all, to
//! the flight controller's address 0xC8. The flight-controller side is a
//! full-duplex UART, 8N1, not inverted, at 420 000 baud ([`BAUD`]).
//!
//! Everything here is fixed-size and allocation-free, so it may run in the
//! real-time loop.
//!
//! - here: the frame constants, [`crc8`], the RC frame ([`encode_rc`],
//!   [`rc_channels`]).
//! - [`receiver`]: how each firmware turns a raw value into microseconds, the
//!   encoder's inverse ([`raw_for`]), and what each does with a frame it took.
//! - [`framing`]: each firmware's byte-stream framing ([`Framer`]).
//! - [`module`]: the handset side, to an ExpressLRS transmitter module: its
//!   timing corrections and its framing.
//! - [`link`]: LINK_STATISTICS (0x14), the frame a receiver sends the flight
//!   controller about the radio link.
//! - [`telemetry`]: a streaming reader of what a flight controller sends back
//!   (battery, GPS, attitude, flight mode, vario, barometric altitude).
//! - [`sample`]: that telemetry as ppmd publishes it for udp-ingress.
//! - [`report`]: that telemetry as the groundstation gets it (the status
//!   reply's `telemetry` member, MAVLink SYS_STATUS, ATTITUDE, GPS_RAW_INT).

pub mod framing;
pub mod link;
pub mod module;
pub mod receiver;
pub mod report;
pub mod sample;
pub mod telemetry;

#[cfg(test)]
mod tests;

pub use framing::{on_wire, Framer, Taken};
pub use link::LinkStatistics;
pub use receiver::{encode_ns, raw_for, raw_for_any, CrsfReceiver, Verdict};
pub use telemetry::{Telemetry, TelemetryCounts, TelemetryReader};

/// The address of a flight controller, which is also the sync byte every
/// frame to or from one starts with.
pub const ADDRESS_FLIGHT_CONTROLLER: u8 = 0xC8;
/// The address of a handset (radio transmitter).
pub const ADDRESS_RADIO_TRANSMITTER: u8 = 0xEA;
/// The address of a CRSF receiver.
pub const ADDRESS_RECEIVER: u8 = 0xEC;
/// The address of a CRSF transmitter module.
pub const ADDRESS_TRANSMITTER: u8 = 0xEE;

/// Frame type: GPS.
pub const TYPE_GPS: u8 = 0x02;
/// Frame type: vertical speed.
pub const TYPE_VARIO: u8 = 0x07;
/// Frame type: battery sensor.
pub const TYPE_BATTERY: u8 = 0x08;
/// Frame type: barometric altitude (and packed vertical speed).
pub const TYPE_BARO_ALTITUDE: u8 = 0x09;
/// Frame type: link statistics.
pub const TYPE_LINK_STATISTICS: u8 = 0x14;
/// Frame type: 16 RC channels of 11 bits.
pub const TYPE_RC_CHANNELS_PACKED: u8 = 0x16;
/// Frame type: attitude.
pub const TYPE_ATTITUDE: u8 = 0x1E;
/// Frame type: flight mode text.
pub const TYPE_FLIGHT_MODE: u8 = 0x21;
/// Frame type: device ping (extended header).
pub const TYPE_DEVICE_PING: u8 = 0x28;
/// Frame type: device information (extended header).
pub const TYPE_DEVICE_INFO: u8 = 0x29;

/// The most bytes a frame has on the wire, address and length included
/// (Betaflight `crsf_protocol.h`, `CRSF_FRAME_SIZE_MAX`; ArduPilot
/// `CRSF_FRAMELEN_MAX`).
pub const MAX_FRAME_LEN: usize = 64;
/// The smallest `len` field: type and CRC.
pub const MIN_LEN_FIELD: u8 = 2;
/// The largest `len` field: [`MAX_FRAME_LEN`] less address and length.
pub const MAX_LEN_FIELD: u8 = (MAX_FRAME_LEN - 2) as u8;

/// Proportional channels in an RC frame.
pub const CHANNELS: usize = 16;
/// Bits per channel.
pub const CHANNEL_BITS: u32 = 11;
/// The highest raw channel value.
pub const RAW_MAX: u16 = (1 << CHANNEL_BITS) - 1;
/// Payload bytes of RC_CHANNELS_PACKED.
pub const RC_PAYLOAD_LEN: usize = 22;
/// Bytes of an RC frame on the wire.
pub const RC_FRAME_LEN: usize = RC_PAYLOAD_LEN + 4;

/// The line rate on the flight controller's side, bits per second: what
/// Betaflight (`crsf_protocol.h`, `CRSF_BAUDRATE`), iNav (`crsf.h`) and
/// ExpressLRS receivers use. The TBS specification says 416 666; ArduPilot
/// runs its UART at that unless `RC_OPTIONS` asks for 420 000, and the 0.8 %
/// between them is well inside what a UART tolerates.
pub const BAUD: u64 = 420_000;
/// Bits on the wire per byte: start, 8 data, stop.
pub const BYTE_BITS: u64 = 10;

/// CRC-8/DVB-S2 (polynomial 0xD5, initial value 0, no reflection, no final
/// xor) of `bytes`: the CRC of every CRSF frame, over its type and payload
/// (Betaflight `common/crc.c`, `crc8_dvb_s2`). Its check value, the CRC of
/// `"123456789"`, is 0xBC.
pub fn crc8(bytes: &[u8]) -> u8 {
    bytes
        .iter()
        .fold(0, |crc, &b| CRC8_TABLE[usize::from(crc ^ b)])
}

/// [`crc8`] a byte at a time.
const CRC8_TABLE: [u8; 256] = {
    let mut table = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        let mut crc = i as u8;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 0x80 != 0 {
                (crc << 1) ^ 0xD5
            } else {
                crc << 1
            };
            bit += 1;
        }
        table[i] = crc;
        i += 1;
    }
    table
};

/// Whether `frame` (address first) is whole and its CRC holds: its `len`
/// field is 2..=62, it is `len + 2` bytes long, and its last byte is the
/// [`crc8`] of the bytes from its type to before it.
pub fn crc_holds(frame: &[u8]) -> bool {
    let Some(&len) = frame.get(1) else {
        return false;
    };
    (MIN_LEN_FIELD..=MAX_LEN_FIELD).contains(&len)
        && frame.len() == usize::from(len) + 2
        && crc8(&frame[2..frame.len() - 1]) == frame[frame.len() - 1]
}

/// A whole frame from `address` of type `kind` with `payload`, its `len`
/// field and CRC filled in: what a device on the bus writes (a flight
/// controller's telemetry, starting 0xC8). Allocates: for tools and tests,
/// not the timing loop (whose frames are [`encode_rc`]'s and
/// [`LinkStatistics::encode`]'s). Panics on a payload over 60 bytes, more
/// than a frame holds.
pub fn frame(address: u8, kind: u8, payload: &[u8]) -> Vec<u8> {
    assert!(
        payload.len() <= usize::from(MAX_LEN_FIELD) - 2,
        "a CRSF payload of {} bytes",
        payload.len()
    );
    let mut f = Vec::with_capacity(payload.len() + 4);
    f.extend_from_slice(&[address, payload.len() as u8 + 2, kind]);
    f.extend_from_slice(payload);
    f.push(crc8(&f[2..]));
    f
}

/// An RC_CHANNELS_PACKED frame to the flight controller: `raw` channel
/// values (each clamped to [`RAW_MAX`], so no value wraps into another),
/// packed 11 bits each, least significant bit first.
pub fn encode_rc(raw: &[u16; CHANNELS]) -> [u8; RC_FRAME_LEN] {
    encode_rc_to(ADDRESS_FLIGHT_CONTROLLER, raw)
}

/// [`encode_rc`] to `address`: a flight controller's (0xC8), or a
/// transmitter module's (0xEE) from a handset.
pub fn encode_rc_to(address: u8, raw: &[u16; CHANNELS]) -> [u8; RC_FRAME_LEN] {
    let mut out = [0u8; RC_FRAME_LEN];
    out[0] = address;
    out[1] = (RC_PAYLOAD_LEN + 2) as u8;
    out[2] = TYPE_RC_CHANNELS_PACKED;
    crate::sbus::pack_channels(raw, &mut out[3..3 + RC_PAYLOAD_LEN]);
    out[RC_FRAME_LEN - 1] = crc8(&out[2..RC_FRAME_LEN - 1]);
    out
}

/// The 16 raw values packed in an RC payload's first 22 bytes (what each
/// firmware's bit-field struct reads).
pub fn rc_channels(payload: &[u8; RC_PAYLOAD_LEN]) -> [u16; CHANNELS] {
    crate::sbus::unpack_channels(payload)
}

/// The channels of a well-formed RC frame (address 0xC8, `len` 24, type
/// 0x16, CRC holding); `None` otherwise. Firmware checks less:
/// [`CrsfReceiver::verdict`].
pub fn decode_rc(frame: &[u8; RC_FRAME_LEN]) -> Option<[u16; CHANNELS]> {
    decode_rc_to(ADDRESS_FLIGHT_CONTROLLER, frame)
}

/// [`decode_rc`] of a frame to `address`.
pub fn decode_rc_to(address: u8, frame: &[u8; RC_FRAME_LEN]) -> Option<[u16; CHANNELS]> {
    let ok = frame[0] == address
        && usize::from(frame[1]) == RC_PAYLOAD_LEN + 2
        && frame[2] == TYPE_RC_CHANNELS_PACKED
        && crc_holds(frame);
    ok.then(|| {
        let mut payload = [0u8; RC_PAYLOAD_LEN];
        payload.copy_from_slice(&frame[3..3 + RC_PAYLOAD_LEN]);
        rc_channels(&payload)
    })
}
