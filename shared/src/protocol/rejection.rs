//! Why a datagram is rejected: the counted [`RejectReason`], and the
//! [`Reject`] that carries it with a detail for the log.

/// Why a datagram was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RejectReason {
    /// The bytes are not UTF-8.
    InvalidUtf8,
    /// The text is not JSON.
    InvalidJson,
    /// A channel value is not a number.
    NotANumber,
    /// A channel value lies outside 500..=2500 us, or any value beyond a
    /// 64-bit float (`1e400`).
    OutOfRange,
    /// More values than the frame has channels.
    TooManyValues,
    /// A channel name the configured order does not have.
    UnknownChannel,
    /// Valid JSON of any other shape (no channels, a bad `seq`, unexpected keys, ...).
    BadShape,
    /// An object with the same key twice, at any depth (`{"thr": 1000,
    /// "thr": 2000}`): JSON readers disagree on which value counts, so the
    /// command has no one meaning.
    DuplicateKey,
    /// A command without a signature while `ingress.auth_key` is set.
    Unsigned,
    /// A signed datagram whose MAC does not match its `msg` (or is not 64 hex characters).
    BadMac,
    /// A signed command without a `seq` (a signature alone does not stop replays).
    NoSeq,
    /// A signed command whose `seq` is not greater than the last accepted one.
    Replay,
    /// A datagram from a source outside `ingress.allow`.
    NotAllowed,
    /// A command for another output: its `to` is not this output's name (a
    /// signed command copied to another output, or sent to the wrong port).
    WrongOutput,
    /// A signed command without `to` (the output it is for): a signature
    /// alone does not say which vehicle it may fly.
    NoTo,
    /// A MAVLink datagram with bytes that start no frame (before, between
    /// or after its frames).
    MavlinkJunk,
    /// A MAVLink frame cut short (its header, payload, CRC or signature).
    MavlinkTruncated,
    /// A MAVLink message whose payload length does not fit its id.
    MavlinkBadLength,
    /// A MAVLink frame whose CRC (with its message's CRC_EXTRA) is wrong.
    MavlinkBadCrc,
    /// A MAVLink message ppm does not take (any id but 0, 69 and 70).
    MavlinkUnknownMessage,
}

impl RejectReason {
    /// Every reason, in counter order.
    pub const ALL: [RejectReason; 20] = [
        RejectReason::InvalidUtf8,
        RejectReason::InvalidJson,
        RejectReason::NotANumber,
        RejectReason::OutOfRange,
        RejectReason::TooManyValues,
        RejectReason::UnknownChannel,
        RejectReason::BadShape,
        RejectReason::DuplicateKey,
        RejectReason::Unsigned,
        RejectReason::BadMac,
        RejectReason::NoSeq,
        RejectReason::Replay,
        RejectReason::NotAllowed,
        RejectReason::WrongOutput,
        RejectReason::NoTo,
        RejectReason::MavlinkJunk,
        RejectReason::MavlinkTruncated,
        RejectReason::MavlinkBadLength,
        RejectReason::MavlinkBadCrc,
        RejectReason::MavlinkUnknownMessage,
    ];

    /// The counter name (`snake_case`).
    pub fn as_str(self) -> &'static str {
        match self {
            RejectReason::InvalidUtf8 => "invalid_utf8",
            RejectReason::InvalidJson => "invalid_json",
            RejectReason::NotANumber => "not_a_number",
            RejectReason::OutOfRange => "out_of_range",
            RejectReason::TooManyValues => "too_many_values",
            RejectReason::UnknownChannel => "unknown_channel",
            RejectReason::BadShape => "bad_shape",
            RejectReason::DuplicateKey => "duplicate_key",
            RejectReason::Unsigned => "unsigned",
            RejectReason::BadMac => "bad_mac",
            RejectReason::NoSeq => "no_seq",
            RejectReason::Replay => "replay",
            RejectReason::NotAllowed => "not_allowed",
            RejectReason::WrongOutput => "wrong_output",
            RejectReason::NoTo => "no_to",
            RejectReason::MavlinkJunk => "mavlink_junk",
            RejectReason::MavlinkTruncated => "mavlink_truncated",
            RejectReason::MavlinkBadLength => "mavlink_bad_length",
            RejectReason::MavlinkBadCrc => "mavlink_bad_crc",
            RejectReason::MavlinkUnknownMessage => "mavlink_unknown_message",
        }
    }

    /// Position in [`RejectReason::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }
}

/// A rejected datagram: the reason (counted) and a detail for the log.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{}: {detail}", reason.as_str())]
pub struct Reject {
    /// The counted reason.
    pub reason: RejectReason,
    /// What exactly was wrong.
    pub detail: String,
}

pub(crate) fn reject(reason: RejectReason, detail: impl Into<String>) -> Reject {
    Reject {
        reason,
        detail: detail.into(),
    }
}
