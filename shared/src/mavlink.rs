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

use crate::frame::{Channels, FrameModel, MAX_CHANNELS};
use crate::protocol::{reject, Command, Reject, RejectReason, VALUE_MAX_US, VALUE_MIN_US};

pub mod telemetry;
pub use telemetry::{servo_output_raw_payload, statustext_payloads, SERVO_OUTPUT_RAW, STATUSTEXT};

/// MAVLink 1's start byte.
pub const STX_V1: u8 = 0xFE;
/// MAVLink 2's start byte.
pub const STX_V2: u8 = 0xFD;
/// MAVLink 2's incompat flag for a signed frame (13 signature bytes follow
/// the CRC).
pub const IFLAG_SIGNED: u8 = 0x01;
/// The length of a MAVLink 2 signature.
pub const SIGNATURE_LEN: usize = 13;

/// True when the datagram is read as MAVLink (its first byte is a start byte).
pub fn is_mavlink(datagram: &[u8]) -> bool {
    matches!(datagram.first(), Some(&STX_V1 | &STX_V2))
}

/// Most start bytes [`junk_before_frame`] tries a frame at.
pub const JUNK_SCAN_MAX_STARTS: usize = 16;

/// For a datagram not read as MAVLink (its first byte starts no frame),
/// refused as not UTF-8: `mavlink_junk` when a good MAVLink frame (one
/// [`read_frame`] takes, CRC and all) starts at one of its first
/// [`JUNK_SCAN_MAX_STARTS`] start bytes, so that bytes before a frame are
/// counted as MAVLink junk, as bytes between or after frames are, and not
/// as a JSON fault. `None` otherwise. At most that many frames are tried,
/// each read within its own few hundred bytes: a flood of start bytes
/// costs little.
pub fn junk_before_frame(datagram: &[u8]) -> Option<Reject> {
    let at = datagram
        .iter()
        .enumerate()
        .skip(1)
        .filter(|(_, b)| matches!(**b, STX_V1 | STX_V2))
        .take(JUNK_SCAN_MAX_STARTS)
        .map(|(i, _)| i)
        .find(|&i| read_frame(&datagram[i..]).is_ok())?;
    let (h, _, _) = read_frame(&datagram[at..]).ok()?;
    Some(reject(
        RejectReason::MavlinkJunk,
        format!(
            "{at} byte(s) that start no MAVLink frame before a MAVLink {} frame (message {}): a MAVLink datagram starts with its first frame (0xFE or 0xFD)",
            h.version, h.msgid
        ),
    ))
}

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

/// MAVLink's CRC (CRC-16/MCRF4XX, the X.25 polynomial) of `bytes`,
/// continued from `crc` (start with 0xFFFF).
pub fn crc_accumulate(mut crc: u16, bytes: &[u8]) -> u16 {
    for &b in bytes {
        let mut tmp = b ^ (crc & 0xFF) as u8;
        tmp ^= tmp << 4;
        crc = (crc >> 8) ^ ((tmp as u16) << 8) ^ ((tmp as u16) << 3) ^ ((tmp as u16) >> 4);
    }
    crc
}

/// A frame's CRC: over `body` (the frame from its length byte to the end
/// of its payload) and the message's CRC_EXTRA.
pub fn frame_crc(spec: &Spec, body: &[u8]) -> u16 {
    crc_accumulate(crc_accumulate(0xFFFF, body), &[spec.crc_extra])
}

/// A frame's header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// 1 or 2.
    pub version: u8,
    /// The sender's 8-bit, wrapping frame count.
    pub seq: u8,
    /// The sender's system id.
    pub sysid: u8,
    /// The sender's component id.
    pub compid: u8,
    /// The message id.
    pub msgid: u32,
    /// A MAVLink 2 frame with a signature (not checked here).
    pub signed: bool,
}

/// `RC_CHANNELS_OVERRIDE`'s fields.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RcOverride {
    /// The system it is for (0: any).
    pub target_system: u8,
    /// The component it is for (0: any).
    pub target_component: u8,
    /// chan1_raw..chan18_raw (chan9..18 are 0 in MAVLink 1).
    pub chan: [u16; 18],
}

