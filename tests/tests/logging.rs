//! Log lines under systemd's journal: `<N>` priority prefixes and no
//! timestamp when standard error is the journal's stream (JOURNAL_STREAM)
//! or with `--log-format journal`; timestamped text otherwise.

use nix::sys::signal::Signal;
use ppm_tests::Sandbox;
use std::os::unix::fs::MetadataExt;
use std::time::Duration;

const SECOND: Duration = Duration::from_secs(1);

/// Starts ppmd (log `log`) with `args` and `env`, with an option that
/// cannot be had (so a warning is logged), stops it, returns its log.
fn ppmd_log(sb: &Sandbox, log: &str, args: &[&str], env: &[(&str, &str)]) -> String {
    let cfg = sb.config("[rt]\npriority = 80\ncpu = 4000\nallow_degraded = true\n");
    let output = format!("sim:{}", sb.dir.join(format!("{log}.trace")).display());
    let mut all = vec!["--config", cfg.to_str().unwrap(), "--output", &output];
    all.extend(args);
    let mut p = sb.spawn_with_env("ppmd", &all, env, log);
    p.wait_for_log("commands from", 30 * SECOND);
    assert!(p.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    p.log_text()
}

fn check_journal(text: &str) {
    let lines: Vec<&str> = text.lines().collect();
    assert!(lines.len() >= 3, "{text}");
    for l in &lines {
        assert!(
            l.starts_with("<3>")
                || l.starts_with("<4>")
                || l.starts_with("<6>")
                || l.starts_with("<7>"),
            "no priority prefix: {l}\n{text}"
        );
        assert!(
            !l.contains("Z INFO") && !l.contains("Z WARN"),
            "a timestamp: {l}"
        );
    }
    assert!(
        lines.iter().any(|l| l.starts_with("<4>DEGRADED RUN")),
        "the warning at priority 4:\n{text}"
    );
    assert!(
        lines.iter().any(|l| l.starts_with("<6>real-time:")),
        "{text}"
    );
}

#[test]
fn under_the_journal_lines_carry_priorities_and_no_timestamp() {
    let sb = Sandbox::new("journal");
    // Asked for.
    check_journal(&ppmd_log(&sb, "asked", &["--log-format", "journal"], &[]));

    // Found: JOURNAL_STREAM names the file standard error is (the log file
    // is created first, and truncated in place by the spawn).
    let path = sb.dir.join("found.log");
    std::fs::write(&path, "").unwrap();
    let m = std::fs::metadata(&path).unwrap();
    let stream = format!("{}:{}", m.dev(), m.ino());
    check_journal(&ppmd_log(&sb, "found", &[], &[("JOURNAL_STREAM", &stream)]));

    // A JOURNAL_STREAM inherited by a process whose standard error is
    // elsewhere: plain, timestamped lines.
    let plain = ppmd_log(&sb, "inherited", &[], &[("JOURNAL_STREAM", "1:2")]);
    assert!(plain.lines().all(|l| l.starts_with("[20")), "{plain}");
    assert!(plain.contains(" WARN  ppmd] DEGRADED RUN"), "{plain}");
}
