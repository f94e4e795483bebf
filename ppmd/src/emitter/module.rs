//! Following an ExpressLRS transmitter module's timing corrections: the
//! module says every 200 ms at what period it wants RC frames (`RATE`) and
//! how early the last ones came against its radio's packet timer
//! (`OFFSET`, less its 100 us margin); a grid output that drives a module
//! sends at `RATE` and adds `OFFSET` to its next period once, as EdgeTX
//! does (`ModuleSyncStatus::getAdjustedRefreshRate`).
//!
//! The telemetry thread, which reads the module's side of the line, leaves
//! each correction in a [`ModuleTiming`]; the timing loop reads it when it
//! places a frame, without a lock or a wait (a sequence-counted copy with
//! one writer). When the module answers for the first time, or again after
//! [`ALIVE_NS`] of silence, the thread asks for the model ID command, which
//! the loop writes right before its next RC frame, in the same write (as
//! EdgeTX sends it when the module comes alive; EdgeTX sends it in place of
//! an RC frame).

use ppm_shared::crsf::module::Correction;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};

/// A correction older than this is dropped: the grid goes back to
/// `ppm.frame_us` (EdgeTX's `isValid`: 2 s without a correction).
pub const STALE_NS: u64 = 2_000_000_000;
/// A module silent this long, then answering, has come back (restarted,
/// or found the handset again after searching the baud rates): it is sent
/// the model ID again (EdgeTX's `MODULE_ALIVE_TIMEOUT`, 500 ms).
pub const ALIVE_NS: u64 = 500_000_000;
/// The longest period a correction may set, ns (EdgeTX's
/// `MAX_REFRESH_RATE`, 50 ms).
pub const PERIOD_MAX_NS: u64 = 50_000_000;

/// The newest correction the module sent, for the timing loop.
#[derive(Debug, Default)]
pub struct ModuleTiming {
    /// Even: the fields are whole; odd: being written. Bumped twice per
    /// correction, so `seq / 2` counts them.
    seq: AtomicU64,
    rate_ns: AtomicU64,
    offset_ns: AtomicI64,
    at_ns: AtomicU64,
    /// The module came (back): the next frame goes after a model ID
    /// command.
    model_id_due: AtomicBool,
    /// Model ID commands the loop sent.
    model_ids: AtomicU64,
}

/// A correction as the loop reads it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Taken {
    /// Its number (1, 2, ...): a new one has a higher number.
    pub number: u64,
    /// The period the module wants, ns.
    pub rate_ns: u64,
    /// How much later the next frame should start, ns (negative: earlier).
    pub offset_ns: i64,
    /// CLOCK_MONOTONIC time it was read, ns.
    pub at_ns: u64,
}

impl ModuleTiming {
    /// Leaves correction `c`, read at `now_ns`. One writer only.
    pub fn set(&self, c: Correction, now_ns: u64) {
        let v = self.seq.load(Ordering::Relaxed);
        self.seq.store(v + 1, Ordering::Relaxed);
        // The odd number is seen before any field it guards (a store
        // after a release fence is not reordered before the fence's
        // earlier stores; on a Pi's weak memory this matters).
        std::sync::atomic::fence(Ordering::Release);
        self.rate_ns.store(c.rate_ns(), Ordering::Relaxed);
        self.offset_ns.store(c.offset_ns(), Ordering::Relaxed);
        self.at_ns.store(now_ns, Ordering::Relaxed);
        self.seq.store(v + 2, Ordering::Release);
    }

    /// The newest correction, if there is one and it was not being written
    /// over the read (then the next read has it). Never waits.
    pub fn get(&self) -> Option<Taken> {
        let before = self.seq.load(Ordering::Acquire);
        if before == 0 || before % 2 == 1 {
            return None;
        }
        let t = Taken {
            number: before / 2,
            rate_ns: self.rate_ns.load(Ordering::Relaxed),
            offset_ns: self.offset_ns.load(Ordering::Relaxed),
            at_ns: self.at_ns.load(Ordering::Relaxed),
        };
        std::sync::atomic::fence(Ordering::Acquire);
        (self.seq.load(Ordering::Relaxed) == before).then_some(t)
    }

    /// Corrections left so far.
    pub fn count(&self) -> u64 {
        self.seq.load(Ordering::Relaxed) / 2
    }

    /// Asks the loop to send the model ID command before its next frame
    /// (the module answered for the first time, or again after
    /// [`ALIVE_NS`] of silence).
    pub fn request_model_id(&self) {
        self.model_id_due.store(true, Ordering::Relaxed);
    }

    /// The loop, at a frame: whether the model ID command goes first
    /// (once per request).
    pub fn take_model_id(&self) -> bool {
        let due = self.model_id_due.swap(false, Ordering::Relaxed);
        if due {
            self.model_ids.fetch_add(1, Ordering::Relaxed);
        }
        due
    }

    /// Model ID commands sent so far.
    pub fn model_ids(&self) -> u64 {
        self.model_ids.load(Ordering::Relaxed)
    }
}
