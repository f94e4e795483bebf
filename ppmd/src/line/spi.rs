//! The SPI line: each frame is one transfer on a spidev device's MOSI,
//! its edges placed by the SPI bit clock.
//!
//! A software-timed GPIO edge is as late as the interrupt that landed in the
//! spin before it. Here the whole frame is shifted out by the SPI controller
//! (DMA-paced on a Raspberry Pi 4 and 5): inside a frame every edge is exact
//! to one bit, 1 us at 1 MHz, and scheduling latency only moves when the
//! transfer starts, that is the sync before the frame, which receivers take
//! anywhere in their sync window.
//!
//! Layout: the transfer runs from the frame's first pulse start (the lead-in
//! pulse's, after silence) to just past its last pulse's end, padded with 0
//! bits to whole bytes; mode 0, 8-bit words, most significant bit first. The
//! sync is the gap between transfers, and the line must be low there: an SPI
//! controller with no transfer running leaves MOSI low or at the last bit
//! sent, which is 0 either way. So only `idle_level = "low"` (high pulses)
//! is possible; the configuration refuses "high". A transmitter that wants
//! the other polarity gets an inverter in the cable.
//!
//! The transfer is one blocking `SPI_IOC_MESSAGE` ioctl from the timing
//! thread at the frame's start time, into a buffer sized at start for the
//! longest frame there can be: no allocation in the loop. The ioctl returns
//! when the frame's pulses are out, before the next frame is decided.

use super::{FrameEdge, FrameLine, LineError, WholeFrame};
use ppm_shared::frame::Level;
use spidev::{SpiModeFlags, Spidev, SpidevOptions, SpidevTransfer};
use std::path::{Path, PathBuf};

/// spidev's transfer limit when its `bufsiz` parameter cannot be read.
pub const SPIDEV_DEFAULT_BUFSIZ: usize = 4096;

/// Where spidev says its per-transfer limit.
const BUFSIZ_PARAM: &str = "/sys/module/spidev/parameters/bufsiz";

/// Why an SPI line could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum SpiError {
    /// The device cannot be opened or configured (why: its source).
    #[error("spi:{path}: {what}")]
    Device {
        path: PathBuf,
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    /// The longest frame does not fit in one transfer.
    #[error(
        "spi:{path} at {hz} Hz: the longest frame ({longest_us} us, the lead-in pulse after silence included) takes {bytes} bytes, more than spidev's {bufsiz}-byte transfer buffer ({BUFSIZ_PARAM}): lower ppmd.spi_hz to {fits_hz} or less, or raise the buffer with spidev.bufsiz=65536 on the kernel command line (or `options spidev bufsiz=65536` in /etc/modprobe.d/spidev.conf)"
    )]
    TooLong {
        path: PathBuf,
        hz: u32,
        longest_us: u64,
        bytes: usize,
        bufsiz: usize,
        fits_hz: u32,
    },
}

/// Bytes of a transfer lasting `ns` at `hz`: its bits, one 0 bit after the
/// last edge, rounded up to whole bytes.
pub fn transfer_bytes(ns: u64, hz: u32) -> usize {
    let bits = bit_index(ns, hz) + 1;
    bits.div_ceil(8) as usize
}

/// The bit boundary nearest to `ns` after the transfer's start.
fn bit_index(ns: u64, hz: u32) -> u64 {
    ((ns as u128 * hz as u128 + 500_000_000) / 1_000_000_000) as u64
}

/// Encodes one frame into `buf`: `edges` in time order, each at `at_ns`
/// after the first (which is at 0), the line low before the first. Bit k
/// (most significant bit first) is the level during bit time k; each edge is
/// placed at the nearest bit boundary. Returns the bytes used, or `None`
/// when `buf` is too small.
pub fn encode(edges: &[FrameEdge], hz: u32, buf: &mut [u8]) -> Option<usize> {
    let last = edges.last()?;
    let len = transfer_bytes(last.at_ns, hz);
    let out = buf.get_mut(..len)?;
    out.fill(0);
    for (i, e) in edges.iter().enumerate() {
        if e.level != Level::High {
            continue;
        }
        let from = bit_index(e.at_ns, hz) as usize;
        let to = edges
            .get(i + 1)
            .map_or(len * 8, |n| bit_index(n.at_ns, hz) as usize);
        set_bits(out, from, to);
    }
    Some(len)
}

