//! The `units` and `norm` keys of `[ppm.channel.NAME]`.

use crate::config::*;
#[test]
fn unit_keys_parse_and_validate() {
    let text = "[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\nunit = 'deg'\nunit_us_min = 1100.0\nunit_us_max = 1900.0\nreverse = true\ntrim_us = -12.5\n[ppm.channel.rud]\nreverse = true\ntrim_us = 5.0";
    let m = Config::parse(text).unwrap().validate().unwrap();
    let a = m.mapping(0);
    assert_eq!(
        (a.units, a.us_lo, a.us_hi, a.reverse, a.trim_us),
        (Some((-15.0, 15.0)), 1_100.0, 1_900.0, true, -12.5)
    );
    let r = m.mapping(3);
    assert_eq!(
        (r.units, r.us_lo, r.us_hi, r.reverse, r.trim_us),
        (None, 1_000.0, 2_000.0, true, 5.0),
        "norm works on every channel: min_us..max_us"
    );
}

#[test]
fn invalid_unit_keys_are_named() {
    let r = "[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\n";
    let cases: &[(&str, &str)] = &[
        (
            "[ppm.channel.ail]\nunit_min = -15.0",
            "ppm.channel.ail.unit_max",
        ),
        (
            "[ppm.channel.ele]\nunit_max = 15.0",
            "ppm.channel.ele.unit_min",
        ),
        (
            "[ppm.channel.ail]\nunit_min = 5.0\nunit_max = 5.0",
            "ppm.channel.ail.unit_min",
        ),
        (
            "[ppm.channel.ail]\nunit_min = 6.0\nunit_max = -5.0",
            "ppm.channel.ail.unit_min",
        ),
        (
            "[ppm.channel.ail]\nunit_min = -inf\nunit_max = 5.0",
            "ppm.channel.ail.unit_min",
        ),
        (
            "[ppm.channel.ail]\nunit_min = 0.0\nunit_max = nan",
            "ppm.channel.ail.unit_max",
        ),
        (
            &format!("{r}unit_us_min = 799.0"),
            "ppm.channel.ail.unit_us_min",
        ),
        (
            &format!("{r}unit_us_max = 2200.5"),
            "ppm.channel.ail.unit_us_max",
        ),
        (
            &format!("{r}unit_us_max = nan"),
            "ppm.channel.ail.unit_us_max",
        ),
        (
            &format!("{r}unit_us_min = 2000.0"),
            "ppm.channel.ail.unit_us_min",
        ),
        (
            &format!("{r}unit_us_min = 1600.0\nunit_us_max = 1400.0"),
            "ppm.channel.ail.unit_us_min",
        ),
        (&format!("{r}trim_us = 500.5"), "ppm.channel.ail.trim_us"),
        (
            "[ppm.channel.thr]\ntrim_us = -501.0",
            "ppm.channel.thr.trim_us",
        ),
        (
            "[ppm.channel.thr]\ntrim_us = nan",
            "ppm.channel.thr.trim_us",
        ),
        (
            "[ppm.channel.thr]\nunit_us_min = 1100.0",
            "ppm.channel.thr.unit_us_min",
        ),
        ("[ppm.channel.thr]\nunit = 'deg'", "ppm.channel.thr.unit"),
    ];
    for (text, key) in cases {
        let c = Config::parse(text).unwrap_or_else(|e| panic!("{text}: {e}"));
        let e = c.validate().unwrap_err();
        assert_eq!(e.key(), Some(*key), "{text}: {e}");
        assert!(e.to_string().contains(key), "{e}");
    }
    // Limits and trim at their edges are fine.
    let ok = format!("{r}unit_us_min = 800.0\nunit_us_max = 2200.0\ntrim_us = -500.0");
    Config::parse(&ok).unwrap().validate().unwrap();
}

/// Found by fuzz/config_structured: a unit range whose width overflows
/// f64 validated, and a `units` value at its end then mapped through
/// inf / inf = NaN to a 0 ns channel period (below min_us).
#[test]
fn unit_range_wider_than_f64_is_refused() {
    for (lo, hi) in [
        ("-1e308", "1e308"),
        ("-1.7976931348623157e308", "1.7976931348623157e308"),
    ] {
        let text = format!("[ppm.channel.ail]\nunit_min = {lo}\nunit_max = {hi}");
        let e = Config::parse(&text).unwrap().validate().unwrap_err();
        assert_eq!(e.key(), Some("ppm.channel.ail.unit_max"), "{text}: {e}");
        assert!(e.to_string().contains("too wide"), "{e}");
    }
    // The widest ranges with a finite width still map within the limits.
    let text = "[ppm.channel.ail]\nunit_min = -8e307\nunit_max = 8e307";
    let m = Config::parse(text).unwrap().validate().unwrap();
    assert_eq!(m.units_to_ns(0, 8e307), Some((2_000_000, false)));
    assert_eq!(m.units_to_ns(0, f64::MAX), Some((2_000_000, true)));
    assert_eq!(m.units_to_ns(0, f64::MIN), Some((1_000_000, true)));
    let cmd = crate::protocol::parse(br#"{"units": {"ail": 1e308}}"#, &m).unwrap();
    assert_eq!(cmd.channels.as_ns()[0], 2_000_000);
}
