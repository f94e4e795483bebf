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
//! form); see [`FrameModel::units_to_ns`] and [`FrameModel::norm_to_ns`].
//!
//! Channels a command does not give take their configured default. Values may
//! be fractional and are kept to the nanosecond. A value outside its channel's
//! limits is clamped (and counted); a command is rejected whole, and never
//! applied, for any [`RejectReason`]. An object with the same key twice, at
//! any depth, is `duplicate_key` ([`json`]): JSON readers disagree on which
//! value counts.

use crate::frame::{Channels, FrameModel, MAX_CHANNELS};
use serde_json::Value;

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

/// The status query, as udp-ingress recognises it (whitespace around it
/// allowed, and used as padding).
pub const STATUS_QUERY: &str = r#"{"get":"status"}"#;

/// No status reply is more than this many times the size of the query that
/// asked for it, unless its source is in `ingress.status_allow`.
pub const STATUS_REPLY_MAX_RATIO: usize = 3;

/// The largest status reply, in bytes, with room to spare for counters to
/// come: a test builds the largest reply there can be (every counter at
/// u64::MAX, the longest name, ...) and checks it fits.
pub const STATUS_REPLY_MAX_LEN: usize = 3_600;

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

/// True when `datagram` may be a JSON object with the key `key`: it holds
/// `key` as a quoted string, or a backslash (an escape may spell the key, as
/// `"\u006dsg"` spells `"msg"`). False means it certainly has no such key,
/// so a command is not parsed a second time only to look; true means parse
/// and look at the parsed keys, which decide.
pub fn may_have_key(datagram: &[u8], key: &str) -> bool {
    let k = key.as_bytes();
    datagram.contains(&b'\\')
        || datagram
            .windows(k.len() + 2)
            .any(|w| w[0] == b'"' && w[k.len() + 1] == b'"' && &w[1..=k.len()] == k)
}

