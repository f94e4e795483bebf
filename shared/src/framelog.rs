//! A row of ppmd's frame log (docs/programs.md, "The frame log"): one JSON
//! line per emitted frame and per line-state transition.
//!
//! One type for both sides of the contract, as [`crate::status`] is for
//! the status reply: ppmd's log writer formats each row with
//! [`Row::to_json`]; ppm-bench and the tests read them back with
//! [`Row::parse`] or [`read`]. A key renamed here is renamed for the writer
//! and every reader at once.
//!
//! - [`Row`]: a line of the log, tagged by its `"type"`: a [`FrameRow`] or a
//!   [`TransitionRow`].
//! - [`Status`]: what became of a frame on the line (`status`).
//! - [`parse_rows`], [`read`]: a whole log, whose last line may be cut
//!   short (the writer appends while it is read), and [`ReadError`].
//!
//! The keys come in alphabetical order, `type` last: the order the log has
//! had since its first row (the writer built a sorted JSON map), kept so
//! that logs stay byte for byte what they were.

use crate::line::LineState;
use crate::signal::Timing;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One line of the frame log.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum Row {
    /// `"type": "frame"`: an emitted frame.
    Frame(FrameRow),
    /// `"type": "transition"`: the line changed state.
    Transition(TransitionRow),
}

/// An emitted frame (`"type": "frame"`).
///
/// Fields in the log's key order (alphabetical; see the module's
/// documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameRow {
    /// With `status` `aborted`: the first channel (1-based) the line did
    /// not carry; `null` otherwise.
    pub aborted_at: Option<u8>,
    /// The channel values the line carried, us: each value sent, moved by
    /// the difference of its two edges' measured lateness, to the
    /// microsecond. An aborted frame has the channels before its abort.
    pub ch_us: Vec<f64>,
    /// Frame number since ppmd started (1, 2, ...).
    pub frame: u64,
    /// Whether an edge receivers time reached the line later than the
    /// late-edge guard (with `status` `glitched`, or `aborted` after it).
    pub glitched: bool,
    /// udp-ingress's number of the command the frame carries; `null`
    /// without one (failsafe defaults).
    pub ingress_seq: Option<u64>,
    /// CLOCK_MONOTONIC time of the frame's first edge, ns.
    pub mono_ns: u64,
    /// CLOCK_REALTIME time of the frame's first edge, ns.
    pub real_ns: u64,
    /// When udp-ingress received the command (CLOCK_MONOTONIC ns); `null`
    /// without one.
    pub recv_mono_ns: Option<u64>,
    /// When udp-ingress received the command (CLOCK_REALTIME ns); `null`
    /// without one.
    pub recv_real_ns: Option<u64>,
    /// The sender's `seq` of the command, if it gave one.
    pub seq: Option<u64>,
    /// The line state the frame was emitted in (`active` or `failsafe`).
    pub state: LineState,
    /// Whether the line carried it whole.
    pub status: Status,
    /// The timing that placed the frame (`grid` or `follow`).
    pub timing: Timing,
}

/// The line changed state (`"type": "transition"`).
///
/// Fields in the log's key order (alphabetical).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TransitionRow {
    /// State before.
    pub from: LineState,
    /// CLOCK_MONOTONIC time of the change, ns.
    pub mono_ns: u64,
    /// CLOCK_REALTIME time of the change, ns.
    pub real_ns: u64,
    /// State after.
    pub to: LineState,
}

/// What became of a frame on the line: its `status` in the log.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Every edge went out within the late-edge guard.
    Whole,
    /// Every edge went out, one of them later than the guard: the values
    /// are as the line carried them.
    Glitched,
    /// An edge was found later than the guard before its write: it and the
    /// rest of the frame were not written (`aborted_at`).
    Aborted,
}

impl Status {
    /// Every status.
    pub const ALL: [Status; 3] = [Status::Whole, Status::Glitched, Status::Aborted];

    /// Its name in the log: `whole`, `glitched` or `aborted`.
    pub fn name(self) -> &'static str {
        match self {
            Status::Whole => "whole",
            Status::Glitched => "glitched",
            Status::Aborted => "aborted",
        }
    }
}

impl Serialize for Row {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        // The tag after the fields: `type` sorts last (see the module's
        // documentation), where an internally tagged enum would put it first.
        #[derive(Serialize)]
        struct Tagged<'a, T> {
            #[serde(flatten)]
            row: &'a T,
            r#type: &'static str,
        }
        match self {
            Row::Frame(row) => Tagged {
                row,
                r#type: "frame",
            }
            .serialize(s),
            Row::Transition(row) => Tagged {
                row,
                r#type: "transition",
            }
            .serialize(s),
        }
    }
}

