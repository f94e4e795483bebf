//! `ppmd`, the PPM daemon: once per frame it takes the newest command, encodes
//! the frame and emits every edge at its scheduled time through an
//! [`output::Output`] backend.
//!
//! - [`cli`]: ppmd's `--output` arguments.
//! - [`clock`]: CLOCK_MONOTONIC reads and absolute sleeps.
//! - [`output`]: the backend trait and the simulated line.
//! - [`emitter`]: the timing loop (no allocation, logging or locks inside).
//! - [`source`]: where commands come from (iceoryx2 in the daemon).
//! - [`framelog`]: the JSON-lines log of every frame sent.
//! - [`lines`]: opening every output's line.
//! - [`monitor`]: the main thread's view of the loop: logs, snapshots, HdrHistogram log.
//! - [`meter`]: histograms of the loop's timing, handed over lock-free.
//! - [`rotating`]: the log files' type: rotated at a size cap, fed by a
//!   lock-free ring and a writer thread.
//! - [`timing`]: the timing thread that runs the lanes.
//! - [`rt`]: the real-time setup of the timing thread.
//! - [`watchdog`]: systemd's watchdog, petted while the timing loop moves.

pub mod cli;
pub mod clock;
pub mod emitter;
pub mod framelog;
pub mod lines;
pub mod meter;
pub mod monitor;
pub mod output;
pub mod rotating;
pub mod rt;
pub mod source;
pub mod timing;
pub mod watchdog;
