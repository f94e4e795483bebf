//! The frame log: one JSON line per emitted frame and per line-state
//! transition, for system identification.
//!
//! The timing loop pushes fixed-size [`Record`]s into a bounded lock-free
//! ring; a writer thread formats and appends them. When the writer falls
//! behind the ring fills and the loop drops rows (and counts them) instead
//! of waiting. The file is rotated at a size cap: `FILE` becomes `FILE.1`,
//! `FILE.1` becomes `FILE.2`, and so on, keeping [`KEEP`] old files. The
//! ring, the writer and the file are [`crate::rotating`]'s. The row's
//! text is [`ppm_shared::framelog::Row`]'s, which the readers share.

use crate::rotating::{self, RotatingFile, WriterOptions};
use ppm_shared::config::Timing;
use ppm_shared::frame::MAX_CHANNELS;
use ppm_shared::framelog::{FrameRow, Row, Status, TransitionRow};
use ppm_shared::line::LineState;
use std::path::Path;
use std::time::Duration;

/// Rows the ring holds: about 90 s of frames at 44 Hz.
const RING: usize = 4096;
/// Rotated files kept besides the current one.
pub const KEEP: usize = 3;
/// How often the writer drains the ring and flushes.
const FLUSH_EVERY: Duration = Duration::from_millis(100);

/// One row, as the loop records it (fixed size, `Copy`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Record {
    /// An emitted frame.
    Frame {
        /// Frame number since ppmd started (1, 2, ...).
        frame: u64,
        /// CLOCK_MONOTONIC time of the frame's first edge, ns.
        start_mono_ns: u64,
        /// CLOCK_REALTIME time of the frame's first edge, ns.
        start_real_ns: u64,
        /// The line state the frame was emitted in (active or failsafe).
        state: LineState,
        /// The timing that placed the frame (grid or follow).
        timing: Timing,
        /// The command the frame carries, if any (none for failsafe defaults).
        command: Option<CommandInfo>,
        /// Whether the line carried it whole.
        status: FrameStatus,
        /// Number of channels in `values_ns`: the frame's, or the ones an
        /// aborted frame carried before its abort.
        channels: u8,
        /// The channel values the line carried, ns: each value sent, moved
        /// by the difference of its two edges' measured lateness, to the
        /// microsecond (the value sent unless an edge was late).
        values_ns: [u32; MAX_CHANNELS],
    },
    /// The line changed state.
    Transition {
        /// CLOCK_MONOTONIC time of the change, ns.
        mono_ns: u64,
        /// CLOCK_REALTIME time of the change, ns.
        real_ns: u64,
        /// State before.
        from: LineState,
        /// State after.
        to: LineState,
    },
}

/// What became of a frame on the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameStatus {
    /// Every edge went out within the late-edge guard.
    Whole,
    /// Every edge went out, but one that receivers time reached the line
    /// later than the guard (the timing thread was held up during its
    /// write): the values are as the line carried them.
    Glitched,
    /// An edge that receivers time was found later than the guard before
    /// its write: it and the rest of the frame were not written. `at` is
    /// the first channel (1-based) the line did not carry; the channels
    /// before it are within the guard, unless `glitched`.
    Aborted {
        /// The first channel not carried, 1-based.
        at: u8,
        /// Before the abort, an edge reached the line later than the guard.
        glitched: bool,
    },
}

impl FrameStatus {
    /// Its `status` in the log: `whole`, `glitched` or `aborted`.
    pub fn logged(self) -> Status {
        match self {
            FrameStatus::Whole => Status::Whole,
            FrameStatus::Glitched => Status::Glitched,
            FrameStatus::Aborted { .. } => Status::Aborted,
        }
    }

    /// Its name in the log: `whole`, `glitched` or `aborted`.
    pub fn name(self) -> &'static str {
        self.logged().name()
    }

    /// Whether an edge receivers time reached the line later than the guard.
    pub fn glitched(self) -> bool {
        matches!(
            self,
            FrameStatus::Glitched | FrameStatus::Aborted { glitched: true, .. }
        )
    }
}

