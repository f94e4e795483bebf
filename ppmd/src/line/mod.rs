//! Lines: what physically carries an output's signal (a GPIO line, one
//! line of a GPIO bank, an SPI device's MOSI, a tty for SBUS ([`serial`]),
//! the simulated line's trace file). A frame leaves one of two ways: edge by edge, the timing loop
//! calling [`Line::write`] (or [`Bank::write`]) at each edge's time, or
//! whole, the loop handing the frame to a [`FrameLine`] at its start.
//! Lines must not allocate, block, log or take a lock in those calls.

pub mod gpio;
pub mod serial;
pub mod spi;

use crate::rotating::{self, RotatingFile, WriterOptions};
use ppm_shared::frame::Level;
use ppm_shared::trace::TraceEdge;
use ppm_shared::wire::UartFormat;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A failed line write in the timing loop (counted, never logged there).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum LineError {
    /// The simulated line's trace buffer was full; the edge was not recorded.
    #[error("trace buffer full, edge not recorded")]
    BufferFull,
    /// The line could not be written.
    #[error("line write failed: {0}")]
    Write(nix::errno::Errno),
    /// A frame longer than the line was opened for (not sent).
    #[error("frame longer than the transfer buffer, not sent")]
    FrameTooLong,
    /// A frame of a protocol the line does not carry (not sent; the
    /// configuration refuses such a pairing at start).
    #[error("a frame of another protocol than the line carries, not sent")]
    WrongProtocol,
    /// The device took only part of a frame (the rest is not sent, so no
    /// frame goes out split in two).
    #[error("short write: {written} of {len} bytes")]
    ShortWrite {
        /// Bytes the device took.
        written: usize,
        /// The frame's length.
        len: usize,
    },
}

/// One edge of a whole PPM frame handed to a [`FrameLine`]: its time after
/// the frame's first edge, and the level after it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameEdge {
    /// Time after the first edge (which is at 0), ns.
    pub at_ns: u64,
    /// The level after the edge.
    pub level: Level,
}

/// One frame as a [`FrameLine`] takes it: what the frame is on the wire,
/// one variant per protocol; the loop hands every whole frame over the same
/// way, at its start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WholeFrame<'a> {
    /// A PPM frame: every edge (the lead-in pulse's included), timed from
    /// the first, which was due at `due_ns`.
    Ppm {
        /// The edges.
        edges: &'a [FrameEdge],
        /// When the first was due (CLOCK_MONOTONIC ns).
        due_ns: u64,
    },
    /// A frame of bytes (SBUS: its 25 bytes), sent back to back from the
    /// write, which was due at `due_ns`.
    Bytes {
        /// The frame.
        bytes: &'a [u8],
        /// When it was due (CLOCK_MONOTONIC ns).
        due_ns: u64,
    },
}

/// A line written edge by edge, each edge at its time as the loop keeps it
/// (a GPIO line, the simulated line).
pub trait Line: Send {
    /// Drives the line to `edge.level`. `edge` also carries the scheduled
    /// time and the time read just before this call.
    fn write(&mut self, edge: &TraceEdge) -> Result<(), LineError>;

    /// Leaves the line at `level` (at start and at exit, outside the loop).
    fn park(&mut self, level: Level) -> Result<(), LineError>;

    /// True for a line whose edge takes the time read just before the
    /// call (`edge.actual_ns`), however long the call takes: the simulated
    /// line, which records that time. For a real line (false) the edge
    /// happens somewhere in the call, so a call held up may have put it
    /// later.
    fn stamped(&self) -> bool {
        false
    }
}

