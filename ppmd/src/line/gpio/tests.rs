use super::*;

fn chip(n: u32, label: &str, lines: u32) -> ChipSummary {
    ChipSummary {
        path: format!("/dev/gpiochip{n}").into(),
        name: format!("gpiochip{n}"),
        label: label.into(),
        num_lines: lines,
        unreadable: None,
    }
}

fn pi4() -> Vec<ChipSummary> {
    vec![
        chip(0, "pinctrl-bcm2711", 58),
        chip(1, "raspberrypi-exp-gpio", 8),
    ]
}

fn line(offset: Offset, name: &str) -> LineInfo {
    LineInfo {
        offset,
        name: name.into(),
        ..Default::default()
    }
}

fn bcm_lines() -> Vec<LineInfo> {
    (0..58).map(|o| line(o, &format!("GPIO{o}"))).collect()
}

#[test]
fn gpio_chip_spec_parses_path_name_label_and_number() {
    assert_eq!(
        ChipSpec::parse("/dev/gpiochip0"),
        ChipSpec::Path("/dev/gpiochip0".into())
    );
    assert_eq!(
        ChipSpec::parse("gpiochip0"),
        ChipSpec::NameOrLabel("gpiochip0".into())
    );
    assert_eq!(
        ChipSpec::parse("pinctrl-rp1"),
        ChipSpec::NameOrLabel("pinctrl-rp1".into())
    );
    assert_eq!(
        ChipSpec::parse("4"),
        ChipSpec::NameOrLabel("gpiochip4".into())
    );
}

#[test]
fn gpio_line_spec_parses_offset_and_name() {
    assert_eq!(LineSpec::parse("18"), LineSpec::Offset(18));
    assert_eq!(LineSpec::parse("GPIO18"), LineSpec::Name("GPIO18".into()));
    assert_eq!(LineSpec::parse("+18"), LineSpec::Name("+18".into()));
    assert_eq!(LineSpec::parse("-1"), LineSpec::Name("-1".into()));
}

#[test]
fn gpio_find_chip_by_path_name_and_label() {
    let chips = pi4();
    assert_eq!(
        find_chip("/dev/gpiochip1", &chips).unwrap().name,
        "gpiochip1"
    );
    assert_eq!(find_chip("gpiochip1", &chips).unwrap().name, "gpiochip1");
    assert_eq!(find_chip("1", &chips).unwrap().name, "gpiochip1");
    assert_eq!(
        find_chip("pinctrl-bcm2711", &chips).unwrap().path,
        Path::new("/dev/gpiochip0")
    );
}

#[test]
fn gpio_find_chip_prefers_name_over_label() {
    let chips = vec![chip(0, "gpiochip1", 4), chip(1, "x", 4)];
    assert_eq!(find_chip("gpiochip1", &chips).unwrap().name, "gpiochip1");
}

#[test]
fn gpio_find_chip_unknown_lists_the_chips() {
    let e = find_chip("pinctrl-rp1", &pi4()).unwrap_err();
    assert!(matches!(e, GpioError::NoSuchChip { .. }));
    let msg = e.to_string();
    assert!(msg.contains("`pinctrl-rp1`"), "{msg}");
    assert!(
        msg.contains("/dev/gpiochip0 (gpiochip0, pinctrl-bcm2711, 58 lines)"),
        "{msg}"
    );
    assert!(
        msg.contains("/dev/gpiochip1 (gpiochip1, raspberrypi-exp-gpio, 8 lines)"),
        "{msg}"
    );
    let e = find_chip("/dev/gpiochip7", &pi4()).unwrap_err();
    assert!(matches!(e, GpioError::NoSuchChip { .. }));
}

#[test]
fn gpio_find_chip_with_no_chips_says_none_found() {
    let msg = find_chip("gpiochip0", &[]).unwrap_err().to_string();
    assert!(msg.contains("no GPIO chips found"), "{msg}");
    assert!(msg.contains("CONFIG_GPIO_CDEV"), "{msg}");
}

#[test]
fn gpio_find_chip_shared_label_is_ambiguous() {
    let chips = vec![chip(0, "gpio-sim", 4), chip(1, "gpio-sim", 4)];
    let e = find_chip("gpio-sim", &chips).unwrap_err();
    assert!(matches!(&e, GpioError::AmbiguousChip { matches, .. } if matches.len() == 2));
    assert!(e.to_string().contains("/dev/gpiochip1"));
}

#[test]
fn gpio_find_chip_unreadable_is_permission_denied() {
    let mut chips = pi4();
    chips[0].unreadable = Some(Errno::EACCES);
    assert_eq!(
        chips[0].to_string(),
        "/dev/gpiochip0 (gpiochip0, cannot open: EACCES: Permission denied)"
    );
    let e = find_chip("gpiochip0", &chips).unwrap_err();
    assert!(matches!(e, GpioError::PermissionDenied { .. }), "{e}");
    chips[0].unreadable = Some(Errno::ENOTTY);
    let e = find_chip("gpiochip0", &chips).unwrap_err();
    assert!(matches!(e, GpioError::NoCdev { .. }), "{e}");
}

