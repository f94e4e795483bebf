//! Where read-back gets its edges: an input line's edges, one
//! [`EdgeEvent`] each, for the capture decoder
//! ([`ppm_shared::capture::decode`]). Read by the read-back thread, which
//! runs at normal priority, never in the timing loop: a source may sleep,
//! poll and return errors with messages.
//!
//! - [`EdgeSource`]: the trait both sources implement, and [`open`], which
//!   opens the one an [`InputSpec`] names.
//! - [`gpio`]: a GPIO line requested as an input, both edges, kernel
//!   timestamps (CLOCK_MONOTONIC), events read in batches from the
//!   kernel's buffer ([`gpio::EVENT_BUFFER_SIZE`] deep).
//! - [`sim`]: a trace of the simulated line (`ppm_shared::trace`) followed
//!   while it grows, across its rotations, like `tail -F`.
//! - [`InputError`]: why an input cannot be opened or read, naming it.

pub mod gpio;
pub mod sim;

use crate::line::gpio::GpioError;
use ppm_shared::capture::{EdgeEvent, InputSpec};
use ppm_shared::signal::Level;
use std::path::PathBuf;
use std::time::Duration;

pub use gpio::GpioInput;
pub use sim::SimInput;

/// The consumer label a GPIO input is requested with (`gpioinfo` shows it).
pub const CONSUMER: &str = "ppmd-readback";
/// The consumer label a pilot's radio's GPIO input is requested with.
pub const PILOT_CONSUMER: &str = "ppmd-pilot";

/// A source of an input line's edges, in the order they happened.
pub trait EdgeSource: Send {
    /// Waits up to `timeout` for edges and puts those available, at most
    /// `out.len()`, at the start of `out`; returns how many. `Ok(0)` when
    /// none came in time (or `out` is empty). Edges not taken stay for the
    /// next call.
    fn read(&mut self, out: &mut [EdgeEvent], timeout: Duration) -> Result<usize, InputError>;

    /// What is read, for messages: `GPIO17 (offset 17) on /dev/gpiochip0
    /// (gpiochip0, pinctrl-bcm2711, 58 lines)`, `sim:/run/ppm/out.trace`.
    fn description(&self) -> &str;

    /// The level the line idles at, when the source knows it (a sim
    /// trace's `# idle_level` header, once read).
    fn idle_level(&self) -> Option<Level> {
        None
    }
}

/// Opens the input `spec` names: a GPIO line requested at once (consumer
/// [`CONSUMER`]), or a sim trace, which need not exist yet.
pub fn open(spec: &InputSpec) -> Result<Box<dyn EdgeSource>, InputError> {
    open_as(spec, CONSUMER)
}

/// [`open`], a GPIO line requested as `consumer` (what `gpioinfo` shows:
/// [`PILOT_CONSUMER`] for a pilot's radio).
pub fn open_as(spec: &InputSpec, consumer: &str) -> Result<Box<dyn EdgeSource>, InputError> {
    match spec {
        InputSpec::Sim { path } => Ok(Box::new(SimInput::open(path))),
        InputSpec::Gpio { chip, line } => Ok(Box::new(GpioInput::open(chip, line, consumer)?)),
    }
}

/// Why an input could not be opened or read. Every message names the input.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// The GPIO line could not be had: no such chip or line (the message
    /// lists what there is), held by another consumer (named), permission.
    #[error("input {input}: {error}")]
    Gpio {
        /// The input as given (`gpio:gpiochip0:17`).
        input: String,
        /// Why, as for an output's line.
        error: GpioError,
    },
    /// Waiting for or reading the requested line's edge events failed.
    #[error("input {line}: {op} failed: {detail}")]
    GpioRead {
        /// The line and its chip.
        line: String,
        /// What was being done.
        op: &'static str,
        /// The error, as gpiocdev reports it.
        detail: String,
    },
    /// The trace exists but cannot be opened, or its name cannot be looked
    /// at (a missing file is waited for, not an error).
    #[error("input sim:{}: cannot open it: {error}", path.display())]
    SimOpen {
        /// The trace's path.
        path: PathBuf,
        /// The system's error.
        error: std::io::Error,
    },
    /// Reading the trace failed (a directory, an I/O error).
    #[error("input sim:{}: cannot read it: {error}", path.display())]
    SimRead {
        /// The trace's path.
        path: PathBuf,
        /// The system's error.
        error: std::io::Error,
    },
    /// A complete line of the trace that is neither an edge nor a comment.
    #[error("input sim:{} line {line}: `{text}` is not an edge (`<scheduled_ns> <actual_ns> <0|1>`) nor a `#` comment", path.display())]
    Malformed {
        /// The trace's path.
        path: PathBuf,
        /// Its line number, counted from the top of the file it is in (a
        /// rotation starts the count again).
        line: usize,
        /// The line (its start, when long).
        text: String,
    },
}

impl InputError {
    /// The GPIO error inside, to tell a configuration's fault (no such
    /// chip or line) from what a restart may cure (a busy line).
    pub fn gpio(&self) -> Option<&GpioError> {
        match self {
            InputError::Gpio { error, .. } => Some(error),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_names_the_missing_gpio_chip_and_what_exists() {
        let spec: InputSpec = "gpio:ppm-no-such-chip:17".parse().unwrap();
        let e = open(&spec).err().expect("no such chip");
        let msg = e.to_string();
        assert!(
            msg.starts_with("input gpio:ppm-no-such-chip:17: no GPIO chip `ppm-no-such-chip`"),
            "{msg}"
        );
        assert!(
            matches!(e.gpio(), Some(GpioError::NoSuchChip { chip, .. }) if chip == "ppm-no-such-chip"),
            "{e:?}"
        );
        let spec: InputSpec = "gpio:PPM_NO_SUCH_LINE".parse().unwrap();
        let e = open(&spec).err().expect("no such line");
        let msg = e.to_string();
        assert!(msg.starts_with("input gpio:PPM_NO_SUCH_LINE: "), "{msg}");
        assert!(msg.contains("`PPM_NO_SUCH_LINE`"), "{msg}");
        assert!(
            matches!(e.gpio(), Some(GpioError::NoLineAnywhere { line, .. }) if line == "PPM_NO_SUCH_LINE"),
            "{e:?}"
        );
    }

    #[test]
    fn open_takes_a_sim_trace_that_does_not_exist_yet() {
        let path = std::env::temp_dir().join(format!("ppmd-input-none-{}", std::process::id()));
        let spec = InputSpec::Sim { path: path.clone() };
        let mut src = open(&spec).unwrap();
        assert_eq!(src.description(), format!("sim:{}", path.display()));
        let mut out = [EdgeEvent {
            at_ns: 0,
            level: Level::Low,
            seq: 0,
        }; 4];
        assert_eq!(src.read(&mut out, Duration::from_millis(3)).unwrap(), 0);
        assert_eq!(src.idle_level(), None);
    }
}
