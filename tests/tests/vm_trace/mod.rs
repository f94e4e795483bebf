//! The kernel's `gpio:gpio_value` trace, as the real-kernel tests (x86 and
//! arm64) read it.

/// `(time_ns, level)` of every value set on global GPIO `gpio`. ftrace's
/// text output (`TASK-PID [CPU] FLAGS SECONDS.MICROS: gpio_value: N set V`)
/// has the fields with microsecond times; its raw output (`PID CPU NS type:
/// ID`) has the same events in the same order with nanosecond times. The
/// two are paired line by line, and each pair must agree to the microsecond.
pub(crate) fn sets(text: &str, raw: &str, gpio: u32) -> Vec<(u64, u8)> {
    let (text, raw) = paired_events(text, raw);
    let needle = format!("gpio_value: {gpio} set ");
    text.iter()
        .zip(&raw)
        .filter_map(|(t, r)| {
            let (head, value) = t.split_once(&needle)?;
            let stamp = head.trim_end().strip_suffix(':')?.rsplit(' ').next()?;
            let (s, us) = stamp.split_once('.')?;
            let us = s.parse::<u64>().ok()? * 1_000_000 + us.parse::<u64>().ok()?;
            let ns: u64 = r.split_whitespace().nth(2)?.parse().ok()?;
            // The text rounds to the microsecond.
            assert!(
                ns.abs_diff(us * 1_000) <= 500,
                "raw `{r}` does not pair with `{t}`"
            );
            Some((ns, value.trim().parse().ok()?))
        })
        .collect()
}

/// The event lines of a trace's text and raw renderings, which list the
/// same events in the same order.
pub(crate) fn paired_events<'a>(text: &'a str, raw: &'a str) -> (Vec<&'a str>, Vec<&'a str>) {
    let events = |s: &'a str| -> Vec<&'a str> {
        s.lines()
            .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
            .collect()
    };
    let (text, raw) = (events(text), events(raw));
    assert_eq!(
        text.len(),
        raw.len(),
        "the text and raw traces list different events"
    );
    (text, raw)
}
