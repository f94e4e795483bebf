//! The UDP wire protocol: one datagram is one command, UTF-8 JSON, in one of
//! five forms.
//!
//! - A bare array of channel periods in microseconds, in the transmitter's
//!   channel order: `[1000, 1200, 1700, 2000]`.
//! - An object with the same array and an optional sequence number:
//!   `{"ch": [1000, 1200], "seq": 42}`.
//! - Named channels, placed through the configured channel order:
//!   `{"ail": 1500, "thr": 1000, "aux1": 1800}` (a `seq` may be added).
//! - Named channels in the engineering units of their configured unit range:
//!   `{"units": {"ail": 3.0, "ele": -2}, "seq": 5}`.
//! - Named channels normalised to -1..=1 (-1 is the channel's minimum, so
//!   throttle's zero actuation): `{"norm": {"ail": 0.2, "thr": -1}}`.
//!
//! An object form may name the output it is for: `"to": "rover"` (the
//! output's `name`). [`parse_for`] checks it as [`To`] says: a signed command
//! must name its output ([`To::Exactly`]), an unsigned one may
//! ([`To::AbsentOr`]).
//!
//! One form per command. `units` and `norm` values outside their range are
//! clamped and counted like microsecond values, never rejected (except a
//! number beyond a 64-bit float, such as `1e400`: `out_of_range` in every
//! form); see
//! [`FrameModel::units_to_ns`](crate::frame::FrameModel::units_to_ns) and
//! [`FrameModel::norm_to_ns`](crate::frame::FrameModel::norm_to_ns).
//!
//! Channels a command does not give take their configured default. Values may
//! be fractional and are kept to the nanosecond. A value outside its channel's
//! limits is clamped (and counted); a command is rejected whole, and never
//! applied, for any [`RejectReason`]. An object with the same key twice, at
//! any depth, is `duplicate_key` ([`json`]): JSON readers disagree on which
//! value counts.
//!
//! Its parts, each re-exported here:
//! - here: a parsed [`Command`], the values it may carry, and the
//!   [`SeqGate`] that drops stale ones.
//! - [`forms`]: the five forms, read into a [`Command`] for an
//!   output ([`parse_for`], [`To`]).
//! - [`json_text`]: a datagram read as JSON, strictly (no key twice), and a
//!   quick look for a key before it is read ([`may_have_key`]).
//! - [`rejection`]: why a datagram is rejected ([`RejectReason`], [`Reject`]).
//! - [`status_query`]: the status query, and the bounds on its reply.

pub mod forms;
pub mod json_text;
pub mod rejection;
pub mod status_query;

#[cfg(test)]
mod tests;

pub use forms::{parse, parse_for, To};
pub use json_text::{json, may_have_key};
pub(crate) use rejection::reject;
pub use rejection::{Reject, RejectReason};
pub use status_query::{
    padded_status_query, STATUS_QUERY, STATUS_QUERY_PADDED_LEN, STATUS_REPLY_MAX_LEN,
    STATUS_REPLY_MAX_RATIO,
};

use crate::frame::Channels;

/// Lowest value a command may carry, in microseconds (before clamping).
pub const VALUE_MIN_US: f64 = 500.0;
/// Highest value a command may carry, in microseconds (before clamping).
pub const VALUE_MAX_US: f64 = 2_500.0;

/// A parsed, valid command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Command {
    /// The sender's sequence number, if it gave one.
    pub seq: Option<u64>,
    /// Every channel's value in nanoseconds (defaults filled in, clamped).
    pub channels: Channels,
    /// How many of the given values were clamped to their channel's limits.
    pub clamped: u32,
}

/// Drops stale commands: once a command with a `seq` was applied, a command
/// whose `seq` is not greater is stale. Commands without a `seq` always pass.
#[derive(Debug, Clone, Copy, Default)]
pub struct SeqGate {
    last: Option<u64>,
}

impl SeqGate {
    /// True (and remembers `seq`) when a command with this `seq` may be applied.
    pub fn admit(&mut self, seq: Option<u64>) -> bool {
        match (seq, self.last) {
            (Some(s), Some(last)) if s <= last => false,
            (Some(s), _) => {
                self.last = Some(s);
                true
            }
            (None, _) => true,
        }
    }
}
