//! Reading PPM back: what a radio's module bay, a radio's trainer jack in
//! "slave" mode or a CPPM receiver output carries, read from the edges of
//! an input line.
//!
//! - [`InputSpec`]: where an input is read (`gpio:CHIP:LINE`, `gpio:LINE`,
//!   `sim:PATH`).
//! - [`EdgeEvent`]: one edge as the GPIO character device reports it (or as
//!   the simulated line's trace holds it).
//! - [`decode`]: the capture decoder: edges in, whole frames out, every
//!   frame it refuses counted by reason.
//! - [`readback`]: whether the frames read are the ones ppm sent: the
//!   `following`, `overridden` or `no_input` state.

pub mod decode;
pub mod readback;

pub use decode::{Capture, CaptureCounts, CaptureSettings, ReadFrame};
pub use readback::{Carried, MatchSettings, Matcher, ReadbackState, Verdict};

use crate::signal::Level;
use std::path::PathBuf;

/// One edge of an input line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EdgeEvent {
    /// When the kernel saw it (its interrupt handler's timestamp),
    /// CLOCK_MONOTONIC ns.
    pub at_ns: u64,
    /// The line's level after the edge (high after a rising edge).
    pub level: Level,
    /// The kernel's sequence number of this edge on its line (1, 2, ...):
    /// a gap between two events means the kernel's event buffer overflowed
    /// and the events between were lost.
    pub seq: u64,
}

/// Where an input is read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum InputSpec {
    /// A trace in the simulated line's format (see [`crate::trace`]), read
    /// while it grows: what a test (or `ppmd`'s own simulated line) writes.
    Sim { path: PathBuf },
    /// A GPIO line through the GPIO character device, requested as an input
    /// with both edges and kernel timestamps; an empty `chip` (`gpio:LINE`):
    /// the chip that has a line named `line`.
    Gpio { chip: String, line: String },
}

impl std::str::FromStr for InputSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.split_once(':') {
            Some(("sim", path)) if !path.is_empty() => Ok(InputSpec::Sim {
                path: PathBuf::from(path),
            }),
            Some(("gpio", rest)) => match rest.rsplit_once(':') {
                Some((chip, line)) if !chip.is_empty() && !line.is_empty() => Ok(InputSpec::Gpio {
                    chip: chip.into(),
                    line: line.into(),
                }),
                None if !rest.is_empty() => Ok(InputSpec::Gpio {
                    chip: String::new(),
                    line: rest.into(),
                }),
                _ => Err(format!(
                    "`{s}`: a gpio input is gpio:CHIP:LINE (e.g. gpio:gpiochip0:17) or gpio:LINE (e.g. gpio:GPIO17)"
                )),
            },
            _ => Err(format!(
                "`{s}` is not an input: use gpio:CHIP:LINE, gpio:LINE or sim:PATH"
            )),
        }
    }
}

impl std::fmt::Display for InputSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            InputSpec::Sim { path } => write!(f, "sim:{}", path.display()),
            InputSpec::Gpio { chip, line } if chip.is_empty() => write!(f, "gpio:{line}"),
            InputSpec::Gpio { chip, line } => write!(f, "gpio:{chip}:{line}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn input_specs_parse_and_print_back() {
        for s in [
            "sim:/tmp/a.trace",
            "gpio:gpiochip0:17",
            "gpio:GPIO17",
            "gpio:/dev/gpiochip1:3",
        ] {
            let spec: InputSpec = s.parse().unwrap();
            assert_eq!(spec.to_string(), s);
        }
        assert_eq!(
            "gpio:GPIO17".parse::<InputSpec>().unwrap(),
            InputSpec::Gpio {
                chip: String::new(),
                line: "GPIO17".into()
            }
        );
        for bad in [
            "sim",
            "sim:",
            "gpio:",
            "gpio::3",
            "gpio:chip:",
            "spi:/dev/spidev0.0",
            "",
        ] {
            let e = bad.parse::<InputSpec>().unwrap_err();
            assert!(e.contains(&format!("`{bad}`")), "{e}");
        }
    }
}
