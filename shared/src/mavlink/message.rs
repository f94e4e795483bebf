//! The messages ppm takes ([`Message`]) and their fields, with their
//! payloads both ways: [`Message::encode`] writes one, and a frame read
//! ([`read_frame`](super::read_frame)) decodes its payload here.

use super::specs::{
    Spec, COMMAND_LONG, HEARTBEAT, IGNORED, MANUAL_CONTROL, PARAM_REQUEST_LIST,
    RC_CHANNELS_OVERRIDE, REQUEST_DATA_STREAM,
};
use crate::protocol::{reject, Reject, RejectReason};

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

    /// The message's spec and its whole payload (extensions included;
    /// [`frame`](super::frame) trims it for MAVLink 2). A HEARTBEAT is a
    /// groundstation's: type GCS (6), autopilot INVALID (8).
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

    /// The message in `payload`, the payload of a good frame (length and
    /// CRC checked) of `spec`'s message; `mavlink_unknown_message` for a
    /// message ppm sends but does not take.
    pub(super) fn decode(spec: &Spec, payload: &[u8]) -> Result<Message, Reject> {
        let p = Payload(payload);
        let message = match spec.id {
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
        Ok(message)
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