impl Row {
    /// The JSON line, without the newline.
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a frame-log row always serializes")
    }

    /// Parses one line of the log.
    pub fn parse(line: &str) -> Result<Row, serde_json::Error> {
        serde_json::from_str(line)
    }

    /// The frame, if the row is one.
    pub fn as_frame(&self) -> Option<&FrameRow> {
        match self {
            Row::Frame(f) => Some(f),
            Row::Transition(_) => None,
        }
    }

    /// The transition, if the row is one.
    pub fn as_transition(&self) -> Option<&TransitionRow> {
        match self {
            Row::Transition(t) => Some(t),
            Row::Frame(_) => None,
        }
    }

    /// CLOCK_MONOTONIC time of the row: a frame's first edge, or the change.
    pub fn mono_ns(&self) -> u64 {
        match self {
            Row::Frame(f) => f.mono_ns,
            Row::Transition(t) => t.mono_ns,
        }
    }
}

impl FrameRow {
    /// `ch_us` in ns, rounded to the ns (the log's values are decimal us).
    pub fn ch_ns(&self) -> Vec<u64> {
        self.ch_us
            .iter()
            .map(|us| (us * 1_000.0).round() as u64)
            .collect()
    }
}

/// A line of a log that is not a row.
#[derive(Debug, thiserror::Error)]
#[error("line {line}: not a frame-log row ({source}): {text}")]
pub struct BadLine {
    /// Its number, 1-based.
    pub line: usize,
    /// The line, cut to its first 200 characters.
    pub text: String,
    /// Why it is not a row.
    #[source]
    pub source: serde_json::Error,
}

/// Why a frame log could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file could not be read.
    #[error("reading the frame log {}: {source}", path.display())]
    Io {
        /// The log.
        path: PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// A line is not a row: not written by this version of ppmd, or not a
    /// frame log.
    #[error("the frame log {}: {source}", path.display())]
    Line {
        /// The log.
        path: PathBuf,
        /// The line.
        #[source]
        source: BadLine,
    },
}

/// The rows of a whole log's text, in order. A last line without its
/// newline that does not parse is skipped: the writer was appending it.
/// Any other line that is not a row is an error naming its number.
pub fn parse_rows(text: &str) -> Result<Vec<Row>, BadLine> {
    let cut_short = !text.is_empty() && !text.ends_with('\n');
    let lines: Vec<&str> = text.lines().collect();
    let mut rows = Vec::with_capacity(lines.len());
    for (i, line) in lines.iter().enumerate() {
        match Row::parse(line) {
            Ok(row) => rows.push(row),
            Err(_) if cut_short && i + 1 == lines.len() => {}
            Err(source) => {
                return Err(BadLine {
                    line: i + 1,
                    text: line.chars().take(200).collect(),
                    source,
                })
            }
        }
    }
    Ok(rows)
}

