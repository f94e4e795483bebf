use super::*;
use std::path::PathBuf;

mod outputs;
mod sbus;
mod units;

#[test]
fn defaults_validate() {
    let c = Config::default();
    let m = c.validate().unwrap();
    assert_eq!(m.channels(), 8);
    assert_eq!(
        m.names(),
        ["ail", "ele", "thr", "rud", "aux1", "aux2", "aux3", "aux4"]
    );
    assert_eq!(
        m.default_ns(2),
        1_000_000,
        "throttle defaults to its minimum"
    );
    assert_eq!(m.default_ns(0), 1_500_000);
}

#[test]
fn example_file_lists_the_defaults() {
    let text = include_str!("../../../../ppm.example.toml");
    // The file writes out the keys whose default depends on the protocol:
    // PPM's, which the default configuration leaves to the model.
    let mut parsed = Config::parse(text).unwrap();
    let ppm = &mut parsed.ppm;
    assert_eq!(ppm.protocol, crate::wire::Protocol::Ppm);
    use crate::frame::section::ppm_defaults;
    assert_eq!(ppm.channels.take(), Some(ppm_defaults::CHANNELS));
    // frame_us is commented out: the example's timing is follow, where it
    // does nothing (a warning at start, were it set).
    assert_eq!(ppm.frame_us.take(), None);
    assert!(text.contains(&format!("# frame_us = {:.1}\n", ppm_defaults::FRAME_US)));
    assert_eq!(ppm.idle_level.take(), Some(crate::signal::Level::Low));
    assert_eq!(
        ppm.follow_sync_min_us.take(),
        Some(ppm_defaults::FOLLOW_SYNC_MIN_US)
    );
    assert_eq!(
        ppm.follow_sync_max_us.take(),
        Some(ppm_defaults::FOLLOW_SYNC_MAX_US)
    );
    assert_eq!(parsed, ConfigFile::default());
}