/// A line that sends each frame whole, timed by its own clock (SPI,
/// [`spi::SpiLine`]): the loop hands it the frame at the frame's first
/// edge. Like [`Line`], must not allocate, block (beyond sending the
/// frame), log or take a lock.
pub trait FrameLine: Send {
    /// Sends one frame, returning when it is out.
    fn write_frame(&mut self, frame: WholeFrame<'_>) -> Result<(), LineError>;

    /// Leaves the line at `level` (at start and at exit, outside the loop).
    fn park(&mut self, level: Level) -> Result<(), LineError>;
}

/// Several lines written together: bit `i` of a mask is the bank's line
/// `i`. Like [`Line`], must not allocate, block, log or take a lock.
pub trait Bank: Send {
    /// Drives every line in `mask` to its bit in `levels` (1 is high), in
    /// one call; lines outside `mask` keep their level. `scheduled_ns` is
    /// when the edges were due.
    fn write(&mut self, scheduled_ns: u64, mask: u64, levels: u64) -> Result<(), LineError>;

    /// Leaves line `bit` at `level` (at exit, outside the loop).
    fn park(&mut self, bit: u32, level: Level) -> Result<(), LineError>;
}

/// How many edges the simulated line buffers between the loop and the
/// writer thread: about 40 s of 16-channel frames at 50 Hz.
const SIM_BUFFER_EDGES: usize = 1 << 16;
/// How often the writer thread drains the buffer and flushes the file.
const SIM_FLUSH_EVERY: Duration = Duration::from_millis(50);

/// The simulated line: every edge goes through a lock-free ring buffer to a
/// writer thread that appends it to a trace file (see `ppm_shared::trace`).
/// At a size cap the writer renames the file to `FILE.1` (replacing the one
/// before) and starts `FILE` again, header included (see
/// [`crate::rotating`]).
pub struct SimLine {
    producer: rotating::Producer<TraceEdge>,
    writer: rotating::Writer,
    path: PathBuf,
}

impl SimLine {
    /// Creates (truncates) the trace file, writes `header` as `#` comment
    /// lines and starts the writer thread, which rotates the file once it
    /// would grow beyond `max_bytes`. Only a regular file is rotated (never
    /// `/dev/null` or a pipe); a rotation that fails is said once and the
    /// trace grows on; a write that fails is said, its edges are counted
    /// lost and the writer goes on.
    pub fn create(path: &Path, header: &[String], max_bytes: u64) -> std::io::Result<SimLine> {
        let header: String = header.iter().map(|h| format!("# {h}\n")).collect();
        let file = RotatingFile::create("sim trace", path, header.as_bytes(), max_bytes, 1)?;
        let (producer, writer) = rotating::spawn(
            file,
            WriterOptions {
                thread: "ppmd-sim-writer",
                capacity: SIM_BUFFER_EDGES,
                flush_every: SIM_FLUSH_EVERY,
                say_write_errors: true,
            },
            |e: &TraceEdge, line: &mut String| {
                use std::fmt::Write as _;
                let _ = write!(line, "{e}");
            },
        )?;
        Ok(SimLine {
            producer,
            writer,
            path: path.to_owned(),
        })
    }

    /// The trace file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Edges written to the file so far.
    pub fn written(&self) -> u64 {
        self.writer.written()
    }

    /// Edges that could not be written to the file (a full disk).
    pub fn lost(&self) -> u64 {
        self.writer.lost()
    }

    /// Writes every buffered edge, flushes, syncs and closes the file; an
    /// error when some edge could not be written.
    pub fn finish(&mut self) -> std::io::Result<()> {
        self.writer.finish();
        self.writer.check()
    }
}

impl Drop for SimLine {
    fn drop(&mut self) {
        let _ = self.finish();
    }
}

/// The simulated line taking whole frames, each written to the trace from
/// the write, every edge at its time from the write (actual) and from when
/// the frame was due (scheduled): a frame of bytes as the UART waveform a
/// line idling at `idle` carries in the wire's format (SBUS's 8E2 at
/// 100 000 baud); a PPM frame (`sim-spi`) with
/// its edges at their offsets, as SPI sends it, so an edge's lateness is
/// the frame's start's whatever the timing thread does during the frame.
pub struct SimFrameLine {
    sim: SimLine,
    idle: Level,
    uart: Option<UartFormat>,
    now_ns: fn() -> u64,
}

impl SimFrameLine {
    /// A whole-frame line on `sim`, idling at `idle`, drawing bytes in
    /// `uart` ([`ppm_shared::wire::WireModel::uart`]; `None` for pulses),
    /// reading the write's time from `now_ns` (CLOCK_MONOTONIC in ppmd).
    pub fn new(
        sim: SimLine,
        idle: Level,
        uart: Option<UartFormat>,
        now_ns: fn() -> u64,
    ) -> SimFrameLine {
        SimFrameLine {
            sim,
            idle,
            uart,
            now_ns,
        }
    }

