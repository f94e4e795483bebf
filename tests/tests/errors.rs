//! A refused start says each cause once: an error's text does not repeat
//! its source, which the programs print after it (`{:#}`, `logging::Chain`).

use ppm_tests::{Sandbox, GENTLE_RT};
use std::time::Duration;

/// Runs `binary` with `args` to its refusal and returns its one error line,
/// without the log prefix (`[time ERROR target] `); its exit status must be
/// `code` (78, EX_CONFIG, for what the configuration can fix).
fn refusal(sb: &Sandbox, binary: &str, args: &[&str], log: &str, code: i32) -> String {
    let mut p = sb.spawn(binary, args, log);
    let status = p.wait(Duration::from_secs(30));
    assert!(!status.success(), "{binary} {args:?} started");
    assert_eq!(
        status.code(),
        Some(code),
        "{binary} {args:?}: {}",
        p.log_text()
    );
    let text = p.log_text();
    let errors: Vec<&str> = text
        .lines()
        .filter_map(|l| {
            l.split_once(" ERROR ")
                .and_then(|(_, r)| r.split_once("] "))
        })
        .map(|(_, msg)| msg)
        .collect();
    assert_eq!(errors.len(), 1, "{text}");
    errors[0].to_string()
}

#[test]
fn a_key_file_that_cannot_be_read_says_why_once() {
    let sb = Sandbox::new("errors-key");
    let cfg = sb.config(GENTLE_RT);
    let cfg = cfg.to_str().unwrap();
    let fifo = sb.dir.join("fifo.key");
    nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
    let big = sb.write_file("big.key", &" ".repeat(5000), 0o600);
    let missing = sb.dir.join("missing.key");
    let dir = sb.dir.join("a-dir");
    std::fs::create_dir(&dir).unwrap();
    for (i, (key, why)) in [
        (&fifo, "it is a FIFO (named pipe), not a regular file"),
        (&dir, "it is a directory, not a regular file"),
        (
            &std::path::PathBuf::from("/dev/null"),
            "it is a character device, not a regular file",
        ),
        (
            &big,
            "it holds 5000 bytes or more, and this file is never larger than 4096",
        ),
        (&missing, "No such file or directory (os error 2)"),
    ]
    .into_iter()
    .enumerate()
    {
        let key = key.to_str().unwrap();
        let got = refusal(
            &sb,
            "udp-ingress",
            &["--config", cfg, "--auth-key", key],
            &format!("key{i}"),
            78,
        );
        assert_eq!(got, format!("cannot read auth key file {key}: {why}"));
    }
    // The config file's own refusal, for comparison: also once.
    let fifo = fifo.to_str().unwrap();
    let got = refusal(&sb, "udp-ingress", &["--config", fifo], "config", 78);
    assert_eq!(
        got,
        format!("cannot read config file {fifo}: it is a FIFO (named pipe), not a regular file")
    );
}

#[test]
fn a_missing_spi_device_says_why_once() {
    let sb = Sandbox::new("errors-spi");
    let cfg = sb.config(GENTLE_RT);
    let dev = sb.dir.join("spidev9.9");
    let dev = dev.to_str().unwrap();
    let got = refusal(
        &sb,
        "ppmd",
        &[
            "--config",
            cfg.to_str().unwrap(),
            "--output",
            &format!("spi:{dev}"),
        ],
        "ppmd",
        78,
    );
    assert_eq!(
        got,
        format!(
            "output `{}`: spi:{dev}: opening: No such file or directory (os error 2)",
            sb.name
        )
    );
}

/// Two ppmd on one output name: the second is refused at start, naming the
/// first by its pid; once the first is killed (SIGKILL, leaving its lock
/// file behind), a new one starts.
#[test]
fn a_second_ppmd_on_one_name_is_refused_and_a_dead_ones_name_is_free() {
    let sb = Sandbox::new("errors-twice");
    let cfg = sb.config(GENTLE_RT);
    let mut first = sb.start_ppmd(&cfg, "a.trace");
    let lock = sb.dir.join("ipc").join(format!("ppmd-{}.lock", sb.name));
    let b = format!("sim:{}", sb.dir.join("b.trace").display());
    let got = refusal(
        &sb,
        "ppmd",
        &["--config", cfg.to_str().unwrap(), "--output", &b],
        "second",
        1,
    );
    assert_eq!(
        got,
        format!(
            "output `{}` is driven by ppmd pid {}, which holds {}: two ppmd on one name would drive two lines with the same commands. Stop that one first, or start this one with another --name (and its udp-ingress with the same --name)",
            sb.name,
            first.pid(),
            lock.display()
        )
    );
    assert!(
        !sb.dir.join("b.trace").exists(),
        "the refused ppmd opened no line"
    );
    first.kill();
    assert!(lock.exists(), "a SIGKILLed ppmd leaves its lock file");
    let mut third = sb.start_ppmd(&cfg, "c.trace");
    assert_eq!(
        std::fs::read_to_string(&lock).unwrap().trim(),
        third.pid().to_string()
    );
    third.kill();
}

/// An output this machine does not have stops ppmd with 78 (EX_CONFIG),
/// which the unit does not restart on, naming what the machine has.
#[test]
fn a_missing_output_is_a_configuration_error() {
    let sb = Sandbox::new("errors-missing");
    let cfg = sb.config(GENTLE_RT);
    let cfg = cfg.to_str().unwrap();
    let got = refusal(
        &sb,
        "ppmd",
        &["--config", cfg, "--output", "gpio:pinctrl-nosuch:GPIO18"],
        "gpio",
        78,
    );
    assert!(got.contains("pinctrl-nosuch"), "{got}");
    let sbus = sb.config(&format!("{GENTLE_RT}[ppm]\nprotocol = \"sbus\"\n"));
    let tty = sb.dir.join("ttyNONE");
    let got = refusal(
        &sb,
        "ppmd",
        &[
            "--config",
            sbus.to_str().unwrap(),
            "--output",
            &format!("serial:{}", tty.display()),
        ],
        "serial",
        78,
    );
    assert!(
        got.contains(&format!("opening {}: No such file", tty.display())),
        "{got}"
    );
    // A file that is not a tty.
    let file = sb.write_file("not-a-tty", "", 0o600);
    let got = refusal(
        &sb,
        "ppmd",
        &[
            "--config",
            sbus.to_str().unwrap(),
            "--output",
            &format!("serial:{}", file.display()),
        ],
        "notty",
        78,
    );
    assert!(got.contains("is not a tty"), "{got}");
}
