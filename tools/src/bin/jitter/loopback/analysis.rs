//! What the edges read back say, against the edges the loop wrote. Pure
//! functions of the two lists, so they are tested on made-up edges.
//!
//! - [`match_edges`]: each read edge paired with the written edge it is
//!   the line's copy of, in order, or counted as lost, missed, unexpected.
//! - [`TimeMap`]: a read edge's time to its written edge's scheduled time.
//! - [`compare_frames`]: the frames a decoder hands on from the read edges
//!   against those it hands on from the schedule (what the loop meant).
//! - [`analyse`]: all of it for one run: edge error as the line carries it
//!   and as ppmd measured it, each modelled receiver, ppm's capture
//!   decoder, and whether the schedule was the sweep.

use super::sweep::Sweep;
use hdrhistogram::Histogram;
use ppm_shared::capture::{Capture, CaptureCounts, CaptureSettings, EdgeEvent};
use ppm_shared::decode::DecoderLimits;
use ppm_shared::frame::Level;
use ppm_shared::receiver::{self, Receiver, TIMED_EDGE};
use ppm_shared::trace::TraceEdge;

/// How much earlier than its scheduled time a read edge may be and still
/// be that edge's copy: none should be (the loop writes an edge at its
/// time or later, and both times are CLOCK_MONOTONIC), so an early one is
/// a finding; 50 us is far less than the 300 us pulse, the shortest time
/// between two edges, so an early edge is never taken for the next one.
pub const EARLY_NS: u64 = 50_000;

/// A value read within this of the value sent is exact: the receivers'
/// resolution (a 1 MHz capture clock; EdgeTX's 2 MHz capture halved to
/// whole microseconds, truncated).
pub const EXACT_NS: u64 = 1_000;

/// The receivers whose reading is reported: a transmitter's trainer input
/// and two flight controllers' PPM inputs.
pub const RECEIVERS: [Receiver; 3] = [Receiver::EdgeTx, Receiver::Betaflight, Receiver::ArduPilot];

/// The read edges paired with the written ones.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Matching {
    /// (read index, written index) of every pair, in order.
    pub pairs: Vec<(usize, usize)>,
    /// Edges the kernel lost: the gaps in the read edges' sequence numbers
    /// (its event buffer overflowed).
    pub lost: u64,
    /// Written edges with no read copy, other than the lost ones.
    pub missed: u64,
    /// Read edges that are no written edge's copy (noise, a glitch).
    pub unexpected: u64,
    /// Read edges before the first written one (the lines' set-up, not
    /// the loop's).
    pub before: u64,
}

/// Pairs each read edge with the written edge it is the line's copy of.
///
/// Both lists are in time order and the loop writes in order, so the read
/// edges are the written ones in the same order, less what was lost and
/// plus what was not written: read edge `r` is the copy of the first
/// written edge not yet paired that goes to `r`'s level, provided that one
/// was due by `r`'s time (with [`EARLY_NS`] to spare); the written edges
/// passed over are missed. A read edge with no such written edge is
/// unexpected (or, before the first written edge, the set-up's). A gap of
/// `g` in the kernel's sequence numbers passes over (as lost) the next `g`
/// written edges due by then.
pub fn match_edges(written: &[TraceEdge], read: &[EdgeEvent]) -> Matching {
    let mut m = Matching::default();
    let mut j = 0;
    let mut prev_seq: Option<u64> = None;
    for (i, r) in read.iter().enumerate() {
        let due = |k: usize| written[k].scheduled_ns <= r.at_ns.saturating_add(EARLY_NS);
        if let Some(p) = prev_seq {
            let mut gap = r.seq.saturating_sub(p.saturating_add(1));
            m.lost += gap;
            while gap > 0 && j < written.len() && due(j) {
                j += 1;
                gap -= 1;
            }
        }
        prev_seq = Some(r.seq);
        match (j..written.len()).find(|&k| written[k].level == r.level) {
            Some(k) if due(k) => {
                m.missed += (k - j) as u64;
                m.pairs.push((i, k));
                j = k + 1;
            }
            _ if m.pairs.is_empty() && (written.is_empty() || !due(0)) => m.before += 1,
            _ => m.unexpected += 1,
        }
    }
    m.missed += (written.len() - j) as u64;
    m
}

/// Each paired read edge's time, to its written edge's scheduled time.
#[derive(Debug, Clone, Default)]
pub struct TimeMap {
    read_ns: Vec<u64>,
    scheduled_ns: Vec<u64>,
}

