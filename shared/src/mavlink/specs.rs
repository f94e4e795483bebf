//! What ppm knows of each MAVLink message it reads or writes ([`Spec`]:
//! id, CRC_EXTRA, payload lengths), those it reads and ignores
//! ([`IGNORED`]), and the MAV_CMD and MAV_DATA_STREAM values it reads.

use super::telemetry::{SERVO_OUTPUT_RAW, STATUSTEXT};

/// What ppm knows of one message: id, CRC_EXTRA, and payload lengths.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Spec {
    /// The message id.
    pub id: u32,
    /// Its name in the common dialect.
    pub name: &'static str,
    /// The seed byte added to its CRC (from its field layout).
    pub crc_extra: u8,
    /// Its payload without the extension fields: the least a MAVLink 1
    /// frame carries (MAVLink 2 trims trailing zeros).
    pub v1_len: u8,
    /// Its whole payload in MAVLink 2, extensions included.
    pub max_len: u8,
}

/// `HEARTBEAT`.
pub const HEARTBEAT: Spec = Spec {
    id: 0,
    name: "HEARTBEAT",
    crc_extra: 50,
    v1_len: 9,
    max_len: 9,
};
/// `RC_CHANNELS`: what ppm sends back (what the radio transmits, read
/// back, with a read-back; the values on the line without one).
pub const RC_CHANNELS: Spec = Spec {
    id: 65,
    name: "RC_CHANNELS",
    crc_extra: 118,
    v1_len: 42,
    max_len: 42,
};
/// `MANUAL_CONTROL`.
pub const MANUAL_CONTROL: Spec = Spec {
    id: 69,
    name: "MANUAL_CONTROL",
    crc_extra: 243,
    v1_len: 11,
    max_len: 30,
};
/// `RC_CHANNELS_OVERRIDE`.
pub const RC_CHANNELS_OVERRIDE: Spec = Spec {
    id: 70,
    name: "RC_CHANNELS_OVERRIDE",
    crc_extra: 124,
    v1_len: 18,
    max_len: 38,
};

/// `PARAM_REQUEST_LIST`: a groundstation asks for the parameters.
pub const PARAM_REQUEST_LIST: Spec = Spec {
    id: 21,
    name: "PARAM_REQUEST_LIST",
    crc_extra: 159,
    v1_len: 2,
    max_len: 2,
};
/// `PARAM_VALUE`: ppm's answer, its one parameter.
pub const PARAM_VALUE: Spec = Spec {
    id: 22,
    name: "PARAM_VALUE",
    crc_extra: 220,
    v1_len: 25,
    max_len: 25,
};

/// `REQUEST_DATA_STREAM`: a groundstation asks for a stream of messages
/// at a rate (the older way, MAVProxy's and pymavlink's).
pub const REQUEST_DATA_STREAM: Spec = Spec {
    id: 66,
    name: "REQUEST_DATA_STREAM",
    crc_extra: 148,
    v1_len: 6,
    max_len: 6,
};
/// `COMMAND_LONG`: a command, such as MAV_CMD_SET_MESSAGE_INTERVAL.
pub const COMMAND_LONG: Spec = Spec {
    id: 76,
    name: "COMMAND_LONG",
    crc_extra: 152,
    v1_len: 33,
    max_len: 33,
};
/// `COMMAND_ACK`: ppm's answer to a COMMAND_LONG.
pub const COMMAND_ACK: Spec = Spec {
    id: 77,
    name: "COMMAND_ACK",
    crc_extra: 143,
    v1_len: 3,
    max_len: 10,
};

/// `PROTOCOL_VERSION`: ppm's answer to a request for it (MAVLink 2 only).
pub const PROTOCOL_VERSION: Spec = Spec {
    id: 300,
    name: "PROTOCOL_VERSION",
    crc_extra: 217,
    v1_len: 22,
    max_len: 22,
};

/// Every message ppm reads or writes.
pub const SPECS: [Spec; 12] = [
    HEARTBEAT,
    PARAM_REQUEST_LIST,
    PARAM_VALUE,
    RC_CHANNELS,
    REQUEST_DATA_STREAM,
    MANUAL_CONTROL,
    RC_CHANNELS_OVERRIDE,
    COMMAND_LONG,
    COMMAND_ACK,
    PROTOCOL_VERSION,
    SERVO_OUTPUT_RAW,
    STATUSTEXT,
];

/// Messages a groundstation sends any vehicle that ppm reads, checks (its
/// length and CRC) and ignores: they are well-formed, not a fault, and
/// counted apart (`mavlink.ignored`) instead of rejected. Lengths from the
/// common dialect, extensions included.
pub const IGNORED: [Spec; 14] = [
    ignored(2, "SYSTEM_TIME", 137, 12, 12),
    ignored(4, "PING", 237, 14, 14),
    ignored(11, "SET_MODE", 89, 6, 6),
    ignored(20, "PARAM_REQUEST_READ", 214, 20, 20),
    ignored(23, "PARAM_SET", 168, 23, 23),
    ignored(40, "MISSION_REQUEST", 230, 4, 5),
    ignored(43, "MISSION_REQUEST_LIST", 132, 2, 3),
    ignored(47, "MISSION_ACK", 153, 3, 8),
    ignored(51, "MISSION_REQUEST_INT", 196, 4, 5),
    ignored(75, "COMMAND_INT", 158, 35, 35),
    ignored(110, "FILE_TRANSFER_PROTOCOL", 84, 254, 254),
    ignored(111, "TIMESYNC", 34, 16, 18),
    ignored(117, "LOG_REQUEST_LIST", 128, 6, 6),
    ignored(256, "SETUP_SIGNING", 71, 42, 42),
];

const fn ignored(id: u32, name: &'static str, crc_extra: u8, v1_len: u8, max_len: u8) -> Spec {
    Spec {
        id,
        name,
        crc_extra,
        v1_len,
        max_len,
    }
}

/// MAV_CMD_SET_MESSAGE_INTERVAL: param1 a message id, param2 its interval
/// in us (-1: stop, 0: the default).
pub const MAV_CMD_SET_MESSAGE_INTERVAL: u16 = 511;
/// MAV_CMD_REQUEST_MESSAGE: param1 a message id, sent once.
pub const MAV_CMD_REQUEST_MESSAGE: u16 = 512;
/// MAV_CMD_REQUEST_PROTOCOL_VERSION (deprecated for REQUEST_MESSAGE).
pub const MAV_CMD_REQUEST_PROTOCOL_VERSION: u16 = 519;
/// MAV_DATA_STREAM_ALL, in REQUEST_DATA_STREAM.
pub const MAV_DATA_STREAM_ALL: u8 = 0;
/// MAV_DATA_STREAM_RC_CHANNELS, in REQUEST_DATA_STREAM.
pub const MAV_DATA_STREAM_RC_CHANNELS: u8 = 3;

/// The spec of message `id`, if ppm knows it ([`SPECS`], [`IGNORED`]).
pub fn spec(id: u32) -> Option<&'static Spec> {
    SPECS.iter().chain(&IGNORED).find(|s| s.id == id)
}
