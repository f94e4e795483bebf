//! The status query ([`STATUS_QUERY`]), and the bounds on its reply: no
//! more than [`STATUS_REPLY_MAX_RATIO`] times the query, unless its source
//! is allowed more, and never more than [`STATUS_REPLY_MAX_LEN`] bytes.

/// The status query, as udp-ingress recognises it (whitespace around it
/// allowed, and used as padding).
pub const STATUS_QUERY: &str = r#"{"get":"status"}"#;

/// No status reply is more than this many times the size of the query that
/// asked for it, unless its source is in `ingress.status_allow`.
pub const STATUS_REPLY_MAX_RATIO: usize = 3;

/// The largest status reply, in bytes, with room to spare for counters to
/// come: a test builds the largest reply there can be (every counter at
/// u64::MAX, the longest name, ...) and checks it fits.
pub const STATUS_REPLY_MAX_LEN: usize = 4_200;

/// The size ppm's tools pad their status queries to: a third of
/// [`STATUS_REPLY_MAX_LEN`], so even the largest reply is no more than
/// [`STATUS_REPLY_MAX_RATIO`] times the query and comes to any source.
pub const STATUS_QUERY_PADDED_LEN: usize = STATUS_REPLY_MAX_LEN.div_ceil(STATUS_REPLY_MAX_RATIO);

/// [`STATUS_QUERY`] padded with spaces to [`STATUS_QUERY_PADDED_LEN`]
/// bytes: it earns the full reply from any source.
pub fn padded_status_query() -> Vec<u8> {
    let mut q = STATUS_QUERY.as_bytes().to_vec();
    q.resize(STATUS_QUERY_PADDED_LEN, b' ');
    q
}
