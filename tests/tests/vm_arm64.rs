//! The Debian package as a Raspberry Pi user installs it, on the Pi's
//! architecture under a real init system: Debian bookworm arm64 boots with
//! systemd as PID 1 under `qemu-system-aarch64 -M virt` (software
//! emulation), once on Debian's standard arm64 kernel and once on its
//! PREEMPT_RT one, with a gpio-sim chip named and labelled like a Pi 4's
//! (`pinctrl-bcm2711`, lines `GPIO0` to `GPIO27`). In each boot the guest
//! (tests/vm/arm64/guest.sh) installs the package that `tools/package
//! arm64` builds with `apt-get install ./ppm_..._arm64.deb` and nothing
//! edited; this test then sends commands from outside the guest, through
//! QEMU's user network, and reads the kernel's trace of GPIO18 with every
//! receiver model. The guest also freezes ppmd for the watchdog; in the
//! standard kernel's boot it upgrades over an edited configuration, removes
//! and purges.
//!
//! Needs the host packages tests/vm/arm64/prepare.sh names (mmdebstrap,
//! qemu-system-arm, ...) and Debian's package archive; the root file system
//! is cached in `PPM_VM_CACHE`. Each boot's files stay in
//! target/vm/arm64-<std|rt>/.

use ppm_shared::frame::Level;
use ppm_shared::receiver::{decode_as, Receiver};
use ppm_tests::{arm64_package, run_ok};
use std::collections::BTreeMap;
use std::net::UdpSocket;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

mod vm_trace;
use vm_trace::sets;

/// Commands `[v, v, v, v]` with v = 1000 + STEP_US * i for i in 0..STEPS,
/// each sent REPEAT times at 50 Hz, the last one LAST_REPEAT times: the
/// channel order does not matter, and a frame names the command it carries.
const STEPS: u64 = 6;
const STEP_US: u64 = 200;
const REPEAT: u64 = 7;
const LAST_REPEAT: u64 = 50;
/// How many commands are sent.
const SENT: u64 = (STEPS - 1) * REPEAT + LAST_REPEAT;

/// The step of the n-th command sent.
fn step_of(n: u64) -> u64 {
    (n / REPEAT).min(STEPS - 1)
}
/// How far a traced channel may be from its command: under half a step, so
/// that a frame is never taken for its neighbour's. Emulation can hold the
/// guest's ppmd up between its last look at the clock and the write, which
/// no guard sees; how far the frames really are is printed.
const TOLERANCE_US: u64 = 95;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_owned()
}

/// One boot at a time: each takes the machine's cores.
static BOOT: Mutex<()> = Mutex::new(());

