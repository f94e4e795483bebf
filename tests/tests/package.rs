//! The Debian package as `tools/package arm64` builds it (cargo-deb, for a
//! Raspberry Pi 4 or 5): every program stripped in /usr/bin with its debug
//! info in the -dbgsym package, the units running /usr/bin with the
//! sandbox of deploy/, the user and groups through sysusers.d before the
//! udev rules are applied, /etc/ppm/ppm.toml as the one conffile, the docs
//! and the licenses; the web view's unit shipped but neither enabled nor
//! started. Needs cargo-deb (`tools/package` installs it) and
//! Debian's dpkg-deb and aarch64 binutils.

use ppm_tests::{arm64_package, run_ok, PROGRAMS};
use std::path::{Path, PathBuf};
use std::process::Command;

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

/// Builds the arm64 package (once) and unpacks it: its .deb, the unpacked
/// tree and its control files.
fn package() -> (PathBuf, PathBuf, PathBuf) {
    let root = Path::new(ROOT);
    let deb = arm64_package();
    let out = root.join("target/package/arm64");
    let _ = std::fs::remove_dir_all(&out);
    let (tree, control) = (out.join("tree"), out.join("control"));
    std::fs::create_dir_all(&out).unwrap();
    run_ok(Command::new("dpkg-deb").arg("-x").arg(&deb).arg(&tree));
    run_ok(Command::new("dpkg-deb").arg("-e").arg(&deb).arg(&control));
    (deb, tree, control)
}

#[test]
fn the_arm64_package_holds_everything_a_pi_needs() {
    let (deb, tree, control) = package();
    let field = |name: &str| {
        run_ok(Command::new("dpkg-deb").arg("-f").arg(&deb).arg(name))
            .trim()
            .to_string()
    };
    assert_eq!(field("Package"), "ppm");
    assert_eq!(field("Architecture"), "arm64");
    assert!(field("Depends").contains("systemd"), "{}", field("Depends"));

    // The programs, stripped: no debug sections; those are in the dbgsym
    // package, by build id.
    for p in PROGRAMS {
        let bin = tree.join("usr/bin").join(p);
        let sections = run_ok(
            Command::new("aarch64-linux-gnu-readelf")
                .arg("-S")
                .arg(&bin),
        );
        assert!(
            sections.contains("AArch64") || sections.contains(".text"),
            "{p}"
        );
        assert!(!sections.contains(".debug_info"), "{p} is not stripped");
        assert!(!sections.contains(".symtab"), "{p} keeps its symbol table");
    }
    let dbgsym = deb.with_file_name(format!(
        "ppm-dbgsym_{}-1_arm64.ddeb",
        env!("CARGO_PKG_VERSION")
    ));
    let debug = run_ok(Command::new("dpkg-deb").arg("-c").arg(&dbgsym));
    assert!(
        debug.matches("/usr/lib/debug/.build-id/").count() >= PROGRAMS.len(),
        "{debug}"
    );

    // The units: deploy/'s, running /usr/bin, the sandbox unchanged.
    for unit in [
        "ppmd.service",
        "udp-ingress.service",
        "udp-ingress@.service",
        "ppm-web.service",
    ] {
        let packaged =
            std::fs::read_to_string(tree.join("usr/lib/systemd/system").join(unit)).unwrap();
        let source = std::fs::read_to_string(Path::new(ROOT).join("deploy").join(unit)).unwrap();
        let directives = |text: &str| -> Vec<String> {
            text.lines()
                .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
                .map(|l| l.replace("/usr/local/bin/", "/usr/bin/"))
                .collect()
        };
        assert_eq!(directives(&packaged), directives(&source), "{unit}");
        assert!(packaged.contains("ExecStart=/usr/bin/"), "{unit}");
        assert!(!packaged.contains("/usr/local/"), "{unit}");
    }

    let web = std::fs::read_to_string(tree.join("usr/lib/systemd/system/ppm-web.service")).unwrap();
    assert!(web.contains("ExecStart=/usr/bin/ppm-web --config /etc/ppm/ppm.toml"));

    // The user and groups, the udev rules, the one conffile.
    let sysusers = std::fs::read_to_string(tree.join("usr/lib/sysusers.d/ppm.conf")).unwrap();
    for line in ["u ppm ", "m ppm gpio", "m ppm spi", "m ppm dialout"] {
        assert!(
            sysusers.lines().any(|l| l.starts_with(line)),
            "{line}: {sysusers}"
        );
    }
    assert_eq!(
        std::fs::read(tree.join("usr/lib/udev/rules.d/60-ppm.rules")).unwrap(),
        std::fs::read(Path::new(ROOT).join("deploy/60-ppm.rules")).unwrap()
    );
    assert_eq!(
        std::fs::read_to_string(control.join("conffiles"))
            .unwrap()
            .trim(),
        "/etc/ppm/ppm.toml"
    );
    assert_eq!(
        std::fs::read(tree.join("etc/ppm/ppm.toml")).unwrap(),
        std::fs::read(Path::new(ROOT).join("deploy/ppm.toml")).unwrap()
    );

    // Maintainer scripts: the user before the udev rules before the units
    // start; the units stop on remove; purge takes the logs.
    let postinst = std::fs::read_to_string(control.join("postinst")).unwrap();
    let at = |needle: &str| {
        postinst
            .find(needle)
            .unwrap_or_else(|| panic!("postinst lacks {needle}:\n{postinst}"))
    };
    assert!(at("systemd-sysusers") < at("udevadm trigger"));
    assert!(at("udevadm trigger") < at("deb-systemd-invoke $_dh_action ppmd.service"));
    assert!(postinst.contains("deb-systemd-helper enable udp-ingress.service"));
    // The web view is shipped, neither enabled nor started: enabled again
    // on upgrade only where the admin had enabled it, restarted only where
    // it runs.
    let enable = at("deb-systemd-helper enable ppm-web.service");
    assert!(at("deb-systemd-helper debian-installed ppm-web.service") < enable);
    assert!(at("deb-systemd-helper --quiet was-enabled ppm-web.service") < enable);
    assert!(postinst.contains("deb-systemd-invoke try-restart ppm-web.service"));
    assert!(
        !postinst.contains("$_dh_action ppm-web.service")
            && !postinst.contains("deb-systemd-invoke start ppm-web.service"),
        "{postinst}"
    );
    let prerm = std::fs::read_to_string(control.join("prerm")).unwrap();
    assert!(
        prerm.contains("deb-systemd-invoke stop ppmd.service"),
        "{prerm}"
    );
    let postrm = std::fs::read_to_string(control.join("postrm")).unwrap();
    assert!(postrm.contains("rm -rf /var/log/ppm"), "{postrm}");

    // Docs and licenses.
    for doc in [
        "README.md",
        "docs/sbus.md",
        "docs/deployment.md",
        "ppm.example.toml",
        "copyright",
        "LICENSE-MIT",
        "LICENSE-APACHE",
    ] {
        assert!(tree.join("usr/share/doc/ppm").join(doc).exists(), "{doc}");
    }
}
