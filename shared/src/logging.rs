//! Log lines of ppmd and udp-ingress: timestamped text on a terminal, and
//! under systemd's journal `<N>` priority prefixes without a timestamp (the
//! journal stamps each line itself), so `journalctl -p warning` finds the
//! warnings.

use std::io::Write;
use std::os::unix::fs::MetadataExt;

/// How log lines look (`--log-format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum LogFormat {
    /// `journal` when standard error is the journal's stream (systemd's
    /// `JOURNAL_STREAM` names it), else `plain`.
    #[default]
    Auto,
    /// `<N>message`: the syslog priority the journal reads, no timestamp.
    Journal,
    /// `[2026-11-23T13:02:30.123Z INFO  MODULE] message`, MODULE naming the
    /// part of the program that said it.
    Plain,
}

/// The syslog priority of a log level: error 3, warn 4, info 6, debug and
/// trace 7.
pub fn priority(level: log::Level) -> u8 {
    match level {
        log::Level::Error => 3,
        log::Level::Warn => 4,
        log::Level::Info => 6,
        log::Level::Debug | log::Level::Trace => 7,
    }
}

/// True when `journal_stream` (`JOURNAL_STREAM`'s `DEVICE:INODE`) names the
/// file `stderr` is (systemd sets it for a service whose standard error
/// goes to the journal; a child with its own standard error inherits the
/// variable, hence the comparison).
pub fn is_journal_stream(journal_stream: &str, stderr: &std::fs::Metadata) -> bool {
    let Some((dev, ino)) = journal_stream.trim().split_once(':') else {
        return false;
    };
    dev.parse::<u64>().ok() == Some(stderr.dev()) && ino.parse::<u64>().ok() == Some(stderr.ino())
}

/// Resolves `Auto` for this process.
pub fn resolve(format: LogFormat) -> LogFormat {
    match format {
        LogFormat::Auto => {
            let stderr =
                std::fs::metadata("/proc/self/fd/2").or_else(|_| std::fs::metadata("/dev/stderr"));
            match (std::env::var("JOURNAL_STREAM"), stderr) {
                (Ok(js), Ok(meta)) if is_journal_stream(&js, &meta) => LogFormat::Journal,
                _ => LogFormat::Plain,
            }
        }
        f => f,
    }
}

/// One journal line: `<N>message`, every further line of a multi-line
/// message with the same prefix.
pub fn journal_line(level: log::Level, message: &str) -> String {
    let p = priority(level);
    let mut out = String::new();
    for line in message.split('\n') {
        out += &format!("<{p}>{line}\n");
    }
    out
}

/// An error and its sources, each after `: ` (as anyhow's `{:#}` shows
/// them), for logging a typed error whole without Debug output:
/// `log::warn!("publishing failed: {}", Chain(&e))`. Formats straight into
/// the log line, making no string of its own.
pub struct Chain<'a>(pub &'a (dyn std::error::Error + 'static));

impl std::fmt::Display for Chain<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)?;
        let mut source = self.0.source();
        while let Some(s) = source {
            write!(f, ": {s}")?;
            source = s.source();
        }
        Ok(())
    }
}

/// Sets up the `log` crate's logger (`RUST_LOG` filters, default `info`).
pub fn init(format: LogFormat) {
    let mut b = env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("info"));
    match resolve(format) {
        LogFormat::Journal => {
            b.format(|buf, record| {
                buf.write_all(journal_line(record.level(), &record.args().to_string()).as_bytes())
            });
        }
        _ => {
            b.format_timestamp_millis();
        }
    }
    b.init();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_get_syslog_priorities() {
        assert_eq!(
            journal_line(log::Level::Warn, "DEGRADED RUN: x"),
            "<4>DEGRADED RUN: x\n"
        );
        assert_eq!(journal_line(log::Level::Error, "a\nb"), "<3>a\n<3>b\n");
        assert_eq!(priority(log::Level::Info), 6);
        assert_eq!(priority(log::Level::Trace), 7);
    }

    #[test]
    fn a_chain_shows_every_cause_in_order() {
        use crate::ipc::{IpcError, PublishError};
        let loan = PublishError::Loan(iceoryx2::port::LoanError::OutOfMemory);
        let e = IpcError::new("publishing a snapshot", loan);
        assert_eq!(
            Chain(&e).to_string(),
            "shared memory: publishing a snapshot: loaning a sample: LoanError::OutOfMemory"
        );
        let plain = std::io::Error::other("alone");
        assert_eq!(Chain(&plain).to_string(), "alone");
    }

    #[test]
    fn the_journal_stream_is_recognised_by_device_and_inode() {
        let p = std::env::temp_dir().join(format!("ppm-log-{}", std::process::id()));
        std::fs::write(&p, "").unwrap();
        let meta = std::fs::metadata(&p).unwrap();
        let mine = format!("{}:{}", meta.dev(), meta.ino());
        assert!(is_journal_stream(&mine, &meta));
        assert!(!is_journal_stream(
            &format!("{}:{}", meta.dev(), meta.ino() + 1),
            &meta
        ));
        assert!(!is_journal_stream("garbage", &meta));
        assert!(!is_journal_stream("", &meta));
        assert_eq!(resolve(LogFormat::Plain), LogFormat::Plain);
        assert_eq!(resolve(LogFormat::Journal), LogFormat::Journal);
        std::fs::remove_file(&p).unwrap();
    }
}
