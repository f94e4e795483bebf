//! Helpers shared by the ppm tools.
//!
//! - [`analysis`]: exact statistics of a recorded waveform.
//! - [`cyclic`]: latency statistics in cyclictest's formats (jitter's output).
//! - [`harness`]: ppm's programs run as separate processes (`ppm-bench`
//!   and the whole-system tests).
//! - [`interfere`]: a higher-priority thread that holds ppmd's CPU busy.
//! - [`plot`]: SVG pictures of latency.
//! - [`send`]: what `ppm-send` sends.
//! - [`status`]: status queries to udp-ingress, and their replies made readable.

pub mod analysis;
pub mod cyclic;
pub mod harness;
pub mod interfere;
pub mod module;
/// SVG pictures of latency: histograms with percentile marks, percentile curves.
pub mod plot;
pub mod radio;
pub mod send;
pub mod status;
pub mod web;

use anyhow::{bail, Result};
use std::time::Duration;

/// Parses a duration with a unit: `250ms`, `2s`, `1.5s`, `500us`; a bare
/// number is seconds.
pub fn parse_duration(s: &str) -> Result<Duration> {
    let s = s.trim();
    let (num, scale) = if let Some(n) = s.strip_suffix("ms") {
        (n, 1e-3)
    } else if let Some(n) = s.strip_suffix("us") {
        (n, 1e-6)
    } else if let Some(n) = s.strip_suffix('s') {
        (n, 1.0)
    } else {
        (s, 1.0)
    };
    match num.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(Duration::from_secs_f64(v * scale)),
        _ => bail!("`{s}` is not a duration (e.g. 500ms, 2s, 1.5)"),
    }
}

/// Adds `"seq": seq` to a JSON command: an array becomes `{"ch": [...], "seq": N}`,
/// an object gets (or replaces) its `seq`.
pub fn with_seq(command: &serde_json::Value, seq: u64) -> Result<serde_json::Value> {
    use serde_json::{json, Value};
    Ok(match command {
        Value::Array(a) => json!({"ch": a, "seq": seq}),
        Value::Object(o) => {
            let mut o = o.clone();
            o.insert("seq".into(), json!(seq));
            Value::Object(o)
        }
        other => bail!("cannot add a seq to {other}: a command is an array or an object"),
    })
}

/// Adds `"to": name` (the output the command is for) to a JSON command: an
/// array becomes `{"ch": [...], "to": NAME}`, an object gets its `to`. A
/// command that already names another output is refused.
pub fn with_to(command: &serde_json::Value, name: &str) -> Result<serde_json::Value> {
    use serde_json::{json, Value};
    Ok(match command {
        Value::Array(a) => json!({"ch": a, "to": name}),
        Value::Object(o) => {
            match o.get("to") {
                None => {}
                Some(Value::String(s)) if s == name => {}
                Some(other) => bail!(
                    "the command's `to` is {other}, but it is sent for output `{name}` (--name)"
                ),
            }
            let mut o = o.clone();
            o.insert("to".into(), json!(name));
            Value::Object(o)
        }
        other => {
            bail!("cannot add an output name to {other}: a command is an array or an object")
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations() {
        assert_eq!(parse_duration("250ms").unwrap(), Duration::from_millis(250));
        assert_eq!(parse_duration("2s").unwrap(), Duration::from_secs(2));
        assert_eq!(parse_duration("1.5").unwrap(), Duration::from_millis(1500));
        assert_eq!(parse_duration("500us").unwrap(), Duration::from_micros(500));
        assert!(parse_duration("-1s").is_err());
        assert!(parse_duration("fast").is_err());
    }

    #[test]
    fn seq_is_added() {
        let a: serde_json::Value = serde_json::from_str("[1000, 1200]").unwrap();
        assert_eq!(
            with_seq(&a, 7).unwrap().to_string(),
            r#"{"ch":[1000,1200],"seq":7}"#
        );
        let o: serde_json::Value = serde_json::from_str(r#"{"ail":1500,"seq":1}"#).unwrap();
        assert_eq!(with_seq(&o, 9).unwrap()["seq"], 9);
        assert!(with_seq(&serde_json::json!(5), 1).is_err());
    }

    #[test]
    fn output_name_is_added() {
        let v = |t: &str| serde_json::from_str::<serde_json::Value>(t).unwrap();
        let a = with_to(&v("[1000, 1200]"), "rover").unwrap();
        assert_eq!(a.to_string(), r#"{"ch":[1000,1200],"to":"rover"}"#);
        assert_eq!(
            with_seq(&a, 7).unwrap().to_string(),
            r#"{"ch":[1000,1200],"seq":7,"to":"rover"}"#
        );
        assert_eq!(
            with_to(&v(r#"{"thr":1000,"to":"rover"}"#), "rover")
                .unwrap()
                .to_string(),
            r#"{"thr":1000,"to":"rover"}"#
        );
        let e = with_to(&v(r#"{"thr":1000,"to":"plane"}"#), "rover").unwrap_err();
        assert_eq!(
            e.to_string(),
            r#"the command's `to` is "plane", but it is sent for output `rover` (--name)"#
        );
        assert!(with_to(&v("5"), "rover").is_err());
    }
}
