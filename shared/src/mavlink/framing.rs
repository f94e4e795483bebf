//! A MAVLink frame as bytes: its start bytes, its CRC, its header; reading
//! one frame ([`read_frame`]) and a whole datagram of them
//! ([`read_datagram`]), telling junk before a frame ([`junk_before_frame`]),
//! and writing one ([`frame`]). What a frame's payload holds is
//! [`message`](super::message)'s; a signature is [`Signing`](super::Signing)'s.

use super::message::Message;
use super::specs::{spec, Spec};
use crate::protocol::{reject, Reject, RejectReason};

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
    let message = Message::decode(spec, &bytes[header_len..header_len + len])?;
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

/// One frame of `spec`'s message with `payload` (MAVLink 2 trims its
/// trailing zeros), unsigned: what ppm sends, and what its tests send.
pub fn frame(version: u8, header: (u8, u8, u8), spec: &Spec, payload: &[u8]) -> Vec<u8> {
    build_frame(version, 0, header, spec, payload)
}

/// [`frame`] with MAVLink 2 incompat flags `incompat` (a signature, when
/// flagged, is the caller's to append).
pub(super) fn build_frame(
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