/// `MANUAL_CONTROL`'s fields that ppm uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ManualControl {
    /// The system it is for (0: any).
    pub target: u8,
    /// x, y, z, r: pitch, roll, thrust, yaw; ±1000, `INT16_MAX` invalid.
    pub axes: [i16; 4],
    /// buttons (1..16) and buttons2 (17..32), a bit each.
    pub buttons: u32,
}

/// `COMMAND_LONG`'s fields.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandLong {
    /// The system it is for (0: any).
    pub target_system: u8,
    /// The component it is for (0: any).
    pub target_component: u8,
    /// The MAV_CMD.
    pub command: u16,
    /// Sent again without an answer: 0, 1, ...
    pub confirmation: u8,
    /// param1..param7.
    pub params: [f32; 7],
}

/// `REQUEST_DATA_STREAM`'s fields.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RequestDataStream {
    /// The system it is for (0: any).
    pub target_system: u8,
    /// The component it is for (0: any).
    pub target_component: u8,
    /// The MAV_DATA_STREAM.
    pub stream: u8,
    /// Messages a second.
    pub rate_hz: u16,
    /// 1 to start, 0 to stop.
    pub start: bool,
}

/// A message ppm takes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Message {
    /// A peer's heartbeat.
    Heartbeat,
    /// Channel values.
    RcOverride(RcOverride),
    /// Joystick axes.
    ManualControl(ManualControl),
    /// A request for the parameters, for (target system, target component).
    ParamRequestList(u8, u8),
    /// A request for a stream of messages.
    RequestDataStream(RequestDataStream),
    /// A command.
    CommandLong(CommandLong),
    /// A well-formed message of [`IGNORED`], by id.
    Ignored(u32),
}

impl Message {
    /// True for the messages that carry a command.
    pub fn is_command(&self) -> bool {
        matches!(self, Message::RcOverride(_) | Message::ManualControl(_))
    }

    /// The message's spec and its whole payload (extensions included; [`frame`]
    /// trims it for MAVLink 2). A HEARTBEAT is a groundstation's: type GCS
    /// (6), autopilot INVALID (8).
    pub fn encode(&self) -> (&'static Spec, Vec<u8>) {
        let mut p = Vec::with_capacity(38);
        match self {
            Message::Heartbeat => {
                p.extend_from_slice(&[0, 0, 0, 0, 6, 8, 0, 0, 3]);
                (&HEARTBEAT, p)
            }
            Message::RcOverride(o) => {
                for c in &o.chan[..8] {
                    p.extend_from_slice(&c.to_le_bytes());
                }
                p.extend_from_slice(&[o.target_system, o.target_component]);
                for c in &o.chan[8..] {
                    p.extend_from_slice(&c.to_le_bytes());
                }
                (&RC_CHANNELS_OVERRIDE, p)
            }
            Message::ManualControl(m) => {
                for a in m.axes {
                    p.extend_from_slice(&a.to_le_bytes());
                }
                p.extend_from_slice(&(m.buttons as u16).to_le_bytes());
                p.push(m.target);
                p.extend_from_slice(&((m.buttons >> 16) as u16).to_le_bytes());
                p.resize(MANUAL_CONTROL.max_len as usize, 0);
                (&MANUAL_CONTROL, p)
            }
            Message::ParamRequestList(s, c) => {
                p.extend_from_slice(&[*s, *c]);
                (&PARAM_REQUEST_LIST, p)
            }
            Message::RequestDataStream(r) => {
                p.extend_from_slice(&r.rate_hz.to_le_bytes());
                p.extend_from_slice(&[r.target_system, r.target_component, r.stream]);
                p.push(r.start as u8);
                (&REQUEST_DATA_STREAM, p)
            }
            Message::CommandLong(c) => {
                for v in c.params {
                    p.extend_from_slice(&v.to_le_bytes());
                }
                p.extend_from_slice(&c.command.to_le_bytes());
                p.extend_from_slice(&[c.target_system, c.target_component, c.confirmation]);
                (&COMMAND_LONG, p)
            }
            // ppm keeps none of its fields: zeros.
            Message::Ignored(id) => {
                let spec = IGNORED
                    .iter()
                    .find(|s| s.id == *id)
                    .expect("an ignored message's id");
                p.resize(spec.v1_len as usize, 0);
                (spec, p)
            }
        }
    }
}

