//! The serial line: each frame is one `write` of its bytes to a tty (a UART
//! such as the Raspberry Pi's `/dev/ttyAMA0`, a USB serial adaptor, or a
//! pseudo-terminal in tests), sent by the UART at its own baud clock.
//!
//! This is the line of a `serial:DEVICE` output, in the UART format its
//! protocol's wire names ([`UartFormat`]: SBUS's 25-byte frames at
//! 100 000 baud, 8 data bits, even parity, 2 stop bits), a [`FrameLine`]:
//! the loop hands it each frame at the frame's start.
//!
//! 100 000 baud is not one of the `Bnnn` rates, so the line is set through
//! `termios2` (`TCGETS2`/`TCSETS2` with `BOTHER` and the rate in
//! `c_ispeed`/`c_ospeed`); nix has no `termios2`, so this goes through libc.
//! The frame is one `write` call: the tty takes all 25 bytes into its
//! output buffer at once and the UART sends them back to back, which the
//! receivers need (a gap inside a frame cuts it in two). A short write is
//! an error, never completed by a second write that would split the frame.
//!
//! A pseudo-terminal takes the same settings and hands the bytes through
//! unchanged, but it has no wire: it keeps the baud rate and the stop bits
//! it was given and clears `PARENB` (see this module's tests).

use super::{FrameLine, LineError, WholeFrame};
use ppm_shared::frame::Level;
pub use ppm_shared::wire::uart::Parity;
use ppm_shared::wire::UartFormat;
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::os::fd::AsRawFd;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

/// The bytes of one SBUS frame.
pub const FRAME_LEN: usize = ppm_shared::sbus::FRAME_LEN;

/// What the serial line was doing when it failed (for [`SerialError`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SerialStep {
    /// Opening the device file.
    Open,
    /// Reading its settings (`TCGETS2`).
    ReadSettings,
    /// Setting raw mode and the wire's format (`TCSETS2`).
    Configure(UartFormat),
}

impl std::fmt::Display for SerialStep {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SerialStep::Open => "opening",
            SerialStep::ReadSettings => "reading the termios2 settings of",
            SerialStep::Configure(u) => {
                return write!(f, "setting raw {} (termios2, BOTHER) on", u.describe())
            }
        })
    }
}

/// Why a serial line could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum SerialError {
    /// A step on the device failed; the message says how to fix the usual
    /// causes.
    #[error("{step} {}: {source}{}", path.display(), hint(source))]
    Device {
        /// The tty path as given.
        path: PathBuf,
        /// The step that failed.
        step: SerialStep,
        /// The system's error.
        #[source]
        source: io::Error,
    },
    /// The path opened but is not a terminal (`TCGETS2` gave `ENOTTY`).
    #[error(
        "{} is not a tty (TCGETS2: inappropriate ioctl for device): name a serial device such as /dev/ttyAMA0 or /dev/ttyUSB0",
        path.display()
    )]
    NotATty {
        /// The path as given.
        path: PathBuf,
    },
}

/// The fix for the usual causes of a failed step, or nothing.
fn hint(err: &io::Error) -> &'static str {
    match err.raw_os_error() {
        Some(libc::EACCES) => ": add the user to the dialout group",
        Some(libc::EPERM) => {
            ": the unit's device policy refuses it (DevicePolicy=closed): add its DeviceAllow= line, one of the commented ones in ppmd.service (`sudo systemctl edit ppmd`)"
        }
        Some(libc::ENOENT) => {
            ": no such device; is the UART enabled (enable_uart=1 or a dtoverlay on a Raspberry Pi)?"
        }
        Some(libc::EBUSY) => {
            ": another program holds it (a serial console? remove console=serial0 from the kernel command line)"
        }
        _ => "",
    }
}

/// A tty's settings as the kernel holds them (read back with `TCGETS2`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SerialSettings {
    /// Input baud rate.
    pub ispeed: u32,
    /// Output baud rate.
    pub ospeed: u32,
    /// Data bits per character (5 to 8).
    pub data_bits: u8,
    /// The parity bit.
    pub parity: Parity,
    /// Stop bits (1 or 2).
    pub stop_bits: u8,
    /// No input or output processing, echo, canonical mode or signal
    /// characters: bytes pass unchanged both ways.
    pub raw: bool,
    /// Hardware (`CRTSCTS`) or software (`IXON`/`IXOFF`) flow control on.
    pub flow_control: bool,
    /// Modem lines ignored (`CLOCAL`) and the receiver on (`CREAD`).
    pub local_and_read: bool,
    /// `VMIN` and `VTIME`: a read returns at once with what there is when
    /// both are 0.
    pub vmin_vtime: (u8, u8),
    /// The raw flag words, `c_iflag`, `c_oflag`, `c_cflag`, `c_lflag`.
    pub flags: [u32; 4],
}

