//! PPM on the wire: what the configuration knows of it ([`SPEC`]), the
//! lines that carry it, and its validated settings ([`PpmWire`]). The model
//! itself is built by [`crate::frame`].

use super::{FrameKind, LineKind, Refusal, Spec};
use crate::signal::Level;

/// `ppm.channels`' default.
pub const CHANNELS_DEFAULT: u32 = 8;
/// `ppm.frame_us`' default.
pub const FRAME_US_DEFAULT: f64 = 22_500.0;

/// PPM's validated settings: the separator pulse.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PpmWire {
    /// Separator pulse width, ns.
    pub(crate) pulse_ns: u64,
}

/// What the configuration knows of PPM.
pub static SPEC: Spec = Spec {
    name: "ppm",
    title: "PPM",
    kind: FrameKind::Pulses,
    channels: CHANNELS_DEFAULT,
    frame_us: FRAME_US_DEFAULT,
    idle_level: Level::Low,
    gap: "sync",
    failsafe_flag: false,
    reads_back: true,
    grid_checks_follow: true,
    uses_spi_hz: true,
    unused_keys: &[],
    check_line,
    line_idle_level: |_| None,
};

/// A PPM output: a line PPM's edges can be written on.
fn check_line(output: LineKind, idle: Option<Level>, shown: &str) -> Result<(), Refusal> {
    let high = idle.unwrap_or(SPEC.idle_level) == Level::High;
    match output {
        LineKind::Spi if high => Err((
            "ppm.idle_level",
            format!(
                "\"high\" cannot be sent through `{shown}`: between transfers an SPI controller leaves MOSI low (or at the last bit), which would add an edge to every sync; use idle_level = \"low\" (an inverter in the cable gives a transmitter that wants high), or a gpio: output"
            ),
        )),
        LineKind::SimWhole if high => Err((
            "ppm.idle_level",
            format!(
                "\"high\" cannot be sent through `{shown}`, which simulates an SPI output (MOSI rests low between transfers): use idle_level = \"low\", or a sim: output"
            ),
        )),
        LineKind::Serial => Err((
            "ppmd.output",
            format!(
                "`{shown}` carries a serial protocol, not PPM: set ppm.protocol = \"sbus\" (a radio's serial trainer input or a flight controller) or \"crsf\" (a flight controller), or use a gpio: or spi: output for a trainer jack"
            ),
        )),
        _ => Ok(()),
    }
}
