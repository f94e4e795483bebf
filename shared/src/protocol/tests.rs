//! Tests of the wire protocol: every accept and reject rule in one table,
//! the forms' details, strict JSON, `to`, and the seq gate.

use super::*;
use crate::config::Config;
use crate::frame::FrameModel;
use serde_json::Value;

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
