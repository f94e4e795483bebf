//! The deployment files agree with the code and with each other: the
//! production configuration is valid, both systemd units read it and share
//! its shared-memory root, and docs/deployment.md installs them where they
//! look.

use ppm_shared::config::{Config, CpuChoice, OutputSpec};

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
const CONFIG_PATH: &str = "/etc/ppm/ppm.toml";

fn read(file: &str) -> String {
    std::fs::read_to_string(format!("{ROOT}/{file}")).unwrap_or_else(|e| panic!("{file}: {e}"))
}

/// The `key=value` directives of a unit file (comments and sections dropped).
fn directives(unit: &str) -> Vec<(String, String)> {
    ppm_tests::unit_directives(unit)
}

fn value<'a>(d: &'a [(String, String)], key: &str) -> &'a str {
    let values: Vec<&str> = d
        .iter()
        .filter(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
        .collect();
    assert_eq!(values.len(), 1, "{key} set once: {values:?}");
    values[0]
}

fn production() -> Config {
    Config::parse(&read("deploy/ppm.toml"))
        .expect("deploy/ppm.toml parses")
        .config
}

#[test]
fn production_config_is_valid() {
    let cfg = production();
    cfg.validate().expect("deploy/ppm.toml validates");
    assert_eq!(cfg.ipc.root.to_str(), Some("/run/ppm"));
    assert_eq!(cfg.ingress.listen.to_string(), "0.0.0.0:5005");
    assert!(!cfg.rt.allow_degraded, "production runs are never degraded");
    // GPIO18 on whichever chip has it (a Pi 4's or a Pi 5's).
    assert_eq!(
        cfg.output().unwrap(),
        OutputSpec::Gpio {
            chip: String::new(),
            line: "GPIO18".into()
        }
    );
    // The variants with the chip that the comment gives are valid too.
    let text = read("deploy/ppm.toml");
    for chip in ["pinctrl-bcm2711", "pinctrl-rp1"] {
        let spec = format!("gpio:{chip}:GPIO18");
        assert!(text.contains(&format!("\"{spec}\"")), "{spec}");
        let with = text.replace("\"gpio:GPIO18\"", &format!("\"{spec}\""));
        let with = Config::parse(&with).unwrap();
        with.validate().unwrap();
        assert!(matches!(with.output().unwrap(), OutputSpec::Gpio { chip: c, .. } if c == chip));
    }
}

#[test]
fn the_ingress_template_is_the_ingress_unit_with_a_name() {
    let plain = directives("udp-ingress.service");
    let template = directives("udp-ingress@.service");
    assert_eq!(
        value(&template, "ExecStart"),
        format!("/usr/local/bin/udp-ingress --config {CONFIG_PATH} --name %i")
    );
    let rest = |d: &[(String, String)]| -> Vec<(String, String)> {
        d.iter()
            .filter(|(k, _)| k != "ExecStart" && k != "Description")
            .cloned()
            .collect()
    };
    assert_eq!(rest(&template), rest(&plain));
}

#[test]
fn units_share_the_root_and_read_the_config() {
    let cfg = production();
    for (unit, binary) in [
        ("ppmd.service", "ppmd"),
        ("udp-ingress.service", "udp-ingress"),
    ] {
        let d = directives(unit);
        assert_eq!(
            value(&d, "ExecStart"),
            format!("/usr/local/bin/{binary} --config {CONFIG_PATH}"),
            "{unit}"
        );
        assert_eq!(
            std::path::Path::new("/run").join(value(&d, "RuntimeDirectory")),
            cfg.ipc.root,
            "{unit}: RuntimeDirectory is ipc.root"
        );
        let ty = if binary == "ppmd" { "notify" } else { "simple" };
        for (key, want) in [
            ("Type", ty),
            ("User", "ppm"),
            ("Restart", "always"),
            ("RestartSec", "1"),
            // The daemons' exit status for a configuration error
            // (ppm_shared::daemon::EXIT_CONFIG): no restart into it.
            ("RestartPreventExitStatus", "78"),
            ("RuntimeDirectoryPreserve", "yes"),
            ("PrivateTmp", "yes"),
            ("WantedBy", "multi-user.target"),
        ] {
            assert_eq!(value(&d, key), want, "{unit}: {key}");
        }
        for key in ["PrivateDevices", "PrivateIPC", "DynamicUser", "RemoveIPC"] {
            assert!(
                d.iter().all(|(k, _)| k != key),
                "{unit}: {key} would split the shared memory"
            );
        }
    }

    let d = directives("ppmd.service");
    assert_eq!(value(&d, "WatchdogSec"), "2s", "ppmd pets its watchdog");
    assert_eq!(value(&d, "NotifyAccess"), "main");
    assert_eq!(value(&d, "LimitRTPRIO"), "99");
    assert_eq!(value(&d, "LimitMEMLOCK"), "infinity");
    let (lo, hi) = value(&d, "CPUAffinity").split_once('-').unwrap();
    let others = lo.parse::<usize>().unwrap()..=hi.parse::<usize>().unwrap();
    assert_eq!(others, 0..=2);
    match cfg.rt.cpu {
        CpuChoice::Index(cpu) => assert!(
            !others.contains(&cpu),
            "rt.cpu {cpu} is kept free of the other threads"
        ),
        other => panic!("deploy/ppm.toml names the timing CPU: {other:?}"),
    }

    let d = directives("udp-ingress.service");
    assert!(value(&d, "After").contains("network-online.target"));
    assert!(value(&d, "Wants").contains("network-online.target"));
}

