//! What ppmd and udp-ingress do alike at start: the options both take
//! (`--config`, `--log-format`) and setting up the logs as they ask. (Each
//! says its own fatal error, so the log line bears its name.)

use crate::logging::LogFormat;
use std::path::PathBuf;

/// The options every ppm daemon takes; a daemon's options flatten them in
/// (`#[command(flatten)]`).
#[derive(clap::Args, Debug, Clone, PartialEq, Eq)]
pub struct DaemonArgs {
    /// Configuration file (TOML); every key has a default.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Log lines: `journal` (`<N>` priority prefixes, no timestamp),
    /// `plain` (timestamped), or `auto`: journal when standard error is
    /// systemd's journal (JOURNAL_STREAM), else plain.
    #[arg(long, value_enum, default_value_t = LogFormat::Auto, value_name = "FORMAT")]
    pub log_format: LogFormat,
}

impl DaemonArgs {
    /// Sets up the logs as `--log-format` asks, and iceoryx2's own log
    /// level (`IOX2_LOG_LEVEL`).
    pub fn init_logging(&self) {
        crate::logging::init(self.log_format);
        crate::ipc::init_ipc_logging();
    }
}

/// The exit status of a daemon stopped by its configuration (a bad key, a
/// file or directory a key names that is missing, of the wrong kind, not
/// permitted or corrupt, a CPU this machine does not have, a real-time
/// setting it does not grant, an output it does not have): `EX_CONFIG` of
/// sysexits.h. The units say `RestartPreventExitStatus=78`, so systemd does
/// not restart into the same error every second.
pub const EXIT_CONFIG: i32 = 78;

/// The exit status of any other fatal error: one a restart may cure (a
/// full disk, a port or GPIO line another process still holds, ...).
pub const EXIT_FAILURE: i32 = 1;

/// The exit status for a daemon's fatal error `e`: [`EXIT_CONFIG`] when
/// the configuration is at fault (a [`ConfigError`](crate::config::ConfigError),
/// a key file's [`KeyError`](crate::auth::KeyError) or a real-time
/// [`Shortfall`](crate::sched::Shortfall) that a restart meets again
/// ([`Shortfall::is_config`](crate::sched::Shortfall::is_config)), anywhere
/// in its chain, or a cause that `is_config` says is one), else
/// [`EXIT_FAILURE`].
pub fn exit_status(
    e: &anyhow::Error,
    is_config: impl Fn(&(dyn std::error::Error + 'static)) -> bool,
) -> i32 {
    let config = e.chain().any(|c| {
        c.is::<crate::config::ConfigError>()
            || c.is::<crate::auth::KeyError>()
            || c.downcast_ref::<crate::sched::Shortfall>()
                .is_some_and(|s| s.is_config())
            || is_config(c)
    });
    if config {
        EXIT_CONFIG
    } else {
        EXIT_FAILURE
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[test]
    fn configuration_errors_exit_78_others_1() {
        let e = anyhow::Error::new(crate::config::ConfigError::invalid("ppm.channels", "bad"))
            .context("starting");
        assert_eq!(exit_status(&e, |_| false), EXIT_CONFIG);
        let e = anyhow::anyhow!("a socket failed");
        assert_eq!(exit_status(&e, |_| false), EXIT_FAILURE);
        let io = anyhow::Error::new(std::io::Error::other("no such line")).context("output `x`");
        assert_eq!(exit_status(&io, |c| c.is::<std::io::Error>()), EXIT_CONFIG);
        let rt = anyhow::Error::new(crate::sched::Shortfall::new(
            "SCHED_FIFO",
            "refused".into(),
            "",
        ))
        .context("config key `rt.priority`");
        assert_eq!(exit_status(&rt, |_| false), EXIT_CONFIG);
        // What a restart may get: locked memory (memory pressure), the
        // latency device (its group comes from udev at boot).
        for what in ["mlockall", "cpu_dma_latency", "timer slack"] {
            let rt = anyhow::Error::new(crate::sched::Shortfall::new(what, "refused".into(), ""));
            assert_eq!(exit_status(&rt, |_| false), EXIT_FAILURE, "{what}");
        }
    }

    #[derive(Parser)]
    struct Daemon {
        #[command(flatten)]
        daemon: DaemonArgs,
    }

    #[test]
    fn both_options_parse_with_their_defaults() {
        let d = Daemon::try_parse_from(["d"]).unwrap().daemon;
        assert_eq!(
            d,
            DaemonArgs {
                config: None,
                log_format: LogFormat::Auto
            }
        );
        let d = Daemon::try_parse_from(["d", "--config", "a.toml", "--log-format", "journal"])
            .unwrap()
            .daemon;
        assert_eq!(d.config, Some(PathBuf::from("a.toml")));
        assert_eq!(d.log_format, LogFormat::Journal);
        assert!(Daemon::try_parse_from(["d", "--log-format", "xml"]).is_err());
    }
}
