//! A CRSF output's telemetry as udp-ingress reports it: ppmd's telemetry
//! thread publishes a [`TelemetrySample`] (the reader's counts and the
//! newest frame of each kind the flight controller sent) whenever it reads
//! a good frame and every tenth of a second; udp-ingress keeps the newest,
//! puts it in every status reply ([`Telemetry::status`]), sends MAVLink
//! peers SYS_STATUS, ATTITUDE and GPS_RAW_INT as new frames come
//! ([`crate::peers::Peers::due`]), and a STATUSTEXT when the flight mode
//! changes ([`Telemetry::seen`]).
//!
//! Logic only, without I/O; its tests are in `src/telemetry/tests.rs`.

use ppm_shared::crsf::report::{printable, TelemetryStatus, FLIGHT_MODE};
use ppm_shared::crsf::Telemetry as Decoded;
use ppm_shared::ipc::TelemetrySample;

/// The telemetry of one output, as seen from udp-ingress.
#[derive(Debug, Clone)]
pub struct Telemetry {
    /// The tty read (the output's `serial:` device).
    port: String,
    newest: Option<TelemetrySample>,
    /// The flight mode last told.
    mode: Option<Vec<u8>>,
}

impl Telemetry {
    /// The telemetry read from `port`, nothing seen yet.
    pub fn new(port: String) -> Telemetry {
        Telemetry {
            port,
            newest: None,
            mode: None,
        }
    }

    /// Takes sample `s` (the newest ppmd published): the flight mode it
    /// carries, if it differs from the one last seen (the first one seen
    /// too: a groundstation learns the mode it starts in).
    pub fn seen(&mut self, s: TelemetrySample) -> Option<String> {
        self.newest = Some(s);
        let Some((_, Decoded::FlightMode(f))) = s.newest(FLIGHT_MODE) else {
            return None;
        };
        if self.mode.as_deref() == Some(f.as_bytes()) {
            return None;
        }
        self.mode = Some(f.as_bytes().to_vec());
        Some(printable(f.as_bytes()))
    }

    /// The newest sample seen, if any.
    pub fn newest(&self) -> Option<&TelemetrySample> {
        self.newest.as_ref()
    }

    /// The status reply's `telemetry` member at CLOCK_MONOTONIC
    /// `now_mono_ns` (`stale` before the first sample).
    pub fn status(&self, now_mono_ns: u64) -> TelemetryStatus {
        TelemetryStatus::of(&self.newest.unwrap_or_default(), &self.port, now_mono_ns)
    }
}

/// The STATUSTEXT telling output `name`'s flight mode `mode`.
pub fn statustext(name: &str, mode: &str) -> String {
    format!("ppm {name}: flight mode {mode}")
}

#[cfg(test)]
mod tests;