/// What a command's `to` (the name of the output it is for) must be.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum To<'a> {
    /// Anything, or nothing: not checked (a string if given).
    Any,
    /// Nothing, or this output's name: unsigned commands.
    AbsentOr(&'a str),
    /// This output's name: signed commands (the name in what is signed binds
    /// the command to its output).
    Exactly(&'a str),
}

/// Parses one datagram against the frame model; its `to`, if any, is not
/// checked ([`To::Any`]).
pub fn parse(datagram: &[u8], model: &FrameModel) -> Result<Command, Reject> {
    parse_for(datagram, model, To::Any)
}

/// Parses one datagram against the frame model, for the output `to` says.
///
/// The `to` is checked right after the JSON is read, before the channels:
/// a command for another output is `wrong_output` (and a signed one without
/// `to`, `no_to`) whatever that output's channels are. A `to` that is not a
/// string is `bad_shape`.
pub fn parse_for(datagram: &[u8], model: &FrameModel, to: To) -> Result<Command, Reject> {
    let value = json(datagram)?;
    check_to(&value, to)?;
    let mut b = Builder::new(model);
    let seq = match value {
        Value::Array(items) => {
            b.positional(&items)?;
            None
        }
        Value::Object(map) => {
            let seq = map.get("seq").map(parse_seq).transpose()?;
            if let Some(ch) = map.get("ch") {
                if let Some(k) = map
                    .keys()
                    .find(|k| !matches!(k.as_str(), "ch" | "seq" | "to"))
                {
                    return Err(reject(
                        RejectReason::BadShape,
                        format!("unexpected key `{k}` beside `ch`"),
                    ));
                }
                let Value::Array(items) = ch else {
                    return Err(reject(RejectReason::BadShape, "`ch` must be an array"));
                };
                b.positional(items)?;
            } else if let Some(form) = Mapped::find(&map) {
                b.mapped(form, &map)?;
            } else {
                for (k, v) in map.iter().filter(|(k, _)| *k != "seq" && *k != "to") {
                    b.set(channel_index(model, k)?, Named::Key(k), v)?;
                }
            }
            seq
        }
        other => {
            return Err(reject(
                RejectReason::BadShape,
                format!("expected an array or an object, got {}", kind(&other)),
            ))
        }
    };
    if b.given == 0 {
        return Err(reject(
            RejectReason::BadShape,
            "the command gives no channel",
        ));
    }
    Ok(Command {
        seq,
        channels: Channels::from_ns(&b.ns[..model.channels()]),
        clamped: b.clamped,
    })
}

/// Reads a datagram as JSON: `invalid_utf8` when it is not UTF-8,
/// `invalid_json` (or `out_of_range`, see [`parse_for`]) when it is not
/// JSON, and `duplicate_key` for an object that has the same key twice, at
/// any depth (keys compared as parsed, so `"\u0074hr"` is `"thr"`). JSON
/// leaves duplicates undefined and its readers disagree on which value
/// counts (serde_json, like Python's, takes the last; others the first, or
/// refuse): such a datagram has no one meaning, and ppm takes none.
///
/// serde_json has no setting for it: the value is built by `Strict`, which
/// is serde_json's own `Value` visitor with the check where a key is
/// inserted (one map lookup the insertion does anyway), so the text is read
/// once, as fast as before.
pub fn json(datagram: &[u8]) -> Result<Value, Reject> {
    let text = std::str::from_utf8(datagram)
        .map_err(|e| reject(RejectReason::InvalidUtf8, e.to_string()))?;
    let mut de = serde_json::Deserializer::from_str(text);
    let Strict(value) = serde::Deserialize::deserialize(&mut de).map_err(json_reject)?;
    // Only whitespace may follow, as serde_json::from_str checks.
    de.end().map_err(json_reject)?;
    Ok(value)
}

/// A JSON value read with every object's keys checked for duplicates
/// ([`json`]).
struct Strict(Value);

impl<'de> serde::Deserialize<'de> for Strict {
    #[inline]
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Strict, D::Error> {
        d.deserialize_any(StrictVisitor).map(Strict)
    }
}

/// serde_json's `Value` visitor, refusing a key an object already has.
struct StrictVisitor;

impl<'de> serde::de::Visitor<'de> for StrictVisitor {
    type Value = Value;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("any JSON value")
    }

    #[inline]
    fn visit_bool<E>(self, v: bool) -> Result<Value, E> {
        Ok(Value::Bool(v))
    }

    #[inline]
    fn visit_i64<E>(self, v: i64) -> Result<Value, E> {
        Ok(Value::Number(v.into()))
    }

    #[inline]
    fn visit_u64<E>(self, v: u64) -> Result<Value, E> {
        Ok(Value::Number(v.into()))
    }

    #[inline]
    fn visit_f64<E>(self, v: f64) -> Result<Value, E> {
        Ok(serde_json::Number::from_f64(v).map_or(Value::Null, Value::Number))
    }

    #[inline]
    fn visit_str<E>(self, v: &str) -> Result<Value, E> {
        Ok(Value::String(v.to_owned()))
    }

    #[inline]
    fn visit_string<E>(self, v: String) -> Result<Value, E> {
        Ok(Value::String(v))
    }

    #[inline]
    fn visit_none<E>(self) -> Result<Value, E> {
        Ok(Value::Null)
    }

    #[inline]
    fn visit_unit<E>(self) -> Result<Value, E> {
        Ok(Value::Null)
    }

    #[inline]
    fn visit_some<D: serde::Deserializer<'de>>(self, d: D) -> Result<Value, D::Error> {
        serde::Deserialize::deserialize(d).map(|Strict(v)| v)
    }

    #[inline]
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Value, A::Error> {
        let mut items = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(64));
        while let Some(Strict(v)) = seq.next_element()? {
            items.push(v);
        }
        Ok(Value::Array(items))
    }

    #[inline]
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<Value, A::Error> {
        use serde_json::map::Entry;
        let mut out = serde_json::Map::new();
        while let Some(key) = map.next_key::<String>()? {
            let Strict(v) = map.next_value()?;
            match out.entry(key) {
                Entry::Vacant(e) => {
                    e.insert(v);
                }
                Entry::Occupied(e) => {
                    return Err(serde::de::Error::custom(format_args!(
                        "{DUPLICATE_KEY} `{}`",
                        e.key()
                    )))
                }
            }
        }
        Ok(Value::Object(out))
    }
}

/// How [`StrictVisitor`]'s error starts (serde_json adds the position).
const DUPLICATE_KEY: &str = "duplicate key";

/// Checks a command's `to` against what `to` asks (see [`parse_for`]).
fn check_to(value: &Value, to: To) -> Result<(), Reject> {
    let given = match value.get("to") {
        None => None,
        Some(Value::String(s)) => Some(s.as_str()),
        Some(v) => {
            return Err(reject(
                RejectReason::BadShape,
                format!(
                    "`to` must be a string, the name of the output the command is for, got {}",
                    kind(v)
                ),
            ))
        }
    };
    match (to, given) {
        (To::Any, _) | (To::AbsentOr(_), None) => Ok(()),
        (To::AbsentOr(name) | To::Exactly(name), Some(g)) if g == name => Ok(()),
        (To::AbsentOr(name) | To::Exactly(name), Some(g)) => Err(reject(
            RejectReason::WrongOutput,
            format!("the command is for output `{g}`, this is `{name}`"),
        )),
        (To::Exactly(name), None) => Err(reject(
            RejectReason::NoTo,
            format!(
                "a signed command names the output it is for: add \"to\": \"{name}\" (ppm-send --name, ppm.Sender(name=...))"
            ),
        )),
    }
}