impl TimeMap {
    /// The map of `m`'s pairs.
    pub fn new(m: &Matching, written: &[TraceEdge], read: &[EdgeEvent]) -> TimeMap {
        let mut pairs: Vec<(u64, u64)> = m
            .pairs
            .iter()
            .map(|&(r, w)| (read[r].at_ns, written[w].scheduled_ns))
            .collect();
        pairs.sort_unstable();
        TimeMap {
            read_ns: pairs.iter().map(|p| p.0).collect(),
            scheduled_ns: pairs.iter().map(|p| p.1).collect(),
        }
    }

    /// The scheduled time of the written edge read at `read_ns`, if that
    /// read edge was paired.
    pub fn scheduled(&self, read_ns: u64) -> Option<u64> {
        let i = self.read_ns.binary_search(&read_ns).ok()?;
        Some(self.scheduled_ns[i])
    }
}

/// A frame as a decoder hands it on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// The timed edge that began its first channel, ns.
    pub start_ns: u64,
    /// Its channels, ns.
    pub values_ns: Vec<u64>,
}

/// One decoder's frames read against its frames sent.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameTally {
    /// Frames it hands on from the written edges at their scheduled times:
    /// what the loop meant it to read.
    pub sent: usize,
    /// Frames it hands on from the read edges.
    pub read: usize,
    /// Read frames that are a sent frame: begun by the read copy of that
    /// frame's first edge, with as many channels.
    pub matched: usize,
    /// Matched frames with every value within [`EXACT_NS`] of the sent one.
    pub exact: usize,
    /// The largest difference between a value read and the value sent
    /// (matched frames), ns.
    pub max_error_ns: u64,
}

impl FrameTally {
    /// Read frames that are no sent frame (another start or channel count).
    pub fn not_sent(&self) -> usize {
        self.read - self.matched
    }

    /// Every frame sent was read, as sent, each value within `max_ns`.
    pub fn all_read_within(&self, max_ns: u64) -> bool {
        self.sent > 0
            && self.read == self.sent
            && self.matched == self.read
            && self.max_error_ns <= max_ns
    }
}

/// Compares the frames a decoder hands on from the read edges (`read`)
/// with those it hands on from the schedule (`sent`, sorted by start):
/// a read frame is a sent one when the read edge that began it is the copy
/// ([`TimeMap`]) of the edge that began the sent one and both have as many
/// channels; its values are then compared one by one.
pub fn compare_frames(sent: &[Frame], read: &[Frame], map: &TimeMap) -> FrameTally {
    let mut t = FrameTally {
        sent: sent.len(),
        read: read.len(),
        ..FrameTally::default()
    };
    for f in read {
        let Some(at) = map.scheduled(f.start_ns) else {
            continue;
        };
        let Ok(i) = sent.binary_search_by_key(&at, |s| s.start_ns) else {
            continue;
        };
        let s = &sent[i];
        if s.values_ns.len() != f.values_ns.len() {
            continue;
        }
        t.matched += 1;
        let worst = f
            .values_ns
            .iter()
            .zip(&s.values_ns)
            .map(|(r, s)| r.abs_diff(*s))
            .max()
            .unwrap_or(0);
        t.exact += (worst <= EXACT_NS) as usize;
        t.max_error_ns = t.max_error_ns.max(worst);
    }
    t
}

/// Whether the frames the loop wrote were the sweep's.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SweepCheck {
    /// Whole frames in the schedule (every channel, closed by a sync).
    pub whole: usize,
    /// Of those, frames that are a step of the sweep, every value exact.
    pub of_sweep: usize,
    /// Frames cut short (fewer channels, closed by a sync): the late-edge
    /// guard aborted them.
    pub cut: usize,
}

