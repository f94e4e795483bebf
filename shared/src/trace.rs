//! The simulated line's trace: one line per edge,
//! `<scheduled_ns> <actual_ns> <level>`, CLOCK_MONOTONIC nanoseconds and the
//! level (0 or 1) after the edge. Lines starting with `#` are comments; ppmd
//! writes its settings there (`# idle_level 0`, ...).

use crate::decode::{self, DecodedFrame, DecoderLimits};
use crate::frame::Level;
use crate::receiver::{Receiver, ReceiverChoice};
use crate::sbus::uart::{self, Character};
use crate::sbus::{Framer, SbusReceiver, Taken, BYTE_NS};
use crate::wire::Protocol;
use std::io::BufRead;

/// One edge of the simulated line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TraceEdge {
    /// When the edge was due (CLOCK_MONOTONIC ns).
    pub scheduled_ns: u64,
    /// When it was written (CLOCK_MONOTONIC ns, read just before the write).
    pub actual_ns: u64,
    /// The level after the edge.
    pub level: Level,
}

impl TraceEdge {
    /// Actual minus scheduled time, ns (negative when early).
    pub fn error_ns(&self) -> i64 {
        self.actual_ns as i64 - self.scheduled_ns as i64
    }
}

impl std::fmt::Display for TraceEdge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} {} {}",
            self.scheduled_ns,
            self.actual_ns,
            self.level.as_u8()
        )
    }
}

/// A malformed trace line.
#[derive(Debug, thiserror::Error)]
pub enum TraceError {
    /// A line that is neither a comment nor three numbers.
    #[error("trace line {line}: `{text}` is not `<scheduled_ns> <actual_ns> <0|1>`")]
    Malformed { line: usize, text: String },
    /// Reading failed (why: its source).
    #[error("reading trace")]
    Io(#[from] std::io::Error),
}

/// Parses one line: `Ok(None)` for comments and blank lines.
pub fn parse_line(text: &str) -> Option<Result<TraceEdge, ()>> {
    let t = text.trim();
    if t.is_empty() || t.starts_with('#') {
        return None;
    }
    let mut it = t.split_ascii_whitespace();
    let edge = (|| {
        let scheduled_ns = it.next()?.parse().ok()?;
        let actual_ns = it.next()?.parse().ok()?;
        let level = match it.next()? {
            "0" => Level::Low,
            "1" => Level::High,
            _ => return None,
        };
        it.next().is_none().then_some(TraceEdge {
            scheduled_ns,
            actual_ns,
            level,
        })
    })();
    Some(edge.ok_or(()))
}

/// A whole trace: its edges and the idle level its header names (if any).
#[derive(Debug, Clone, Default)]
pub struct Trace {
    /// Edges in file order.
    pub edges: Vec<TraceEdge>,
    /// From a `# idle_level N` comment.
    pub idle_level: Option<Level>,
    /// From a `# receiver NAME` comment: what ppmd's configuration was for.
    pub receiver: Option<ReceiverChoice>,
    /// From a `# protocol NAME` comment (PPM when absent).
    pub protocol: Protocol,
    /// From a `# channels NAME,NAME,...` comment: how many channels a
    /// whole frame has.
    pub channels: Option<usize>,
    /// From a `# baud N` comment: a protocol of bytes' UART rate (the
    /// protocol's default when absent).
    pub baud: Option<u32>,
}

impl Trace {
    /// Reads a trace. A final line without a newline may be cut short by a
    /// writer still running; it is ignored.
    pub fn read(r: impl BufRead) -> Result<Trace, TraceError> {
        let mut trace = Trace::default();
        let lines: Vec<String> = r.lines().collect::<Result<_, _>>()?;
        let n = lines.len();
        for (i, text) in lines.into_iter().enumerate() {
            if let Some(v) = text.trim().strip_prefix("# idle_level ") {
                trace.idle_level = Some(Level::from_bit(v.trim() == "1"));
            }
            if let Some(v) = text.trim().strip_prefix("# receiver ") {
                trace.receiver = v.trim().parse().ok();
            }
            if let Some(p) = text.trim().strip_prefix("# protocol ") {
                trace.protocol = p.trim().parse().unwrap_or(trace.protocol);
            }
            if let Some(v) = text.trim().strip_prefix("# channels ") {
                trace.channels = Some(v.trim().split(',').count());
            }
            if let Some(v) = text.trim().strip_prefix("# baud ") {
                trace.baud = v.trim().parse().ok().filter(|&b: &u32| b > 0);
            }
            match parse_line(&text) {
                None => {}
                Some(Ok(e)) => trace.edges.push(e),
                Some(Err(())) if i + 1 == n => {}
                Some(Err(())) => return Err(TraceError::Malformed { line: i + 1, text }),
            }
        }
        Ok(trace)
    }

