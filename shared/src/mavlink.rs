//! MAVLink 1 and 2 commands on the command socket.
//!
//! A datagram whose first byte is a MAVLink start byte (0xFE for MAVLink 1,
//! 0xFD for MAVLink 2) is read as MAVLink; anything else as JSON. No JSON
//! text can start with either byte: neither is valid UTF-8 anywhere, let
//! alone as a first byte. So one socket, one port, one allowlist and one
//! set of counters serve both, and a groundstation needs no second port.
//!
//! A datagram that does not start with a start byte, is not UTF-8 and has a
//! good frame at one of its first start bytes is refused as `mavlink_junk`
//! too ([`junk_before_frame`]), not as a JSON fault: bytes before a frame
//! are junk as bytes between or after frames are.
//!
//! A datagram holds one or more whole frames back to back (the MAVLink
//! senders we know put exactly one in each). Every frame is checked (start
//! byte, length, CRC with the message's CRC_EXTRA); any byte that is not
//! part of a good frame rejects the whole datagram, which is then never
//! applied in part. A MAVLink 2 payload trimmed of its trailing zeros is
//! zero-extended, as the specification asks.
//!
//! Messages taken ([`Message`]):
//! - `RC_CHANNELS_OVERRIDE` (70): chan1..8, and chan9..18 (a MAVLink 2
//!   extension). `UINT16_MAX` keeps the channel's current value (0 too on
//!   chan9..18); 0 on chan1..8 and `UINT16_MAX - 1` on chan9..18 release the
//!   channel to its configured default. Any other value is a period in
//!   microseconds, checked and clamped as a JSON value is.
//! - `MANUAL_CONTROL` (69): the x, y, z and r axes, ±1000, onto the
//!   channels [`Settings::axes`] names (pitch, roll, thrust, yaw onto ele,
//!   ail, thr, rud by default); `INT16_MAX` keeps the channel's value.
//! - `HEARTBEAT` (0): a peer's presence; no command.
//! - `PARAM_REQUEST_LIST` (21): answered with ppm's one parameter (the
//!   channel count), which is what QGroundControl waits for before it lets
//!   its joystick be enabled.
//!
//! Any other message id is `mavlink_unknown_message`: its CRC cannot be
//! checked without its CRC_EXTRA, so it is no more trusted than junk.
//!
//! What ppm sends back beside HEARTBEAT, RC_CHANNELS and the answers to
//! requests (SERVO_OUTPUT_RAW, STATUSTEXT) is encoded in [`telemetry`].
//!
//! Its parts, each re-exported here:
//! - [`framing`]: start bytes, the CRC, a frame's header, reading frames
//!   and datagrams, writing a frame.
//! - [`specs`]: each message's id, CRC_EXTRA and lengths ([`Spec`]), and the
//!   MAV_CMD and MAV_DATA_STREAM values ppm reads.
//! - [`message`]: the messages ppm takes ([`Message`]), their fields, and
//!   their payloads both ways.
//! - [`commands`]: what RC_CHANNELS_OVERRIDE and MANUAL_CONTROL do to the
//!   channels ([`command()`]).
//! - [`settings`]: what a MAVLink command needs from the configuration
//!   ([`Settings`]).
//! - [`signing`]: MAVLink 2 signing ([`Signing`]).
//! - [`replies`]: the payloads of RC_CHANNELS and of the answers to
//!   requests (PROTOCOL_VERSION, COMMAND_ACK).
//! - [`telemetry`]: SERVO_OUTPUT_RAW and STATUSTEXT.

pub mod commands;
pub mod framing;
pub mod message;
pub mod replies;
pub mod settings;
pub mod signing;
pub mod specs;
pub mod telemetry;

pub use commands::command;
pub use framing::{
    crc_accumulate, frame, frame_crc, is_mavlink, junk_before_frame, read_datagram,
    read_datagram_with, read_frame, Datagram, Header, IFLAG_SIGNED, JUNK_SCAN_MAX_STARTS,
    SIGNATURE_LEN, STX_V1, STX_V2,
};
pub use message::{CommandLong, ManualControl, Message, RcOverride, RequestDataStream};
pub use replies::{command_ack_payload, protocol_version_payload, rc_channels_payload};
pub use settings::{
    addressed, Settings, Thrust, VehicleType, DEFAULT_AXES, RC_CHANNELS_HZ, RC_CHANNELS_MAX_HZ,
};
pub use signing::{
    signing_timestamp, Signing, MAX_STREAMS, NEW_STREAM_MAX_LAG, SIGNING_EPOCH_UNIX_S,
};
pub use specs::{
    spec, Spec, COMMAND_ACK, COMMAND_LONG, HEARTBEAT, IGNORED, MANUAL_CONTROL,
    MAV_CMD_REQUEST_MESSAGE, MAV_CMD_REQUEST_PROTOCOL_VERSION, MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_DATA_STREAM_ALL, MAV_DATA_STREAM_RC_CHANNELS, PARAM_REQUEST_LIST, PARAM_VALUE,
    PROTOCOL_VERSION, RC_CHANNELS, RC_CHANNELS_OVERRIDE, REQUEST_DATA_STREAM, SPECS,
};
pub use telemetry::{
    attitude_payload, gps_raw_int_payload, servo_output_raw_payload, statustext_payloads,
    sys_status_payload, GpsRawInt, ATTITUDE, GPS_RAW_INT, SERVO_OUTPUT_RAW, STATUSTEXT, SYS_STATUS,
};

#[cfg(test)]
mod tests;
