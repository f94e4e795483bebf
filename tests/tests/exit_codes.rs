//! Exit statuses and start-up words, with the real binaries.
//!
//! - Every fault of the configuration, or of a file, directory, device or
//!   CPU a key names, stops ppmd and udp-ingress with exit status 78
//!   (EX_CONFIG: the units' `RestartPreventExitStatus=78` keeps systemd
//!   from restarting into it every second), and the error names the key
//!   (or the command-line option that gave the value). A fault a restart
//!   may cure (a port another process still holds) stays 1.
//! - A channel-model mismatch met on every command is said once, then as a
//!   count at most every 10 s, not 10 times a second.
//! - A key set in the file that does nothing where it is (`ppm.frame_us`
//!   under follow timing) is named at start, with what governs instead.

use nix::sys::signal::Signal;
use ppm_tests::{Sandbox, Sender, GENTLE_RT};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const SECOND: Duration = Duration::from_secs(1);

/// Runs `binary` with `args` (log `log`) to its refusal: its exit status
/// must be 78 and its one error line must name `names` (a key, in
/// backquotes, or an option). Returns the error line.
fn refused(sb: &Sandbox, binary: &str, args: &[&str], log: &str, names: &str) -> String {
    let mut p = sb.spawn(binary, args, log);
    let status = p.wait(30 * SECOND);
    let text = p.log_text();
    assert_eq!(status.code(), Some(78), "{binary} {args:?}: {text}");
    let errors: Vec<&str> = text.lines().filter(|l| l.contains(" ERROR ")).collect();
    assert_eq!(errors.len(), 1, "{binary} {args:?}: {text}");
    assert!(
        errors[0].contains(names),
        "{binary} {args:?}: the error does not name {names}: {}",
        errors[0]
    );
    errors[0].to_string()
}

/// `--config` and the sandbox's configuration with `extra` (see
/// [`Sandbox::config`]), as arguments.
fn config(sb: &Sandbox, extra: &str) -> String {
    sb.config(extra).to_str().unwrap().to_string()
}

/// `path` as a TOML string.
fn toml_path(path: &Path) -> String {
    format!("{:?}", path.to_str().unwrap())
}

/// A FIFO, a directory and a regular file in the sandbox, for paths that
/// must be something else.
fn odd_files(sb: &Sandbox) -> (PathBuf, PathBuf, PathBuf) {
    let fifo = sb.dir.join("a-fifo");
    nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
    let dir = sb.dir.join("a-dir");
    std::fs::create_dir(&dir).unwrap();
    let file = sb.write_file("a-file", "", 0o600);
    (fifo, dir, file)
}

const KEY_HEX: &str = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f\n";

/// `ingress.seq_file` and `mavlink.timestamp_file`: a FIFO, a directory,
/// a directory that cannot be made, and content that is not a number.
#[test]
fn state_files_that_cannot_be_used_exit_78_naming_their_key() {
    let sb = Sandbox::new("exit-state");
    let (fifo, dir, file) = odd_files(&sb);
    let key = sb.write_file("good.key", KEY_HEX, 0o600);
    let corrupt = sb.write_file("corrupt", "garbage\n", 0o600);
    let under_file = file.join("ppm.last_seq");
    for (i, (path, says)) in [
        (&fifo, "a FIFO (named pipe), not a regular file"),
        (&dir, "Is a directory"),
        (&under_file, "is there, and is not a directory"),
        (&corrupt, "holds `garbage`"),
    ]
    .into_iter()
    .enumerate()
    {
        let cfg = sb
            .config_with_ingress(
                &format!(
                    "auth_key = {}\nseq_file = {}",
                    toml_path(&key),
                    toml_path(path)
                ),
                GENTLE_RT,
            )
            .to_str()
            .unwrap()
            .to_string();
        let err = refused(
            &sb,
            "udp-ingress",
            &["--config", &cfg],
            &format!("seq{i}"),
            "config key `ingress.seq_file`",
        );
        assert!(err.contains(says), "{err}");

        let cfg = config(
            &sb,
            &format!(
                "{GENTLE_RT}[mavlink]\nkey_file = {}\ntimestamp_file = {}\n",
                toml_path(&key),
                toml_path(path)
            ),
        );
        let err = refused(
            &sb,
            "udp-ingress",
            &["--config", &cfg],
            &format!("ts{i}"),
            "config key `mavlink.timestamp_file`",
        );
        assert!(err.contains(says), "{err}");
    }
}