/// A config path naming a FIFO, a device or a huge file is refused at
/// once with what it is (a FIFO used to hang ppmd and udp-ingress at start).
#[test]
fn config_files_that_are_not_small_regular_files_are_refused_at_once() {
    let dir = std::env::temp_dir().join(format!("ppm-config-odd-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let fifo = dir.join("ppm.toml");
    nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
    let big = dir.join("big.toml");
    std::fs::File::create(&big)
        .unwrap()
        .set_len(crate::files::CONFIG_MAX_BYTES + 1)
        .unwrap();
    for (path, what) in [
        (fifo, "a FIFO (named pipe), not a regular file"),
        (PathBuf::from("/dev/zero"), "a character device"),
        (
            big,
            "1048577 bytes or more, and this file is never larger than 1048576",
        ),
    ] {
        let shown = path.display().to_string();
        let e = crate::files::tests::within_10s(move || Config::load(&path)).unwrap_err();
        let e = crate::logging::Chain(&e).to_string();
        assert!(
            e.contains("cannot read config file") && e.contains(&shown) && e.contains(what),
            "{e}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn empty_file_is_the_default() {
    assert_eq!(Config::parse("").unwrap(), ConfigFile::default());
}

#[test]
fn unknown_key_is_named() {
    let e = Config::parse("[ppm]\nframe_len = 20000\n").unwrap_err();
    assert!(e.to_string().contains("frame_len"), "{e}");
}

#[test]
fn rt_words_and_numbers() {
    let c = Config::parse("[rt]\ncpu = 3\nspin_margin_us = 150").unwrap();
    assert_eq!(
        (c.rt.cpu, c.rt.spin_margin_us),
        (CpuChoice::Index(3), SpinMargin::Fixed(150))
    );
    let c = Config::parse("[rt]\ncpu = 'none'\nspin_margin_us = 'auto'").unwrap();
    assert_eq!(
        (c.rt.cpu, c.rt.spin_margin_us),
        (CpuChoice::None, SpinMargin::Auto)
    );
    for (text, key) in [
        ("[rt]\ncpu = 'first'", "rt.cpu"),
        ("[rt]\ncpu = -1", "rt.cpu"),
        ("[rt]\nspin_margin_us = 'fast'", "rt.spin_margin_us"),
        ("[rt]\nspin_margin_us = 9000", "rt.spin_margin_us"),
    ] {
        let e = Config::parse(text).unwrap_err().to_string();
        assert!(e.contains(key), "{text}: {e}");
    }
}

/// Validates `[ppm]` lines under `receiver`: Ok, or the key refused.
fn under(receiver: &str, ppm: &str) -> Result<(), String> {
    let text = format!("[ppm]\nreceiver = '{receiver}'\n{ppm}");
    let c = Config::parse(&text).map_err(|e| e.to_string())?;
    c.validate()
        .map(|_| ())
        .map_err(|e| e.key().unwrap_or("?").to_string())
}

#[test]
fn receivers_bound_the_channel_count() {
    let ch = "channels";
    for (receiver, fewest, most) in [
        ("any", 5, 12),
        ("edgetx", 1, 16),
        ("opentx", 1, 16),
        ("betaflight", 4, 12),
        ("ardupilot", 5, 16),
    ] {
        // A frame long enough for 16 channels at 2000 us, short enough
        // for 1 at 1000 us under the 18.5 ms longest sync: follow timing.
        let t = "timing = 'follow'\n";
        assert_eq!(under(receiver, &format!("{t}{ch} = {fewest}")), Ok(()));
        assert_eq!(under(receiver, &format!("{t}{ch} = {most}")), Ok(()));
        let want = Err("ppm.channels".to_string());
        if fewest > 1 {
            assert_eq!(under(receiver, &format!("{t}{ch} = {}", fewest - 1)), want);
        }
        assert_eq!(under(receiver, &format!("{t}{ch} = {}", most + 1)), want);
    }
    let e = Config::parse("[ppm]\nchannels = 4")
        .unwrap()
        .validate()
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ArduPilot") && e.contains("MIN_RCIN_CHANNELS"),
        "{e}"
    );
    assert!(e.contains("5..=12"), "{e}");
}

#[test]
fn receivers_bound_the_channel_values() {
    for (receiver, lo, hi) in [
        ("any", 905.0, 2_095.0),
        ("edgetx", 820.0, 2_180.0),
        ("opentx", 821.0, 2_179.0),
        ("betaflight", 905.0, 2_095.0),
        ("ardupilot", 800.0, 2_200.0),
    ] {
        let limits = |min: f64, max: f64| {
            format!("min_us = {min}\nmax_us = {max}\ndefault_us = {min}\ntiming = 'follow'")
        };
        assert_eq!(under(receiver, &limits(lo, hi)), Ok(()), "{receiver}");
        assert_eq!(
            under(receiver, &limits(lo - 0.1, hi)),
            Err("ppm.min_us".into()),
            "{receiver}"
        );
        assert_eq!(
            under(receiver, &limits(lo, hi + 0.1)),
            Err("ppm.max_us".into()),
            "{receiver}"
        );
    }
    let e = Config::parse("[ppm.channel.ail]\nmin_us = 850.0")
        .unwrap()
        .validate()
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ppm.channel.ail.min_us")
            && e.contains("Betaflight")
            && e.contains("raise ppm.channel.ail.min_us to 905 us"),
        "{e}"
    );
}

#[test]
fn receivers_bound_the_grid_sync() {
    // 8 channels of 1000..=2000 us: 16 ms at the most, 8 at the least.
    for (receiver, shortest, longest) in [
        ("any", 4_500.0, 18_500.0),
        ("edgetx", 4_500.0, 18_500.0),
        ("opentx", 4_500.0, 18_500.0),
        // A 16-bit capture at 1 MHz, less the margin.
        ("betaflight", 3_200.0, 65_036.0),
        ("ardupilot", 3_200.0, 65_036.0),
    ] {
        let frame = |us: f64| format!("timing = 'grid'\nframe_us = {us}");
        assert_eq!(under(receiver, &frame(16_000.0 + shortest)), Ok(()));
        assert_eq!(
            under(receiver, &frame(16_000.0 + shortest - 1.0)),
            Err("ppm.frame_us".into()),
            "{receiver}"
        );
        assert_eq!(under(receiver, &frame(8_000.0 + longest)), Ok(()));
        assert_eq!(
            under(receiver, &frame(8_000.0 + longest + 1.0)),
            Err("ppm.frame_us".into())
        );
        // Follow timing's shortest sync, likewise.
        let follow = |us: f64| format!("timing = 'follow'\nfollow_sync_min_us = {us}");
        assert_eq!(under(receiver, &follow(shortest)), Ok(()));
        assert_eq!(
            under(receiver, &follow(shortest - 1.0)),
            Err("ppm.follow_sync_min_us".into())
        );
        // Either polarity: the receivers time the edges that leave idle.
        assert_eq!(under(receiver, "idle_level = 'high'"), Ok(()));
    }
    assert!(under("spektrum", "").unwrap_err().contains("spektrum"));
    // No receiver takes an endless frame (the fuzzer's 1e300).
    for r in ["any", "edgetx", "opentx", "betaflight", "ardupilot"] {
        assert_eq!(
            under(r, "timing = 'grid'\nframe_us = 1e300"),
            Err("ppm.frame_us".into()),
            "{r}"
        );
    }
}

#[test]
fn the_late_edge_guard_defaults_to_a_few_us_and_refuses_what_receivers_misread() {
    let m = Config::default().validate().unwrap();
    assert_eq!(m.late_edge_guard_ns(), 3_000);
    let m = Config::parse("[ppm]\nlate_edge_guard_us = 20.0")
        .unwrap()
        .validate()
        .unwrap();
    assert_eq!(m.late_edge_guard_ns(), 20_000);
    for v in ["0.5", "0.0", "20.5", "300.0", "nan", "-3.0"] {
        let e = Config::parse(&format!("[ppm]\nlate_edge_guard_us = {v}"))
            .unwrap()
            .validate()
            .unwrap_err();
        assert_eq!(e.key(), Some("ppm.late_edge_guard_us"), "{v}");
        assert!(e.to_string().contains("1..=20 us"), "{e}");
    }
}

#[test]
fn follow_timing_keys() {
    let c = Config::parse(
        "[ppm]\ntiming = 'follow'\nfollow_sync_min_us = 4500.0\nfollow_sync_max_us = 18500.0",
    )
    .unwrap();
    assert_eq!(c.ppm.timing, Timing::Follow);
    let m = c.validate().unwrap();
    assert_eq!(m.timing(), Timing::Follow);
    assert_eq!(m.follow_sync_ns(), (4_500_000, 18_500_000));
    assert_eq!(Config::default().ppm.timing, Timing::Follow);
    assert_eq!(
        Config::default().validate().unwrap().follow_sync_ns(),
        (5_000_000, 18_000_000)
    );
    // Follow timing does not use frame_us: 12 channels of up to 2000 us
    // need no longer frame (grid would refuse it).
    let twelve = "[ppm]\nchannels = 12\ntiming = 'follow'";
    Config::parse(twelve).unwrap().validate().unwrap();
    let e = Config::parse(&twelve.replace("follow", "grid"))
        .unwrap()
        .validate()
        .unwrap_err();
    assert_eq!(e.key(), Some("ppm.frame_us"));
    for (text, key) in [
        ("timing = 'fast'", "timing"),
        ("follow_sync_min_us = 4499.0", "ppm.follow_sync_min_us"),
        ("follow_sync_min_us = 4000.0", "ppm.follow_sync_min_us"),
        ("follow_sync_min_us = nan", "ppm.follow_sync_min_us"),
        ("follow_sync_max_us = 18501.0", "ppm.follow_sync_max_us"),
        ("follow_sync_max_us = 19000.0", "ppm.follow_sync_max_us"),
        ("follow_sync_max_us = inf", "ppm.follow_sync_max_us"),
        (
            "follow_sync_min_us = 9000.0\nfollow_sync_max_us = 8000.0",
            "ppm.follow_sync_max_us",
        ),
    ] {
        // Checked in either timing.
        for timing in ["grid", "follow"] {
            let text = format!("[ppm]\ntiming = '{timing}'\n{text}");
            let e = match Config::parse(&text) {
                Err(e) => e.to_string(),
                Ok(c) => c.validate().unwrap_err().to_string(),
            };
            assert!(e.contains(key), "{text}: {e}");
        }
    }
    assert_eq!("follow".parse(), Ok(Timing::Follow));
    assert_eq!("grid".parse(), Ok(Timing::Grid));
    assert!("Follow".parse::<Timing>().is_err());
    // Per output, and named there.
    let c = Config::parse(
        "[[outputs]]\nname = 'a'\noutput = 'sim:a'\n[[outputs]]\nname = 'b'\noutput = 'sim:b'\nppm.timing = 'follow'\nppm.follow_sync_min_us = 100.0",
    )
    .unwrap();
    let e = Plan::resolve(&c).unwrap_err();
    assert_eq!(e.key(), Some("outputs[1].ppm.follow_sync_min_us"));
    let c = Config::parse(
        "[[outputs]]\nname = 'a'\noutput = 'sim:a'\n[[outputs]]\nname = 'b'\noutput = 'sim:b'\nppm.timing = 'grid'\ningress.listen = '127.0.0.1:5006'",
    )
    .unwrap();
    let outs = Plan::resolve(&c).unwrap().outputs;
    assert_eq!(outs[0].model.timing(), Timing::Follow);
    assert_eq!(outs[1].model.timing(), Timing::Grid);
}

#[test]
fn ingress_scheduling_keys() {
    let c = Config::parse("[ingress]\npriority = 79\ncpu = 0\nbusy_poll = true").unwrap();
    c.validate().unwrap();
    assert_eq!(
        (c.ingress.priority, c.ingress.cpu, c.ingress.busy_poll),
        (79, IngressCpu::Index(0), true)
    );
    let c = Config::parse("[ingress]\ncpu = 'none'").unwrap();
    assert_eq!(c.ingress.cpu, IngressCpu::None);
    // Pinned to ppmd's CPU without busy_poll is allowed (the thread sleeps).
    Config::parse("[ingress]\ncpu = 1\n[rt]\ncpu = 1")
        .unwrap()
        .validate()
        .unwrap();
    // Values of the wrong kind are refused while parsing, naming the key.
    for (text, key) in [
        ("[ingress]\ncpu = 'last'", "ingress.cpu"),
        ("[ingress]\ncpu = -1", "ingress.cpu"),
        ("[ingress]\ncpu = 4096", "ingress.cpu"),
        ("[ingress]\nbusy_poll = 'yes'", "busy_poll"),
        ("[ingress]\nbusy_poll = 1", "busy_poll"),
        ("[ingress]\npriority = -1", "priority"),
        ("[ingress]\npriority = 'high'", "priority"),
    ] {
        let e = Config::parse(text).unwrap_err().to_string();
        assert!(e.contains(key), "{text}: {e}");
    }
    // `rt.cpu = "last"` is resolved on the machine: the caller gives it.
    let c = Config::parse("[ingress]\nbusy_poll = true\ncpu = 1").unwrap();
    let (_, out) = Plan::resolve_one(&c).unwrap();
    assert_eq!(
        out.check_busy_poll_cpu(Some(1)).unwrap_err().key(),
        Some("ingress.cpu")
    );
    out.check_busy_poll_cpu(Some(0)).unwrap();
    out.check_busy_poll_cpu(None).unwrap();
    assert_eq!("3".parse(), Ok(IngressCpu::Index(3)));
    assert_eq!("none".parse(), Ok(IngressCpu::None));
    assert!("last".parse::<IngressCpu>().is_err());
}

#[test]
fn wrong_type_is_named() {
    let e = Config::parse("[ppm]\nchannels = \"eight\"\n").unwrap_err();
    assert!(e.to_string().contains("channels"), "{e}");
}

#[test]
fn orders() {
    assert_eq!(
        channel_names("taer", 5).unwrap(),
        ["thr", "ail", "ele", "rud", "aux1"]
    );
    assert_eq!(channel_names("ATER", 2).unwrap(), ["ail", "thr"]);
    for bad in ["AETX", "AET", "AETRR", "AAER", ""] {
        let e = channel_names(bad, 4).unwrap_err();
        assert_eq!(e.key, "ppm.order", "{bad}");
    }
}

#[test]
fn output_specs() {
    assert_eq!(
        "sim".parse(),
        Ok(OutputSpec::Sim {
            path: None,
            whole: false
        })
    );
    assert_eq!(
        "sim:/tmp/x.trace".parse(),
        Ok(OutputSpec::Sim {
            path: Some("/tmp/x.trace".into()),
            whole: false
        })
    );
    assert_eq!(
        "sim-spi".parse(),
        Ok(OutputSpec::Sim {
            path: None,
            whole: true
        })
    );
    assert_eq!(
        "sim-spi:q/line.trace".parse(),
        Ok(OutputSpec::Sim {
            path: Some("q/line.trace".into()),
            whole: true
        })
    );
    assert_eq!(
        "gpio:/dev/gpiochip0:GPIO18".parse(),
        Ok(OutputSpec::Gpio {
            chip: "/dev/gpiochip0".into(),
            line: "GPIO18".into()
        })
    );
    assert_eq!(
        "spi:/dev/spidev0.0".parse(),
        Ok(OutputSpec::Spi {
            device: "/dev/spidev0.0".into()
        })
    );
    // gpio:LINE: the chip that has a line of this name.
    assert_eq!(
        "gpio:GPIO18".parse(),
        Ok(OutputSpec::Gpio {
            chip: String::new(),
            line: "GPIO18".into()
        })
    );
    for bad in ["", "sim:", "gpio:", "gpio::3", "pwm:1", "spi:"] {
        assert!(bad.parse::<OutputSpec>().is_err(), "{bad}");
    }
}

/// An spi output: its rate within bounds, only with idle_level low (the
/// gap between transfers is low), and alone on its ppmd.
#[test]
fn spi_outputs_are_checked() {
    let spi = "[ppmd]\noutput = 'spi:/dev/spidev0.0'\n";
    assert!(Config::parse(spi).unwrap().validate().is_ok());
    let key = |text: &str| {
        let c = Config::parse(text).unwrap();
        let e = Plan::resolve(&c).unwrap_err();
        (e.key().map(str::to_string), e.to_string())
    };
    for (hz, ok) in [
        (49_999, false),
        (50_000, true),
        (20_000_000, true),
        (20_000_001, false),
    ] {
        let c = Config::parse(&format!("{spi}spi_hz = {hz}")).unwrap();
        assert_eq!(c.validate().is_ok(), ok, "{hz}");
        if !ok {
            assert_eq!(c.validate().unwrap_err().key(), Some("ppmd.spi_hz"));
        }
    }
    let (k, e) = key(&format!("[ppm]\nidle_level = 'high'\n{spi}"));
    assert_eq!(k.as_deref(), Some("ppm.idle_level"));
    assert!(
        e.contains("idle_level = \"low\"") && e.contains("inverter"),
        "{e}"
    );
    // The same is fine on a gpio line.
    assert!(
        Config::parse("[ppm]\nidle_level = 'high'\n[ppmd]\noutput = 'gpio:0:18'")
            .unwrap()
            .validate()
            .is_ok()
    );
    let two = "[[outputs]]\nname = 'a'\noutput = 'spi:/dev/spidev0.0'\n[outputs.ingress]\nlisten = '127.0.0.1:5005'\n[[outputs]]\nname = 'b'\noutput = 'sim'\n[outputs.ingress]\nlisten = '127.0.0.1:5006'\n";
    let (k, e) = key(two);
    assert_eq!(k.as_deref(), Some("outputs[0].output"), "{e}");
    assert!(e.contains("runs alone"), "{e}");
}

#[test]
fn invalid_keys_are_named() {
    let cases: &[(&str, &str)] = &[
        ("name = 'a b'", "name"),
        ("[ppm]\nchannels = 0", "ppm.channels"),
        ("[ppm]\nchannels = 17", "ppm.channels"),
        ("[ppmd]\nreadback = 'spi:/dev/spidev0.0'", "ppmd.readback"),
        ("[ppmd]\nreadback = 'gpio:'", "ppmd.readback"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\n", "ppmd.pilot"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\n[ppmd]\npilot = 'spi:/dev/spidev0.0'", "ppmd.pilot"),
        ("[ppmd]\npilot = 'gpio:GPIO17'", "pilot.switch_channel"),
        ("[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 0", "pilot.switch_channel"),
        ("[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 17", "pilot.switch_channel"),
        ("[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\nchannels = 4", "pilot.switch_channel"),
        ("[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\nchannels = 17", "pilot.channels"),
        ("[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\nswitch_above_us = 899", "pilot.switch_above_us"),
        ("[ppmd]\npilot = 'gpio:GPIO17'\nreadback = 'gpio:GPIO27'\n[pilot]\nswitch_channel = 5", "ppmd.pilot"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\ncrsf_baud = 9600\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\n", "ppm.crsf_baud"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\nframe_us = 700\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\n", "ppm.frame_us"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\ncrsf_baud = 420000\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\n", "ppm.crsf_baud"),
        ("[ppm]\ncrsf_target = 'module'\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\n", "ppm.crsf_target"),
        ("[ppm]\nprotocol = 'sbus'\ncrsf_target = 'module'", "ppm.crsf_target"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\ncrsf_model_id = 64\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\n", "ppm.crsf_model_id"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\nframe_us = 50001\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\n", "ppm.frame_us"),
        ("[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\nreceiver = 'edgetx'\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5\n", "ppm.receiver"),
        (
            "[ppm]\nprotocol = 'sbus'\n[ppmd]\nreadback = 'gpio:GPIO17'",
            "ppmd.readback",
        ),
        (
            "[ppmd]\nreadback = 'gpio:GPIO17'\n[readback]\ntolerance_us = 0",
            "readback.tolerance_us",
        ),
        (
            "[ppmd]\nreadback = 'gpio:GPIO17'\n[readback]\ntolerance_us = 501",
            "readback.tolerance_us",
        ),
        (
            "[ppmd]\nreadback = 'gpio:GPIO17'\n[readback]\nwindow_ms = 9",
            "readback.window_ms",
        ),
        (
            "[ppmd]\nreadback = 'gpio:GPIO17'\n[readback]\nframes = 0",
            "readback.frames",
        ),
        (
            "[ppmd]\nreadback = 'gpio:GPIO17'\n[readback]\nframes = 11",
            "readback.frames",
        ),
        (
            "[ppmd]\nreadback = 'gpio:GPIO17'\n[readback]\nchannels = 0",
            "readback.channels",
        ),
        (
            "[ppmd]\nreadback = 'gpio:GPIO17'\n[readback]\nchannels = 17",
            "readback.channels",
        ),
        ("[ppm]\nmin_us = 700", "ppm.min_us"),
        ("[ppm]\nmax_us = 2300", "ppm.max_us"),
        (
            "[ppm]\nmin_us = 1600\ndefault_us = 1500\nmax_us = 2000",
            "ppm.default_us",
        ),
        ("[ppm]\npulse_us = 1000", "ppm.pulse_us"),
        ("[ppm]\npulse_us = 0", "ppm.pulse_us"),
        ("[ppm]\ntiming = 'grid'\nframe_us = 19000", "ppm.frame_us"),
        (
            "[ppm]\ntiming = 'grid'\nchannels = 3\nreceiver = 'edgetx'",
            "ppm.frame_us",
        ),
        ("[ppm]\nchannels = 3", "ppm.channels"),
        ("[ppm.channel.aux9]\nmin_us = 900", "ppm.channel.aux9"),
        ("[ppm.channel.ail]\nmax_us = 2250", "ppm.channel.ail.max_us"),
        (
            "[ppm.channel.ail]\nmin_us = 1900\nmax_us = 1800",
            "ppm.channel.ail.min_us",
        ),
        (
            "[ingress]\nrecv_buffer_bytes = 100",
            "ingress.recv_buffer_bytes",
        ),
        ("[ppmd]\noutput = 'pwm'", "ppmd.output"),
        ("[rt]\npriority = 100", "rt.priority"),
        ("[ppmd]\nframe_log_max_mb = 0", "ppmd.frame_log_max_mb"),
        ("[ppmd]\ntrace_max_mb = 0", "ppmd.trace_max_mb"),
        ("[ppmd]\ntrace_max_mb = 65537", "ppmd.trace_max_mb"),
        ("[rt]\nspin_margin_max_us = 6000", "rt.spin_margin_max_us"),
        (
            "[rt]\nspin_margin_min_us = 600\nspin_margin_max_us = 500",
            "rt.spin_margin_min_us",
        ),
        ("[failsafe]\nafter_ms = 0", "failsafe.after_ms"),
        ("[failsafe]\nstartup = 'hold'", "failsafe.startup"),
        ("[ipc]\nroot = 'relative'", "ipc.root"),
        (
            "[ingress]\nallow = ['10.0.0.0/24', '10.0.0.300/32']",
            "ingress.allow",
        ),
        ("[ingress]\nallow = ['10.0.0.0/33']", "ingress.allow"),
        (
            "[ingress]\nstatus_allow = ['::1/129']",
            "ingress.status_allow",
        ),
        ("[ingress]\nallow = ['localhost']", "ingress.allow"),
        ("[ingress]\npriority = 100", "ingress.priority"),
        ("[ingress]\npriority = 80", "ingress.priority"),
        (
            "[ingress]\npriority = 70\n[rt]\npriority = 60",
            "ingress.priority",
        ),
        (
            "[ingress]\npriority = 1\n[rt]\npriority = 0",
            "ingress.priority",
        ),
        (
            "[ingress]\nbusy_poll = true\ncpu = 3\n[rt]\ncpu = 3",
            "ingress.cpu",
        ),
    ];
    for (text, key) in cases {
        let c = Config::parse(text).unwrap_or_else(|e| panic!("{text}: {e}"));
        let e = c.validate().unwrap_err();
        assert_eq!(e.key(), Some(*key), "{text}: {e}");
        assert!(e.to_string().contains(key), "{e}");
    }
}

#[test]
fn sync_error_gives_the_numbers() {
    let c = Config::parse("[ppm]\ntiming = 'grid'\nframe_us = 19000\n").unwrap();
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("16000") && e.contains("4000"), "{e}");
}

#[test]
fn ingress_allow_and_seq_file() {
    let c =
        Config::parse("name = 'v1'\n[ingress]\nallow = ['10.0.0.0/24', '127.0.0.1', '::1/128']\n")
            .unwrap();
    c.validate().unwrap();
    let nets: Vec<String> = c.allow().unwrap().iter().map(|n| n.to_string()).collect();
    assert_eq!(nets, ["10.0.0.0/24", "127.0.0.1/32", "::1/128"]);
    assert_eq!(c.seq_file(), PathBuf::from("/tmp/ppm/v1.last_seq"));
    let c =
        Config::parse("[ingress]\nseq_file = '/var/lib/ppm/seq'\nauth_key = '/etc/ppm/k'").unwrap();
    assert_eq!(c.seq_file(), PathBuf::from("/var/lib/ppm/seq"));
    assert_eq!(c.ingress.auth_key, Some(PathBuf::from("/etc/ppm/k")));
    let e = Config::parse("[ingress]\nallow = ['10.1.2.3/40']")
        .unwrap()
        .validate()
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ingress.allow") && e.contains("10.1.2.3/40"),
        "{e}"
    );
}

#[test]
fn mavlink_keys_resolve_against_the_channels_or_name_the_key() {
    let plan = |text: &str| -> Result<crate::mavlink::Settings, String> {
        let c = Config::parse(text).map_err(|e| e.to_string())?;
        Plan::resolve(&c)
            .map(|p| p.outputs[0].mavlink.clone())
            .map_err(|e| e.to_string())
    };
    let s = plan("").unwrap();
    assert_eq!((s.system_id, s.component_id), (1, 1));
    assert_eq!(s.rc_channels_hz, 4);
    assert_eq!(s.vehicle_type, crate::mavlink::VehicleType::Generic);
    let rover = plan("[mavlink]\nvehicle_type = 'ground_rover'").unwrap();
    assert_eq!(rover.vehicle_type.mav_type(), 10);
    assert_eq!(
        plan("[mavlink]\nrc_channels_hz = 0")
            .unwrap()
            .rc_channels_hz,
        0
    );
    assert_eq!(
        plan("[mavlink]\nrc_channels_hz = 10")
            .unwrap()
            .rc_channels_hz,
        10
    );
    // AETR: x (pitch) ele, y (roll) ail, z thr, r rud.
    assert_eq!(s.axes, [Some(1), Some(0), Some(2), Some(3)]);
    let s = plan("[ppm]\norder = 'TAER'\n[mavlink]\nsystem_id = 42\naxes = ['none', 'ail', 'aux1', 'rud']\nbuttons = ['aux2', 'aux1']\nthrust = 'signed'").unwrap();
    assert_eq!(s.system_id, 42);
    assert_eq!(s.axes, [None, Some(1), Some(4), Some(3)]);
    assert_eq!(s.buttons, [5, 4]);
    assert_eq!(s.thrust, crate::mavlink::Thrust::Signed);
    // A frame of 2 channels (EdgeTX reads one or more): the axes it has.
    let s = plan("[ppm]\nreceiver = 'edgetx'\ntiming = 'follow'\nchannels = 2").unwrap();
    assert_eq!(s.axes, [Some(1), Some(0), None, None]);
    for (text, key) in [
        ("[mavlink]\nsystem_id = 0", "mavlink.system_id"),
        ("[mavlink]\ncomponent_id = 0", "mavlink.component_id"),
        ("[mavlink]\nsystem_id = 256", "mavlink.system_id"),
        ("[mavlink]\naxes = ['ele', 'ail', 'thr']", "mavlink.axes"),
        (
            "[mavlink]\naxes = ['ele', 'ail', 'thr', 'yaw']",
            "mavlink.axes",
        ),
        ("[mavlink]\nbuttons = ['aux9']", "mavlink.buttons"),
        ("[mavlink]\nthrust = 'unsigned'", "thrust"),
        ("[mavlink]\nsysid = 3", "sysid"),
        ("[mavlink]\nrc_channels_hz = 11", "mavlink.rc_channels_hz"),
        ("[mavlink]\nrc_channels_hz = -1", "rc_channels_hz"),
        ("[mavlink]\nvehicle_type = 'car'", "vehicle_type"),
    ] {
        let e = plan(text).unwrap_err();
        assert!(e.contains(key), "{text}: {e}");
    }
    // Each output its own system id.
    let two = "[[outputs]]\nname = 'a'\noutput = 'sim:a.trace'\n[outputs.mavlink]\nsystem_id = 2\n[[outputs]]\nname = 'b'\noutput = 'sim:b.trace'\ningress.listen = '127.0.0.1:5006'\n";
    let c = Config::parse(two).unwrap();
    let p = Plan::resolve(&c).unwrap();
    let ids: Vec<u8> = p.outputs.iter().map(|o| o.mavlink.system_id).collect();
    assert_eq!(ids, [2, 1]);
}

#[test]
fn a_pilot_and_a_module_resolve_into_their_plan() {
    use crate::capture::{CaptureSettings, InputSpec};
    use crate::wire::crsf::CrsfTarget;
    let c = Config::parse(
        "[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\n[ppmd]\noutput = 'serial:/dev/ttyUSB0'\npilot = 'sim:pilot.trace'\n[pilot]\nswitch_channel = 6\nswitch_above_us = 1700\nidle_level = 'low'\nchannels = 8",
    )
    .unwrap();
    let (_, plan) = crate::config::Plan::resolve_one(&c).unwrap();
    assert_eq!(
        plan.pilot,
        Some(crate::config::PilotPlan {
            input: InputSpec::Sim {
                path: "pilot.trace".into()
            },
            capture: CaptureSettings {
                idle: Some(crate::signal::Level::Low),
                channels: Some(8)
            },
            switch_channel: 5,
            switch_above_ns: 1_700_000,
        })
    );
    assert_eq!(plan.readback, None);
    let crate::wire::WireModel::Crsf(w) = plan.model.wire() else {
        panic!("a CRSF model");
    };
    assert_eq!(w.target(), CrsfTarget::Module);
    assert_eq!(w.uart().baud, 400_000);
    assert_eq!(w.frame_len(), 26);
    // A grid every 4 ms until the module's first correction, whatever
    // ppm.timing (follow by default) says.
    assert_eq!(plan.model.timing(), crate::signal::Timing::Grid);
    assert_eq!(plan.model.frame_ns(), 4_000_000);
    assert_eq!(
        plan.telemetry_port(),
        Some(std::path::Path::new("/dev/ttyUSB0"))
    );
    // A flight controller's CRSF: 420000, link statistics, ppm.timing.
    let c = Config::parse("[ppm]\nprotocol = 'crsf'\n").unwrap();
    let (_, plan) = crate::config::Plan::resolve_one(&c).unwrap();
    let crate::wire::WireModel::Crsf(w) = plan.model.wire() else {
        panic!("a CRSF model");
    };
    assert_eq!(
        (w.target(), w.uart().baud, w.frame_len()),
        (CrsfTarget::FlightController, 420_000, 40)
    );
    assert_eq!(plan.model.timing(), crate::signal::Timing::Follow);
    assert_eq!(plan.pilot, None);
    let e = Config::parse("[ppm]\ncrsf_target = 'fc'")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("`ppm.crsf_target`") && e.contains("`flight_controller` or `module`"),
        "{e}"
    );
}

