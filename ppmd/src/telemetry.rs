//! The telemetry thread of a CRSF `serial:` output: reads what the flight
//! controller sends back on its TX line (wired to the board's RX), CRC-checks
//! and decodes it ([`ppm_shared::crsf::TelemetryReader`], which counts every
//! byte it drops), and publishes the counts and the newest frame of each kind
//! for udp-ingress (`ppm/NAME/telemetry`).
//!
//! A thread of its own at normal priority, never on the timing thread's
//! CPU: the timing loop writes the tty and never reads it, so nothing the
//! flight controller sends (junk, a flood, a frame cut off) reaches the
//! loop. The thread opens the tty a second time, read-only and
//! non-blocking: the settings (raw, the wire's baud rate both ways) are the
//! line's, set when the line opened it. It waits in `poll` for bytes; a
//! pause of [`GAP`] while a frame is unfinished drops that frame as
//! `truncated` (a flight controller sends each frame back to back, and
//! Betaflight's own receive side resets after 1.75 ms of quiet).

use crate::emitter::module::{ModuleTiming, ALIVE_NS};
use anyhow::{Context, Result};
use ppm_shared::crsf::TelemetryReader;
use ppm_shared::ipc::{self, TelemetrySample};
use ppm_shared::logging::Chain;
use ppm_shared::time::now_ns;
use std::fs::{File, OpenOptions};
use std::io::{self, Read};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// A pause in the middle of a frame this long ends it ([`TelemetryReader::gap`]).
pub const GAP: Duration = Duration::from_millis(2);
/// The longest wait for bytes before the thread looks at its stop flag and
/// publishes again.
const WAIT: Duration = Duration::from_millis(50);
/// How often the sample is published while nothing comes.
const PUBLISH_EVERY_NS: u64 = 100_000_000;

/// A telemetry port opened, its thread not yet started.
pub struct Opened {
    name: String,
    tag: String,
    port: PathBuf,
    file: File,
    module: Option<Arc<ModuleTiming>>,
}