/// Little-endian field readers over a payload that is zero beyond its end
/// (a MAVLink 2 payload trimmed of trailing zeros).
struct Payload<'a>(&'a [u8]);

impl Payload<'_> {
    fn u8(&self, at: usize) -> u8 {
        self.0.get(at).copied().unwrap_or(0)
    }
    fn u16(&self, at: usize) -> u16 {
        u16::from_le_bytes([self.u8(at), self.u8(at + 1)])
    }
    fn i16(&self, at: usize) -> i16 {
        self.u16(at) as i16
    }
    fn f32(&self, at: usize) -> f32 {
        f32::from_le_bytes([
            self.u8(at),
            self.u8(at + 1),
            self.u8(at + 2),
            self.u8(at + 3),
        ])
    }
}

/// Reads one frame at the start of `bytes`: its header, its message, and
/// its length in bytes (signature included).
pub fn read_frame(bytes: &[u8]) -> Result<(Header, Message, usize), Reject> {
    let (version, header_len) = match bytes.first() {
        Some(&STX_V1) => (1u8, 6usize),
        Some(&STX_V2) => (2u8, 10usize),
        _ => {
            return Err(reject(
                RejectReason::MavlinkJunk,
                format!(
                    "{} byte(s) that start no MAVLink frame (0xFE or 0xFD)",
                    bytes.len()
                ),
            ))
        }
    };
    if bytes.len() < header_len {
        return Err(reject(
            RejectReason::MavlinkTruncated,
            format!(
                "a MAVLink {version} header is {header_len} bytes, {} left",
                bytes.len()
            ),
        ));
    }
    let len = bytes[1] as usize;
    let (seq, sysid, compid, msgid, signed) = if version == 1 {
        (bytes[2], bytes[3], bytes[4], bytes[5] as u32, false)
    } else {
        let (incompat, seq, sysid, compid) = (bytes[2], bytes[4], bytes[5], bytes[6]);
        if incompat & !IFLAG_SIGNED != 0 {
            return Err(reject(
                RejectReason::BadShape,
                format!("MAVLink 2 incompat flags {incompat:#04x}: only 0x01 (signed) is known, so the frame cannot be read"),
            ));
        }
        let msgid = u32::from_le_bytes([bytes[7], bytes[8], bytes[9], 0]);
        (seq, sysid, compid, msgid, incompat & IFLAG_SIGNED != 0)
    };
    let total = header_len + len + 2 + if signed { SIGNATURE_LEN } else { 0 };
    if bytes.len() < total {
        return Err(reject(
            RejectReason::MavlinkTruncated,
            format!(
                "message {msgid} says {total} bytes with its CRC{}, {} left",
                if signed { " and signature" } else { "" },
                bytes.len()
            ),
        ));
    }
    let Some(spec) = spec(msgid) else {
        return Err(reject(
            RejectReason::MavlinkUnknownMessage,
            format!("message id {msgid}: ppm takes RC_CHANNELS_OVERRIDE (70), MANUAL_CONTROL (69), HEARTBEAT (0), PARAM_REQUEST_LIST (21), REQUEST_DATA_STREAM (66) and COMMAND_LONG (76), and ignores a few more a groundstation sends"),
        ));
    };
    // MAVLink 1 is never trimmed, and pymavlink (like the C library's
    // reader) packs the extension fields into it as well.
    let least = if version == 1 {
        spec.v1_len as usize
    } else {
        0
    };
    if !(least..=spec.max_len as usize).contains(&len) {
        let want = format!("{least}..={}", spec.max_len);
        return Err(reject(
            RejectReason::MavlinkBadLength,
            format!(
                "{} in MAVLink {version}: a {len}-byte payload, {want} expected",
                spec.name
            ),
        ));
    }
    let crc = frame_crc(spec, &bytes[1..header_len + len]);
    let got = u16::from_le_bytes([bytes[header_len + len], bytes[header_len + len + 1]]);
    if crc != got {
        return Err(reject(
            RejectReason::MavlinkBadCrc,
            format!(
                "{} CRC {got:#06x}, {crc:#06x} computed (with CRC_EXTRA {})",
                spec.name, spec.crc_extra
            ),
        ));
    }
    let p = Payload(&bytes[header_len..header_len + len]);
    let message = match msgid {
        0 => Message::Heartbeat,
        21 => Message::ParamRequestList(p.u8(0), p.u8(1)),
        66 => Message::RequestDataStream(RequestDataStream {
            rate_hz: p.u16(0),
            target_system: p.u8(2),
            target_component: p.u8(3),
            stream: p.u8(4),
            start: p.u8(5) != 0,
        }),
        76 => Message::CommandLong(CommandLong {
            params: std::array::from_fn(|i| p.f32(4 * i)),
            command: p.u16(28),
            target_system: p.u8(30),
            target_component: p.u8(31),
            confirmation: p.u8(32),
        }),
        69 => Message::ManualControl(ManualControl {
            axes: [p.i16(0), p.i16(2), p.i16(4), p.i16(6)],
            buttons: p.u16(8) as u32 | (p.u16(11) as u32) << 16,
            target: p.u8(10),
        }),
        70 => {
            let mut chan = [0u16; 18];
            for (i, c) in chan.iter_mut().enumerate().take(8) {
                *c = p.u16(2 * i);
            }
            for (i, c) in chan.iter_mut().enumerate().skip(8) {
                *c = p.u16(18 + 2 * (i - 8));
            }
            Message::RcOverride(RcOverride {
                target_system: p.u8(16),
                target_component: p.u8(17),
                chan,
            })
        }
        id if IGNORED.iter().any(|s| s.id == id) => Message::Ignored(id),
        _ => {
            return Err(reject(
                RejectReason::MavlinkUnknownMessage,
                format!("{} is sent by ppm, not taken", spec.name),
            ))
        }
    };
    let header = Header {
        version,
        seq,
        sysid,
        compid,
        msgid,
        signed,
    };
    Ok((header, message, total))
}