/// Where a frame's command came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CommandInfo {
    /// The sender's `seq`, if it gave one.
    pub seq: Option<u64>,
    /// The ingress's number for the command.
    pub ingress_seq: u64,
    /// When the ingress received it (CLOCK_MONOTONIC ns).
    pub recv_mono_ns: u64,
    /// When the ingress received it (CLOCK_REALTIME ns).
    pub recv_real_ns: u64,
}

impl Record {
    /// The row the writer formats ([`Row::to_json`]): values in us.
    pub fn row(&self) -> Row {
        match *self {
            Record::Frame {
                frame,
                start_mono_ns,
                start_real_ns,
                state,
                timing,
                command,
                status,
                channels,
                values_ns,
            } => Row::Frame(FrameRow {
                aborted_at: match status {
                    FrameStatus::Aborted { at, .. } => Some(at),
                    _ => None,
                },
                ch_us: values_ns[..channels as usize]
                    .iter()
                    .map(|&ns| ns as f64 / 1_000.0)
                    .collect(),
                frame,
                glitched: status.glitched(),
                ingress_seq: command.map(|c| c.ingress_seq),
                mono_ns: start_mono_ns,
                real_ns: start_real_ns,
                recv_mono_ns: command.map(|c| c.recv_mono_ns),
                recv_real_ns: command.map(|c| c.recv_real_ns),
                seq: command.and_then(|c| c.seq),
                state,
                status: status.logged(),
                timing,
            }),
            Record::Transition {
                mono_ns,
                real_ns,
                from,
                to,
            } => Row::Transition(TransitionRow {
                from,
                mono_ns,
                real_ns,
                to,
            }),
        }
    }

    /// The JSON line (without the newline).
    pub fn to_json(&self) -> String {
        self.row().to_json()
    }
}

/// The loop's end of the log: [`rotating::Producer::push`] queues a row,
/// or drops and counts it when the ring is full (never waits).
pub type Producer = rotating::Producer<Record>;

/// The writer thread and its counters: rows `written`, `lost` (the file
/// could not be written; the writer goes on), `dropped` (the ring was
/// full), the `last_error`; `finish` writes what is queued, flushes and
/// syncs.
pub type Writer = rotating::Writer;