impl Opened {
    /// Opens `port` (the tty of output `name`, `tag` its log prefix) to
    /// read, not as the controlling terminal, without blocking.
    pub fn open(name: &str, tag: &str, port: &Path) -> Result<Opened> {
        let file = OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK)
            .open(port)
            .with_context(|| {
                format!(
                    "output `{name}`: opening {} to read the flight controller's telemetry",
                    port.display()
                )
            })?;
        Ok(Opened {
            name: name.to_owned(),
            tag: tag.to_owned(),
            port: port.to_owned(),
            file,
            module: None,
        })
    }

    /// The port is a transmitter module's: its timing corrections are left
    /// in `timing`, which the timing loop's grid follows.
    pub fn module(mut self, timing: Arc<ModuleTiming>) -> Opened {
        self.module = Some(timing);
        self
    }

    /// Starts the thread, which publishes under the shared-memory `root`
    /// and stays off `avoid_cpu` (the timing thread's). Returns once it
    /// publishes, or why it cannot.
    pub fn start(self, root: &Path, avoid_cpu: Option<usize>) -> Result<Telemetry> {
        let stop = Arc::new(AtomicBool::new(false));
        let (name, root) = (self.name.clone(), root.to_owned());
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let flag = stop.clone();
        let thread = std::thread::Builder::new()
            .name("ppmd-telemetry".into())
            .spawn(move || {
                crate::readback::avoid(avoid_cpu);
                let opened = (|| -> Result<_, ipc::IpcError> {
                    let node = ipc::create_node(&root, &format!("ppmd-{name}-telemetry"))?;
                    let service = ipc::open_telemetry_service(&node, &name)?;
                    let publisher = service.publisher_builder().create().map_err(|e| {
                        ipc::IpcError::new(
                            format!("creating the telemetry publisher of `{name}`"),
                            e,
                        )
                    })?;
                    Ok((node, service, publisher))
                })();
                match opened {
                    Ok((_node, _service, publisher)) => {
                        let _ = ready_tx.send(Ok(()));
                        self.run(&publisher, &flag);
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                }
            })
            .context("spawning the telemetry thread")?;
        let mut t = Telemetry {
            stop,
            thread: Some(thread),
        };
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(t),
            Ok(Err(e)) => {
                t.finish();
                Err(e.into())
            }
            Err(_) => {
                t.finish();
                anyhow::bail!("the telemetry thread stopped at start")
            }
        }
    }

    fn run(mut self, publisher: &ipc::Publisher<TelemetrySample>, stop: &AtomicBool) {
        let from = match self.module {
            Some(_) => "the transmitter module: link statistics and timing corrections",
            None => "the flight controller",
        };
        log::info!(
            "{}telemetry: reading {} (CRSF from {from})",
            self.tag,
            self.port.display()
        );
        let mut reader = TelemetryReader::new();
        let mut sample = TelemetrySample::default();
        let mut buf = [0u8; 512];
        let mut published = 0u64;
        let mut failing = false;
        // When the module last sent a good frame (0: never).
        let mut module_heard = 0u64;
        while !stop.load(Relaxed) {
            let wait = if reader.buffered() > 0 { GAP } else { WAIT };
            let before = reader.counts().frames;
            match wait_readable(&self.file, wait) {
                Ok(Readable::Yes) => match self.file.read(&mut buf) {
                    // Readable with nothing to read: the tty hung up (a USB
                    // adaptor unplugged). Wait, rather than poll at once.
                    Ok(0) => {
                        let e = io::Error::from_raw_os_error(libc::EIO);
                        self.failed(&mut failing, &e);
                    }
                    Ok(n) => {
                        if failing {
                            log::info!(
                                "{}telemetry: {} reads again",
                                self.tag,
                                self.port.display()
                            );
                            failing = false;
                        }
                        let now = now_ns();
                        reader.feed(&buf[..n], |frame, t| sample.take(frame, &t, now));
                        if let Some(timing) = &self.module {
                            if let Some(c) = reader.take_timing() {
                                // The module is heard by its corrections
                                // (every 200 ms while it takes frames),
                                // never by ppm's own frames echoed on a
                                // half-duplex wire.
                                if module_heard == 0 || now - module_heard > ALIVE_NS {
                                    log::info!(
                                        "{}telemetry: the module answers; the model ID command goes before the next frame",
                                        self.tag
                                    );
                                    timing.request_model_id();
                                }
                                module_heard = now;
                                if timing.count() == 0 {
                                    log::info!(
                                        "{}telemetry: the module asks for a frame every {} us (offset {} us)",
                                        self.tag,
                                        c.rate_ns() as f64 / 1e3,
                                        c.offset_ns() as f64 / 1e3
                                    );
                                }
                                timing.set(c, now);
                            }
                        }
                    }
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(e) => self.failed(&mut failing, &e),
                },
                Ok(Readable::Quiet) => {
                    let now = now_ns();
                    reader.gap(|frame, t| sample.take(frame, &t, now));
                }
                Ok(Readable::HungUp) => {
                    // The other end of a pseudo-terminal closed, or the
                    // device went away: poll would return at once.
                    let e = io::Error::from_raw_os_error(libc::EIO);
                    self.failed(&mut failing, &e);
                }
                Err(e) => self.failed(&mut failing, &e),
            }
            let now = now_ns();
            if reader.counts().frames != before || now.saturating_sub(published) >= PUBLISH_EVERY_NS
            {
                sample.counts = reader.counts().to_array();
                sample.published_mono_ns = now;
                if let Err(e) = ipc::publish(publisher, sample) {
                    log::debug!("publishing the telemetry: {}", Chain(&e));
                }
                published = now;
            }
        }
    }

    /// Says once that reading failed, and waits a little before the next
    /// try.
    fn failed(&mut self, failing: &mut bool, e: &io::Error) {
        if !*failing {
            log::warn!(
                "{}telemetry: reading {}: {e}",
                self.tag,
                self.port.display()
            );
            *failing = true;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// What `poll` found.
enum Readable {
    /// Bytes to read.
    Yes,
    /// None within the wait.
    Quiet,
    /// The tty hung up or failed.
    HungUp,
}

fn wait_readable(file: &File, wait: Duration) -> io::Result<Readable> {
    use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
    let mut fds = [PollFd::new(file.as_fd(), PollFlags::POLLIN)];
    let ms = u16::try_from(wait.as_millis()).unwrap_or(u16::MAX);
    match poll(&mut fds, PollTimeout::from(ms)) {
        Ok(0) => Ok(Readable::Quiet),
        Ok(_) => {
            let r = fds[0].revents().unwrap_or(PollFlags::empty());
            // A hang-up comes with POLLIN on a real tty (read then gives
            // 0 bytes): it counts first.
            if r.intersects(PollFlags::POLLHUP | PollFlags::POLLERR | PollFlags::POLLNVAL) {
                Ok(Readable::HungUp)
            } else if r.contains(PollFlags::POLLIN) {
                Ok(Readable::Yes)
            } else {
                Ok(Readable::Quiet)
            }
        }
        // Interrupted: look again (a read finds nothing, harmlessly).
        Err(nix::errno::Errno::EINTR) => Ok(Readable::Yes),
        Err(e) => Err(io::Error::from(e)),
    }
}

/// A running telemetry thread.
pub struct Telemetry {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Telemetry {
    /// Stops the thread.
    pub fn finish(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Telemetry {
    fn drop(&mut self) {
        self.finish();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;
    use std::os::fd::FromRawFd;

    /// A pseudo-terminal pair: the master end, and the slave's path.
    fn pty() -> (File, PathBuf) {
        // SAFETY: plain libc calls on a descriptor this function owns; the
        // name buffer outlives ptsname_r, which NUL-terminates within it.
        unsafe {
            let fd = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC);
            assert!(fd >= 0, "posix_openpt");
            assert_eq!(libc::grantpt(fd), 0);
            assert_eq!(libc::unlockpt(fd), 0);
            let mut name = [0 as libc::c_char; 128];
            assert_eq!(libc::ptsname_r(fd, name.as_mut_ptr(), name.len()), 0);
            let path = std::ffi::CStr::from_ptr(name.as_ptr());
            (
                File::from_raw_fd(fd),
                PathBuf::from(path.to_string_lossy().into_owned()),
            )
        }
    }

    /// The wait tells bytes, quiet and a hang-up apart: a port whose other
    /// end went away is not "readable" (which would make the thread spin).
    #[test]
    fn the_wait_tells_bytes_quiet_and_a_hang_up_apart() {
        let (mut master, slave) = pty();
        // Raw, as the line sets it (a cooked tty holds bytes until a newline).
        let format = ppm_shared::wire::UartFormat {
            baud: 420_000,
            parity: ppm_shared::wire::uart::Parity::None,
            stop_bits: 1,
        };
        use crate::line::serial::{SerialError, SerialLine, SerialStep};
        let _line = match SerialLine::open(&slave, format) {
            Ok(line) => line,
            // qemu-user (the Pi's unit tests in CI) has no termios2: this
            // holds on a kernel, native or in the VM, not there.
            Err(SerialError::Device {
                step: SerialStep::ReadSettings,
                source,
                ..
            }) if source.raw_os_error() == Some(libc::ENOSYS) => {
                eprintln!("not tested here: this environment does not implement TCGETS2");
                return;
            }
            Err(e) => panic!("the line: {e:?}"),
        };
        let opened = Opened::open("t", "", &slave).expect("opening the slave");
        let wait = Duration::from_millis(20);
        assert!(matches!(
            wait_readable(&opened.file, wait),
            Ok(Readable::Quiet)
        ));
        master.write_all(&[0xC8]).unwrap();
        assert!(matches!(
            wait_readable(&opened.file, wait),
            Ok(Readable::Yes)
        ));
        drop(master);
        assert!(matches!(
            wait_readable(&opened.file, wait),
            Ok(Readable::HungUp)
        ));
    }
}