#[test]
fn gpio_find_line_by_offset_and_name() {
    let c = &pi4()[0];
    let lines = bcm_lines();
    assert_eq!(find_line(c, "18", &lines).unwrap().offset, 18);
    assert_eq!(find_line(c, "GPIO18", &lines).unwrap().offset, 18);
    assert_eq!(find_line(c, "gpio18", &lines).unwrap().offset, 18);
    assert_eq!(find_line(c, "0", &lines).unwrap().name, "GPIO0");
}

#[test]
fn gpio_find_line_case_insensitive_only_when_unique() {
    let c = chip(0, "", 2);
    let lines = vec![line(0, "led"), line(1, "LED")];
    assert_eq!(find_line(&c, "LED", &lines).unwrap().offset, 1);
    assert!(find_line(&c, "Led", &lines).is_err());
}

#[test]
fn gpio_find_line_unknown_names_count_and_examples() {
    let c = &pi4()[0];
    let lines = bcm_lines();
    let e = find_line(c, "58", &lines).unwrap_err();
    assert!(matches!(e, GpioError::NoSuchLine { num_lines: 58, .. }));
    let msg = e.to_string();
    assert!(msg.contains("`58`"), "{msg}");
    assert!(msg.contains("gpiochip0 (pinctrl-bcm2711)"), "{msg}");
    assert!(msg.contains("58 lines (offsets 0..=57)"), "{msg}");
    assert!(msg.contains("GPIO0, GPIO1"), "{msg}");
    assert!(msg.contains("GPIO7, ..."), "{msg}");
    assert!(!msg.contains("GPIO8"), "{msg}");

    let unnamed: Vec<_> = (0..4).map(|o| line(o, "")).collect();
    let msg = find_line(&chip(2, "gpio-sim.0-node0", 4), "GPIO1", &unnamed)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("no names, so give an offset"), "{msg}");
    assert!(msg.contains("4 lines (offsets 0..=3)"), "{msg}");
}

#[test]
fn gpio_error_messages_name_chip_line_and_fix() {
    let busy = GpioError::Busy {
        chip: "gpiochip0".into(),
        line: "GPIO18 (offset 18)".into(),
        consumer: "pwm".into(),
    }
    .to_string();
    assert!(
        busy.starts_with("GPIO18 (offset 18) on gpiochip0 is in use by `pwm`"),
        "{busy}"
    );
    assert!(busy.contains("pick another line"), "{busy}");
    let kernel = GpioError::Busy {
        chip: "gpiochip0".into(),
        line: "GPIO18 (offset 18)".into(),
        consumer: String::new(),
    }
    .to_string();
    assert!(kernel.contains("in use by the kernel"), "{kernel}");

    let perm = GpioError::PermissionDenied {
        chip: "gpiochip0".into(),
        path: "/dev/gpiochip0".into(),
    }
    .to_string();
    assert!(perm.contains("/dev/gpiochip0"), "{perm}");
    assert!(perm.contains("sudo usermod -aG gpio $USER"), "{perm}");
    assert!(perm.contains("udev rule"), "{perm}");

    let cdev = GpioError::NoCdev {
        chip: "gpiochip0".into(),
        errno: Errno::ENOTTY,
    }
    .to_string();
    assert!(cdev.contains("gpiochip0"), "{cdev}");
    assert!(cdev.contains("CONFIG_GPIO_CDEV"), "{cdev}");
    assert!(cdev.contains("ENOTTY"), "{cdev}");

    let failed = GpioError::Failed {
        chip: "gpiochip0".into(),
        line: Some("GPIO18 (offset 18)".into()),
        op: "requesting the line as an output",
        detail: "EIO".into(),
    }
    .to_string();
    assert_eq!(
        failed,
        "GPIO chip gpiochip0, GPIO18 (offset 18): requesting the line as an output failed: EIO"
    );
}

#[test]
fn gpio_open_missing_chip_is_no_such_chip() {
    let e = open("gpiochip99", "3", Level::Low).unwrap_err();
    assert!(matches!(e, GpioError::NoSuchChip { .. }), "{e}");
    assert!(e.to_string().contains("gpiochip99"), "{e}");
    let e = open("/nonexistent/gpiochip0", "3", Level::Low).unwrap_err();
    assert!(matches!(e, GpioError::NoSuchChip { .. }), "{e}");
}