/// What a MAVLink datagram holds.
#[derive(Debug, Clone, PartialEq)]
pub struct Datagram {
    /// Its last command message, if any (an earlier one in the same
    /// datagram is superseded by it).
    pub command: Option<(Header, Message)>,
    /// Its frames.
    pub frames: usize,
    /// The MAVLink version of its last frame.
    pub version: u8,
    /// Its requests (PARAM_REQUEST_LIST, REQUEST_DATA_STREAM,
    /// COMMAND_LONG) and ignored messages, in order.
    pub requests: Vec<(Header, Message)>,
}

/// Reads a whole MAVLink datagram: every frame must be good, or the
/// datagram is rejected with the first fault.
pub fn read_datagram(bytes: &[u8]) -> Result<Datagram, Reject> {
    read_datagram_with(bytes, |_, _| Ok(()))
}

/// Reads a whole MAVLink datagram like [`read_datagram`], handing each
/// good frame (its bytes, signature included, and its header) to `check`
/// as well, whose refusal rejects the datagram.
pub fn read_datagram_with(
    bytes: &[u8],
    mut check: impl FnMut(&[u8], &Header) -> Result<(), Reject>,
) -> Result<Datagram, Reject> {
    let mut d = Datagram {
        command: None,
        frames: 0,
        version: 0,
        requests: Vec::new(),
    };
    let mut at = 0;
    while at < bytes.len() {
        let (header, message, len) = read_frame(&bytes[at..]).map_err(|mut r| {
            if d.frames > 0 {
                r.detail = format!("after {} good frame(s): {}", d.frames, r.detail);
            }
            r
        })?;
        check(&bytes[at..at + len], &header)?;
        d.frames += 1;
        d.version = header.version;
        if message.is_command() {
            d.command = Some((header, message));
        } else if message != Message::Heartbeat {
            d.requests.push((header, message));
        }
        at += len;
    }
    Ok(d)
}

