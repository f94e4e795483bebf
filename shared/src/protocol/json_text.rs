//! A datagram's text read as JSON ([`json`]): strictly, an object with a
//! key twice refused; and a quick look for a key before the text is read
//! ([`may_have_key`]).

use super::rejection::{reject, Reject, RejectReason};
use serde_json::Value;

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
/// Reads a datagram as JSON: `invalid_utf8` when it is not UTF-8,
/// `invalid_json` (or `out_of_range`, see [`parse_for`](super::parse_for)) when it is not
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
    // "number out of range at line L column C" (pinned by a test).
    if e.is_syntax() && detail.starts_with("number out of range") {
        return reject(
            RejectReason::OutOfRange,
            format!("{detail}: a number beyond a 64-bit float (about 1.8e308) is no channel value in any form"),
        );
    }
    reject(RejectReason::InvalidJson, detail)
}