/// The rejection for text serde_json does not parse: `out_of_range` for a
/// number beyond a 64-bit float (`1e400`, in any form: such a number has no
/// value to clamp, so `norm` and `units` reject it too), `duplicate_key` for
/// an object with a key twice ([`json`]), `invalid_json` for anything else.
fn json_reject(e: serde_json::Error) -> Reject {
    let detail = e.to_string();
    // The only data error reading a value can have: any JSON text is a
    // `Value`, so serde_json's own are all syntax (or I/O) errors.
    if e.is_data() && detail.starts_with(DUPLICATE_KEY) {
        return reject(
            RejectReason::DuplicateKey,
            format!("{detail}: JSON readers disagree on which of the two counts, so the datagram has no one meaning; give each key once"),
        );
    }
    // serde_json has no public error code; its message for this case is
    // "number out of range at line L column C" (pinned by a test below).
    if e.is_syntax() && detail.starts_with("number out of range") {
        return reject(
            RejectReason::OutOfRange,
            format!("{detail}: a number beyond a 64-bit float (about 1.8e308) is no channel value in any form"),
        );
    }
    reject(RejectReason::InvalidJson, detail)
}

/// The index of the channel named `name`, or the rejection that lists the
/// model's channels.
fn channel_index(model: &FrameModel, name: &str) -> Result<usize, Reject> {
    model.index_of(name).ok_or_else(|| {
        reject(
            RejectReason::UnknownChannel,
            format!(
                "no channel `{name}`; channels are {}",
                model.names().join(", ")
            ),
        )
    })
}

/// How an error names a value: `channel 2` (an array's second) or `ail`.
#[derive(Clone, Copy)]
enum Named<'a> {
    Position(usize),
    Key(&'a str),
}

impl std::fmt::Display for Named<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Named::Position(i) => write!(f, "channel {}", i + 1),
            Named::Key(k) => f.write_str(k),
        }
    }
}

struct Builder<'a> {
    model: &'a FrameModel,
    ns: [u32; MAX_CHANNELS],
    given: usize,
    clamped: u32,
}

impl<'a> Builder<'a> {
    fn new(model: &'a FrameModel) -> Self {
        let mut ns = [0; MAX_CHANNELS];
        ns[..model.channels()].copy_from_slice(model.defaults().as_ns());
        Builder {
            model,
            ns,
            given: 0,
            clamped: 0,
        }
    }

    fn positional(&mut self, items: &[Value]) -> Result<(), Reject> {
        if items.len() > self.model.channels() {
            return Err(reject(
                RejectReason::TooManyValues,
                format!(
                    "{} values for {} channels",
                    items.len(),
                    self.model.channels()
                ),
            ));
        }
        for (i, v) in items.iter().enumerate() {
            self.set(i, Named::Position(i), v)?;
        }
        Ok(())
    }

    /// Sets channel `i` from `v`, named `what` in an error (formatted only
    /// then: the accepted path does not allocate for it).
    fn set(&mut self, i: usize, what: Named, v: &Value) -> Result<(), Reject> {
        let us = v.as_f64().ok_or_else(|| {
            reject(
                RejectReason::NotANumber,
                format!("{what} is {}, not a number", kind(v)),
            )
        })?;
        if !(VALUE_MIN_US..=VALUE_MAX_US).contains(&us) {
            return Err(reject(
                RejectReason::OutOfRange,
                format!("{what} = {us} us is outside {VALUE_MIN_US}..={VALUE_MAX_US}"),
            ));
        }
        let (ns, clamped) = self.model.clamp(i, (us * 1_000.0).round() as u32);
        self.ns[i] = ns;
        self.clamped += clamped as u32;
        self.given += 1;
        Ok(())
    }
}

/// The two forms whose values go through a channel's
/// [`UnitMapping`](crate::frame::UnitMapping): `{"units": {...}}` and
/// `{"norm": {...}}`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mapped {
    Units,
    Norm,
}

impl Mapped {
    /// The mapped form an object command uses, if any.
    fn find(map: &serde_json::Map<String, Value>) -> Option<Mapped> {
        if map.contains_key("units") {
            Some(Mapped::Units)
        } else if map.contains_key("norm") {
            Some(Mapped::Norm)
        } else {
            None
        }
    }

    fn key(self) -> &'static str {
        match self {
            Mapped::Units => "units",
            Mapped::Norm => "norm",
        }
    }
}