/// `ingress.auth_key` and `mavlink.key_file` from the file: missing, open
/// to others, not a key. The error names the key and where to point it.
#[test]
fn key_files_that_cannot_be_used_exit_78_naming_their_key() {
    let sb = Sandbox::new("exit-keys");
    let missing = sb.dir.join("missing.key");
    let open = sb.write_file("open.key", KEY_HEX, 0o644);
    let short = sb.write_file("short.key", "abcd\n", 0o600);
    for (i, (path, says)) in [
        (&missing, "No such file or directory"),
        (&open, "chmod 600"),
        (&short, "64 hex characters"),
    ]
    .into_iter()
    .enumerate()
    {
        let cfg = sb
            .config_with_ingress(&format!("auth_key = {}", toml_path(path)), GENTLE_RT)
            .to_str()
            .unwrap()
            .to_string();
        let err = refused(
            &sb,
            "udp-ingress",
            &["--config", &cfg],
            &format!("auth{i}"),
            "config key `ingress.auth_key`",
        );
        assert!(err.contains(says), "{err}");
        let cfg = config(
            &sb,
            &format!("{GENTLE_RT}[mavlink]\nkey_file = {}\n", toml_path(path)),
        );
        let err = refused(
            &sb,
            "udp-ingress",
            &["--config", &cfg],
            &format!("mav{i}"),
            "config key `mavlink.key_file`",
        );
        assert!(err.contains(says), "{err}");
    }
    let err = refused(
        &sb,
        "udp-ingress",
        &[
            "--config",
            &config(&sb, GENTLE_RT),
            "--auth-key",
            missing.to_str().unwrap(),
        ],
        "option",
        "cannot read auth key file",
    );
    assert!(err.contains(missing.to_str().unwrap()), "{err}");
}

/// `ipc.root` that cannot be a directory stops both programs; so does a
/// configuration file that is not there (no key to name: its path).
#[test]
fn an_ipc_root_that_cannot_be_made_exits_78() {
    let sb = Sandbox::new("exit-ipc");
    let (_, _, file) = odd_files(&sb);
    let text = format!(
        "name = \"{}\"\n[ingress]\nlisten = \"127.0.0.1:{}\"\n[ipc]\nroot = {}\n{GENTLE_RT}",
        sb.name,
        sb.port,
        toml_path(&file.join("ipc"))
    );
    let cfg = sb.dir.join("ipc.toml");
    std::fs::write(&cfg, text).unwrap();
    let cfg = cfg.to_str().unwrap();
    for binary in ["ppmd", "udp-ingress"] {
        let err = refused(
            &sb,
            binary,
            &["--config", cfg],
            binary,
            "config key `ipc.root`",
        );
        assert!(err.contains("Not a directory"), "{err}");
    }
    let none = sb.dir.join("none.toml");
    for binary in ["ppmd", "udp-ingress"] {
        refused(
            &sb,
            binary,
            &["--config", none.to_str().unwrap()],
            &format!("{binary}-none"),
            &format!("cannot read config file {}", none.display()),
        );
    }
}

/// `rt.cpu` and `ingress.cpu` naming a CPU this machine does not have:
/// refused before anything is opened, unless a degraded run is allowed.
#[test]
fn cpus_this_machine_lacks_exit_78() {
    let sb = Sandbox::new("exit-cpu");
    let rt = "[rt]\npriority = 0\ncpu = 4095\ncpu_dma_latency = false\nmlock = false\n";
    let cfg = config(&sb, rt);
    let err = refused(
        &sb,
        "ppmd",
        &["--config", &cfg],
        "ppmd",
        "config key `rt.cpu`",
    );
    assert!(
        err.contains("CPU 4095 does not exist or is offline"),
        "{err}"
    );
    assert!(
        !sb.dir.join(format!("ppm-{}.trace", sb.name)).exists(),
        "no line was opened"
    );
    // Allowed to run degraded, it runs, unpinned.
    let mut p = sb.spawn("ppmd", &["--config", &cfg, "--allow-degraded"], "degraded");
    p.wait_for_log("commands from", 30 * SECOND);
    assert!(p.log_text().contains("DEGRADED RUN"), "{}", p.log_text());
    assert!(p.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());

    let cfg = sb
        .config_with_ingress("cpu = 4095", "[rt]\nallow_degraded = false\n")
        .to_str()
        .unwrap()
        .to_string();
    refused(
        &sb,
        "udp-ingress",
        &["--config", &cfg],
        "ingress",
        "config key `ingress.cpu`",
    );
    let cfg = config(&sb, "[rt]\nallow_degraded = false\n");
    refused(
        &sb,
        "udp-ingress",
        &["--config", &cfg, "--cpu", "4095"],
        "ingress-option",
        "--cpu 4095",
    );
}

