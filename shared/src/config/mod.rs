//! The configuration: the TOML file both `ppmd` and `udp-ingress` read, and
//! the plan it resolves to.
//!
//! Every key is optional; a missing key takes the default documented on its
//! field. Unknown keys are errors, so a typo cannot silently fall back to a
//! default. Errors name the key and say how to fix it.
//!
//! - [`schema`]: the file's sections ([`Config`]), as serde reads them, and
//!   [`Config::load`].
//! - [`merge`]: the `[[outputs]]` entries, each laid over the top-level
//!   sections, and how an error met in one is named (`outputs[1].ppm.channels`).
//! - [`check`]: the checks of one output's keys ([`Config::validate`]); the
//!   `[ppm]` section is checked by the frame module, which builds the
//!   [`FrameModel`](crate::frame::FrameModel) ([`FrameModel::build`](crate::frame::FrameModel::build)).
//! - [`keys`]: which keys the file set, and how messages name them;
//!   [`inert`]: the keys set that do nothing where they are (a warning at
//!   start); [`fault`]: the files and devices keys name, and which of their
//!   faults stop a program as the configuration's (exit status 78).
//! - [`plan`]: the lowering: a file with the command line applied resolves
//!   once into a [`Plan`] (shared settings, one [`OutputPlan`] per output),
//!   which both programs run.

pub mod check;
pub mod fault;
pub mod inert;
pub mod keys;
pub mod merge;
pub mod plan;
pub mod schema;
#[cfg(test)]
mod tests;

pub use crate::frame::{
    channel_names, ChannelOverride, InvalidKey, PpmSection, FOLLOW_SYNC_CEILING_US,
    LATE_EDGE_GUARD_MAX_US, LATE_EDGE_GUARD_US, TRIM_MAX_US,
};
pub use crate::signal::Timing;
pub use crate::signal::{CHANNEL_MAX_US, CHANNEL_MIN_US, SYNC_MAX_US, SYNC_MIN_US};
pub use check::{parse_net, validate_name};
pub use inert::{Inert, Program};
pub use keys::{KeyName, SetKeys};
pub use merge::{ConfigFile, OutputEntry, MAX_OUTPUTS};
pub use plan::{OutputPlan, PilotPlan, Plan, ReadbackPlan, Shared};
pub use schema::{
    Config, CpuChoice, FailsafeAction, FailsafeSection, IngressCpu, IngressSection, IpcSection,
    OutputSpec, PilotSection, PpmdSection, ReadbackSection, RtSection, SpinMargin, DEFAULT_NAME,
};
use std::path::PathBuf;

/// Why a configuration was refused. Every variant names the file or the key.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read (why: its source).
    #[error("cannot read config file {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is not valid TOML, has an unknown key or a value of the wrong type.
    #[error("config file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    /// A key has a value a transmitter would reject or misread.
    #[error("config key `{key}`: {message}")]
    Invalid { key: String, message: String },
    /// A command-line choice does not fit the configuration.
    #[error("{0}")]
    Usage(String),
}

impl ConfigError {
    pub(crate) fn invalid(key: impl Into<String>, message: impl Into<String>) -> Self {
        ConfigError::Invalid {
            key: key.into(),
            message: message.into(),
        }
    }

    /// The key this error is about, when it is about one key.
    pub fn key(&self) -> Option<&str> {
        match self {
            ConfigError::Invalid { key, .. } => Some(key),
            _ => None,
        }
    }
}

impl From<InvalidKey> for ConfigError {
    fn from(e: InvalidKey) -> Self {
        ConfigError::Invalid {
            key: e.key,
            message: e.message,
        }
    }
}
