//! What `ppm-send` sends: a command template with swept channels.

use crate::parse_duration;
use anyhow::{bail, Context, Result};
use ppm_shared::config::{channel_names, Config};
use ppm_shared::frame::FrameModel;
use ppm_shared::protocol::{parse_for, To, VALUE_MAX_US, VALUE_MIN_US};
use ppm_shared::MAX_CHANNELS;
use serde_json::{json, Value};
use std::time::Duration;

/// Which channel a sweep moves.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SweepChannel {
    /// By position in the frame, from 1.
    Number(usize),
    /// By name (`thr`, `aux1`, ...).
    Name(String),
}

/// `--sweep CH:MIN:MAX:PERIOD`: a channel following a triangle wave from
/// MIN (at the start) to MAX (half a period later) and back.
#[derive(Debug, Clone, PartialEq)]
pub struct Sweep {
    /// The channel.
    pub channel: SweepChannel,
    /// Value at the start of each period, us.
    pub min_us: f64,
    /// Value in the middle of each period, us.
    pub max_us: f64,
    /// Length of one period.
    pub period: Duration,
}

impl Sweep {
    /// Parses `CH:MIN:MAX:PERIOD`, e.g. `3:1000:2000:4s` or `thr:1000:1400:2.5s`.
    pub fn parse(s: &str) -> Result<Sweep> {
        let parts: Vec<&str> = s.split(':').collect();
        let [ch, min, max, period] = parts[..] else {
            bail!("`{s}` is not CH:MIN:MAX:PERIOD (e.g. 3:1000:2000:4s)");
        };
        let channel = match ch.trim().parse::<usize>() {
            Ok(n) if (1..=MAX_CHANNELS).contains(&n) => SweepChannel::Number(n),
            Ok(_) => bail!("`{s}`: channel numbers are 1..={MAX_CHANNELS}"),
            Err(_) if !ch.trim().is_empty() => SweepChannel::Name(ch.trim().to_owned()),
            Err(_) => bail!("`{s}`: no channel before the first `:`"),
        };
        let us = |v: &str, what: &str| -> Result<f64> {
            match v.trim().parse::<f64>() {
                Ok(x) if (VALUE_MIN_US..=VALUE_MAX_US).contains(&x) => Ok(x),
                _ => bail!(
                    "`{s}`: {what} `{v}` is not a value in {VALUE_MIN_US}..={VALUE_MAX_US} us"
                ),
            }
        };
        let (min_us, max_us) = (us(min, "MIN")?, us(max, "MAX")?);
        let period = parse_duration(period).with_context(|| format!("`{s}`: PERIOD"))?;
        if period.is_zero() {
            bail!("`{s}`: PERIOD must be longer than 0");
        }
        Ok(Sweep {
            channel,
            min_us,
            max_us,
            period,
        })
    }

    /// The value at `t` seconds from the start, us (to the ns).
    pub fn at(&self, t: f64) -> f64 {
        let phase = (t / self.period.as_secs_f64()).rem_euclid(1.0);
        let tri = 1.0 - (2.0 * phase - 1.0).abs();
        ((self.min_us + (self.max_us - self.min_us) * tri) * 1e3).round() / 1e3
    }
}

/// Where a swept value goes in the command.
#[derive(Debug, Clone, PartialEq)]
enum Slot {
    /// Position in the array (the bare array, or `ch`).
    Index(usize),
    /// A named channel.
    Key(String),
}

/// The command to send, with the sweeps placed in it.
#[derive(Debug, Clone, PartialEq)]
pub struct Template {
    base: Value,
    slots: Vec<(Slot, Sweep)>,
}