/// The bit rate of an SBUS output through SPI: one SPI bit a UART bit.
pub const SBUS_HZ: u32 = ppm_shared::sbus::BAUD as u32;

/// Bytes of an SBUS frame's transfer: its 300 bits, padded with idle (0)
/// bits to whole bytes.
pub const SBUS_TRANSFER_BYTES: usize =
    (ppm_shared::sbus::FRAME_LEN * ppm_shared::sbus::BYTE_BITS as usize).div_ceil(8);

/// Encodes one SBUS frame into `buf` as true (inverted) SBUS at
/// [`SBUS_HZ`], most significant bit first: MOSI idles low, a start bit is
/// high, a data or parity 1 is low, the stop bits are low; the last byte is
/// padded with idle bits. Returns the bytes used, or `None` when `buf` is
/// too small.
pub fn encode_sbus(bytes: &[u8; ppm_shared::sbus::FRAME_LEN], buf: &mut [u8]) -> Option<usize> {
    let out = buf.get_mut(..SBUS_TRANSFER_BYTES)?;
    out.fill(0);
    for (k, level) in ppm_shared::sbus::uart::waveform(bytes, Level::Low).enumerate() {
        if level == Level::High {
            out[k / 8] |= 0x80 >> (k % 8);
        }
    }
    Some(SBUS_TRANSFER_BYTES)
}

/// Sets bits `from..to` (bit 0 is the first byte's most significant).
fn set_bits(out: &mut [u8], from: usize, to: usize) {
    let mut b = from;
    while b < to {
        if b.is_multiple_of(8) && to - b >= 8 {
            out[b / 8] = 0xff;
            b += 8;
        } else {
            out[b / 8] |= 0x80 >> (b % 8);
            b += 1;
        }
    }
}

/// A spidev device opened for PPM frames.
pub struct SpiLine {
    dev: Spidev,
    hz: u32,
    buf: Vec<u8>,
    description: String,
}

impl std::fmt::Debug for SpiLine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.description)
    }
}

/// spidev's per-transfer limit (its `bufsiz` module parameter).
pub fn spidev_bufsiz() -> usize {
    std::fs::read_to_string(BUFSIZ_PARAM)
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(SPIDEV_DEFAULT_BUFSIZ)
}

/// Refuses a rate at which a frame of `longest_ns` does not fit in
/// `bufsiz` bytes, naming the rate that would.
pub fn check_fits(path: &Path, hz: u32, longest_ns: u64, bufsiz: usize) -> Result<usize, SpiError> {
    let bytes = transfer_bytes(longest_ns, hz);
    if bytes <= bufsiz {
        return Ok(bytes);
    }
    // The highest rate (in kHz steps) whose longest frame fits.
    let bits = (bufsiz * 8).saturating_sub(1) as u128;
    let fits_hz = ((bits * 1_000_000_000 / longest_ns.max(1) as u128) / 1_000 * 1_000) as u32;
    Err(SpiError::TooLong {
        path: path.to_owned(),
        hz,
        longest_us: longest_ns / 1_000,
        bytes,
        bufsiz,
        fits_hz,
    })
}

impl SpiLine {
    /// Opens `path` (mode 0, 8-bit words, MSB first, `hz`), checks that a
    /// frame of `longest_ns` fits in one transfer, and leaves MOSI low.
    pub fn open(path: &Path, hz: u32, longest_ns: u64) -> Result<SpiLine, SpiError> {
        let bytes = check_fits(path, hz, longest_ns, spidev_bufsiz())?;
        let device = |what, source| SpiError::Device {
            path: path.to_owned(),
            what,
            source,
        };
        // A spidev device is a character device: refuse anything else
        // before any ioctl.
        use std::os::unix::fs::FileTypeExt;
        let meta = std::fs::metadata(path).map_err(|e| device("opening", e))?;
        if !meta.file_type().is_char_device() {
            return Err(device(
                "not a spidev device",
                std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "not a character device (spidev devices are /dev/spidevB.C)",
                ),
            ));
        }
        let mut dev = Spidev::open(path).map_err(|e| device("opening", e))?;
        dev.configure(
            &SpidevOptions::new()
                .bits_per_word(8)
                .max_speed_hz(hz)
                .lsb_first(false)
                .mode(SpiModeFlags::SPI_MODE_0)
                .build(),
        )
        .map_err(|e| device("setting mode 0, 8 bits, the rate", e))?;
        let mut out = SpiLine {
            dev,
            hz,
            buf: vec![0; bytes],
            description: format!("{} at {hz} Hz", path.display()),
        };
        out.park(Level::Low)
            .map_err(|e| device("a first transfer", std::io::Error::other(e.to_string())))?;
        Ok(out)
    }

    /// `path at HZ Hz`.
    pub fn description(&self) -> &str {
        &self.description
    }
}

