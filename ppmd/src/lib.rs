//! `ppmd`, the PPM daemon: once per frame it takes the newest command, encodes
//! the frame and emits every edge at its scheduled time through an
//! [`output::Output`] backend.
//!
//! - [`cli`]: ppmd's command line: its options and how they override the
//!   configuration.
//! - [`clock`]: the [`clock::Clock`] the timing loop reads and waits on
//!   (CLOCK_MONOTONIC and absolute sleeps; a simulated one in tests), and the
//!   sleep-then-spin [`clock::EdgeTimer`].
//! - [`output`]: the backend trait and the simulated line.
//! - [`emitter`]: the timing loop (no allocation, logging or locks inside).
//! - [`source`]: where commands come from (iceoryx2 in the daemon).
//! - [`framelog`]: the JSON-lines log of every frame sent.
//! - [`lines`]: opening every output's line.
//! - [`monitor`]: the main thread's view of the loop: logs, snapshots, HdrHistogram log.
//! - [`meter`]: histograms of the loop's timing, handed over lock-free.
//! - [`rotating`]: the log files' type: rotated at a size cap, fed by a
//!   lock-free ring and a writer thread.
//! - [`startup`]: what the main thread sets up for each output around the
//!   timing thread, and its last words at exit.
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
pub mod startup;
pub mod timing;
pub mod watchdog;