impl Template {
    /// From COMMAND (JSON text, if any) and the sweeps. A numbered sweep goes
    /// by position when COMMAND is an array (or `{"ch": [...]}`) that gives
    /// every channel before it; otherwise the command is in named form and
    /// the number is named through `order` (the ingress's `ppm.order`).
    pub fn new(command: Option<&str>, sweeps: &[Sweep], order: &str) -> Result<Template> {
        let base: Value = match command {
            // Read as udp-ingress reads it: a key given twice is refused.
            Some(text) => {
                ppm_shared::protocol::json(text.as_bytes()).map_err(|r| refusal(text, &r))?
            }
            None => json!({}),
        };
        if sweeps.is_empty() {
            return Ok(Template {
                base,
                slots: vec![],
            });
        }
        let positional = match &base {
            Value::Array(a) => Some(a.len()),
            Value::Object(o) => match o.get("ch") {
                Some(Value::Array(a)) => Some(a.len()),
                Some(_) => bail!("`ch` in COMMAND must be an array"),
                None => None,
            },
            other => bail!("cannot sweep in {other}: COMMAND must be an array or an object"),
        };
        let names =
            channel_names(order, MAX_CHANNELS).map_err(|e| anyhow::anyhow!("--order: {e}"))?;
        let mut sorted: Vec<&Sweep> = sweeps.iter().collect();
        sorted.sort_by_key(|s| match s.channel {
            SweepChannel::Number(n) => n,
            SweepChannel::Name(_) => 0,
        });
        let mut slots = vec![];
        let mut len = positional.unwrap_or(0);
        for s in sorted {
            let slot = match (&s.channel, positional) {
                (SweepChannel::Number(n), Some(_)) if *n <= len + 1 => {
                    len = len.max(*n);
                    Slot::Index(n - 1)
                }
                (SweepChannel::Number(n), Some(given)) => bail!(
                    "COMMAND gives {given} channels by position: sweeping channel {n} needs values for channels 1..={} first (or sweep it by name)",
                    n - 1
                ),
                (SweepChannel::Number(n), None) => Slot::Key(names[n - 1].clone()),
                (SweepChannel::Name(name), None) => {
                    if !names.contains(name) {
                        bail!(
                            "--sweep: no channel `{name}`; channels are ail, ele, thr, rud, aux1, ..."
                        );
                    }
                    Slot::Key(name.clone())
                }
                (SweepChannel::Name(name), Some(_)) => bail!(
                    "--sweep {name}: COMMAND gives channels by position; sweep by number, or give COMMAND with named channels"
                ),
            };
            if slots.iter().any(|(other, _)| *other == slot) {
                bail!("two --sweep options move the same channel");
            }
            slots.push((slot, s.clone()));
        }
        Ok(Template { base, slots })
    }

    /// The command at `t` seconds from the start.
    pub fn at(&self, t: f64) -> Value {
        let mut v = self.base.clone();
        for (slot, sweep) in &self.slots {
            let x = json!(sweep.at(t));
            match slot {
                Slot::Key(k) => v[k.as_str()] = x,
                Slot::Index(i) => {
                    let a = match &mut v {
                        Value::Array(a) => a,
                        other => other["ch"].as_array_mut().expect("checked in new"),
                    };
                    if *i < a.len() {
                        a[*i] = x;
                    } else {
                        a.push(x);
                    }
                }
            }
        }
        v
    }
}

/// The widest configuration a udp-ingress may have: 16 channels (ail, ele,
/// thr, rud, aux1..aux12, in any order the same names), each with a unit
/// range. A command it refuses, every udp-ingress refuses.
fn widest() -> &'static FrameModel {
    static MODEL: std::sync::OnceLock<FrameModel> = std::sync::OnceLock::new();
    MODEL.get_or_init(|| {
        let names = channel_names("AETR", MAX_CHANNELS).expect("the widest order");
        let mut text = format!(
            "[ppm]\ntiming = \"follow\"\nreceiver = \"edgetx\"\nchannels = {MAX_CHANNELS}\n"
        );
        for n in &names {
            text += &format!("[ppm.channel.{n}]\nunit_min = -1.0\nunit_max = 1.0\n");
        }
        Config::parse(&text)
            .and_then(|c| c.validate())
            .expect("the widest configuration is valid")
    })
}

/// Checks `command` as udp-ingress reads it, refusing what every
/// configuration refuses, with the reason the ingress would count: not UTF-8
/// or not JSON, a key twice, a value that is not a number or lies outside
/// 500..=2500 us, more than 16 values, a channel no configuration has, a
/// shape that is no command. What depends on the ingress's configuration
/// (its channel count and names, unit ranges, output name) is left to it.
pub fn check_command(command: &str) -> Result<()> {
    // A status query, or a command signed already (`{"msg": ..., "mac":
    // ...}`, its command checked inside): not commands of their own.
    if let Ok(Value::Object(map)) = ppm_shared::protocol::json(command.as_bytes()) {
        if map.contains_key("get") {
            return Ok(());
        }
        if let (Some(Value::String(msg)), true) = (map.get("msg"), map.contains_key("mac")) {
            return check_command(msg);
        }
    }
    parse_for(command.as_bytes(), widest(), To::Any)
        .map(|_| ())
        .map_err(|r| refusal(command, &r))
}