/// ppmd's log files: `ppmd.frame_log` (in a directory that does not
/// exist, or a directory), its `[[outputs]]` form, `--frame-log` and
/// `--hdr-log`.
#[test]
fn log_files_that_cannot_be_written_exit_78() {
    let sb = Sandbox::new("exit-logs");
    let (_, dir, _) = odd_files(&sb);
    let nodir = sb.dir.join("no-such-dir").join("frames.jsonl");
    for (i, (path, says)) in [(&nodir, "does not exist"), (&dir, "Is a directory")]
        .into_iter()
        .enumerate()
    {
        let cfg = config(
            &sb,
            &format!("{GENTLE_RT}[ppmd]\nframe_log = {}\n", toml_path(path)),
        );
        let err = refused(
            &sb,
            "ppmd",
            &["--config", &cfg],
            &format!("log{i}"),
            "config key `ppmd.frame_log`",
        );
        assert!(err.contains(says), "{err}");
    }
    let cfg = config(&sb, GENTLE_RT);
    let nodir_s = nodir.to_str().unwrap();
    for (option, log) in [("--frame-log", "frame-log"), ("--hdr-log", "hdr-log")] {
        let err = refused(
            &sb,
            "ppmd",
            &["--config", &cfg, option, nodir_s],
            log,
            &format!("{option}: "),
        );
        assert!(
            err.contains(nodir_s) && err.contains("does not exist"),
            "{err}"
        );
    }
    // Output b of two, its own frame log: named as its entry writes it.
    let (cfg, _) = ppm_tests::two_outputs(
        &sb,
        ppm_tests::free_udp_port(),
        &format!("frame_log = {}", toml_path(&nodir)),
    );
    refused(
        &sb,
        "ppmd",
        &["--config", cfg.to_str().unwrap()],
        "outputs",
        "config key `outputs[1].frame_log`",
    );
}