/// MAVLink 2 signing's epoch: 2015-01-01T00:00:00Z, in Unix seconds.
pub const SIGNING_EPOCH_UNIX_S: u64 = 1_420_070_400;
/// A stream not seen before is taken only with a timestamp at most this far
/// behind ppm's (60 s, in the signature's 10 us units), as the MAVLink C
/// library takes it.
pub const NEW_STREAM_MAX_LAG: u64 = 6_000_000;
/// Most signing streams (system, component, link) remembered; the one
/// updated longest ago makes room.
pub const MAX_STREAMS: usize = 32;

/// A signature timestamp (10 us units since 2015) for a CLOCK_REALTIME time.
pub fn signing_timestamp(unix_ns: u64) -> u64 {
    unix_ns.saturating_sub(SIGNING_EPOCH_UNIX_S * 1_000_000_000) / 10_000
}

/// One signing stream: a (system, component, link) and its last
/// timestamp.
#[derive(Debug, Clone, Copy)]
struct Stream {
    id: (u8, u8, u8),
    last: u64,
    /// When it was last updated (a count of accepted frames).
    touched: u64,
}

/// MAVLink 2 message signing with one key: checks what comes in (the
/// signature, and a timestamp that grows per stream) and signs what goes
/// out. Its timestamp is the newest of the clock's and every one accepted.
#[derive(Debug, Clone)]
pub struct Signing {
    key: crate::auth::AuthKey,
    streams: Vec<Stream>,
    updates: u64,
    timestamp: u64,
    /// A stream not seen since the start needs a timestamp above this: the
    /// newest accepted before a restart ([`Signing::with_floor`]).
    floor: u64,
    /// The newest timestamp accepted, if any.
    newest: Option<u64>,
}

impl Signing {
    /// Signing with `key` (a key file's 32 bytes, as pymavlink and MAVProxy
    /// take them).
    pub fn new(key: crate::auth::AuthKey) -> Signing {
        Signing {
            key,
            streams: Vec::new(),
            updates: 0,
            timestamp: 0,
            floor: 0,
            newest: None,
        }
    }

    /// After a restart: every frame needs a timestamp above `floor`, the
    /// newest accepted before ([`Signing::newest`], kept in a file), so
    /// that no frame accepted, or signed, before the restart is taken
    /// again.
    pub fn with_floor(mut self, floor: u64) -> Signing {
        self.floor = floor;
        self.timestamp = self.timestamp.max(floor);
        self
    }

    /// The newest timestamp accepted since the start (or the floor).
    pub fn newest(&self) -> Option<u64> {
        self.newest.or((self.floor > 0).then_some(self.floor))
    }

    fn signature(&self, signed: &[u8]) -> [u8; 6] {
        use sha2::{Digest, Sha256};
        let mut h = Sha256::new();
        h.update(self.key.bytes());
        h.update(signed);
        let d = h.finalize();
        [d[0], d[1], d[2], d[3], d[4], d[5]]
    }