#[test]
fn gpio_open_non_gpio_device_is_not_a_chip() {
    let e = open("/dev/null", "0", Level::Low).unwrap_err();
    assert!(matches!(e, GpioError::NotAChip { .. }), "{e}");
    assert!(e.to_string().contains("/dev/null"), "{e}");
}

#[test]
fn gpio_describe_chips_matches_the_system() {
    let chips = list_chips();
    let text = describe_chips();
    if chips.is_empty() {
        assert_eq!(text, "no GPIO chips found");
    } else {
        assert!(text.contains(&chips[0].path.display().to_string()));
    }
}

#[test]
fn gpio_errno_mapping() {
    let uapi = |n: Errno| {
        gpiocdev::Error::Uapi(
            gpiocdev::UapiCall::GetLine,
            gpiocdev_uapi::Error::Os(gpiocdev_uapi::Errno(n as i32)),
        )
    };
    assert_eq!(errno_of(&uapi(Errno::EBUSY)), Some(Errno::EBUSY));
    assert_eq!(write_errno(&uapi(Errno::ENOTTY)), Errno::ENOTTY);
    let under = gpiocdev::Error::Uapi(
        gpiocdev::UapiCall::GetLineValues,
        gpiocdev_uapi::Error::UnderRead(gpiocdev_uapi::v2::UnderReadError {
            obj: "x",
            expected: 8,
            found: 0,
        }),
    );
    assert_eq!(errno_of(&under), None);
    assert_eq!(write_errno(&under), Errno::EIO);
    let no_code = gpiocdev::Error::from(std::io::Error::other("x"));
    assert_eq!(errno_of(&no_code), None);
    let os = gpiocdev::Error::from(std::io::Error::from_raw_os_error(libc_eacces()));
    assert_eq!(errno_of(&os), Some(Errno::EACCES));
    assert_eq!(write_errno(&os), Errno::EACCES);
    let other = gpiocdev::Error::InvalidArgument("x".into());
    assert_eq!(errno_of(&other), None);
    assert_eq!(write_errno(&other), Errno::EIO);
}

fn libc_eacces() -> i32 {
    Errno::EACCES as i32
}

#[test]
fn gpio_level_high_is_active() {
    assert_eq!(value_of(Level::High), Value::Active);
    assert_eq!(value_of(Level::Low), Value::Inactive);
}

/// `gpio:GPIO18`: the chip that has the line, on a Pi 4 (pinctrl-bcm2711,
/// gpiochip0) and on a Pi 5 whose RP1 chip moved between kernels.
#[test]
fn a_line_named_without_its_chip_is_found_on_the_chip_that_has_it() {
    let exp: Vec<LineInfo> = (0..8).map(|o| line(o, &format!("EXP{o}"))).collect();
    let pi4 = vec![
        (chip(0, "pinctrl-bcm2711", 58), bcm_lines()),
        (chip(1, "raspberrypi-exp-gpio", 8), exp.clone()),
    ];
    assert_eq!(chip_with_line("GPIO18", &pi4).unwrap().name, "gpiochip0");
    assert_eq!(chip_with_line("gpio18", &pi4).unwrap().name, "gpiochip0");
    let rp1: Vec<LineInfo> = (0..54).map(|o| line(o, &format!("GPIO{o}"))).collect();
    let pi5 = vec![
        (
            chip(0, "gpio-brcmstb@107d508500", 32),
            vec![line(0, "RP1_SDA")],
        ),
        (chip(4, "pinctrl-rp1", 54), rp1),
    ];
    assert_eq!(chip_with_line("GPIO18", &pi5).unwrap().name, "gpiochip4");
    // Elsewhere: none has it, and the message lists what they have.
    let other = vec![(chip(0, "pl061", 8), exp)];
    let e = chip_with_line("GPIO18", &other).unwrap_err();
    assert!(matches!(e, GpioError::NoLineAnywhere { .. }), "{e}");
    let m = e.to_string();
    assert!(
        m.contains("`GPIO18`")
            && m.contains("pl061")
            && m.contains("EXP0")
            && m.contains("ppmd.output"),
        "{m}"
    );
    let m = chip_with_line("GPIO18", &[]).unwrap_err().to_string();
    assert!(m.contains("no GPIO chips found"), "{m}");
    // Two chips with it: name the chip.
    let two = vec![
        (chip(0, "a", 58), bcm_lines()),
        (chip(1, "b", 58), bcm_lines()),
    ];
    let e = chip_with_line("GPIO18", &two).unwrap_err();
    assert!(matches!(e, GpioError::AmbiguousLine { .. }), "{e}");
    assert!(e.to_string().contains("gpio:CHIP:GPIO18"), "{e}");
    // An offset means nothing without its chip.
    let e = chip_with_line("18", &pi4).unwrap_err();
    assert!(matches!(e, GpioError::OffsetWithoutChip { .. }), "{e}");
}