/// `ppmd.output` naming a line this machine does not have, or cannot be
/// one: a sim trace in a missing directory, a missing spidev device, a
/// regular file as a serial device, a GPIO chip it lacks.
#[test]
fn outputs_this_machine_lacks_exit_78_naming_the_key() {
    let sb = Sandbox::new("exit-output");
    let (_, _, file) = odd_files(&sb);
    let missing = sb.dir.join("no-such-dir");
    for (i, (output, ppm, says)) in [
        (
            format!("sim:{}", missing.join("line.trace").display()),
            "",
            "does not exist",
        ),
        (
            format!("spi:{}", missing.join("spidev0.0").display()),
            "",
            "name a spidev device this machine has",
        ),
        (
            format!("serial:{}", file.display()),
            "protocol = \"sbus\"\n",
            "is not a tty",
        ),
        (
            "gpio:pinctrl-nosuch:GPIO18".to_string(),
            "",
            "pinctrl-nosuch",
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let cfg = config(
            &sb,
            &format!("{GENTLE_RT}[ppmd]\noutput = {output:?}\n[ppm]\n{ppm}"),
        );
        let err = refused(
            &sb,
            "ppmd",
            &["--config", &cfg],
            &format!("out{i}"),
            "config key `ppmd.output`",
        );
        assert!(err.contains(says), "{output}: {err}");
    }
}

/// What a restart may cure is not refused as the configuration's: the
/// listen port still held by another process (a udp-ingress stopping)
/// exits with 1, and systemd tries again a second later.
#[test]
fn a_port_another_process_holds_exits_1() {
    let sb = Sandbox::new("exit-busy");
    let _holder = std::net::UdpSocket::bind(sb.addr()).unwrap();
    let cfg = config(&sb, GENTLE_RT);
    let mut p = sb.spawn("udp-ingress", &["--config", &cfg], "busy");
    let status = p.wait(30 * SECOND);
    let text = p.log_text();
    assert_eq!(status.code(), Some(1), "{text}");
    assert!(text.contains("cannot listen on"), "{text}");
}

/// A udp-ingress left with another channel model than ppmd's has every
/// command refused. ppmd says so once, then as a count every 10 s: two
/// lines in 12 s of commands at 50 Hz, where it used to say it ten times a
/// second (with each monitor tick that found new ones).
#[test]
fn a_channel_model_mismatch_is_said_once_then_counted() {
    let sb = Sandbox::new("exit-mismatch");
    let ppmd_cfg = sb.dir.join("ppmd.toml");
    std::fs::copy(sb.config("[ppm]\norder = 'TAER'"), &ppmd_cfg).unwrap();
    let ingress_cfg = sb.config("");
    let mut ppmd = sb.start_ppmd(&ppmd_cfg, "line.trace");
    let mut ingress = sb.start_ingress(&ingress_cfg, &[]);
    let sender = Sender::new(sb.addr());
    let end = Instant::now() + 12 * SECOND;
    while Instant::now() < end {
        sender.send(b"[1500, 1500, 1000, 1500]");
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    assert!(ingress
        .signal_and_wait(Signal::SIGTERM, 10 * SECOND)
        .success());
    let log = ppmd.log_text();
    let said: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("command(s) refused"))
        .collect();
    assert_eq!(said.len(), 2, "{log}");
    assert!(
        said[0].contains("refused: udp-ingress made them under another channel model"),
        "{}",
        said[0]
    );
    assert!(
        said[1].contains("more command(s) refused under another channel model (")
            && said[1].contains(" since start)"),
        "{}",
        said[1]
    );
}

/// `ppm.frame_us` under follow timing (the default) does nothing: ppmd
/// says so at start, naming the key and what governs instead; under grid
/// timing, or left out, nothing is said. udp-ingress says the same of a
/// seq file without a key.
#[test]
fn keys_that_do_nothing_are_named_at_start() {
    let sb = Sandbox::new("exit-inert");
    let cfg = sb.config(&format!(
        "{GENTLE_RT}[ppm]\ntiming = \"follow\"\nframe_us = 20000.0\n"
    ));
    let p = sb.start_ppmd(&cfg, "follow.trace");
    let log = p.log_text();
    let warned: Vec<&str> = log.lines().filter(|l| l.contains("does nothing")).collect();
    assert_eq!(warned.len(), 1, "{log}");
    assert!(
        warned[0].contains(" WARN ")
            && warned[0].contains("config key `ppm.frame_us` is set but does nothing")
            && warned[0].contains("ppm.follow_sync_min_us")
            && warned[0].contains("ppm.timing = \"grid\""),
        "{}",
        warned[0]
    );
    p.terminate();
    // Grid timing: frame_us is the frame length.
    let cfg = sb.config(&format!("{GENTLE_RT}[ppm]\nframe_us = 22500.0\n"));
    let p = sb.start_ppmd(&cfg, "grid.trace");
    assert!(!p.log_text().contains("does nothing"), "{}", p.log_text());
    p.terminate();

    let cfg = sb.config_with_ingress(
        &format!("seq_file = {}", toml_path(&sb.dir.join("s.last_seq"))),
        GENTLE_RT,
    );
    let p = sb.start_ingress(&cfg, &[]);
    assert!(
        p.log_text()
            .contains("config key `ingress.seq_file` is set but does nothing"),
        "{}",
        p.log_text()
    );
    p.terminate();
}

/// docs/configuration.md shows the warning the code gives, word for word.
#[test]
fn the_documented_warning_is_the_real_one() {
    use ppm_shared::config::{Config, Program};
    let docs = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../docs/configuration.md"
    ))
    .unwrap();
    let inert = Config::parse("[ppm]\nframe_us = 20000.0")
        .unwrap()
        .inert_keys(Program::Ppmd);
    assert_eq!(inert.len(), 1, "{inert:?}");
    assert!(
        docs.contains(&format!("\n{}\n", inert[0])),
        "docs/configuration.md shows another warning than:\n{}",
        inert[0]
    );
}