/// Opens (appends to) the log at `path`, rotating at `max_bytes` (a regular
/// file only). The path must be writable at start; later write errors are
/// counted and the writer goes on, never fatal; a rotation that fails is
/// said once and the file grows on.
pub fn open(path: &Path, max_bytes: u64) -> std::io::Result<(Producer, Writer)> {
    let file = RotatingFile::append("frame log", path, max_bytes, KEEP)?;
    rotating::spawn(
        file,
        WriterOptions {
            thread: "ppmd-frame-log",
            capacity: RING,
            flush_every: FLUSH_EVERY,
            // The main thread reads `lost` and `last_error` and says them.
            say_write_errors: false,
        },
        |r: &Record, line: &mut String| line.push_str(&r.to_json()),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(n: u64) -> Record {
        let mut values_ns = [0; MAX_CHANNELS];
        values_ns[0] = 1_500_250;
        values_ns[1] = 1_000_000;
        Record::Frame {
            frame: n,
            start_mono_ns: 1_000 + n,
            start_real_ns: 2_000 + n,
            state: LineState::Active,
            timing: Timing::Follow,
            command: Some(CommandInfo {
                seq: Some(7),
                ingress_seq: 3,
                recv_mono_ns: 5,
                recv_real_ns: 6,
            }),
            status: FrameStatus::Whole,
            channels: 2,
            values_ns,
        }
    }

    /// The writer as it was before [`Row`]: `json!`, a sorted map.
    fn old_json(r: &Record) -> String {
        match r {
            Record::Frame {
                frame,
                start_mono_ns,
                start_real_ns,
                state,
                timing,
                command,
                status,
                channels,
                values_ns,
            } => {
                let ch: Vec<serde_json::Value> = values_ns[..*channels as usize]
                    .iter()
                    .map(|&ns| serde_json::json!(ns as f64 / 1_000.0))
                    .collect();
                let c = command.as_ref();
                serde_json::json!({
                    "type": "frame",
                    "frame": frame,
                    "mono_ns": start_mono_ns,
                    "real_ns": start_real_ns,
                    "state": state.name(),
                    "timing": timing.name(),
                    "seq": c.and_then(|c| c.seq),
                    "ingress_seq": c.map(|c| c.ingress_seq),
                    "recv_mono_ns": c.map(|c| c.recv_mono_ns),
                    "recv_real_ns": c.map(|c| c.recv_real_ns),
                    "status": status.name(),
                    "aborted_at": match status {
                        FrameStatus::Aborted { at, .. } => Some(*at),
                        _ => None,
                    },
                    "glitched": status.glitched(),
                    "ch_us": ch,
                })
                .to_string()
            }
            Record::Transition {
                mono_ns,
                real_ns,
                from,
                to,
            } => serde_json::json!({
                "type": "transition",
                "mono_ns": mono_ns,
                "real_ns": real_ns,
                "from": from.name(),
                "to": to.name(),
            })
            .to_string(),
        }
    }

    /// Frames of every status, timing, state and command, with values of
    /// every kind, and every transition.
    fn records() -> Vec<Record> {
        let mut out = Vec::new();
        let statuses = [
            FrameStatus::Whole,
            FrameStatus::Glitched,
            FrameStatus::Aborted {
                at: 1,
                glitched: false,
            },
            FrameStatus::Aborted {
                at: 16,
                glitched: true,
            },
        ];
        let commands = [
            None,
            Some(CommandInfo {
                seq: None,
                ingress_seq: 1,
                recv_mono_ns: u64::MAX,
                recv_real_ns: 0,
            }),
            Some(CommandInfo {
                seq: Some(u64::MAX),
                ingress_seq: 42,
                recv_mono_ns: 123_456_789,
                recv_real_ns: 1_700_000_000_123_456_789,
            }),
        ];
        let mut values_ns = [0; MAX_CHANNELS];
        for (i, v) in values_ns.iter_mut().enumerate() {
            *v = [
                1_500_250,
                999_999,
                1,
                0,
                u32::MAX,
                2_000_000,
                1_234_567,
                1_000_001,
            ][i % 8]
                + i as u32 % 2;
        }
        for (k, status) in statuses.into_iter().enumerate() {
            for command in commands {
                for (timing, state) in [
                    (Timing::Grid, LineState::Active),
                    (Timing::Follow, LineState::Failsafe),
                ] {
                    out.push(Record::Frame {
                        frame: k as u64 * 1_000_003,
                        start_mono_ns: 17 + k as u64,
                        start_real_ns: 1_700_000_000_000_000_000,
                        state,
                        timing,
                        command,
                        status,
                        channels: [0, 1, 8, 16][k] as u8,
                        values_ns,
                    });
                }
            }
        }
        for from in LineState::ALL {
            for to in LineState::ALL {
                out.push(Record::Transition {
                    mono_ns: u64::MAX,
                    real_ns: 3,
                    from,
                    to,
                });
            }
        }
        out
    }

    #[test]
    fn the_text_is_the_old_writers_byte_for_byte() {
        for r in records() {
            assert_eq!(r.to_json(), old_json(&r), "{r:?}");
        }
    }

    #[test]
    fn rows_read_back_as_written() {
        for r in records() {
            assert_eq!(Row::parse(&r.to_json()).unwrap(), r.row(), "{r:?}");
        }
        let Row::Frame(f) = frame(1).row() else {
            unreachable!()
        };
        assert_eq!(f.ch_us, [1500.25, 1000.0]);
        assert_eq!((f.seq, f.frame), (Some(7), 1));
        assert_eq!(
            (f.timing, f.status, f.aborted_at),
            (Timing::Follow, Status::Whole, None)
        );
        let mut grid = frame(1);
        let Record::Frame {
            timing,
            status,
            channels,
            ..
        } = &mut grid
        else {
            unreachable!()
        };
        *timing = Timing::Grid;
        *status = FrameStatus::Aborted {
            at: 2,
            glitched: false,
        };
        *channels = 1;
        let Row::Frame(f) = Row::parse(&grid.to_json()).unwrap() else {
            unreachable!()
        };
        assert_eq!(
            (f.timing, f.status, f.aborted_at, f.glitched),
            (Timing::Grid, Status::Aborted, Some(2), false)
        );
        assert_eq!(f.ch_us, [1500.25], "what it carried");
    }

    #[test]
    fn rotates_at_the_cap_and_keeps_three() {
        let dir = std::env::temp_dir().join(format!("ppmd-framelog-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("frames.jsonl");
        // Frames 10..=64: rows of one length.
        let line_len = frame(10).to_json().len() as u64 + 1;
        let (mut p, mut w) = open(&path, line_len * 10).unwrap();
        for n in 10..=64 {
            p.push(frame(n));
        }
        w.finish();
        assert_eq!(w.written(), 55);
        let lines = |p: &Path| {
            std::fs::read_to_string(p)
                .map(|s| s.lines().count())
                .unwrap_or(0)
        };
        assert_eq!(lines(&path), 5, "55 rows, 10 a file: 5 in the current one");
        for n in 1..=KEEP {
            assert_eq!(lines(&dir.join(format!("frames.jsonl.{n}"))), 10);
        }
        assert!(!dir.join(format!("frames.jsonl.{}", KEEP + 1)).exists());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_log_that_cannot_rotate_loses_nothing() {
        // FILE.3 is a directory with something in it: the third rotation's
        // first rename fails; the log grows on instead of losing rows.
        let dir = std::env::temp_dir().join(format!("ppmd-framelog-stuck-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("frames.jsonl.3")).unwrap();
        std::fs::write(dir.join("frames.jsonl.3/keep"), "x").unwrap();
        let path = dir.join("frames.jsonl");
        let line_len = frame(10).to_json().len() as u64 + 1;
        let (mut p, mut w) = open(&path, line_len * 10).unwrap();
        for n in 10..=64 {
            p.push(frame(n));
        }
        w.finish();
        assert_eq!((w.written(), w.lost(), w.last_error()), (55, 0, None));
        let count = |p: &Path| std::fs::read_to_string(p).unwrap().lines().count();
        assert_eq!(count(&dir.join("frames.jsonl.2")), 10);
        assert_eq!(count(&dir.join("frames.jsonl.1")), 10);
        assert_eq!(count(&path), 35, "the rest, in the current file");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_full_ring_drops_and_counts() {
        let dir = std::env::temp_dir().join(format!("ppmd-framelog-full-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (mut p, mut w) = open(&dir.join("f.jsonl"), u64::MAX).unwrap();
        // The writer sleeps between drains: pushing far more than the ring at
        // once must drop, not block.
        for n in 0..(RING as u64 * 4) {
            p.push(frame(n));
        }
        w.finish();
        assert!(w.dropped() > 0);
        assert_eq!(w.dropped() + w.written(), RING as u64 * 4);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_log_that_cannot_be_written_counts_its_losses_and_goes_on() {
        // /dev/full takes the open and refuses every write (ENOSPC); as a
        // device it is never rotated (renamed), whatever the cap.
        let (mut p, mut w) = open(Path::new("/dev/full"), 100).unwrap();
        for n in 0..50 {
            p.push(frame(n));
        }
        std::thread::sleep(FLUSH_EVERY * 3);
        assert_eq!(w.lost(), 50, "counted while running");
        assert!(w.last_error().is_some_and(|e| !e.is_empty()));
        for n in 50..60 {
            p.push(frame(n));
        }
        w.finish();
        assert_eq!((w.lost(), w.written()), (60, 0));
        assert!(Path::new("/dev/full").exists(), "not rotated");
    }
}