/// What one run's edges say.
#[derive(Debug, Clone)]
pub struct Analysis {
    /// Edges the loop wrote.
    pub written: usize,
    /// Edges read back.
    pub read: usize,
    /// The pairing.
    pub matching: Matching,
    /// Read time minus scheduled time of every paired edge, ns (an early
    /// edge counted at 0: see `early`).
    pub line_error: Histogram<u64>,
    /// Paired edges read before their scheduled time.
    pub early: u64,
    /// The smallest read-minus-scheduled difference, ns.
    pub min_error_ns: i64,
    /// The loop's own time just before each write minus its scheduled
    /// time: what ppmd measures, ns.
    pub own_error: Histogram<u64>,
    /// Each receiver of [`RECEIVERS`]: its tally, or the rule by which it
    /// does not take this many channels.
    pub receivers: Vec<(Receiver, Result<FrameTally, &'static str>)>,
    /// ppm's capture decoder (the read-back's): frames.
    pub capture: FrameTally,
    /// ppm's capture decoder: what it refused of the read edges.
    pub capture_counts: CaptureCounts,
    /// The schedule against the sweep.
    pub sweep: SweepCheck,
}

fn histogram() -> Histogram<u64> {
    ppmd::meter::histogram()
}

/// The frames `receiver` hands on whole from `edges`.
fn receiver_frames(receiver: Receiver, edges: impl Iterator<Item = (u64, Level)>) -> Vec<Frame> {
    receiver::decode_as(receiver, edges, TIMED_EDGE)
        .0
        .into_iter()
        .filter(|f| f.complete)
        .map(|f| Frame {
            start_ns: f.start_ns,
            values_ns: f.channels_ns,
        })
        .collect()
}

/// The frames ppm's capture decoder hands on from `edges`, and its counts.
fn capture_frames(
    settings: CaptureSettings,
    edges: impl Iterator<Item = EdgeEvent>,
) -> (Vec<Frame>, CaptureCounts) {
    let mut c = Capture::new(settings);
    let frames = edges
        .filter_map(|e| c.push(e))
        .map(|f| Frame {
            start_ns: f.start_ns,
            values_ns: f.values().iter().map(|&v| u64::from(v)).collect(),
        })
        .collect();
    (frames, c.counts())
}

/// Analyses one run: `written` as the loop wrote them (recorded by the
/// `Recorder`), `read` as the input gave them, the line idling at `idle`.
pub fn analyse(written: &[TraceEdge], read: &[EdgeEvent], sweep: &Sweep, idle: Level) -> Analysis {
    let matching = match_edges(written, read);
    let map = TimeMap::new(&matching, written, read);
    let mut line_error = histogram();
    let (mut early, mut min_error_ns) = (0, i64::MAX);
    for &(r, w) in &matching.pairs {
        let e = read[r].at_ns as i64 - written[w].scheduled_ns as i64;
        min_error_ns = min_error_ns.min(e);
        early += (e < 0) as u64;
        line_error.saturating_record(e.max(0) as u64);
    }
    let mut own_error = histogram();
    for w in written {
        own_error.saturating_record(w.actual_ns.saturating_sub(w.scheduled_ns));
    }
    let scheduled = || written.iter().map(|e| (e.scheduled_ns, e.level));
    let as_read = || read.iter().map(|e| (e.at_ns, e.level));
    let n = sweep.channels();
    let receivers = RECEIVERS
        .iter()
        .map(|&r| {
            let rules = r.rules();
            let tally = if (rules.min_channels.0..=rules.max_channels.0).contains(&n) {
                let sent = receiver_frames(r, scheduled());
                Ok(compare_frames(&sent, &receiver_frames(r, as_read()), &map))
            } else if n < rules.min_channels.0 {
                Err(rules.min_channels.1)
            } else {
                Err(rules.max_channels.1)
            };
            (r, tally)
        })
        .collect();
    let settings = CaptureSettings {
        idle: Some(idle),
        channels: Some(n as u8),
    };
    let (sent, _) = capture_frames(
        settings,
        written.iter().enumerate().map(|(i, e)| EdgeEvent {
            at_ns: e.scheduled_ns,
            level: e.level,
            seq: i as u64 + 1,
        }),
    );
    let (got, capture_counts) = capture_frames(settings, read.iter().copied());
    let mut check = SweepCheck::default();
    for f in ppm_shared::decode::decode(scheduled(), idle.opposite(), DecoderLimits::default()) {
        if !f.complete {
            continue;
        }
        if f.channels_ns.len() == n {
            check.whole += 1;
            check.of_sweep += sweep.step_of(&f.channels_ns).is_some() as usize;
        } else {
            check.cut += 1;
        }
    }
    Analysis {
        written: written.len(),
        read: read.len(),
        line_error,
        early,
        min_error_ns: if matching.pairs.is_empty() {
            0
        } else {
            min_error_ns
        },
        own_error,
        receivers,
        capture: compare_frames(&sent, &got, &map),
        capture_counts,
        sweep: check,
        matching,
    }
}
