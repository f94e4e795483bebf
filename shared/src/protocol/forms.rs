//! The five forms of a command, read into a [`Command`] against the frame
//! model ([`parse`]), for the output its `to` names ([`parse_for`], [`To`]).

use super::json_text::json;
use super::rejection::{reject, Reject, RejectReason};
use super::{Command, VALUE_MAX_US, VALUE_MIN_US};
use crate::frame::{Channels, FrameModel, MAX_CHANNELS};
use serde_json::Value;

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