    /// Checks one frame (`frame`: its bytes, signature included) received
    /// when the clock's timestamp was `now` ([`signing_timestamp`]):
    /// `unsigned` without a signature (and every MAVLink 1 frame), `bad_mac`
    /// when the signature is not the key's, `replay` when its timestamp is
    /// not above its stream's last, or (a new stream) more than
    /// [`NEW_STREAM_MAX_LAG`] behind ppm's.
    pub fn check(&mut self, frame: &[u8], header: &Header, now: u64) -> Result<(), Reject> {
        if header.version == 1 {
            return Err(reject(
                RejectReason::Unsigned,
                "a MAVLink 1 frame: mavlink.key_file is set, so frames must be signed with its key, and only MAVLink 2 carries a signature: send MAVLink 2 (pymavlink writes it only with MAVLINK20=1 set in the environment before it is imported; MAVProxy does unless started with --mavversion 1.0)",
            ));
        }
        if !header.signed {
            return Err(reject(
                RejectReason::Unsigned,
                "an unsigned MAVLink 2 frame: mavlink.key_file is set, so frames must be signed with its key (pymavlink: setup_signing(key, sign_outgoing=True); MAVProxy: signing key PASSPHRASE)",
            ));
        }
        let n = frame.len();
        let sig = &frame[n - SIGNATURE_LEN..];
        let want = self.signature(&frame[..n - 6]);
        let diff = want
            .iter()
            .zip(&sig[7..])
            .fold(0u8, |d, (a, b)| d | (a ^ b));
        if diff != 0 {
            return Err(reject(
                RejectReason::BadMac,
                "the MAVLink signature is not that of mavlink.key_file's key",
            ));
        }
        let link = sig[0];
        let ts = u64::from_le_bytes([sig[1], sig[2], sig[3], sig[4], sig[5], sig[6], 0, 0]);
        self.timestamp = self.timestamp.max(now);
        let id = (header.sysid, header.compid, link);
        self.updates += 1;
        match self.streams.iter_mut().find(|s| s.id == id) {
            Some(s) if ts <= s.last => {
                return Err(reject(
                    RejectReason::Replay,
                    format!(
                        "signed timestamp {ts} of system {}, component {}, link {link} is not above its last, {}",
                        id.0, id.1, s.last
                    ),
                ))
            }
            Some(s) => {
                s.last = ts;
                s.touched = self.updates;
            }
            None if ts <= self.floor => {
                return Err(reject(
                    RejectReason::Replay,
                    format!(
                        "signed timestamp {ts} of system {}, component {}, link {link} is not above {}, the newest accepted before udp-ingress started",
                        id.0, id.1, self.floor
                    ),
                ))
            }
            None if ts + NEW_STREAM_MAX_LAG < self.timestamp => {
                return Err(reject(
                    RejectReason::Replay,
                    format!(
                        "a new signing stream (system {}, component {}, link {link}) whose timestamp {ts} is more than a minute behind ppm's {}",
                        id.0, id.1, self.timestamp
                    ),
                ))
            }
            None => {
                if self.streams.len() == MAX_STREAMS {
                    let oldest = (0..self.streams.len())
                        .min_by_key(|&i| self.streams[i].touched)
                        .expect("MAX_STREAMS > 0");
                    self.streams.swap_remove(oldest);
                }
                self.streams.push(Stream {
                    id,
                    last: ts,
                    touched: self.updates,
                });
            }
        }
        self.timestamp = self.timestamp.max(ts);
        self.newest = Some(self.newest.map_or(ts, |n| n.max(ts)));
        Ok(())
    }

    /// One signed MAVLink 2 frame (link 0) of `spec`'s message with
    /// `payload`, at a timestamp above every one used or seen and the
    /// clock's `now`.
    pub fn frame(
        &mut self,
        header: (u8, u8, u8),
        spec: &Spec,
        payload: &[u8],
        now: u64,
    ) -> Vec<u8> {
        let mut out = build_frame(2, IFLAG_SIGNED, header, spec, payload);
        self.timestamp = self.timestamp.max(now) + 1;
        out.push(0);
        out.extend_from_slice(&self.timestamp.to_le_bytes()[..6]);
        let sig = self.signature(&out);
        out.extend_from_slice(&sig);
        out
    }
}

/// The kind of vehicle ppm says it is in its HEARTBEAT (MAV_TYPE):
/// QGroundControl keeps its joystick mode per kind, and shows the kind's
/// icon.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VehicleType {
    /// MAV_TYPE_GENERIC (0): a vehicle of no particular kind.
    #[default]
    Generic,
    /// MAV_TYPE_FIXED_WING (1).
    FixedWing,
    /// MAV_TYPE_QUADROTOR (2).
    Quadrotor,
    /// MAV_TYPE_HELICOPTER (4).
    Helicopter,
    /// MAV_TYPE_GROUND_ROVER (10).
    GroundRover,
    /// MAV_TYPE_SURFACE_BOAT (11).
    SurfaceBoat,
    /// MAV_TYPE_SUBMARINE (12).
    Submarine,
    /// MAV_TYPE_HEXAROTOR (13).
    Hexarotor,
    /// MAV_TYPE_OCTOROTOR (14).
    Octorotor,
}

