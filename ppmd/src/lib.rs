//! `ppmd`, the PPM daemon: once per frame it takes the newest command, encodes
//! the frame and sends it on each output's line: edge by edge, every edge at
//! its scheduled time ([`line::Line`], [`line::Bank`]), or whole to a line
//! timed by its own clock ([`line::FrameLine`]).
//!
//! Words, one per thing across the crate:
//!
//! - **output**: one configured output (an `[[outputs]]` entry): a name, a
//!   frame model, settings, counters, a frame log, a line and a command
//!   source. Each thread holds its pieces of one output in one struct:
//!   [`startup::Output`] is one as the main thread holds it (plan, frame
//!   log writer, snapshot publisher, and its view of the loop: the meter's
//!   reader until the loop runs, then the monitor, [`startup::Watched`]);
//!   [`timing::TimedOutput`] is the
//!   part the timing thread takes (model, settings, meter, frame log, line;
//!   the thread opens its command source), and [`emitter::Output`] one as
//!   the loop drives it.
//! - **line**: what physically carries an output's signal: a GPIO line, one
//!   line of a GPIO bank, an SPI device's MOSI, the simulated line's trace
//!   file. Its frames leave edge by edge ([`line::Line`], [`line::Bank`]) or
//!   whole ([`line::FrameLine`]); [`emitter::LineRef`] says which.
//!
//! Modules:
//!
//! - [`cli`]: ppmd's command line: its options and how they override the
//!   configuration.
//! - [`clock`]: the [`clock::Clock`] the timing loop reads and waits on
//!   (CLOCK_MONOTONIC and absolute sleeps; a simulated one in tests), and the
//!   sleep-then-spin [`clock::EdgeTimer`].
//! - [`line`](mod@line): the lines (GPIO, bank, SPI, simulated) and their traits;
//!   the serial line for the coming SBUS output, not selectable yet.
//! - [`emitter`]: the timing loop (no allocation, logging or locks inside),
//!   in parts: when a frame starts (grid or follow), the decision, the
//!   emission of a due step, the recording, and what a frame is on the wire
//!   (the protocol seam).
//! - [`source`]: where commands come from (iceoryx2 in the daemon).
//! - [`framelog`]: the JSON-lines log of every frame sent.
//! - [`lines`]: opening every output's line, handed back with its output.
//! - [`monitor`]: the main thread's view of the loop: logs, snapshots, HdrHistogram log.
//! - [`meter`]: histograms of the loop's timing, handed over lock-free.
//! - [`rotating`]: the log files' type: rotated at a size cap, fed by a
//!   lock-free ring and a writer thread.
//! - [`startup`]: what the main thread holds of each output around the
//!   timing thread: set up, then watched, and its last words at exit.
//! - [`timing`]: the timing thread that runs the outputs.
//! - [`instance`]: one ppmd per output name (a lock file under the ipc root).
//! - [`rt`]: the real-time setup of the timing thread.
//! - [`watchdog`]: systemd's watchdog, petted while the timing loop moves.

pub mod cli;
pub mod clock;
pub mod emitter;
pub mod framelog;
pub mod instance;
pub mod line;
pub mod lines;
pub mod meter;
pub mod monitor;
pub mod rotating;
pub mod rt;
pub mod source;
pub mod startup;
pub mod timing;
pub mod watchdog;

/// Whether `e` says the configured output is not on this machine: a GPIO
/// chip or line it does not have, or a serial or SPI device that does not
/// exist or is no such device. ppmd then exits with
/// [`EXIT_CONFIG`](ppm_shared::daemon::EXIT_CONFIG), as for a bad key:
/// restarting cannot help.
pub fn output_missing(e: &(dyn std::error::Error + 'static)) -> bool {
    use line::gpio::GpioError;
    use line::serial::{SerialError, SerialStep};
    use line::spi::SpiError;
    if let Some(g) = e.downcast_ref::<GpioError>() {
        return matches!(
            g,
            GpioError::NoSuchChip { .. }
                | GpioError::AmbiguousChip { .. }
                | GpioError::NotAChip { .. }
                | GpioError::NoSuchLine { .. }
                | GpioError::NoLineAnywhere { .. }
                | GpioError::AmbiguousLine { .. }
                | GpioError::OffsetWithoutChip { .. }
        );
    }
    let missing = |io: &std::io::Error| io.kind() == std::io::ErrorKind::NotFound;
    if let Some(s) = e.downcast_ref::<SerialError>() {
        return match s {
            SerialError::NotATty { .. } => true,
            SerialError::Device { step, source, .. } => {
                *step == SerialStep::Open && missing(source)
            }
        };
    }
    if let Some(SpiError::Device { what, source, .. }) = e.downcast_ref::<SpiError>() {
        return *what == "not a spidev device" || missing(source);
    }
    false
}