impl FrameLine for SpiLine {
    fn write_frame(&mut self, frame: WholeFrame<'_>) -> Result<(), LineError> {
        let len = match frame {
            WholeFrame::Ppm { edges, .. } => encode(edges, self.hz, &mut self.buf),
            WholeFrame::Bytes { bytes, .. } if self.hz == SBUS_HZ => {
                let Ok(bytes) = bytes.try_into() else {
                    return Err(LineError::WrongProtocol);
                };
                encode_sbus(bytes, &mut self.buf)
            }
            WholeFrame::Bytes { .. } => return Err(LineError::WrongProtocol),
        }
        .ok_or(LineError::FrameTooLong)?;
        let mut t = SpidevTransfer::write(&self.buf[..len]);
        t.speed_hz = self.hz;
        self.dev
            .transfer(&mut t)
            .map_err(|e| LineError::Write(errno_of(&e)))
    }

    fn park(&mut self, level: Level) -> Result<(), LineError> {
        // One byte at the level: MOSI stays there (or drops to 0, the same
        // for low) after the transfer.
        let byte = [if level == Level::High { 0xff } else { 0 }];
        let mut t = SpidevTransfer::write(&byte);
        t.speed_hz = self.hz;
        self.dev
            .transfer(&mut t)
            .map_err(|e| LineError::Write(errno_of(&e)))
    }
}

