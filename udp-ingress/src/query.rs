//! The read-only queries a datagram may carry instead of a command
//! (`{"get": "status"}`, `{"get": "telemetry"}`), and what a query's
//! source gets: never more than [`STATUS_REPLY_MAX_RATIO`] times the query,
//! unless it lies in `ingress.status_allow`.

use crate::in_blocks;
use ipnet::IpNet;
use ppm_shared::protocol::{self, Reject, RejectReason, STATUS_REPLY_MAX_RATIO};
use serde_json::Value;
use std::net::IpAddr;

/// A read-only query a datagram may carry instead of a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Query {
    /// `{"get": "status"}`: the counters and ppmd's timing summary.
    Status,
    /// `{"get": "telemetry"}`: the status reply's `telemetry` member alone
    /// (a CRSF output's flight controller telemetry).
    Telemetry,
}

/// Recognises a query, before a datagram is parsed as a command.
///
/// `None`: not a query (no `"get"` key in a JSON object), parse it as a
/// command. `Some(Err(_))`: an object with a `get` key that is not exactly
/// `{"get": "status"}`, rejected as `bad_shape`. The parsed keys decide, so
/// `{"\u0067et": "status"}` is a status query; a command that cannot have a
/// `get` key ([`protocol::may_have_key`]) is not parsed twice.
pub fn query(datagram: &[u8]) -> Option<Result<Query, Reject>> {
    if !protocol::may_have_key(datagram, "get") {
        return None;
    }
    // Not JSON, or with a key twice: the command's parse says why.
    let Ok(Value::Object(map)) = protocol::json(datagram) else {
        return None;
    };
    let get = map.get("get")?;
    let bad = |detail: String| {
        Some(Err(Reject {
            reason: RejectReason::BadShape,
            detail,
        }))
    };
    if let Some(k) = map.keys().find(|k| *k != "get") {
        return bad(format!(
            "unexpected key `{k}` beside `get`: a query is {{\"get\": \"status\"}} (or \"telemetry\") alone"
        ));
    }
    match get.as_str() {
        Some("status") => Some(Ok(Query::Status)),
        Some("telemetry") => Some(Ok(Query::Telemetry)),
        _ => bad(format!(
            "unknown query {get}: the queries are {{\"get\": \"status\"}} and {{\"get\": \"telemetry\"}}"
        )),
    }
}

/// What a status query gets ([`status_answer`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StatusAnswer {
    /// The whole reply.
    Full,
    /// `{"pad_to": N}`: the query must be at least N bytes for the reply.
    PadTo(usize),
    /// Nothing: even `{"pad_to": N}` would be more than 3 times the query.
    Nothing,
}

/// The text of [`StatusAnswer::PadTo`].
pub fn pad_to_text(n: usize) -> String {
    format!(r#"{{"pad_to":{n}}}"#)
}

/// What a status query of `query_len` bytes from `from` gets, when the
/// reply is `reply_len` bytes: the reply when `from` lies in `status_allow`
/// or the reply is at most [`STATUS_REPLY_MAX_RATIO`] times the query;
/// otherwise `{"pad_to": N}` (N the query size that would earn the reply),
/// or nothing when even that is too large. A spoofed query never makes
/// the ingress send more than 3 times what it received.
pub fn status_answer(
    reply_len: usize,
    query_len: usize,
    from: IpAddr,
    status_allow: &[IpNet],
) -> StatusAnswer {
    if in_blocks(status_allow, from) {
        return StatusAnswer::Full;
    }
    let cap = query_len.saturating_mul(STATUS_REPLY_MAX_RATIO);
    if reply_len <= cap {
        return StatusAnswer::Full;
    }
    let need = reply_len.div_ceil(STATUS_REPLY_MAX_RATIO);
    if pad_to_text(need).len() <= cap {
        StatusAnswer::PadTo(need)
    } else {
        StatusAnswer::Nothing
    }
}