impl Builder<'_> {
    /// `{"units": {"ail": 3.0}, "seq": 5}` or `{"norm": {"thr": -1}}`: named
    /// channels whose values are mapped by the model; values outside their
    /// range are clamped and counted, never rejected.
    fn mapped(&mut self, form: Mapped, map: &serde_json::Map<String, Value>) -> Result<(), Reject> {
        let key = form.key();
        if let Some(k) = map.keys().find(|k| *k != key && *k != "seq" && *k != "to") {
            return Err(reject(
                RejectReason::BadShape,
                format!("unexpected key `{k}` beside `{key}` (one form per command)"),
            ));
        }
        let Some(Value::Object(values)) = map.get(key) else {
            return Err(reject(
                RejectReason::BadShape,
                format!("`{key}` must be an object of channel names and values"),
            ));
        };
        for (k, v) in values {
            let model = self.model;
            let i = channel_index(model, k)?;
            let x = v.as_f64().ok_or_else(|| {
                reject(
                    RejectReason::NotANumber,
                    format!("{key}.{k} is {}, not a number", kind(v)),
                )
            })?;
            let (ns, clamped) = match form {
                Mapped::Norm => model.norm_to_ns(i, x),
                Mapped::Units => model.units_to_ns(i, x).ok_or_else(|| {
                    let with: Vec<&str> = (0..model.channels())
                        .filter(|&j| model.unit_range(j).is_some())
                        .map(|j| model.names()[j].as_str())
                        .collect();
                    reject(
                        RejectReason::UnknownChannel,
                        format!(
                            "channel `{k}` has no unit range (set ppm.channel.{k}.unit_min and unit_max); channels with one: {}",
                            if with.is_empty() { "none".to_string() } else { with.join(", ") }
                        ),
                    )
                })?,
            };
            self.ns[i] = ns;
            self.clamped += clamped as u32;
            self.given += 1;
        }
        Ok(())
    }
}

