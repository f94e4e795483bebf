//! `ppm.protocol = "sbus"`: its defaults, and every key refused with its
//! name and the fix.

use super::*;
use crate::frame::{FrameModel, Level, Protocol};

/// The model of `text` (a whole file), or the key and message of its error.
fn model(text: &str) -> Result<FrameModel, (Option<String>, String)> {
    let c = Config::parse(text).map_err(|e| (None, e.to_string()))?;
    Plan::resolve(&c)
        .map(|p| p.outputs[0].model.clone())
        .map_err(|e| (e.key().map(str::to_string), e.to_string()))
}

fn sbus(extra: &str) -> String {
    format!("[ppm]\nprotocol = 'sbus'\n{extra}")
}

#[test]
fn sbus_defaults_are_sixteen_channels_encoded_for_the_receiver() {
    let m = model(&sbus("")).unwrap();
    assert_eq!(m.protocol(), Protocol::Sbus);
    assert_eq!(m.channels(), 16);
    assert_eq!(m.names()[4..6], ["aux1", "aux2"]);
    assert_eq!(m.names()[15], "aux12");
    // `any`: every receiver, so ArduPilot's idle line: a 7 ms grid, 4 ms
    // idle line when following.
    assert_eq!(m.frame_ns(), 7_000_000);
    assert_eq!(m.follow_sync_ns(), (4_000_000, 20_000_000));
    assert_eq!(m.idle_level(), Level::High, "a plain UART's");
    assert_eq!(m.sync_window_ns().0, 3_080_000);
    // EdgeTX alone: 400 us.
    let m = model(&sbus("receiver = 'edgetx'")).unwrap();
    assert_eq!(m.follow_sync_ns(), (400_000, 20_000_000));
    // An spi output sends true SBUS, idling low.
    let m = model(&format!(
        "{}\n[ppmd]\noutput = 'spi:/dev/spidev0.0'",
        sbus("")
    ))
    .unwrap();
    assert_eq!(m.idle_level(), Level::Low);
    // The command model is PPM's: a command of any length up to 16.
    let p = crate::protocol::parse(b"[1000, 1200, 1700, 2000]", &m).unwrap();
    assert_eq!(p.channels.len(), 16);
}

#[test]
fn sbus_keys_are_refused_with_their_name_and_fix() {
    let cases: &[(&str, &str, &str)] = &[
        ("channels = 8", "ppm.channels", "16 channels"),
        ("receiver = 'opentx'", "ppm.receiver", "not modelled"),
        ("min_us = 880", "ppm.min_us", "882..=2159"),
        (
            "receiver = 'edgetx'\nmin_us = 879",
            "ppm.min_us",
            "880..=2159",
        ),
        (
            "receiver = 'ardupilot'\nmax_us = 2155",
            "ppm.max_us",
            "876..=2154",
        ),
        (
            "receiver = 'ardupilot'\n[ppm.channel.thr]\nmin_us = 875",
            "ppm.channel.thr.min_us",
            "raise",
        ),
        (
            "receiver = 'edgetx'\nfollow_sync_min_us = 319",
            "ppm.follow_sync_min_us",
            "320",
        ),
        (
            "follow_sync_min_us = 3000",
            "ppm.follow_sync_min_us",
            "3080",
        ),
        (
            "follow_sync_max_us = 60001",
            "ppm.follow_sync_max_us",
            "60000",
        ),
        (
            "follow_sync_min_us = 9000\nfollow_sync_max_us = 8000",
            "ppm.follow_sync_max_us",
            "9000",
        ),
        ("frame_us = 6000", "ppm.frame_us", "6080"),
        (
            "receiver = 'edgetx'\nframe_us = 3300",
            "ppm.frame_us",
            "3320",
        ),
        ("frame_us = 70000", "ppm.frame_us", "63000"),
        ("frame_us = nan", "ppm.frame_us", "period"),
    ];
    for (extra, key, says) in cases {
        let (k, e) = model(&sbus(extra)).unwrap_err();
        assert_eq!(k.as_deref(), Some(*key), "{extra}: {e}");
        assert!(e.contains(says), "{extra}: {e}");
    }
    // The edges of each range are taken.
    for ok in [
        "min_us = 882\nmax_us = 2159",
        "receiver = 'edgetx'\nmin_us = 880\nfollow_sync_min_us = 320\nframe_us = 3320",
        "receiver = 'ardupilot'\nmin_us = 876\nmax_us = 2154\nframe_us = 6080",
        "follow_sync_min_us = 60000\nfollow_sync_max_us = 60000\nframe_us = 63000",
    ] {
        assert!(model(&sbus(ok)).is_ok(), "{ok}: {:?}", model(&sbus(ok)));
    }
}

