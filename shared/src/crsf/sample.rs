//! The sample ppmd's telemetry thread publishes for udp-ingress
//! (`ppm/NAME/telemetry`, the service `crate::ipc` names): plain
//! bytes in shared memory, the newest frame of each kind as it came, which
//! readers decode themselves.

use iceoryx2::prelude::ZeroCopySend;

/// Kinds of telemetry a [`TelemetrySample`] carries
/// ([`super::telemetry::KIND_NAMES`]).
pub const TELEMETRY_KINDS: usize = super::telemetry::KINDS;
/// Counts a [`TelemetrySample`] carries
/// ([`super::TelemetryCounts::NAMES`]).
pub const TELEMETRY_COUNTS: usize = super::TelemetryCounts::LEN;

/// Output `name`'s CRSF telemetry, published by ppmd's telemetry thread at
/// every batch of bytes it reads that held a good frame, and every tenth of
/// a second, on `ppm/NAME/telemetry`: the reader's counts and the
/// newest good frame of each kind, as it came (address to CRC). Readers
/// decode the frames with [`super::telemetry::decode_frame`], so the
/// sample stays plain bytes, whatever the frames hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ppm::TelemetrySample")]
#[repr(C)]
pub struct TelemetrySample {
    /// CLOCK_MONOTONIC time of publication, ns.
    pub published_mono_ns: u64,
    /// The reader's counts ([`super::TelemetryCounts::to_array`]).
    pub counts: [u64; TELEMETRY_COUNTS],
    /// CLOCK_MONOTONIC time the newest frame of each kind was read, ns (0:
    /// none yet).
    pub at_mono_ns: [u64; TELEMETRY_KINDS],
    /// The newest frame of each kind, address to CRC, zeros after it.
    pub frames: [[u8; super::MAX_FRAME_LEN]; TELEMETRY_KINDS],
}

impl Default for TelemetrySample {
    fn default() -> Self {
        TelemetrySample {
            published_mono_ns: 0,
            counts: [0; TELEMETRY_COUNTS],
            at_mono_ns: [0; TELEMETRY_KINDS],
            frames: [[0; super::MAX_FRAME_LEN]; TELEMETRY_KINDS],
        }
    }
}

impl TelemetrySample {
    /// Keeps `frame` (a good frame, address to CRC), which decoded to `t`,
    /// read at `at_ns`, as the newest of its kind.
    pub fn take(&mut self, frame: &[u8], t: &super::Telemetry, at_ns: u64) {
        let k = t.kind();
        let n = frame.len().min(super::MAX_FRAME_LEN);
        self.frames[k] = [0; super::MAX_FRAME_LEN];
        self.frames[k][..n].copy_from_slice(&frame[..n]);
        self.at_mono_ns[k] = at_ns;
    }

    /// The newest telemetry of kind `k` and when it was read, if any.
    pub fn newest(&self, k: usize) -> Option<(u64, super::Telemetry)> {
        let at = *self.at_mono_ns.get(k)?;
        if at == 0 {
            return None;
        }
        let f = &self.frames[k];
        let len = (usize::from(f[1]) + 2).min(f.len());
        super::telemetry::decode_frame(&f[..len])
            .filter(|t| t.kind() == k)
            .map(|t| (at, t))
    }

    /// The reader's counts.
    pub fn counts(&self) -> super::TelemetryCounts {
        super::TelemetryCounts::from_array(self.counts)
    }
}