/// Reads the log at `path` (the current file; not its rotated
/// `PATH.1`...): [`parse_rows`] of its text.
pub fn read(path: &Path) -> Result<Vec<Row>, ReadError> {
    let text = std::fs::read_to_string(path).map_err(|source| ReadError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_rows(&text).map_err(|source| ReadError::Line {
        path: path.to_path_buf(),
        source,
    })
}

/// The frames of the log at `path`, in order (its transitions left out).
pub fn read_frames(path: &Path) -> Result<Vec<FrameRow>, ReadError> {
    Ok(read(path)?
        .into_iter()
        .filter_map(|r| match r {
            Row::Frame(f) => Some(f),
            Row::Transition(_) => None,
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame as ppmd writes it: a command, two channels.
    const FRAME: &str = r#"{"aborted_at":null,"ch_us":[1500.25,1000.0],"frame":1,"glitched":false,"ingress_seq":3,"mono_ns":1001,"real_ns":2001,"recv_mono_ns":5,"recv_real_ns":6,"seq":7,"state":"active","status":"whole","timing":"follow","type":"frame"}"#;
    /// A failsafe frame aborted at channel 2 after a glitch: no command.
    const ABORTED: &str = r#"{"aborted_at":2,"ch_us":[1500.001],"frame":18446744073709551615,"glitched":true,"ingress_seq":null,"mono_ns":0,"real_ns":1,"recv_mono_ns":null,"recv_real_ns":null,"seq":null,"state":"failsafe","status":"aborted","timing":"grid","type":"frame"}"#;
    const TRANSITION: &str =
        r#"{"from":"active","mono_ns":1,"real_ns":2,"to":"silent","type":"transition"}"#;

    fn frame() -> FrameRow {
        FrameRow {
            aborted_at: None,
            ch_us: vec![1500.25, 1000.0],
            frame: 1,
            glitched: false,
            ingress_seq: Some(3),
            mono_ns: 1001,
            real_ns: 2001,
            recv_mono_ns: Some(5),
            recv_real_ns: Some(6),
            seq: Some(7),
            state: LineState::Active,
            status: Status::Whole,
            timing: Timing::Follow,
        }
    }

    fn aborted() -> FrameRow {
        FrameRow {
            aborted_at: Some(2),
            ch_us: vec![1500.001],
            frame: u64::MAX,
            glitched: true,
            ingress_seq: None,
            mono_ns: 0,
            real_ns: 1,
            recv_mono_ns: None,
            recv_real_ns: None,
            seq: None,
            state: LineState::Failsafe,
            status: Status::Aborted,
            timing: Timing::Grid,
        }
    }

    fn transition() -> TransitionRow {
        TransitionRow {
            from: LineState::Active,
            mono_ns: 1,
            real_ns: 2,
            to: LineState::Silent,
        }
    }

    #[test]
    fn rows_are_the_text_the_log_has_always_had() {
        // The text is the old writer's (`json!`, a sorted map), byte for
        // byte; ppmd's tests compare the two writers on more records.
        assert_eq!(Row::Frame(frame()).to_json(), FRAME);
        assert_eq!(Row::Frame(aborted()).to_json(), ABORTED);
        assert_eq!(Row::Transition(transition()).to_json(), TRANSITION);
    }

    #[test]
    fn every_variant_round_trips() {
        let mut rows = vec![
            Row::Frame(frame()),
            Row::Frame(aborted()),
            Row::Frame(FrameRow {
                ch_us: vec![],
                status: Status::Glitched,
                ..frame()
            }),
        ];
        for from in LineState::ALL {
            for to in LineState::ALL {
                rows.push(Row::Transition(TransitionRow {
                    from,
                    to,
                    ..transition()
                }));
            }
        }
        for row in rows {
            assert_eq!(Row::parse(&row.to_json()).unwrap(), row);
        }
        assert_eq!(Row::parse(FRAME).unwrap(), Row::Frame(frame()));
        assert_eq!(Row::parse(TRANSITION).unwrap().mono_ns(), 1);
    }

    #[test]
    fn names_are_the_logs() {
        for s in Status::ALL {
            assert_eq!(
                serde_json::to_string(&s).unwrap(),
                format!("\"{}\"", s.name())
            );
        }
        for s in LineState::ALL {
            assert_eq!(
                serde_json::to_string(&s).unwrap(),
                format!("\"{}\"", s.name())
            );
        }
        for t in [Timing::Grid, Timing::Follow] {
            assert_eq!(
                serde_json::to_string(&t).unwrap(),
                format!("\"{}\"", t.name())
            );
        }
    }

    #[test]
    fn a_cut_short_last_line_is_skipped() {
        let whole = format!("{FRAME}\n{TRANSITION}\n");
        assert_eq!(parse_rows(&whole).unwrap().len(), 2);
        // Cut anywhere in the last row: the rows before it.
        for cut in 1..TRANSITION.len() {
            let text = format!("{FRAME}\n{}", &TRANSITION[..cut]);
            let rows = parse_rows(&text).unwrap();
            assert_eq!(rows, [Row::Frame(frame())], "cut at {cut}");
        }
        // Only its newline missing: the row is whole.
        assert_eq!(
            parse_rows(&format!("{FRAME}\n{TRANSITION}")).unwrap().len(),
            2
        );
        assert_eq!(parse_rows("").unwrap(), []);
    }

    #[test]
    fn a_bad_line_is_an_error_with_its_number() {
        let text = format!("{FRAME}\n{}\n{TRANSITION}\n", &FRAME[..40]);
        let e = parse_rows(&text).unwrap_err();
        assert_eq!(e.line, 2);
        assert!(
            e.to_string().starts_with("line 2: not a frame-log row"),
            "{e}"
        );
        // A bad last line that ends in its newline was written whole.
        let e = parse_rows(&format!("{FRAME}\n{{\"type\":\"nope\"}}\n")).unwrap_err();
        assert_eq!(e.line, 2, "{e}");
        let dir = std::env::temp_dir().join(format!("ppm-framelog-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("f.jsonl");
        std::fs::write(&path, &text).unwrap();
        let e = read(&path).unwrap_err();
        assert!(
            e.to_string()
                .contains("f.jsonl: line 2: not a frame-log row"),
            "{e}"
        );
        std::fs::write(&path, format!("{TRANSITION}\n{FRAME}\n{}", &FRAME[..9])).unwrap();
        assert_eq!(read_frames(&path).unwrap(), [frame()]);
        let _ = std::fs::remove_dir_all(dir);
        assert!(matches!(read(&path), Err(ReadError::Io { .. })));
    }

    #[test]
    fn ch_ns_rounds_to_the_ns() {
        assert_eq!(aborted().ch_ns(), [1_500_001]);
        assert_eq!(frame().ch_ns(), [1_500_250, 1_000_000]);
    }
}
