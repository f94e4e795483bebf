//! Helpers shared by the ppm tools.

pub mod analysis;
pub mod cyclic;
/// SVG pictures of latency: histograms with percentile marks, percentile curves.
pub mod plot;
pub mod send;
pub mod status;

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
}