impl VehicleType {
    /// Its MAV_TYPE.
    pub fn mav_type(self) -> u8 {
        match self {
            VehicleType::Generic => 0,
            VehicleType::FixedWing => 1,
            VehicleType::Quadrotor => 2,
            VehicleType::Helicopter => 4,
            VehicleType::GroundRover => 10,
            VehicleType::SurfaceBoat => 11,
            VehicleType::Submarine => 12,
            VehicleType::Hexarotor => 13,
            VehicleType::Octorotor => 14,
        }
    }
}

/// How z, MANUAL_CONTROL's thrust axis, maps onto its channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Thrust {
    /// 0..1000: 0 is the channel's minimum, 1000 its maximum (what
    /// QGroundControl sends, and ArduPilot reads). A negative z clamps.
    #[default]
    Positive,
    /// -1000..1000 like the other axes (-1000 the minimum, 0 the middle).
    Signed,
}

/// What a MAVLink command needs from the configuration.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Settings {
    /// ppm's system id: a message's target system must be it, or 0.
    pub system_id: u8,
    /// ppm's component id: an RC_CHANNELS_OVERRIDE's target component must
    /// be it, or 0.
    pub component_id: u8,
    /// The channels MANUAL_CONTROL's x, y, z and r drive (`None`: that
    /// axis is not used).
    pub axes: [Option<usize>; 4],
    /// How z is read.
    pub thrust: Thrust,
    /// The channels buttons 1.. drive (pressed: the channel's maximum,
    /// released: its minimum).
    pub buttons: Vec<usize>,
    /// The signing key's file (`mavlink.key_file`), if any.
    pub key_file: Option<std::path::PathBuf>,
    /// Where the newest signing timestamp accepted is kept
    /// (`mavlink.timestamp_file`, resolved), used with `key_file`.
    pub timestamp_file: Option<std::path::PathBuf>,
    /// RC_CHANNELS per second to each peer, unless it asks otherwise
    /// (`mavlink.rc_channels_hz`, 0..=[`RC_CHANNELS_MAX_HZ`]).
    pub rc_channels_hz: u8,
    /// The HEARTBEAT's type (`mavlink.vehicle_type`).
    pub vehicle_type: VehicleType,
}

/// RC_CHANNELS a second to each groundstation by default.
pub const RC_CHANNELS_HZ: u8 = 4;
/// The most RC_CHANNELS a second: ppmd publishes its line every tenth of a
/// second, so more would repeat the same frame.
pub const RC_CHANNELS_MAX_HZ: u8 = 10;

impl Settings {
    /// Ids 1 and 1, and the axes onto ele, ail, thr and rud, those of them
    /// the frame has.
    pub fn defaults_for(model: &FrameModel) -> Settings {
        Settings {
            system_id: 1,
            component_id: 1,
            axes: DEFAULT_AXES.map(|n| model.index_of(n)),
            thrust: Thrust::Positive,
            buttons: Vec::new(),
            key_file: None,
            timestamp_file: None,
            rc_channels_hz: RC_CHANNELS_HZ,
            vehicle_type: VehicleType::Generic,
        }
    }
}

/// True when a message's `target` (system or component) addresses ppm's
/// `id`: it is that id, or 0 (any).
pub fn addressed(target: u8, id: u8) -> bool {
    target == 0 || target == id
}

/// The channels MANUAL_CONTROL's x, y, z and r drive by default.
pub const DEFAULT_AXES: [&str; 4] = ["ele", "ail", "thr", "rud"];