/// Input flags that change bytes or stop the flow; cleared in raw mode.
const COOKED_IFLAGS: libc::tcflag_t = libc::IGNBRK
    | libc::BRKINT
    | libc::PARMRK
    | libc::ISTRIP
    | libc::INLCR
    | libc::IGNCR
    | libc::ICRNL
    | libc::IXON
    | libc::IXOFF
    | libc::IXANY;

/// Local flags of a cooked terminal; cleared in raw mode.
const COOKED_LFLAGS: libc::tcflag_t =
    libc::ECHO | libc::ECHONL | libc::ICANON | libc::ISIG | libc::IEXTEN;

impl SerialSettings {
    fn from_termios2(t: &libc::termios2) -> Self {
        let data_bits = match t.c_cflag & libc::CSIZE {
            libc::CS5 => 5,
            libc::CS6 => 6,
            libc::CS7 => 7,
            _ => 8,
        };
        let parity = match (t.c_cflag & libc::PARENB != 0, t.c_cflag & libc::PARODD != 0) {
            (false, _) => Parity::None,
            (true, false) => Parity::Even,
            (true, true) => Parity::Odd,
        };
        SerialSettings {
            ispeed: t.c_ispeed,
            ospeed: t.c_ospeed,
            data_bits,
            parity,
            stop_bits: if t.c_cflag & libc::CSTOPB != 0 { 2 } else { 1 },
            raw: t.c_iflag & COOKED_IFLAGS == 0
                && t.c_oflag & libc::OPOST == 0
                && t.c_lflag & COOKED_LFLAGS == 0,
            flow_control: t.c_cflag & libc::CRTSCTS != 0
                || t.c_iflag & (libc::IXON | libc::IXOFF) != 0,
            local_and_read: t.c_cflag & (libc::CLOCAL | libc::CREAD) == libc::CLOCAL | libc::CREAD,
            vmin_vtime: (t.c_cc[libc::VMIN], t.c_cc[libc::VTIME]),
            flags: [t.c_iflag, t.c_oflag, t.c_cflag, t.c_lflag],
        }
    }
}

/// Makes `t` raw, in `format` both ways (8 data bits, its baud rate,
/// parity and stop bits), no flow control, with reads returning at once.
fn make_raw(t: &mut libc::termios2, format: UartFormat) {
    t.c_iflag &= !(COOKED_IFLAGS | libc::INPCK);
    t.c_oflag &= !libc::OPOST;
    t.c_lflag &= !COOKED_LFLAGS;
    t.c_cflag &= !(libc::CSIZE
        | libc::PARENB
        | libc::PARODD
        | libc::CSTOPB
        | libc::CMSPAR
        | libc::CRTSCTS
        | libc::CBAUD
        | libc::CIBAUD);
    t.c_cflag |=
        libc::CS8 | libc::CLOCAL | libc::CREAD | libc::BOTHER | (libc::BOTHER << libc::IBSHIFT);
    t.c_cflag |= match format.parity {
        Parity::None => 0,
        Parity::Even => libc::PARENB,
        Parity::Odd => libc::PARENB | libc::PARODD,
    };
    if format.stop_bits == 2 {
        t.c_cflag |= libc::CSTOPB;
    }
    t.c_ispeed = format.baud;
    t.c_ospeed = format.baud;
    t.c_cc[libc::VMIN] = 0;
    t.c_cc[libc::VTIME] = 0;
}

/// The serial output's line: a tty in raw mode in the wire's UART format
/// (SBUS: 100 000 baud, 8E2), written one whole frame per call.
#[derive(Debug)]
pub struct SerialLine {
    file: File,
    path: PathBuf,
    short_writes: u64,
}