#[test]
fn sbus_outputs_must_carry_it_at_their_polarity() {
    let out = |o: &str, extra: &str| model(&format!("{}\n[ppmd]\noutput = '{o}'", sbus(extra)));
    assert!(out("serial:/dev/ttyAMA0", "").is_ok());
    assert!(out("serial:/dev/ttyAMA0", "idle_level = 'high'").is_ok());
    assert!(out("spi:/dev/spidev0.0", "idle_level = 'low'").is_ok());
    assert!(out("sim", "idle_level = 'low'").is_ok());
    let (k, e) = out("serial:/dev/ttyAMA0", "idle_level = 'low'").unwrap_err();
    assert_eq!(k.as_deref(), Some("ppm.idle_level"));
    assert!(e.contains("spi:") && e.contains("inverter"), "{e}");
    let (k, e) = out("spi:/dev/spidev0.0", "idle_level = 'high'").unwrap_err();
    assert_eq!(k.as_deref(), Some("ppm.idle_level"));
    assert!(e.contains("serial:") && e.contains("inverter"), "{e}");
    let (k, e) = out("gpio:gpiochip0:18", "").unwrap_err();
    assert_eq!(k.as_deref(), Some("ppmd.output"));
    assert!(
        e.contains("serial:DEVICE") && e.contains("spi:DEVICE"),
        "{e}"
    );
    // PPM refuses a serial output, and SBUS's failsafe flag.
    let (k, e) = model("[ppmd]\noutput = 'serial:/dev/ttyAMA0'").unwrap_err();
    assert_eq!(k.as_deref(), Some("ppmd.output"));
    assert!(e.contains("protocol = \"sbus\""), "{e}");
    for key in ["action", "startup"] {
        let (k, e) = model(&format!("[failsafe]\n{key} = 'flag'")).unwrap_err();
        assert_eq!(k, Some(format!("failsafe.{key}")));
        assert!(e.contains("PPM has none"), "{e}");
        assert!(model(&format!("{}\n[failsafe]\n{key} = 'flag'", sbus(""))).is_ok());
    }
    assert_eq!(
        "serial:/dev/ttyUSB0".parse(),
        Ok(OutputSpec::Serial {
            device: "/dev/ttyUSB0".into()
        })
    );
    assert!("serial:".parse::<OutputSpec>().is_err());
}

/// Two outputs of one ppmd, a PPM trainer jack and an SBUS serial port:
/// each its own protocol.
#[test]
fn ppm_and_sbus_outputs_share_a_ppmd() {
    let text = "[[outputs]]\nname = 'jack'\noutput = 'sim:a'\n[outputs.ingress]\nlisten = '127.0.0.1:5005'\n[[outputs]]\nname = 'fc'\noutput = 'serial:/dev/ttyAMA0'\n[outputs.ppm]\nprotocol = 'sbus'\nreceiver = 'betaflight'\n[outputs.ingress]\nlisten = '127.0.0.1:5006'\n";
    let plan = Plan::resolve(&Config::parse(text).unwrap()).unwrap();
    assert_eq!(plan.outputs[0].model.protocol(), Protocol::Ppm);
    assert_eq!(plan.outputs[1].model.protocol(), Protocol::Sbus);
    assert_eq!(plan.outputs[1].model.channels(), 16);
    let bad = text.replace(
        "receiver = 'betaflight'",
        "receiver = 'betaflight'\nchannels = 8",
    );
    let e = Plan::resolve(&Config::parse(&bad).unwrap()).unwrap_err();
    assert_eq!(e.key(), Some("outputs[1].ppm.channels"), "{e}");
}
