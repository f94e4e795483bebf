use super::*;

/// A sample whose newest flight mode frame says `mode`.
fn with_mode(mode: &[u8]) -> TelemetrySample {
    let mut text = mode.to_vec();
    text.push(0);
    let f = ppm_shared::crsf::frame(ppm_shared::crsf::ADDRESS_FLIGHT_CONTROLLER, 0x21, &text);
    let mut s = TelemetrySample::default();
    let t = ppm_shared::crsf::telemetry::decode_frame(&f).expect("a flight mode frame");
    s.take(&f, &t, 5);
    s.published_mono_ns = 5;
    s
}

#[test]
fn each_new_flight_mode_is_told_once() {
    let mut t = Telemetry::new("/dev/ttyAMA0".into());
    assert_eq!(t.seen(TelemetrySample::default()), None, "no mode yet");
    assert_eq!(t.seen(with_mode(b"ACRO")).as_deref(), Some("ACRO"));
    assert_eq!(t.seen(with_mode(b"ACRO")), None);
    assert_eq!(t.seen(with_mode(b"!FS!")).as_deref(), Some("!FS!"));
    assert_eq!(t.seen(with_mode(b"ACRO")).as_deref(), Some("ACRO"));
    assert_eq!(statustext("plane", "ACRO"), "ppm plane: flight mode ACRO");
    // Control bytes from the port never reach a groundstation's log.
    assert_eq!(
        t.seen(with_mode(b"A\x1b[2J\r\n")).as_deref(),
        Some("A?[2J??")
    );
}

#[test]
fn the_status_is_stale_before_any_sample_and_names_the_port() {
    let mut t = Telemetry::new("/dev/ttyAMA0".into());
    let st = t.status(10);
    assert_eq!(
        (st.state.as_str(), st.port.as_str()),
        ("stale", "/dev/ttyAMA0")
    );
    t.seen(with_mode(b"ANGL"));
    let st = t.status(1_000_005);
    assert_eq!(st.state, "receiving");
    assert_eq!(st.flight_mode.map(|f| f.mode), Some("ANGL".to_owned()));
    assert_eq!(st.age_ms, 1.0);
}