/// Boots `flavor` with the package and guest.sh in its share, sends the
/// commands once the guest says it is ready; returns the share. With
/// `full` false the guest stops after the watchdog check: the upgrade,
/// remove and purge do not depend on the kernel, and are run once.
/// With `PPM_VM_REUSE=1`, reads the files of the last boot again instead
/// of booting (to work on the checks).
fn boot(flavor: &str, full: bool) -> PathBuf {
    let _one = BOOT.lock().unwrap_or_else(|e| e.into_inner());
    let ws = workspace();
    let share = ws.join("target/vm").join(format!("arm64-{flavor}"));
    if std::env::var_os("PPM_VM_REUSE").is_some_and(|v| v == "1") {
        return share;
    }
    let prepare = Command::new(ws.join("tests/vm/arm64/prepare.sh"))
        .output()
        .expect("running tests/vm/arm64/prepare.sh");
    assert!(
        prepare.status.success(),
        "tests/vm/arm64/prepare.sh failed (it names any host package to install):\n{}",
        String::from_utf8_lossy(&prepare.stderr)
    );
    let deb = arm64_package();
    let _ = std::fs::remove_dir_all(&share);
    std::fs::create_dir_all(&share).unwrap();
    std::fs::copy(ws.join("tests/vm/arm64/guest.sh"), share.join("guest.sh")).unwrap();
    if !full {
        std::fs::write(share.join("short"), b"").unwrap();
    }
    std::fs::copy(&deb, share.join(deb.file_name().unwrap())).unwrap();
    // The same package as the next Debian revision, for the upgrade.
    let version = env!("CARGO_PKG_VERSION");
    let tree = ws.join("target/package/arm64-next");
    let _ = std::fs::remove_dir_all(&tree);
    run_ok(Command::new("dpkg-deb").arg("-R").arg(&deb).arg(&tree));
    let control = tree.join("DEBIAN/control");
    let text = std::fs::read_to_string(&control).unwrap();
    let old = format!("Version: {version}-1\n");
    assert!(text.contains(&old), "{text}");
    std::fs::write(
        &control,
        text.replace(&old, &format!("Version: {version}-2\n")),
    )
    .unwrap();
    run_ok(
        Command::new("dpkg-deb")
            .args(["--root-owner-group", "-Zgzip", "-b"])
            .arg(&tree)
            .arg(share.join(format!("ppm_{version}-2_arm64.deb"))),
    );

    let port = UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut vm = Command::new(ws.join("tests/vm/arm64/run.sh"))
        .arg(flavor)
        .arg(&share)
        .arg(port.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running tests/vm/arm64/run.sh");

    // The guest says when its services are up.
    let started = Instant::now();
    while !share.join("ready").exists() {
        if vm.try_wait().unwrap().is_some() || started.elapsed() > Duration::from_secs(900) {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    if share.join("ready").exists() {
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        ppm_tests::at_50hz(SENT, |n| {
            let v = command_us(step_of(n));
            socket
                .send_to(
                    format!("[{v}, {v}, {v}, {v}]").as_bytes(),
                    ("127.0.0.1", port),
                )
                .unwrap();
        });
        std::fs::write(share.join("sent"), b"").unwrap();
    }
    let out = vm.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "the arm64 guest test failed on the {flavor} kernel ({}):\n{}\nguest.log:\n{}\nconsole (last lines):\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr),
        read_or_empty(&share, "guest.log"),
        tail(&read_or_empty(&share, "console.log"), 40),
    );
    share
}

fn command_us(i: u64) -> u64 {
    1000 + STEP_US * i
}

fn read_or_empty(dir: &Path, file: &str) -> String {
    std::fs::read_to_string(dir.join(file)).unwrap_or_default()
}

fn tail(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

/// results.txt's `KEY=VALUE` lines.
fn results(share: &Path) -> BTreeMap<String, String> {
    read_or_empty(share, "results.txt")
        .lines()
        .filter_map(|l| l.split_once('='))
        .map(|(k, v)| (k.to_owned(), v.trim().to_owned()))
        .collect()
}

/// The command a frame read by a receiver carries: the median of its
/// first four channels (or of as many as a trainer input applied before the
/// frame was cut short) within [`TOLERANCE_US`] of one command's value. An
/// edge that the guest's ppmd wrote late, after its last look at the clock,
/// lengthens one channel and shortens the next by as much: the median
/// stands.
fn command_of(channels: &[u64]) -> Option<u64> {
    let mut first: Vec<u64> = channels.iter().take(4).copied().collect();
    first.sort_unstable();
    let median = match first.len() {
        0 => return None,
        n if n % 2 == 1 => first[n / 2],
        n => (first[n / 2 - 1] + first[n / 2]) / 2,
    };
    let i = (median + STEP_US / 2).saturating_sub(1000) / STEP_US;
    (i < STEPS && median.abs_diff(command_us(i)) <= TOLERANCE_US).then_some(i)
}

fn check(flavor: &str, full: bool) {
    let share = boot(flavor, full);
    let r = results(&share);
    let get = |k: &str| r.get(k).map(String::as_str).unwrap_or("");
    eprintln!("arm64 {flavor}: {r:?}");

    // The boot and the install, with nothing edited.
    assert_eq!(
        get("kernel").contains("-rt-"),
        flavor == "rt",
        "{flavor} booted {}",
        get("kernel")
    );
    assert_eq!(
        get("system"),
        "running",
        "failed units:\n{}",
        read_or_empty(&share, "failed.txt")
    );
    let version = format!("{}-1", env!("CARGO_PKG_VERSION"));
    assert_eq!(get("version"), version);
    assert_eq!(get("enabled_ppmd"), "enabled");
    assert_eq!(get("enabled_udp-ingress"), "enabled");
    assert!(
        get("user_groups").split(',').any(|g| g == "gpio"),
        "user ppm is in {}",
        get("user_groups")
    );
    assert_eq!(get("chip_group"), "gpio", "the GPIO chip's group");

    // The commands, on GPIO18 as each receiver reads it: the trainer
    // inputs read the last command, and no receiver reads a frame that
    // names no command, or an older one after a newer, beyond the frames
    // ppmd itself counted glitched. Guest time counts instructions
    // (run.sh), so the host's load does not make ppmd late; but the four
    // vCPUs take turns on one host thread, and a vCPU's turn can hold ppmd
    // up between its last look at the clock and the write, which no guard
    // sees, or before an edge, which aborts the frame (a late edge is never
    // written). How many frames each receiver read, and how far off, is
    // printed: the exact timing is the x86 tests' (one vCPU), and the Pi's
    // own needs a Pi.
    let gpio18: u32 = get("gpio18").parse().expect("gpio18 in results.txt");
    let edges = sets(
        &read_or_empty(&share, "trace.txt"),
        &read_or_empty(&share, "trace_raw.txt"),
        gpio18,
    );
    assert!(edges.len() > 20, "{} changes of GPIO18 traced", edges.len());
    // What udp-ingress and ppmd counted (ppm-status, after the commands).
    let status = read_or_empty(&share, "ppm_status.txt");
    // Each applied, or superseded by a newer one that came with it.
    assert!(
        status.contains(&format!("received {SENT}, applied "))
            && status.contains("stale 0, clamped 0")
            && status.contains("rejected: 0"),
        "{flavor}: not every command was received and taken:\n{status}"
    );
    let count = |what: &str| -> usize {
        status
            .split(&format!(" {what} frames"))
            .next()
            .and_then(|head| head.rsplit(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no {what} frame count in:\n{status}"))
    };
    let (aborted, glitched) = (count("aborted"), count("glitched"));
    for receiver in Receiver::ALL {
        let (frames, _) = decode_as(
            receiver,
            edges.iter().map(|&(t, v)| (t, Level::from_bit(v == 1))),
            Level::High,
        );
        let trainer = matches!(receiver, Receiver::EdgeTx | Receiver::OpenTx);
        let read: Vec<Vec<u64>> = frames
            .iter()
            .filter(|f| f.complete || trainer)
            .map(|f| f.channels_us())
            .filter(|c| !c.is_empty())
            .collect();
        let mut last = None;
        let mut odd = Vec::new();
        for channels in &read {
            match command_of(channels) {
                Some(i) if last.is_none_or(|l| i >= l) => last = Some(i),
                _ => odd.push(channels),
            }
        }
        assert!(
            odd.len() <= glitched,
            "{flavor}: {receiver:?} read {} frames that carry no command or come out of order, ppmd counted {glitched} glitched: {odd:?}",
            odd.len()
        );
        let worst = read
            .iter()
            .flat_map(|c| {
                let want = command_of(c).map_or(0, command_us);
                c.iter().take(4).map(move |v| v.abs_diff(want))
            })
            .max()
            .unwrap_or(0);
        let distinct = {
            let mut v: Vec<u64> = read.iter().filter_map(|c| command_of(c)).collect();
            v.dedup();
            v.len()
        };
        eprintln!(
            "arm64 {flavor} (reported): {receiver:?} read {} frames carrying {distinct} of {STEPS} commands, the last read {}; {} odd, ppmd counted {aborted} aborted and {glitched} glitched; channels off by {worst} us at most",
            read.len(),
            last.map_or("none".to_string(), |i| command_us(i).to_string()),
            odd.len()
        );
        if trainer {
            assert_eq!(
                last,
                Some(STEPS - 1),
                "{flavor}: {receiver:?} never read the last command"
            );
        }
    }

    // A clean run warns of nothing; both sandboxes hold.
    let warnings = read_or_empty(&share, "journal_warnings.txt");
    assert!(
        warnings.trim().is_empty(),
        "{flavor}: the journal has warnings:\n{warnings}"
    );
    for unit in ["ppmd", "udp-ingress"] {
        let exposure: f64 = get(&format!("exposure_{unit}"))
            .parse()
            .unwrap_or_else(|_| panic!("no exposure level for {unit}: {r:?}"));
        assert!(exposure <= 2.0, "{unit}: exposure {exposure}");
    }

    // The watchdog restarted the frozen ppmd.
    assert!(
        get("watchdog_restarts").parse::<u32>().unwrap_or(0) >= 1,
        "{r:?}"
    );
    assert!(
        get("watchdog_result").parse::<u32>().unwrap_or(0) >= 1,
        "{r:?}"
    );

    if !full {
        return;
    }
    // The upgrade kept the edit and restarted both services.
    assert_eq!(
        get("upgraded_version"),
        format!("{}-2", env!("CARGO_PKG_VERSION"))
    );
    assert_eq!(get("upgraded_keeps_edit"), "1");
    let before: Vec<&str> = get("upgraded_pids_before").split(' ').collect();
    let after: Vec<&str> = get("upgraded_pids_after").split(' ').collect();
    assert_eq!(before.len(), 2, "{r:?}");
    for (b, a) in before.iter().zip(&after) {
        assert_ne!(b, a, "a service was not restarted by the upgrade: {r:?}");
    }

    // Removal stops; purge removes the configuration and the logs.
    assert_eq!(get("removed_states"), "inactive inactive", "{r:?}");
    assert_eq!(get("removed_keeps_config"), "yes");
    assert_eq!(get("purged_config"), "gone");
    assert_eq!(get("purged_logs"), "gone");
}

#[test]
fn the_package_on_debian_arm64_with_the_standard_kernel() {
    check("std", true);
}

#[test]
fn the_package_on_debian_arm64_with_the_preempt_rt_kernel() {
    check("rt", false);
}

#[test]
fn a_frame_names_the_command_it_carries() {
    assert_eq!(command_of(&[1000, 1003, 995, 1090]), Some(0));
    assert_eq!(command_of(&[2000, 2000, 2000, 2000, 1500]), Some(5));
    // one late edge: a channel longer, the next shorter
    assert_eq!(command_of(&[1600, 1750, 1450, 1600]), Some(3));
    // cut short: what came before the late edge
    assert_eq!(command_of(&[1401, 1399]), Some(2));
    assert_eq!(command_of(&[1446, 1623, 1548]), Some(3));
    // between two commands
    assert_eq!(command_of(&[1100, 1100, 1100, 1100]), None);
    assert_eq!(command_of(&[1200, 1200, 1400, 1400]), None);
    // beyond the commands sent
    assert_eq!(command_of(&[2200, 2200, 2200, 2200]), None);
    assert_eq!(command_of(&[910, 910, 910, 910]), Some(0));
    assert_eq!(command_of(&[900, 900, 900, 900]), None);
    assert_eq!(command_of(&[]), None);
}