fn errno_of(e: &std::io::Error) -> nix::errno::Errno {
    nix::errno::Errno::from_raw(e.raw_os_error().unwrap_or(nix::libc::EIO))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ppm_shared::config::Config;
    use ppm_shared::decode::{decode, DecoderLimits};

    fn edges_of(model: &ppm_shared::FrameModel, us: &[f64]) -> Vec<FrameEdge> {
        let ch = ppm_shared::Channels::from_ns(
            &us.iter().map(|u| (u * 1_000.0) as u32).collect::<Vec<_>>(),
        );
        model
            .encode(&ch)
            .edges()
            .iter()
            .map(|e| FrameEdge {
                at_ns: e.at_ns,
                level: e.level,
            })
            .collect()
    }

    /// The bits back to (time, level) edges, in bit time.
    fn bit_edges(bytes: &[u8], hz: u32) -> Vec<(u64, Level)> {
        let mut out = Vec::new();
        let mut prev = false;
        for k in 0..bytes.len() * 8 {
            let bit = bytes[k / 8] & (0x80 >> (k % 8)) != 0;
            if bit != prev {
                let t = k as u64 * 1_000_000_000 / hz as u64;
                out.push((t, Level::from_bit(bit)));
                prev = bit;
            }
        }
        out
    }

    #[test]
    fn the_papers_command_is_exact_to_the_bit() {
        let model = Config::default().validate().unwrap();
        let want = [
            1000.0, 1200.0, 1700.0, 2000.0, 1500.0, 1500.0, 1500.0, 1500.0,
        ];
        for hz in [1_000_000u32, 2_000_000, 100_000] {
            let edges = edges_of(&model, &want);
            let mut buf = vec![0u8; 8192];
            let len = encode(&edges, hz, &mut buf).unwrap();
            let last = edges.last().unwrap().at_ns;
            assert_eq!(len, transfer_bytes(last, hz));
            assert_eq!(buf[len - 1] & 1, 0, "the last bit is low");
            let got = bit_edges(&buf[..len], hz);
            // Every edge where the schedule has it (all are whole bits here).
            let sched: Vec<(u64, Level)> = edges.iter().map(|e| (e.at_ns, e.level)).collect();
            assert_eq!(got, sched, "at {hz} Hz");
            // And a transmitter's reading of it, between two syncs.
            const SHIFT: u64 = 10_000_000;
            let mut line = vec![(0, Level::High), (300_000, Level::Low)];
            line.extend(got.iter().map(|&(t, l)| (t + SHIFT, l)));
            line.push((SHIFT + last + 10_000_000, Level::High));
            let frames = decode(line, Level::High, DecoderLimits::default());
            let read: Vec<Vec<u64>> = frames.iter().map(|f| f.channels_us()).collect();
            assert!(
                read.contains(&want.map(|v| v as u64).to_vec()),
                "at {hz} Hz: {read:?}"
            );
        }
    }

    #[test]
    fn edges_between_bits_go_to_the_nearest_boundary() {
        let e = |at_ns, level| FrameEdge { at_ns, level };
        let edges = [
            e(0, Level::High),
            e(300_400, Level::Low),    // 300.4 bits: 300
            e(1_000_600, Level::High), // 1000.6 bits: 1001
            e(1_300_500, Level::Low),  // 1300.5 bits: rounds up, 1301
        ];
        let mut buf = [0u8; 200];
        let len = encode(&edges, 1_000_000, &mut buf).unwrap();
        assert_eq!(len, 163, "1302 bits");
        let got = bit_edges(&buf[..len], 1_000_000);
        assert_eq!(
            got,
            [
                (0, Level::High),
                (300_000, Level::Low),
                (1_001_000, Level::High),
                (1_301_000, Level::Low)
            ]
        );
        assert_eq!(
            encode(&edges, 1_000_000, &mut buf[..100]),
            None,
            "too small"
        );
        assert_eq!(encode(&[], 1_000_000, &mut buf), None);
    }

    #[test]
    fn an_sbus_frame_is_true_sbus_exact_to_the_bit() {
        use ppm_shared::sbus;
        let raw: [u16; sbus::CHANNELS] = std::array::from_fn(|i| (i as u16 * 131 + 7) & 0x7FF);
        let frame = sbus::encode(
            &raw,
            sbus::Flags {
                failsafe: true,
                ..Default::default()
            },
        );
        let mut buf = [0u8; 64];
        assert_eq!(
            encode_sbus(&frame, &mut buf),
            Some(38),
            "300 bits in 38 bytes"
        );
        assert_eq!(buf[37] & 0x0F, 0, "the 4 padding bits idle low");
        assert!(buf[38..].iter().all(|&b| b == 0));
        // Read back as a UART receiver of inverted SBUS would.
        let edges = bit_edges(&buf[..38], SBUS_HZ);
        let got = sbus::uart::decode(&edges, Level::Low);
        assert_eq!(got.len(), sbus::FRAME_LEN);
        for (k, c) in got.iter().enumerate() {
            assert_eq!(c.byte, frame[k], "byte {k}");
            assert!(c.parity_ok && c.stop_ok, "byte {k}");
            assert_eq!(c.start_ns, k as u64 * 120_000, "back to back");
        }
        assert_eq!(encode_sbus(&frame, &mut buf[..37]), None, "too small");
    }

    #[test]
    fn a_frame_that_cannot_fit_names_the_rate_that_does() {
        let p = Path::new("/dev/spidev0.0");
        // 21.3 ms at 1 MHz: 2663 bytes, fits 4096.
        assert_eq!(check_fits(p, 1_000_000, 21_300_000, 4096).unwrap(), 2663);
        let e = check_fits(p, 2_000_000, 21_300_000, 4096)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("5326 bytes")
                && e.contains("4096-byte")
                && e.contains("ppmd.spi_hz to 1538000")
                && e.contains("spidev.bufsiz=65536"),
            "{e}"
        );
        let fits: u32 = 1_538_000;
        assert!(check_fits(p, fits, 21_300_000, 4096).is_ok());
        assert!(check_fits(p, fits + 1_000, 21_300_000, 4096).is_err());
    }

    #[test]
    fn a_path_that_is_not_a_spidev_device_is_refused() {
        let e = SpiLine::open(Path::new("/dev/null"), 1_000_000, 1_000_000).unwrap_err();
        assert!(e.to_string().contains("/dev/null"), "{e}");
        let e = SpiLine::open(Path::new("/nonexistent/spidev9.9"), 1_000_000, 1_000_000)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("/nonexistent/spidev9.9") && e.contains("opening"),
            "{e}"
        );
        let dir = std::env::temp_dir();
        let e = SpiLine::open(&dir, 1_000_000, 1_000_000).unwrap_err();
        let e = ppm_shared::logging::Chain(&e).to_string();
        assert!(e.contains("not a character device"), "{e}");
    }
}