    /// The simulated line under it.
    pub fn sim(&mut self) -> &mut SimLine {
        &mut self.sim
    }
}

impl FrameLine for SimFrameLine {
    fn write_frame(&mut self, frame: WholeFrame<'_>) -> Result<(), LineError> {
        let now = (self.now_ns)();
        match frame {
            WholeFrame::Bytes { bytes, due_ns } => {
                let format = self.uart.ok_or(LineError::WrongProtocol)?;
                let edges = ppm_shared::wire::uart::edges(format, bytes, 0, self.idle);
                write_whole(&mut self.sim, due_ns, now, edges)
            }
            WholeFrame::Ppm { edges, due_ns } => {
                let edges = edges.iter().map(|e| (e.at_ns, e.level));
                write_whole(&mut self.sim, due_ns, now, edges)
            }
        }
    }

    fn park(&mut self, _level: Level) -> Result<(), LineError> {
        Ok(())
    }
}

/// Writes a whole frame's `edges` (offset from its start, level) to `sim`:
/// scheduled from `due_ns`, actual from `now`.
fn write_whole(
    sim: &mut SimLine,
    due_ns: u64,
    now: u64,
    edges: impl Iterator<Item = (u64, Level)>,
) -> Result<(), LineError> {
    let mut full = false;
    for (at, level) in edges {
        full |= sim
            .write(&TraceEdge {
                scheduled_ns: due_ns + at,
                actual_ns: now + at,
                level,
            })
            .is_err();
    }
    if full {
        Err(LineError::BufferFull)
    } else {
        Ok(())
    }
}

impl Line for SimLine {
    fn write(&mut self, edge: &TraceEdge) -> Result<(), LineError> {
        if self.producer.push(*edge) {
            Ok(())
        } else {
            Err(LineError::BufferFull)
        }
    }

    fn park(&mut self, _level: Level) -> Result<(), LineError> {
        // The trace records edges only; between pulses the line is already idle.
        Ok(())
    }