fn parse_seq(v: &Value) -> Result<u64, Reject> {
    v.as_u64().ok_or_else(|| {
        reject(
            RejectReason::BadShape,
            format!("`seq` must be an unsigned integer, got {v}"),
        )
    })
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    fn model() -> FrameModel {
        Config::default().validate().unwrap()
    }

    /// The defaults plus unit ranges: ail -15..15 (deg) on 1000..2000 us,
    /// ele -20..20 on 1100..1900 us reversed, trimmed -12.5 us.
    fn units_model() -> FrameModel {
        let text = "[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\n\
            [ppm.channel.ele]\nunit_min = -20.0\nunit_max = 20.0\nunit_us_min = 1100.0\n\
            unit_us_max = 1900.0\nreverse = true\ntrim_us = -12.5";
        Config::parse(text).unwrap().validate().unwrap()
    }

    fn us(v: &[f64]) -> Vec<u32> {
        v.iter().map(|&u| (u * 1000.0).round() as u32).collect()
    }

    /// Every accept and reject rule of the wire protocol, one row each.
    #[test]
    fn table() {
        use RejectReason::*;
        let d = [
            1500.0, 1500.0, 1000.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0,
        ];
        let with = |pairs: &[(usize, f64)]| {
            let mut v = d;
            for &(i, x) in pairs {
                v[i] = x;
            }
            us(&v)
        };
        type Row = (
            &'static [u8],
            Result<(Option<u64>, Vec<u32>, u32), RejectReason>,
        );
        let rows: Vec<Row> = vec![
            // Accepted: the seed's bare array.
            (
                b"[1000, 1200, 1700, 2000]",
                Ok((
                    None,
                    with(&[(0, 1000.0), (1, 1200.0), (2, 1700.0), (3, 2000.0)]),
                    0,
                )),
            ),
            // Fractional values keep 0.1 us (and finer).
            (
                b"[1500.25, 1000.1]",
                Ok((None, with(&[(0, 1500.25), (1, 1000.1)]), 0)),
            ),
            // All eight channels.
            (b"[1,2,3,4,5,6,7,8]", Err(OutOfRange)),
            (
                b"[1100,1200,1300,1400,1500,1600,1700,1800]",
                Ok((
                    None,
                    us(&[
                        1100.0, 1200.0, 1300.0, 1400.0, 1500.0, 1600.0, 1700.0, 1800.0,
                    ]),
                    0,
                )),
            ),
            // Object form with and without seq.
            (
                br#"{"ch": [1100], "seq": 42}"#,
                Ok((Some(42), with(&[(0, 1100.0)]), 0)),
            ),
            (br#"{"ch": [1100]}"#, Ok((None, with(&[(0, 1100.0)]), 0))),
            // Named channels through the order; seq allowed.
            (
                br#"{"ail": 1600, "thr": 1200, "aux1": 1800}"#,
                Ok((None, with(&[(0, 1600.0), (2, 1200.0), (4, 1800.0)]), 0)),
            ),
            (
                br#"{"rud": 1400, "seq": 7}"#,
                Ok((Some(7), with(&[(3, 1400.0)]), 0)),
            ),
            // Clamped to min..max and counted (still applied).
            (
                b"[900, 2100, 2500, 500]",
                Ok((
                    None,
                    with(&[(0, 1000.0), (1, 2000.0), (2, 2000.0), (3, 1000.0)]),
                    4,
                )),
            ),
            // Rejected: not UTF-8.
            (b"[1500, \xff]", Err(InvalidUtf8)),
            // Rejected: not JSON.
            (b"[1500, 1500", Err(InvalidJson)),
            (b"", Err(InvalidJson)),
            (b"hello", Err(InvalidJson)),
            // Rejected: a value that is not a number.
            (br#"[1500, "1500"]"#, Err(NotANumber)),
            (b"[1500, null]", Err(NotANumber)),
            (br#"{"ail": true}"#, Err(NotANumber)),
            (br#"{"ch": [[1500]]}"#, Err(NotANumber)),
            // Rejected: outside 500..2500 us.
            (b"[499.9]", Err(OutOfRange)),
            (b"[2500.1]", Err(OutOfRange)),
            (b"[-1500]", Err(OutOfRange)),
            (b"[1e300]", Err(OutOfRange)),
            // Beyond a 64-bit float: out of range in every form, even the
            // clamped ones (there is no value to clamp).
            (b"[1e400]", Err(OutOfRange)),
            (b"[-1e400]", Err(OutOfRange)),
            (br#"{"ch": [1500, 1e400]}"#, Err(OutOfRange)),
            (br#"{"ail": 1e400}"#, Err(OutOfRange)),
            (br#"{"norm": {"thr": 1e400}}"#, Err(OutOfRange)),
            (br#"{"norm": {"thr": -1e400}}"#, Err(OutOfRange)),
            (br#"{"units": {"ail": 1e400}}"#, Err(OutOfRange)),
            // Below a 64-bit float's precision: zero, a valid value.
            (
                br#"{"norm": {"thr": 1e-400}}"#,
                Ok((None, with(&[(2, 1500.0)]), 0)),
            ),
            (br#"{"ele": 3000}"#, Err(OutOfRange)),
            // Rejected: more values than channels.
            (
                b"[1500,1500,1500,1500,1500,1500,1500,1500,1500]",
                Err(TooManyValues),
            ),
            (
                br#"{"ch": [1500,1500,1500,1500,1500,1500,1500,1500,1500]}"#,
                Err(TooManyValues),
            ),
            // Rejected: unknown channel name.
            (br#"{"aileron": 1500}"#, Err(UnknownChannel)),
            (br#"{"aux5": 1500}"#, Err(UnknownChannel)),
            // Rejected: any other shape.
            (b"1500", Err(BadShape)),
            (br#""[1500]""#, Err(BadShape)),
            (b"null", Err(BadShape)),
            (b"[]", Err(BadShape)),
            (b"{}", Err(BadShape)),
            (br#"{"seq": 3}"#, Err(BadShape)),
            (br#"{"ch": 1500}"#, Err(BadShape)),
            (br#"{"ch": [1500], "ail": 1500}"#, Err(BadShape)),
            (br#"{"ch": [1500], "seq": -1}"#, Err(BadShape)),
            (br#"{"ch": [1500], "seq": 1.5}"#, Err(BadShape)),
            (br#"{"ch": [1500], "seq": "1"}"#, Err(BadShape)),
            // Engineering units (units_model: ail -15..15 deg on 1000..2000 us,
            // ele -20..20 on 1100..1900 us reversed, trim -12.5 us).
            (
                br#"{"units": {"ail": 3.0, "ele": -2}, "seq": 5}"#,
                Ok((Some(5), with(&[(0, 1600.0), (1, 1527.5)]), 0)),
            ),
            (
                br#"{"units": {"ail": 3.0333}}"#,
                Ok((None, with(&[(0, 1601.11)]), 0)),
            ),
            // Outside the unit range: clamped and counted, not rejected.
            (
                br#"{"units": {"ail": 20, "ele": -25}}"#,
                Ok((None, with(&[(0, 2000.0), (1, 1887.5)]), 2)),
            ),
            // Normalised: -1..1 onto min_us..max_us (or unit_us_min..unit_us_max).
            (
                br#"{"norm": {"ail": 0.2, "thr": -1}, "seq": 6}"#,
                Ok((Some(6), with(&[(0, 1600.0), (2, 1000.0)]), 0)),
            ),
            (
                br#"{"norm": {"thr": 0, "rud": 1, "aux1": -0.5}}"#,
                Ok((None, with(&[(2, 1500.0), (3, 2000.0), (4, 1250.0)]), 0)),
            ),
            (
                br#"{"norm": {"ele": 1}}"#,
                Ok((None, with(&[(1, 1087.5)]), 0)),
            ),
            (
                br#"{"norm": {"rud": 1.5, "aux2": -2}}"#,
                Ok((None, with(&[(3, 2000.0), (5, 1000.0)]), 2)),
            ),
            // Rejected: a channel without a unit range in `units`, or no such channel.
            (br#"{"units": {"thr": 0.5}}"#, Err(UnknownChannel)),
            (br#"{"units": {"yaw": 1}}"#, Err(UnknownChannel)),
            (br#"{"norm": {"aileron": 0}}"#, Err(UnknownChannel)),
            // Rejected: not a number (JSON has no NaN at all).
            (br#"{"norm": {"ail": "0.2"}}"#, Err(NotANumber)),
            (br#"{"units": {"ail": null}}"#, Err(NotANumber)),
            (br#"{"norm": {"ail": [0.2]}}"#, Err(NotANumber)),
            (br#"{"norm": {"ail": NaN}}"#, Err(InvalidJson)),
            // Rejected: one form per command; the values must be an object.
            (br#"{"norm": 0.2}"#, Err(BadShape)),
            (br#"{"units": [3.0]}"#, Err(BadShape)),
            (br#"{"norm": {}}"#, Err(BadShape)),
            (br#"{"norm": {"ail": 0.2}, "ail": 1500}"#, Err(BadShape)),
            (
                br#"{"units": {"ail": 3}, "norm": {"thr": -1}}"#,
                Err(BadShape),
            ),
            (br#"{"ch": [1500], "norm": {"ail": 0}}"#, Err(BadShape)),
            (br#"{"norm": {"ail": 0}, "seq": -1}"#, Err(BadShape)),
            // `to`, the output a command is for, beside any object form
            // (parse checks no name: see to_names_the_output).
            (
                br#"{"to": "rover", "ch": [1100], "seq": 9}"#,
                Ok((Some(9), with(&[(0, 1100.0)]), 0)),
            ),
            (
                br#"{"ail": 1600, "to": "rover"}"#,
                Ok((None, with(&[(0, 1600.0)]), 0)),
            ),
            (
                br#"{"norm": {"thr": -1}, "to": "rover"}"#,
                Ok((None, with(&[(2, 1000.0)]), 0)),
            ),
            (br#"{"ch": [1500], "to": 5}"#, Err(BadShape)),
            (br#"{"ail": 1500, "to": null}"#, Err(BadShape)),
            (br#"{"to": "rover"}"#, Err(BadShape)),
            (br#"{"to": "rover", "seq": 3}"#, Err(BadShape)),
        ];
        let m = units_model();
        for (input, want) in rows {
            let got = parse(input, &m)
                .map(|c| (c.seq, c.channels.as_ns().to_vec(), c.clamped))
                .map_err(|r| r.reason);
            assert_eq!(got, want, "input {:?}", String::from_utf8_lossy(input));
        }
    }

    #[test]
    fn numbers_near_the_float_limit_are_valid_json() {
        // JSON sets no range on numbers. The largest finite doubles, spelled
        // out in full, are numbers out of range for a channel, not bad JSON
        // (serde_json's default float parser overflowed on them; found by
        // the wire_structured fuzz target).
        use RejectReason::*;
        let m = model();
        for v in [f64::MAX, -f64::MAX, 1.7e308, -9.9e307] {
            for text in [format!("[{v}]"), format!("[{v:e}]"), format!("[{v}.5]")] {
                let got = parse(text.as_bytes(), &m).map_err(|r| r.reason);
                assert_eq!(got.err(), Some(OutOfRange), "{text}");
            }
        }
        let nine = format!("[{}]", vec![f64::MAX.to_string(); 9].join(","));
        let got = parse(nine.as_bytes(), &m).map_err(|r| r.reason);
        assert_eq!(got.err(), Some(TooManyValues));
    }

    #[test]
    fn a_number_beyond_f64_is_out_of_range_and_says_so() {
        let e = parse(br#"{"norm": {"thr": 1e400}}"#, &model()).unwrap_err();
        assert_eq!(e.reason, RejectReason::OutOfRange);
        assert_eq!(
            e.to_string(),
            "out_of_range: number out of range at line 1 column 22: a number beyond a \
             64-bit float (about 1.8e308) is no channel value in any form"
        );
        // Other bad JSON stays invalid_json.
        let e = parse(b"[1e]", &model()).unwrap_err();
        assert_eq!(e.reason, RejectReason::InvalidJson, "{e}");
    }

    #[test]
    fn named_channels_follow_the_order() {
        let c = Config::parse("[ppm]\norder = 'TAER'\nchannels = 4\nreceiver = 'edgetx'").unwrap();
        let m = c.validate().unwrap();
        let cmd = parse(br#"{"thr": 1100, "rud": 1900}"#, &m).unwrap();
        assert_eq!(cmd.channels.as_ns(), us(&[1100.0, 1500.0, 1500.0, 1900.0]));
    }

    #[test]
    fn reject_detail_is_specific() {
        let e = parse(br#"{"aileron": 1500}"#, &model()).unwrap_err();
        assert!(
            e.to_string().contains("aileron") && e.to_string().contains("ail, ele"),
            "{e}"
        );
        // A mapped form names an unknown channel as the named form does.
        let named = parse(br#"{"yaw": 1500}"#, &units_model()).unwrap_err();
        let mapped = parse(br#"{"norm": {"yaw": 0}}"#, &units_model()).unwrap_err();
        assert_eq!(named.detail, mapped.detail);
        assert!(named
            .detail
            .starts_with("no channel `yaw`; channels are ail, ele"));
        let e = parse(b"[1500, 9000]", &model()).unwrap_err();
        assert!(e.to_string().contains("channel 2"), "{e}");
    }

    #[test]
    fn units_reject_detail_names_the_fix() {
        let e = parse(br#"{"units": {"thr": 0.5}}"#, &units_model()).unwrap_err();
        let e = e.to_string();
        assert!(
            e.contains("`thr` has no unit range")
                && e.contains("ppm.channel.thr.unit_min")
                && e.contains("ail, ele"),
            "{e}"
        );
        let e = parse(br#"{"norm": {"ail": 0}, "ele": 1500}"#, &model()).unwrap_err();
        assert!(e.to_string().contains("beside `norm`"), "{e}");
    }

    #[test]
    fn a_key_may_be_present_when_quoted_or_escaped() {
        assert!(may_have_key(br#"{"get":"status"}"#, "get"));
        assert!(may_have_key(br#"{"\u0067et":"status"}"#, "get"));
        assert!(!may_have_key(br#"{"ail":1500,"target":1}"#, "get"));
        assert!(!may_have_key(b"[1500, 1000]", "msg"));
        assert!(!may_have_key(br#"{"ms":1}"#, "msg"));
        assert!(
            may_have_key(br#"["msg"]"#, "msg"),
            "a quoted string, parsed to look"
        );
    }

    #[test]
    fn escaped_channel_names_are_the_names_they_spell() {
        let m = model();
        let plain = parse(br#"{"ch":[1100],"seq":3}"#, &m).unwrap();
        assert_eq!(
            parse(br#"{"\u0063h":[1100],"s\u0065q":3}"#, &m).unwrap(),
            plain
        );
        assert_eq!(
            parse(br#"{"\u0061il":1100}"#, &m).unwrap(),
            parse(br#"{"ail":1100}"#, &m).unwrap()
        );
    }

    #[test]
    fn to_names_the_output() {
        use RejectReason::*;
        let m = model();
        let reason = |d: &[u8], to: To| parse_for(d, &m, to).map(|c| c.seq).map_err(|r| r.reason);
        let rover = br#"{"ch":[1100],"seq":5,"to":"rover"}"#;
        let plane = br#"{"ch":[1100],"seq":5,"to":"plane"}"#;
        let none = br#"{"ch":[1100],"seq":5}"#;
        // Signed commands: exactly this output's name.
        assert_eq!(reason(rover, To::Exactly("rover")), Ok(Some(5)));
        assert_eq!(reason(plane, To::Exactly("rover")), Err(WrongOutput));
        assert_eq!(reason(none, To::Exactly("rover")), Err(NoTo));
        assert_eq!(reason(b"[1100]", To::Exactly("rover")), Err(NoTo));
        assert_eq!(
            reason(br#"{"ch":[1100],"to":"Rover"}"#, To::Exactly("rover")),
            Err(WrongOutput),
            "names are compared exactly"
        );
        // Unsigned commands: this output's name, or none.
        assert_eq!(reason(rover, To::AbsentOr("rover")), Ok(Some(5)));
        assert_eq!(reason(none, To::AbsentOr("rover")), Ok(Some(5)));
        assert_eq!(reason(b"[1100]", To::AbsentOr("rover")), Ok(None));
        assert_eq!(reason(plane, To::AbsentOr("rover")), Err(WrongOutput));
        // Not checked.
        assert_eq!(reason(plane, To::Any), Ok(Some(5)));
        // `to` is checked before the channels: a copy of a command for an
        // output with other channels is wrong_output, not unknown_channel.
        let other_model = br#"{"aux7":1100,"seq":6,"to":"plane"}"#;
        assert_eq!(reason(other_model, To::Any), Err(UnknownChannel));
        assert_eq!(reason(other_model, To::Exactly("rover")), Err(WrongOutput));
        assert_eq!(
            reason(br#"{"aux7":1100,"seq":6}"#, To::Exactly("rover")),
            Err(NoTo)
        );
        // A `to` that is no string is bad_shape, whatever is asked.
        for to in [To::Any, To::AbsentOr("rover"), To::Exactly("rover")] {
            assert_eq!(
                reason(br#"{"ch":[1100],"to":["rover"]}"#, to),
                Err(BadShape)
            );
        }
        // Escaped, `to` is the key it spells.
        assert_eq!(
            reason(br#"{"ch":[1100],"t\u006f":"plane"}"#, To::Exactly("rover")),
            Err(WrongOutput)
        );
        // The detail says which output the command was for, and the fix.
        let e = parse_for(plane, &m, To::Exactly("rover")).unwrap_err();
        assert_eq!(
            e.to_string(),
            "wrong_output: the command is for output `plane`, this is `rover`"
        );
        let e = parse_for(none, &m, To::Exactly("rover")).unwrap_err();
        assert!(e.detail.contains(r#""to": "rover""#), "{e}");
    }

    /// The same key twice, at the top or in a nested object, whatever the
    /// form, spelled alike or escaped: `duplicate_key`, never the last one
    /// flown (serde_json's `Value` takes the last, silently). Alike keys in
    /// different objects, and alike values, are no duplicates.
    #[test]
    fn a_key_given_twice_is_refused_at_any_depth() {
        let m = units_model();
        for d in [
            r#"{"thr": 1000, "thr": 2000}"#,
            r#"{"thr": 1000, "ail": 1500, "thr": 1000}"#,
            r#"{"ch": [1500], "seq": 1, "seq": 2}"#,
            r#"{"seq": 1, "ch": [1500], "seq": 1}"#,
            r#"{"ch": [1500], "ch": [1600]}"#,
            r#"{"ch": [1500], "to": "rover", "to": "plane"}"#,
            r#"{"norm": {"ail": 0.2, "ail": -1}}"#,
            r#"{"norm": {"thr": -1}, "norm": {"thr": 1}}"#,
            r#"{"units": {"ail": 3.0, "ele": 1, "ail": -3.0}, "seq": 5}"#,
            r#"{"thr": 1000, "\u0074hr": 2000}"#,
            r#"[1500, {"a": 1, "a": 2}]"#,
            r#"{"get": "status", "get": "status"}"#,
        ] {
            let e = parse(d.as_bytes(), &m).unwrap_err();
            assert_eq!(e.reason, RejectReason::DuplicateKey, "{d}: {e}");
            assert!(e.detail.starts_with("duplicate key `"), "{d}: {e}");
            assert_eq!(json(d.as_bytes()).unwrap_err(), e, "{d}");
        }
        // The detail names the key and where the second one ends.
        let e = parse(br#"{"norm": {"ail": 0.2, "ail": -1}}"#, &m).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("duplicate_key: duplicate key `ail` at line 1 column "),
            "{e}"
        );
        // Once per object: the same names in two objects, or values alike.
        for d in [
            r#"{"norm": {"ail": 0.2}, "seq": 1}"#,
            r#"{"ail": 1500, "ele": 1500}"#,
            r#"{"ch": [1500, 1500], "seq": 1}"#,
        ] {
            assert!(parse(d.as_bytes(), &m).is_ok(), "{d}");
        }
        assert_eq!(
            json(br#"[{"a": 1}, {"a": 1, "b": {"a": 2}}]"#).unwrap(),
            serde_json::json!([{"a": 1}, {"a": 1, "b": {"a": 2}}])
        );
        // A fault before the second key is what the datagram is refused for.
        let e = parse(br#"{"thr": 1000, "ail": x, "thr": 2000}"#, &m).unwrap_err();
        assert_eq!(e.reason, RejectReason::InvalidJson, "{e}");
        let e = parse(br#"{"thr": 1000, "thr": 2000, "ail": x}"#, &m).unwrap_err();
        assert_eq!(e.reason, RejectReason::DuplicateKey, "{e}");
    }

    /// [`json`] reads what serde_json reads, to the same value: numbers in
    /// every spelling, escapes, nesting, trailing whitespace; and refuses
    /// what it refuses, with the same reason.
    #[test]
    fn json_reads_as_serde_json_does() {
        for d in [
            "[1500, -1, 0, -0, 1.5, 1e3, 18446744073709551615, 18446744073709551616, -9223372036854775809]",
            r#"{"a": [null, true, false, "s\u00e9\n", {}], "b": {"c": [[]]}}  "#,
            "\t 7 \n",
            r#""x""#,
            "1e-400",
            "-1.7976931348623157e308",
        ] {
            let want: Value = serde_json::from_str(d).unwrap();
            assert_eq!(json(d.as_bytes()).unwrap(), want, "{d}");
        }
        for (d, reason) in [
            ("[1500] x", RejectReason::InvalidJson),
            ("", RejectReason::InvalidJson),
            ("[1e400]", RejectReason::OutOfRange),
            ("{\"a\": 1,}", RejectReason::InvalidJson),
            ("\u{ff}", RejectReason::InvalidJson),
        ] {
            assert!(serde_json::from_str::<Value>(d).is_err(), "{d}");
            assert_eq!(json(d.as_bytes()).unwrap_err().reason, reason, "{d}");
        }
        // Nesting deeper than serde_json's limit (128) is refused, not a
        // stack overflow.
        let deep = format!("{}{}", "[".repeat(10_000), "]".repeat(10_000));
        assert_eq!(
            json(deep.as_bytes()).unwrap_err().reason,
            RejectReason::InvalidJson
        );
    }

    #[test]
    fn seq_gate() {
        let mut g = SeqGate::default();
        assert!(g.admit(None));
        assert!(g.admit(Some(5)));
        assert!(!g.admit(Some(5)));
        assert!(!g.admit(Some(4)));
        assert!(g.admit(None));
        assert!(g.admit(Some(6)));
        assert!(g.admit(Some(u64::MAX)));
        assert!(!g.admit(Some(0)));
    }

    #[test]
    fn reasons_are_listed_in_index_order_with_unique_names() {
        for (i, r) in RejectReason::ALL.iter().enumerate() {
            assert_eq!(r.index(), i, "{r:?}");
        }
        let mut names: Vec<&str> = RejectReason::ALL.iter().map(|r| r.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), RejectReason::ALL.len());
    }
}