/// `command` would be refused, for reason `r`, as udp-ingress counts it.
fn refusal(command: &str, r: &ppm_shared::protocol::Reject) -> anyhow::Error {
    anyhow::anyhow!(
        "`{command}` would be refused by udp-ingress ({}): {}",
        r.reason.as_str(),
        r.detail
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_command_every_ingress_refuses_is_refused_with_its_reason() {
        for (command, reason) in [
            ("[3000]", "out_of_range"),
            (r#"[1500,"x"]"#, "not_a_number"),
            (r#"{"norm":{"thr":0,"thr":1}}"#, "duplicate_key"),
            (r#"{"yaw":1500}"#, "unknown_channel"),
            ("[1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500]", "too_many_values"),
            ("1500", "bad_shape"),
            ("{}", "bad_shape"),
            (r#"{"msg": "[3000]", "mac": "00"}"#, "out_of_range"),
        ] {
            let e = check_command(command).unwrap_err().to_string();
            assert!(e.contains(reason), "{command}: {e}");
        }
        // What some configuration takes is left to the ingress: 16
        // channels, aux12, any unit range, any output name.
        for command in [
            "[1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500,1500]",
            r#"{"aux12": 1800, "seq": 3}"#,
            r#"{"units": {"ail": 300.0}}"#,
            r#"{"norm": {"thr": -1}, "to": "rover"}"#,
            r#"{"ch": [1000, 2000]}"#,
            r#"{"get": "status"}"#,
            r#"{"msg": "{\"ch\": [1500], \"seq\": 4}", "mac": "00"}"#,
        ] {
            check_command(command).unwrap_or_else(|e| panic!("{command}: {e}"));
        }
    }

    fn sweep(s: &str) -> Sweep {
        Sweep::parse(s).unwrap()
    }

    #[test]
    fn sweeps_parse() {
        assert_eq!(
            sweep("3:1000:2000:4s"),
            Sweep {
                channel: SweepChannel::Number(3),
                min_us: 1000.0,
                max_us: 2000.0,
                period: Duration::from_secs(4)
            }
        );
        assert_eq!(
            sweep("thr:1100:1300:500ms").channel,
            SweepChannel::Name("thr".into())
        );
        for bad in [
            "3:1000:2000",
            "0:1000:2000:1s",
            "17:1000:2000:1s",
            "3:100:2000:1s",
            "3:1000:x:1s",
            "3:1000:2000:0s",
            ":1000:2000:1s",
        ] {
            assert!(Sweep::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn triangle() {
        let s = sweep("1:1000:2000:4s");
        let at: Vec<f64> = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 0.4]
            .iter()
            .map(|&t| s.at(t))
            .collect();
        assert_eq!(at, [1000.0, 1500.0, 2000.0, 1500.0, 1000.0, 1500.0, 1200.0]);
        let down = sweep("1:2000:1000:2s");
        assert_eq!(down.at(0.5), 1500.0);
        assert_eq!(down.at(1.0), 1000.0);
    }

    #[test]
    fn templates() {
        let t = |cmd: Option<&str>, sw: &[&str], order: &str| {
            let sweeps: Vec<Sweep> = sw.iter().map(|s| sweep(s)).collect();
            Template::new(cmd, &sweeps, order)
        };
        let at1 = |tpl: Template| tpl.at(1.0).to_string();
        // No COMMAND: named through the order.
        assert_eq!(
            at1(t(None, &["3:1000:2000:4s"], "AETR").unwrap()),
            r#"{"thr":1500.0}"#
        );
        assert_eq!(
            at1(t(None, &["3:1000:2000:4s"], "TAER").unwrap()),
            r#"{"ele":1500.0}"#
        );
        assert_eq!(
            at1(t(None, &["aux2:1000:2000:4s"], "AETR").unwrap()),
            r#"{"aux2":1500.0}"#
        );
        // Named COMMAND: merged.
        assert_eq!(
            at1(t(Some(r#"{"ail": 1200}"#), &["thr:1000:2000:4s"], "AETR").unwrap()),
            r#"{"ail":1200,"thr":1500.0}"#
        );
        // Positional COMMAND: replaced, or appended right after the last value.
        assert_eq!(
            at1(t(Some("[1100, 1200, 1300]"), &["2:1000:2000:4s"], "AETR").unwrap()),
            "[1100,1500.0,1300]"
        );
        assert_eq!(
            at1(t(
                Some("[1100, 1200]"),
                &["4:1000:2000:4s", "3:1000:2000:2s"],
                "AETR"
            )
            .unwrap()),
            "[1100,1200,2000.0,1500.0]"
        );
        assert_eq!(
            at1(t(
                Some(r#"{"ch": [1100], "seq": 3}"#),
                &["2:1000:2000:4s"],
                "AETR"
            )
            .unwrap()),
            r#"{"ch":[1100,1500.0],"seq":3}"#
        );
        // Refused: a gap before a positional sweep, names with positions,
        // unknown names, the same channel twice, not a command.
        assert!(t(Some("[1100]"), &["3:1000:2000:4s"], "AETR").is_err());
        assert!(t(Some("[1100]"), &["thr:1000:2000:4s"], "AETR").is_err());
        assert!(t(None, &["yaw:1000:2000:4s"], "AETR").is_err());
        assert!(t(None, &["3:1000:2000:4s", "thr:1000:2000:1s"], "AETR").is_err());
        assert!(t(Some("1500"), &["1:1000:2000:4s"], "AETR").is_err());
        assert!(t(None, &["1:1000:2000:4s"], "AEX").is_err());
        // Without sweeps COMMAND is sent as given.
        assert_eq!(at1(t(Some("1500"), &[], "AETR").unwrap()), "1500");
    }
}