    /// Decodes by scheduled time (`actual = false`) or by actual time, timing
    /// the edges that leave the idle level (low when the trace does not say).
    pub fn decode(&self, actual: bool) -> Vec<DecodedFrame> {
        let leading = self.idle_level.unwrap_or(Level::Low).opposite();
        decode::decode(
            self.edges.iter().map(|e| {
                let t = if actual { e.actual_ns } else { e.scheduled_ns };
                (t, e.level)
            }),
            leading,
            DecoderLimits::default(),
        )
    }

    /// The frames `receiver` hands on, decoded as its firmware does (see
    /// [`crate::receiver`]: timing the rising edges), by scheduled or actual
    /// time.
    pub fn decode_as(&self, receiver: Receiver, actual: bool) -> Vec<DecodedFrame> {
        crate::receiver::decode_as(
            receiver,
            self.edges.iter().map(|e| {
                let t = if actual { e.actual_ns } else { e.scheduled_ns };
                (t, e.level)
            }),
            crate::receiver::TIMED_EDGE,
        )
        .0
    }

    /// An SBUS trace's characters, read by a UART receiver from the
    /// scheduled or actual edge times (the line idling at the header's
    /// level, high when it does not say).
    pub fn sbus_characters(&self, actual: bool) -> Vec<Character> {
        let edges: Vec<(u64, Level)> = self
            .edges
            .iter()
            .map(|e| (if actual { e.actual_ns } else { e.scheduled_ns }, e.level))
            .collect();
        uart::decode(&edges, self.idle_level.unwrap_or(Level::High))
    }

    /// The SBUS frames `receiver`'s framing takes from the trace (see
    /// [`Trace::sbus_characters`]), each with when it was taken; a
    /// character with a parity or stop bit error is taken too, as the
    /// receivers do.
    pub fn sbus_taken(&self, receiver: SbusReceiver, actual: bool) -> Vec<Taken> {
        let mut framer = Framer::new(receiver);
        let chars = self.sbus_characters(actual);
        let mut taken: Vec<Taken> = chars
            .iter()
            .filter_map(|c| framer.push(c.byte, c.end_ns))
            .collect();
        if let Some(last) = chars.last() {
            taken.extend(framer.idle(last.end_ns + BYTE_NS));
        }
        taken
    }

    /// The receiver tools decode as by default: the one the trace's header
    /// names, EdgeTX 2.10 when it names `any` or none.
    pub fn default_receiver(&self) -> Receiver {
        match self.receiver {
            Some(ReceiverChoice::One(r)) => r,
            _ => Receiver::EdgeTx,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines() {
        assert_eq!(parse_line("# x"), None);
        assert_eq!(parse_line("  "), None);
        let e = parse_line("10 12 1").unwrap().unwrap();
        assert_eq!(
            (e.scheduled_ns, e.actual_ns, e.level, e.error_ns()),
            (10, 12, Level::High, 2)
        );
        assert_eq!(e.to_string(), "10 12 1");
        for bad in ["1 2", "1 2 3", "a 2 1", "1 2 1 4"] {
            assert_eq!(parse_line(bad), Some(Err(())), "{bad}");
        }
    }

    #[test]
    fn an_sbus_trace_reads_back_as_the_frames_sent() {
        let frame = crate::sbus::encode(&[992; 16], Default::default());
        let mut text = String::from("# idle_level 1\n# protocol sbus\n");
        for start in [1_000_000u64, 9_000_000] {
            for (t, l) in uart::edges(&frame, start, Level::High) {
                text += &format!("{t} {} {}\n", t + 7, l.as_u8());
            }
        }
        let t = Trace::read(text.as_bytes()).unwrap();
        assert_eq!(t.protocol, Protocol::Sbus);
        let chars = t.sbus_characters(false);
        assert_eq!(chars.len(), 50);
        assert!(chars.iter().all(|c| c.parity_ok && c.stop_ok));
        for r in SbusReceiver::ALL {
            let taken = t.sbus_taken(r, true);
            assert_eq!(taken.len(), 2, "{r:?}");
            assert!(taken.iter().all(|k| k.frame == frame));
        }
        // EdgeTX takes each an idle character after its last byte ends.
        let taken = t.sbus_taken(SbusReceiver::EdgeTx, false);
        assert_eq!(taken[1].at_ns, 9_000_000 + 3_000_000 + 120_000);
    }

    #[test]
    fn read_tolerates_a_cut_last_line_only() {
        let t = Trace::read("# idle_level 1\n1 1 0\n2 2 1\n3 3".as_bytes()).unwrap();
        assert_eq!(t.edges.len(), 2);
        assert_eq!(t.idle_level, Some(Level::High));
        assert!(Trace::read("1 1 0\nbad\n2 2 1\n".as_bytes()).is_err());
    }
}