/// The web view's unit: the same user, shared-memory root and
/// configuration as the daemons, the package's binary, no restart into a
/// configuration error, and nothing that would split the shared memory.
#[test]
fn the_web_unit_reads_what_the_daemons_share() {
    let cfg = production();
    let d = directives("ppm-web.service");
    assert_eq!(
        value(&d, "ExecStart"),
        format!("/usr/local/bin/ppm-web --config {CONFIG_PATH}")
    );
    assert_eq!(
        std::path::Path::new("/run").join(value(&d, "RuntimeDirectory")),
        cfg.ipc.root
    );
    for (key, want) in [
        ("Type", "simple"),
        ("User", "ppm"),
        ("Group", "ppm"),
        ("Restart", "always"),
        ("RestartPreventExitStatus", "2 78"),
        ("TasksMax", "64"),
        ("MemoryMax", "128M"),
        ("RuntimeDirectoryPreserve", "yes"),
        ("PrivateTmp", "yes"),
        ("ProtectSystem", "strict"),
        ("NoNewPrivileges", "yes"),
        ("CapabilityBoundingSet", ""),
        ("WantedBy", "multi-user.target"),
    ] {
        assert_eq!(value(&d, key), want, "ppm-web.service: {key}");
    }
    for key in ["PrivateDevices", "PrivateIPC", "DynamicUser", "RemoveIPC"] {
        assert!(
            d.iter().all(|(k, _)| k != key),
            "ppm-web.service: {key} would split the shared memory"
        );
    }
}

#[test]
fn readme_installs_what_the_units_run() {
    let readme = read("docs/deployment.md");
    let install = readme
        .split("## Installing as a service")
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .expect("docs/deployment.md has \"## Installing as a service\"");
    for needle in [
        CONFIG_PATH,
        "/usr/local/bin",
        "deploy/ppm.toml",
        "deploy/ppmd.service",
        "deploy/udp-ingress.service",
        "deploy/60-ppm.rules",
        "systemctl enable --now udp-ingress ppmd",
        "useradd",
        "gpio",
        "cargo build --release --target aarch64-unknown-linux-gnu",
        "ppm-status --to 127.0.0.1:5005",
    ] {
        assert!(
            install.contains(needle),
            "docs/deployment.md's install section lacks `{needle}`"
        );
    }
    let rules = read("deploy/60-ppm.rules");
    assert!(rules.contains("KERNEL==\"cpu_dma_latency\", GROUP=\"ppm\""));
    assert!(rules.contains("KERNEL==\"gpiochip*\", GROUP=\"gpio\""));
    // spidev to the group spi, which the package's user is in and its
    // postinst triggers the rules for.
    assert!(rules.contains("SUBSYSTEM==\"spidev\", KERNEL==\"spidev*\", GROUP=\"spi\""));
    let postinst = read("deploy/debian/postinst");
    assert!(postinst.contains("--subsystem-match=spidev"), "{postinst}");
    assert!(read("deploy/debian/ppm.sysusers").contains("m ppm spi"));
}

/// `tools/package arm64` on a machine without the aarch64 cross toolchain
/// stops before building anything and names the packages to install.
#[test]
fn the_package_script_names_the_cross_toolchain_it_lacks() {
    let dir = std::env::temp_dir().join(format!("ppm-package-path-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    // A PATH with only what the script needs before its check.
    for tool in ["bash", "dirname"] {
        let found = which(tool);
        std::os::unix::fs::symlink(found, dir.join(tool)).unwrap();
    }
    let out = std::process::Command::new(dir.join("bash"))
        .arg(format!("{ROOT}/tools/package"))
        .arg("arm64")
        .env("PATH", &dir)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("gcc-aarch64-linux-gnu") && err.contains("apt-get install"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Where `tool` is on this machine's PATH.
fn which(tool: &str) -> std::path::PathBuf {
    std::env::var_os("PATH")
        .iter()
        .flat_map(std::env::split_paths)
        .map(|d| d.join(tool))
        .find(|p| p.is_file())
        .unwrap_or_else(|| panic!("{tool} not on PATH"))
}
