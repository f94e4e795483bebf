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
//! - [`input`]: where read-back gets an input line's edges (a GPIO line
//!   with kernel timestamps, or a sim trace followed as it grows).
//! - [`framelog`]: the JSON-lines log of every frame sent.
//! - [`lines`]: opening every output's line, handed back with its output.
//! - [`monitor`]: the main thread's view of the loop: logs, snapshots, HdrHistogram log.
//! - [`meter`]: histograms of the loop's timing, handed over lock-free.
//! - [`readback`]: the read-back thread: what the radio transmits, compared
//!   with what the line carried.
//! - [`pilot`]: a pilot's radio as a takeover input: its thread reads the
//!   takeover switch, and [`pilot::PilotMux`] hands the loop the pilot's
//!   channels or the groundstation's commands (none while it is not read).
//! - [`telemetry`]: the telemetry thread of a CRSF serial output: what
//!   the flight controller sends back, read, counted and published.
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
pub mod input;
pub mod instance;
pub mod line;
pub mod lines;
pub mod meter;
pub mod monitor;
pub mod pilot;
pub mod readback;
pub mod rotating;
pub mod rt;
pub mod source;
pub mod startup;
pub mod telemetry;
pub mod timing;
pub mod watchdog;

/// Whether `e` says the configured output cannot be had on this machine
/// as configured, which a restart does not change: a GPIO chip or line it
/// does not have, a serial or SPI device that does not exist, is the wrong
/// kind of file or is kept from ppmd by the unit's device policy (EPERM:
/// `DeviceAllow=`), a PPM frame too long for spidev's buffer at
/// `ppmd.spi_hz`. ppmd then exits with
/// [`EXIT_CONFIG`](ppm_shared::daemon::EXIT_CONFIG), as for a bad key.
///
/// Left to a restart (exit status 1): a line or device another process
/// holds (EBUSY), a device node without its hardware (ENXIO, ENODEV: a
/// USB adaptor enumerating or just unplugged), and a device file this user
/// may not open (EACCES): at
/// boot udev gives a device its group (`60-ppm.rules`) only after the
/// kernel made it, so a ppmd started in between is cured by its restart a
/// second later. A device that appears late (a USB serial adaptor) is
/// waited for by ordering the unit after it (docs/deployment.md), not by
/// restarting into its absence.
pub fn output_fault(e: &(dyn std::error::Error + 'static)) -> bool {
    use line::gpio::GpioError;
    use line::serial::{SerialError, SerialStep};
    use line::spi::SpiError;
    let gpio = e
        .downcast_ref::<GpioError>()
        .or_else(|| e.downcast_ref::<input::InputError>()?.gpio());
    if let Some(g) = gpio {
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
    // Opening the device: what path_at_fault says, but for EACCES (udev
    // gives the device its group at boot, maybe after ppmd started) and
    // ENXIO or ENODEV (the node is there but its hardware is not yet, or no
    // more: a USB adaptor enumerating or just unplugged). A restart may
    // cure those.
    let open_fault = |io: &std::io::Error| {
        !matches!(
            io.raw_os_error(),
            Some(libc::EACCES | libc::ENXIO | libc::ENODEV)
        ) && ppm_shared::config::fault::path_at_fault(io)
    };
    if let Some(s) = e.downcast_ref::<SerialError>() {
        return match s {
            SerialError::NotATty { .. } => true,
            SerialError::Device { step, source, .. } => {
                *step == SerialStep::Open && open_fault(source)
            }
        };
    }
    match e.downcast_ref::<SpiError>() {
        Some(SpiError::Device { what, source, .. }) => {
            *what == "not a spidev device" || (*what == "opening" && open_fault(source))
        }
        Some(SpiError::TooLong { .. }) => true,
        None => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use line::serial::{SerialError, SerialStep};
    use line::spi::SpiError;
    use std::io::Error;
    use std::path::PathBuf;

    /// What stays wrong stops ppmd with 78; what a restart may cure (a
    /// device udev has not given its group yet, a busy one) does not.
    #[test]
    fn outputs_that_cannot_be_had_as_configured_are_faults_of_the_configuration() {
        let serial = |step, errno: i32| SerialError::Device {
            path: PathBuf::from("/dev/ttyAMA0"),
            step,
            source: Error::from_raw_os_error(errno),
        };
        let spi = |what, errno: i32| SpiError::Device {
            path: PathBuf::from("/dev/spidev0.0"),
            what,
            source: Error::from_raw_os_error(errno),
        };
        for (e, fault) in [
            (serial(SerialStep::Open, libc::ENOENT), true),
            (serial(SerialStep::Open, libc::EISDIR), true),
            (serial(SerialStep::Open, libc::EPERM), true),
            (serial(SerialStep::Open, libc::EACCES), false),
            (serial(SerialStep::Open, libc::EBUSY), false),
            (serial(SerialStep::Open, libc::ENXIO), false),
            (serial(SerialStep::Open, libc::ENODEV), false),
            (
                serial(
                    SerialStep::Configure(ppm_shared::sbus::uart::FORMAT),
                    libc::EINVAL,
                ),
                false,
            ),
        ] {
            assert_eq!(output_fault(&e), fault, "{e}");
        }
        assert!(output_fault(&SerialError::NotATty {
            path: PathBuf::from("/tmp/x")
        }));
        for (e, fault) in [
            (spi("opening", libc::ENOENT), true),
            (spi("opening", libc::EPERM), true),
            (spi("opening", libc::EACCES), false),
            (spi("opening", libc::ENODEV), false),
            (spi("not a spidev device", libc::EINVAL), true),
            (spi("a first transfer", libc::EIO), false),
        ] {
            assert_eq!(output_fault(&e), fault, "{e}");
        }
        let long = SpiError::TooLong {
            path: PathBuf::from("/dev/spidev0.0"),
            hz: 20_000_000,
            longest_us: 30_000,
            bytes: 75_000,
            bufsiz: 4096,
            fits_hz: 1_000_000,
        };
        assert!(
            output_fault(&long),
            "ppmd.spi_hz too high for spidev's buffer"
        );
        assert!(!output_fault(&Error::other("anything else")));
    }
}
