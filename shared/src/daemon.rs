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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

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