#[test]
fn a_readback_resolves_into_its_plan() {
    use crate::capture::{CaptureSettings, InputSpec, MatchSettings};
    let c = Config::parse(
        "[ppmd]\nreadback = 'gpio:GPIO17'\nreadback_log = 'rb.jsonl'\n[readback]\ntolerance_us = 25\nwindow_ms = 60\nframes = 3\nidle_level = 'high'\nchannels = 8",
    )
    .unwrap();
    let (_, plan) = crate::config::Plan::resolve_one(&c).unwrap();
    let rb = plan.readback.expect("a read-back");
    assert_eq!(
        rb.input,
        InputSpec::Gpio {
            chip: String::new(),
            line: "GPIO17".into()
        }
    );
    assert_eq!(rb.log, Some(std::path::PathBuf::from("rb.jsonl")));
    assert_eq!(
        rb.capture,
        CaptureSettings {
            idle: Some(crate::signal::Level::High),
            channels: Some(8)
        }
    );
    assert_eq!(
        rb.matching,
        MatchSettings {
            tolerance_ns: 25_000,
            window_ns: 60_000_000,
            frames: 3
        }
    );
    // Found from the signal unless set; none without ppmd.readback.
    let c = Config::parse("[ppmd]\nreadback = 'sim:radio.trace'").unwrap();
    let (_, plan) = crate::config::Plan::resolve_one(&c).unwrap();
    let rb = plan.readback.unwrap();
    assert_eq!(rb.capture, CaptureSettings::default());
    assert_eq!(rb.matching, MatchSettings::default());
    let (_, plan) = crate::config::Plan::resolve_one(&ConfigFile::default()).unwrap();
    assert_eq!(plan.readback, None);
}