    fn stamped(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ppm_shared::trace::Trace;
    use std::fs::File;

    #[test]
    fn sim_writes_every_edge_and_the_header() {
        let dir = std::env::temp_dir().join(format!("ppmd-sim-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.trace");
        let mut out = SimLine::create(&path, &["idle_level 1".into()], u64::MAX).unwrap();
        for i in 0..1000u64 {
            let level = Level::from_bit(i % 2 == 1);
            out.write(&TraceEdge {
                scheduled_ns: i * 10,
                actual_ns: i * 10 + 1,
                level,
            })
            .unwrap();
        }
        out.finish().unwrap();
        assert_eq!(out.written(), 1000);
        let t = Trace::read(std::io::BufReader::new(File::open(&path).unwrap())).unwrap();
        assert_eq!(t.idle_level, Some(Level::High));
        assert_eq!(t.edges.len(), 1000);
        assert_eq!(t.edges[999].actual_ns, 9991);
        std::fs::remove_dir_all(dir).unwrap();
    }

    fn edge(i: u64) -> TraceEdge {
        TraceEdge {
            scheduled_ns: 1_000_000_000 + i * 1_000,
            actual_ns: 1_000_000_000 + i * 1_000 + 7,
            level: Level::from_bit(i % 2 == 1),
        }
    }

    #[test]
    fn sim_rotates_at_the_cap_keeping_one_file_with_the_header() {
        let dir = std::env::temp_dir().join(format!("ppmd-simrot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.trace");
        let header = ["idle_level 1".to_string(), "frame_ns 22500000".to_string()];
        let mut out = SimLine::create(&path, &header, 4_000).unwrap();
        // About 26 bytes an edge: several rotations.
        for i in 0..1000 {
            out.write(&edge(i)).unwrap();
            if i % 100 == 99 {
                // Let the writer drain in several rounds, as it does live.
                std::thread::sleep(SIM_FLUSH_EVERY * 2);
            }
        }
        out.finish().unwrap();
        assert_eq!(out.written(), 1000);
        let old = dir.join("t.trace.1");
        assert!(!dir.join("t.trace.2").exists(), "one file kept");
        let mut edges = vec![];
        for p in [&old, &path] {
            let size = std::fs::metadata(p).unwrap().len();
            assert!(size <= 4_000, "{} is {size} bytes", p.display());
            let t = Trace::read(std::io::BufReader::new(File::open(p).unwrap())).unwrap();
            assert_eq!(
                t.idle_level,
                Some(Level::High),
                "{} has the header",
                p.display()
            );
            assert!(!t.edges.is_empty());
            edges.extend(t.edges);
        }
        // The two files hold the newest edges, in order, none lost between them.
        let first = (edges[0].scheduled_ns - 1_000_000_000) / 1_000;
        assert!(first > 0, "older edges rotated away");
        for (k, e) in edges.iter().enumerate() {
            assert_eq!(*e, edge(first + k as u64));
        }
        assert_eq!(first + edges.len() as u64, 1000);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn sim_keeps_writing_when_it_cannot_rotate() {
        // FILE.1 is a directory with something in it: the rename fails.
        let dir = std::env::temp_dir().join(format!("ppmd-simnorot-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("t.trace.1")).unwrap();
        std::fs::write(dir.join("t.trace.1/keep"), "x").unwrap();
        let path = dir.join("t.trace");
        let mut out = SimLine::create(&path, &["idle_level 1".into()], 2_000).unwrap();
        for i in 0..1000 {
            out.write(&edge(i)).unwrap();
        }
        out.finish().unwrap();
        let t = Trace::read(std::io::BufReader::new(File::open(&path).unwrap())).unwrap();
        assert_eq!(t.edges.len(), 1000, "every edge, in the one file");
        assert!(dir.join("t.trace.1/keep").exists());
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn sim_counts_the_edges_it_cannot_write_and_goes_on() {
        // /dev/full refuses every write: the writer counts, it does not end
        // (the loop's pushes go on succeeding).
        let mut out = SimLine::create(Path::new("/dev/full"), &[], u64::MAX).unwrap();
        for i in 0..20_000 {
            out.write(&edge(i)).unwrap();
            if i % 5_000 == 4_999 {
                std::thread::sleep(SIM_FLUSH_EVERY * 2);
            }
        }
        let e = out.finish().unwrap_err().to_string();
        assert!(e.contains("No space left"), "{e}");
        assert_eq!((out.lost(), out.written()), (20_000, 0));
    }

    #[test]
    fn sim_never_rotates_what_is_not_a_regular_file() {
        // A symbolic link to /dev/null: were it rotated, only the link
        // would move.
        let dir = std::env::temp_dir().join(format!("ppmd-simnull-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let link = dir.join("null.trace");
        std::os::unix::fs::symlink("/dev/null", &link).unwrap();
        let mut out = SimLine::create(&link, &["idle_level 1".into()], 100).unwrap();
        for i in 0..1000 {
            out.write(&edge(i)).unwrap();
        }
        out.finish().unwrap();
        assert_eq!(out.written(), 1000);
        assert!(std::fs::symlink_metadata(&link).unwrap().is_symlink());
        assert!(!dir.join("null.trace.1").exists());
        std::fs::remove_dir_all(dir).unwrap();
    }
}