impl SerialLine {
    /// Opens the tty at `path` (read-write, not as the controlling
    /// terminal, closed on exec, blocking writes) and sets it raw, in
    /// `format` (SBUS's: 100 000 baud, 8 data bits, even parity, 2 stop
    /// bits), no flow control.
    pub fn open(path: &Path, format: UartFormat) -> Result<Self, SerialError> {
        let fail = |step, source| SerialError::Device {
            path: path.to_path_buf(),
            step,
            source,
        };
        // std opens with O_CLOEXEC always; O_NOCTTY keeps a tty from
        // becoming the daemon's controlling terminal (and its hangups ours).
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NOCTTY)
            .open(path)
            .map_err(|e| fail(SerialStep::Open, e))?;
        let line = SerialLine {
            file,
            path: path.to_path_buf(),
            short_writes: 0,
        };
        let mut t = line.termios2().map_err(|e| {
            if e.raw_os_error() == Some(libc::ENOTTY) {
                SerialError::NotATty {
                    path: path.to_path_buf(),
                }
            } else {
                fail(SerialStep::ReadSettings, e)
            }
        })?;
        make_raw(&mut t, format);
        // SAFETY: TCSETS2 reads one termios2 from the pointer, which is a
        // live, initialised termios2 for the whole call.
        let rc = unsafe { libc::ioctl(line.file.as_raw_fd(), libc::TCSETS2, &t) };
        if rc != 0 {
            return Err(fail(
                SerialStep::Configure(format),
                io::Error::last_os_error(),
            ));
        }
        Ok(line)
    }

    /// The rate the UART runs at, when it is off by more than a receiver
    /// takes ([`baud_off`]) from `asked`: a UART whose clock cannot make
    /// the rate gets another one (the nearest its divisor makes, or the one
    /// it had) without an error, so the rate is read back. `None` when it
    /// runs at the rate (or cannot be read back).
    pub fn rate_off(&self, asked: u32) -> Option<u32> {
        let now = self.settings().ok()?;
        baud_off(asked, now.ospeed).then_some(now.ospeed)
    }

    /// The path the line was opened at.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Frames refused because the tty took only part of them.
    pub fn short_writes(&self) -> u64 {
        self.short_writes
    }

    /// The settings the kernel holds for the tty now.
    pub fn settings(&self) -> io::Result<SerialSettings> {
        Ok(SerialSettings::from_termios2(&self.termios2()?))
    }

    /// The settings the kernel holds for the tty at `path` (opened
    /// read-only, not as the controlling terminal, without waiting for a
    /// carrier): what another program, a test or a tool, sees.
    pub fn settings_of(path: &Path) -> io::Result<SerialSettings> {
        let file = OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK)
            .open(path)?;
        Ok(SerialSettings::from_termios2(&termios2_of(&file)?))
    }

    fn termios2(&self) -> io::Result<libc::termios2> {
        termios2_of(&self.file)
    }

    /// Sends one frame in one `write` call, returning when the tty has
    /// taken it (it blocks only while the tty's output buffer is full). A
    /// write interrupted before it took any byte is made again; one that
    /// took part of the frame is counted in [`SerialLine::short_writes`]
    /// and returned as [`LineError::ShortWrite`], the rest never sent.
    pub fn write_frame(&mut self, frame: &[u8]) -> Result<(), LineError> {
        loop {
            match self.file.write(frame) {
                Ok(written) if written == frame.len() => return Ok(()),
                Ok(written) => {
                    self.short_writes += 1;
                    return Err(LineError::ShortWrite {
                        written,
                        len: frame.len(),
                    });
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => {
                    return Err(LineError::Write(nix::errno::Errno::from_raw(
                        e.raw_os_error().unwrap_or(libc::EIO),
                    )))
                }
            }
        }
    }
}

/// Whether a UART set to `asked` baud that reports `got` is off by more
/// than the 2 % a UART receiver takes (half a bit over a 10 to 12 bit
/// character is about 4 %, shared by both ends).
pub fn baud_off(asked: u32, got: u32) -> bool {
    (asked as u64).abs_diff(got as u64) * 50 > asked as u64
}

/// The termios2 settings of the tty open as `file`.
fn termios2_of(file: &File) -> io::Result<libc::termios2> {
    // SAFETY: termios2 is plain integers, for which all zeroes is valid.
    let mut t: libc::termios2 = unsafe { std::mem::zeroed() };
    // SAFETY: TCGETS2 writes one termios2 through the pointer, which is a
    // live, writable termios2 for the whole call.
    let rc = unsafe { libc::ioctl(file.as_raw_fd(), libc::TCGETS2, &mut t) };
    if rc != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(t)
}

impl FrameLine for SerialLine {
    fn write_frame(&mut self, frame: WholeFrame<'_>) -> Result<(), LineError> {
        match frame {
            WholeFrame::Bytes { bytes, .. } => SerialLine::write_frame(self, bytes),
            WholeFrame::Ppm { .. } => Err(LineError::WrongProtocol),
        }
    }

    /// A UART idles high by itself between characters: nothing to do.
    fn park(&mut self, _level: Level) -> Result<(), LineError> {
        Ok(())
    }
}

#[cfg(test)]
mod tests;