/// The command a message carries, for a line now carrying `current` (the
/// values "keep" keeps).
pub fn command(
    message: &Message,
    model: &FrameModel,
    settings: &Settings,
    current: &Channels,
) -> Result<Command, Reject> {
    let n = model.channels();
    let mut ns = [0u32; MAX_CHANNELS];
    ns[..n].copy_from_slice(current.as_ns());
    let mut clamped = 0;
    let target = |system: u8| -> Result<(), Reject> {
        if addressed(system, settings.system_id) {
            Ok(())
        } else {
            Err(reject(
                RejectReason::WrongOutput,
                format!(
                    "target system {system}: this is system {} (mavlink.system_id)",
                    settings.system_id
                ),
            ))
        }
    };
    match message {
        Message::Heartbeat
        | Message::ParamRequestList(..)
        | Message::RequestDataStream(_)
        | Message::CommandLong(_)
        | Message::Ignored(_) => return Err(reject(RejectReason::BadShape, "not a command")),
        Message::RcOverride(o) => {
            target(o.target_system)?;
            let c = o.target_component;
            if !addressed(c, settings.component_id) {
                return Err(reject(
                    RejectReason::WrongOutput,
                    format!(
                        "target component {c}: this is component {} (mavlink.component_id)",
                        settings.component_id
                    ),
                ));
            }
            for (i, &v) in o.chan.iter().enumerate() {
                let (keep, release) = if i < 8 {
                    (v == u16::MAX, v == 0)
                } else {
                    (v == u16::MAX || v == 0, v == u16::MAX - 1)
                };
                if keep {
                    continue;
                }
                if i >= n {
                    if release {
                        continue;
                    }
                    return Err(reject(
                        RejectReason::TooManyValues,
                        format!("chan{}_raw is {v} but the frame has {n} channels", i + 1),
                    ));
                }
                if release {
                    ns[i] = model.default_ns(i);
                    continue;
                }
                let us = v as f64;
                if !(VALUE_MIN_US..=VALUE_MAX_US).contains(&us) {
                    return Err(reject(
                        RejectReason::OutOfRange,
                        format!(
                            "chan{}_raw is {v} us, outside {VALUE_MIN_US}..={VALUE_MAX_US}",
                            i + 1
                        ),
                    ));
                }
                let (c, was) = model.clamp(i, v as u32 * 1_000);
                ns[i] = c;
                clamped += was as u32;
            }
        }
        Message::ManualControl(m) => {
            target(m.target)?;
            for (axis, (&v, ch)) in m.axes.iter().zip(settings.axes).enumerate() {
                let Some(i) = ch else { continue };
                if v == i16::MAX {
                    continue;
                }
                let norm = if axis == 2 && settings.thrust == Thrust::Positive {
                    v as f64 / 500.0 - 1.0
                } else {
                    v as f64 / 1000.0
                };
                let (c, was) = model.norm_to_ns(i, norm);
                ns[i] = c;
                clamped += was as u32;
            }
            for (b, &i) in settings.buttons.iter().enumerate() {
                ns[i] = if m.buttons & (1 << b) != 0 {
                    model.max_ns(i)
                } else {
                    model.min_ns(i)
                };
            }
        }
    }
    Ok(Command {
        seq: None,
        channels: Channels::from_ns(&ns[..n]),
        clamped,
    })
}

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

/// One frame of `spec`'s message with `payload` (MAVLink 2 trims its
/// trailing zeros), unsigned: what ppm sends, and what its tests send.
pub fn frame(version: u8, header: (u8, u8, u8), spec: &Spec, payload: &[u8]) -> Vec<u8> {
    build_frame(version, 0, header, spec, payload)
}

/// [`frame`] with MAVLink 2 incompat flags `incompat` (a signature, when
/// flagged, is the caller's to append).
fn build_frame(
    version: u8,
    incompat: u8,
    header: (u8, u8, u8),
    spec: &Spec,
    payload: &[u8],
) -> Vec<u8> {
    let (seq, sysid, compid) = header;
    debug_assert!(version == 2 || spec.id <= 255, "MAVLink 1 has 8-bit ids");
    let mut out = Vec::with_capacity(payload.len() + 12 + SIGNATURE_LEN);
    if version == 1 {
        out.extend_from_slice(&[
            STX_V1,
            payload.len() as u8,
            seq,
            sysid,
            compid,
            spec.id as u8,
        ]);
        out.extend_from_slice(payload);
    } else {
        let mut len = payload.len();
        while len > 1 && payload[len - 1] == 0 {
            len -= 1;
        }
        let id = spec.id.to_le_bytes();
        out.extend_from_slice(&[
            STX_V2, len as u8, incompat, 0, seq, sysid, compid, id[0], id[1], id[2],
        ]);
        out.extend_from_slice(&payload[..len]);
    }
    let crc = frame_crc(spec, &out[1..]);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

#[cfg(test)]
mod tests;
