//! `ppmd`, the PPM daemon: once per frame it takes the newest command, encodes
//! the frame and emits every edge at its scheduled time through an
//! [`output::Output`] backend.
//!
//! - [`clock`]: CLOCK_MONOTONIC reads and absolute sleeps.
//! - [`output`]: the backend trait and the simulated line.
//! - [`emitter`]: the timing loop (no allocation, logging or locks inside).
//! - [`source`]: where commands come from (iceoryx2 in the daemon).

pub mod clock;
pub mod emitter;
pub mod meter;
pub mod output;
pub mod rt;
pub mod source;
