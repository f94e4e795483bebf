//! SBUS on the wire: what the configuration knows of it ([`SPEC`]), the
//! lines that carry it and its validated settings ([`SbusWire`]: the
//! receivers of `ppm.receiver`). The frame, the receivers and their timing
//! are [`crate::sbus`]'s; the model's build is [`crate::frame`]'s.

use super::{FrameKind, LineKind, Refusal, Spec};
use crate::sbus::{self, timing::SbusChoice};
use crate::signal::Level;

/// SBUS's validated settings: the receivers of `ppm.receiver`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SbusWire {
    /// The receivers covered, and whose scaling the values are encoded for.
    pub(crate) choice: SbusChoice,
}

impl SbusWire {
    /// See [`super::WireModel::encode_bytes`].
    pub(crate) fn encode(
        &self,
        values_ns: &[u64; crate::signal::MAX_CHANNELS],
        failsafe: bool,
        out: &mut [u8; super::MAX_FRAME_BYTES],
    ) -> usize {
        let mut raw = [0u16; sbus::CHANNELS];
        for (r, &ns) in raw.iter_mut().zip(values_ns) {
            *r = self.choice.raw(ns);
        }
        let flags = sbus::Flags {
            failsafe,
            ..Default::default()
        };
        out[..sbus::FRAME_LEN].copy_from_slice(&sbus::encode(&raw, flags));
        sbus::FRAME_LEN
    }

    /// See [`super::WireModel::reads`].
    pub(crate) fn reads(
        &self,
        bytes: &[u8],
        values: &mut [u64; crate::signal::MAX_CHANNELS],
    ) -> usize {
        let Ok(frame) = bytes.try_into() else {
            return 0;
        };
        let r = self.choice.encode_for();
        for (v, raw) in values.iter_mut().zip(sbus::channels(frame)) {
            *v = r.read_ns(raw);
        }
        sbus::CHANNELS
    }
}

/// What the configuration knows of SBUS.
pub static SPEC: Spec = Spec {
    name: "sbus",
    title: "SBUS",
    kind: FrameKind::Bytes,
    channels: sbus::CHANNELS as u32,
    frame_us: sbus::timing::PERIOD_DEFAULT_US,
    idle_level: Level::High,
    gap: "idle line",
    failsafe_flag: true,
    reads_back: false,
    grid_checks_follow: false,
    uses_spi_hz: false,
    unused_keys: &[
        (
            "ppm.pulse_us",
            "an SBUS frame is bytes at 100000 baud, without separator pulses",
        ),
        (
            "ppm.late_edge_guard_us",
            "an SBUS frame leaves whole, in one write, so no edge of it is guarded",
        ),
    ],
    check_line,
    line_idle_level,
};

/// The idle level an SBUS output takes when `ppm.idle_level` is not given:
/// low (true SBUS) through SPI, high (a UART's) elsewhere.
fn line_idle_level(output: LineKind) -> Option<Level> {
    Some(match output {
        LineKind::Spi => Level::Low,
        _ => Level::High,
    })
}

/// An SBUS output: a line that sends its bytes whole, at the polarity
/// `ppm.idle_level` names.
fn check_line(output: LineKind, idle: Option<Level>, out: &str) -> Result<(), Refusal> {
    match (output, idle) {
        (LineKind::SimWhole, _) => Err((
            "ppmd.output",
            format!(
                "`{out}` simulates a PPM output sent whole through SPI; an SBUS output's simulated line (sim or sim:PATH) already takes each frame whole"
            ),
        )),
        (LineKind::Gpio, _) => Err((
            "ppmd.output",
            format!(
                "`{out}`: SBUS is 10 us bits that must leave back to back, which a GPIO line written from software cannot hold: use serial:DEVICE (a UART, SBUS idling high) or spi:DEVICE (true SBUS, idling low)"
            ),
        )),
        (LineKind::Serial, Some(Level::Low)) => Err((
            "ppm.idle_level",
            format!(
                "\"low\" (true, inverted SBUS) cannot be sent through `{out}`: a UART idles high; use an spi: output (MOSI idles low), or an inverter in the cable with idle_level = \"high\""
            ),
        )),
        (LineKind::Spi, Some(Level::High)) => Err((
            "ppm.idle_level",
            format!(
                "\"high\" SBUS cannot be sent through `{out}`: between transfers an SPI controller leaves MOSI low, a break in an idle-high line; use a serial: output (a UART idles high), or an inverter in the cable with idle_level = \"low\""
            ),
        )),
        _ => Ok(()),
    }
}
