//! What a frame is on the wire: the protocol seam of the loop. The loop
//! (decide, emit, record, pace) never reaches into a frame's encoding; it
//! asks a [`WireFrame`] when its next write is due, whether that write is
//! one receivers time and too late to make (the late-edge guard), what a
//! whole-frame line takes, where the frame's last pulse is, and which
//! values the frame carried for the frame log.
//!
//! - PPM ([`PpmFrame`]): a frame is an edge schedule, written edge by edge
//!   (GPIO) or handed whole to a line timed by its own clock (SPI), after a
//!   lead-in pulse following silence; a late rising edge would change a
//!   channel's value, so the guard aborts the frame there.
//! - Bytes ([`BytesFrame`], SBUS): the bytes the model's [`WireModel`]
//!   encodes, handed whole to a line at the frame's start (a UART, or SPI),
//!   which sends them back to back: no edges of the loop's, no lead-in, no
//!   late-edge guard, since a late write moves the frame but not the values
//!   it carries. Its "last pulse" is its end on the wire, where the idle
//!   line before the next frame is measured from.
//!
//! Which of the two a frame is, is the model's [`FrameKind`]; the protocol
//! itself is asked only through the [`WireModel`].

use super::pace::alias_later;
use crate::line::{FrameEdge, WholeFrame};
use ppm_shared::frame::{
    Channels, EdgeSchedule, FrameKind, FrameModel, Level, MAX_CHANNELS, MAX_EDGES,
};
use ppm_shared::wire::{WireModel, MAX_FRAME_BYTES};

/// A frame as it goes on the wire, in the protocol of its output.
#[derive(Clone, Copy)]
// Kept by value, not boxed: the loop allocates nothing.
#[allow(clippy::large_enum_variant)]
pub(super) enum WireFrame {
    /// PPM: edges at their times.
    Ppm(PpmFrame),
    /// Bytes (SBUS): one frame of bytes.
    Bytes(BytesFrame),
}

/// Room on the stack for a frame handed whole to a line, so the loop never
/// allocates one.
pub(super) struct WholeBuf {
    edges: [FrameEdge; MAX_EDGES + 2],
    bytes: [u8; MAX_FRAME_BYTES],
}

impl WholeBuf {
    /// An empty buffer.
    pub fn new() -> WholeBuf {
        WholeBuf {
            edges: [FrameEdge {
                at_ns: 0,
                level: Level::Low,
            }; MAX_EDGES + 2],
            bytes: [0; MAX_FRAME_BYTES],
        }
    }
}

impl WireFrame {
    /// `channels` encoded by `model` in its protocol, not placed yet; a
    /// frame of bytes with its failsafe flag set when `failsafe_flag` (and
    /// the protocol has one).
    pub fn encode(model: &FrameModel, channels: &Channels, failsafe_flag: bool) -> WireFrame {
        let wire = model.wire();
        match wire.kind() {
            FrameKind::Pulses => WireFrame::Ppm(PpmFrame::new(model.encode(channels))),
            FrameKind::Bytes => {
                let mut bytes = [0; MAX_FRAME_BYTES];
                let len = model.encode_bytes(channels, failsafe_flag, &mut bytes);
                WireFrame::Bytes(BytesFrame {
                    bytes,
                    len,
                    wire_ns: wire.frame_wire_ns(),
                    late_margin_ns: wire.late_margin_ns(),
                    wire: *wire,
                    start: 0,
                })
            }
        }
    }

    /// Where the frame's last pulse starts, from the frame's start (bytes:
    /// where its last byte ends on the wire).
    pub fn last_pulse(&self) -> u64 {
        match self {
            WireFrame::Ppm(f) => f.last_pulse(),
            WireFrame::Bytes(f) => f.wire_ns,
        }
    }

    /// After its whole-frame write, due at `due`, returned at `written`:
    /// where it ends on the wire at the latest, when the next frame's idle
    /// line must be measured from there rather than from its planned end.
    /// Bytes: the frame left no later than the write's return; when that is
    /// later than the margin the idle lines keep for a late frame
    /// ([`WireModel::late_margin_ns`]), the next frame starts its idle line
    /// after this end. `None` otherwise, and for PPM, whose sync a
    /// whole-frame line times itself.
    pub fn ends_by(&self, due: u64, written: u64) -> Option<u64> {
        match self {
            WireFrame::Ppm(_) => None,
            WireFrame::Bytes(f) => {
                (written.saturating_sub(due) > f.late_margin_ns).then_some(written + f.wire_ns)
            }
        }
    }

    /// Places the frame at `start`, after a lead-in pulse of `lead_in_ns`
    /// (0: none); the line's previous pulse started at `before_pulse`.
    pub fn place(&mut self, start: u64, lead_in_ns: u64, before_pulse: Option<u64>) {
        match self {
            WireFrame::Ppm(f) => {
                f.start = start;
                f.lead_in_ns = lead_in_ns;
                f.before_pulse = before_pulse;
            }
            WireFrame::Bytes(f) => f.start = start,
        }
    }

    /// When its next write is due.
    pub fn due(&self) -> u64 {
        match self {
            WireFrame::Ppm(f) => f.edge().0,
            WireFrame::Bytes(f) => f.start,
        }
    }

    /// The level its next write sets, on a line written edge by edge (a
    /// frame of bytes is never written so: its level is the start bit's).
    pub fn level(&self) -> Level {
        match self {
            WireFrame::Ppm(f) => f.edge().1,
            WireFrame::Bytes(_) => Level::Low,
        }
    }

    /// Whether its next write, due at `due` and found at `now`, is one
    /// receivers time and later than the model's guard: it must not be
    /// made, and the frame is aborted there.
    pub fn guarded(&self, model: &FrameModel, due: u64, now: u64) -> bool {
        match self {
            WireFrame::Ppm(f) => {
                f.tail.is_none()
                    && model.timed(f.edge().1)
                    && now - due > model.late_edge_guard_ns()
            }
            WireFrame::Bytes(_) => false,
        }
    }

    /// Whether a whole-frame line started at `now` would send the frame too
    /// late to be read as its transmitter meant.
    pub fn sync_overrun(&self, model: &FrameModel, now: u64) -> bool {
        match self {
            WireFrame::Ppm(f) => f.sync_overrun(model, now),
            WireFrame::Bytes(_) => false,
        }
    }

    /// The rest of the frame, from its next write due at `due`, as a
    /// whole-frame line takes it (in `buf`), and how many writes of it that
    /// is.
    pub fn whole<'b>(&self, due: u64, buf: &'b mut WholeBuf) -> (WholeFrame<'b>, usize) {
        match self {
            WireFrame::Ppm(f) => f.whole(due, &mut buf.edges),
            WireFrame::Bytes(f) => {
                buf.bytes = f.bytes;
                (
                    WholeFrame::Bytes {
                        bytes: &buf.bytes[..f.len],
                        due_ns: due,
                    },
                    1,
                )
            }
        }
    }

    /// After its rest was handed whole to a line: everything it carries
    /// went out exactly as scheduled.
    pub fn sent_whole(&mut self, model: &FrameModel) {
        match self {
            WireFrame::Ppm(f) => f.timed = model.channels() + 1,
            WireFrame::Bytes(_) => {}
        }
    }

    /// When the last write of its rest that receivers time is due, if any:
    /// when it reaches the line, handed whole to a line timed by its own
    /// clock.
    pub fn last_timed(&self, model: &FrameModel) -> Option<u64> {
        match self {
            WireFrame::Ppm(f) => f.last_timed(model),
            WireFrame::Bytes(_) => None,
        }
    }

    /// Whether its next write is one receivers time.
    pub fn timed(&self, model: &FrameModel) -> bool {
        match self {
            WireFrame::Ppm(f) => model.timed(f.edge().1),
            WireFrame::Bytes(_) => false,
        }
    }

    /// A timed write of the frame's own reached the line `late_ns` late:
    /// kept for the values the frame carried. False: the write ends an
    /// aborted frame, it is none of its own.
    pub fn timed_written(&mut self, late_ns: u64) -> bool {
        match self {
            WireFrame::Ppm(f) => f.timed_written(late_ns),
            WireFrame::Bytes(_) => false,
        }
    }

    /// After its due write (`whole`: the rest of the frame at once): moves
    /// on to the next one. True when the frame has ended.
    pub fn advance(&mut self, whole: bool) -> bool {
        match self {
            WireFrame::Ppm(f) => f.advance(whole),
            WireFrame::Bytes(_) => true,
        }
    }

    /// Aborts the frame at its next write, found late at `at` (the last
    /// timed write reached the line at `timed_ns`). True when it ends here;
    /// false when one more write (at [`WireFrame::due`]) must put the line
    /// back to its idle level.
    pub fn abort(&mut self, model: &FrameModel, at: u64, timed_ns: Option<u64>) -> bool {
        match self {
            WireFrame::Ppm(f) => f.abort(model, at, timed_ns),
            WireFrame::Bytes(_) => true,
        }
    }

    /// Where the pulse starts whose timed write reached the line at
    /// `timed_ns`: where the receivers' sync after it is measured from.
    pub fn pulse_of(&self, model: &FrameModel, timed_ns: Option<u64>) -> Option<u64> {
        match self {
            WireFrame::Ppm(_) => timed_ns.map(|t| t - model.timed_offset_ns()),
            WireFrame::Bytes(_) => None,
        }
    }

    /// Of an aborted frame: the timed write it was aborted at, from 1.
    pub fn aborted_at(&self) -> usize {
        match self {
            WireFrame::Ppm(f) => f.timed.max(1),
            WireFrame::Bytes(_) => 1,
        }
    }

    /// The values (ns) the line carried whole, given `sent`, into `values`
    /// (channel by channel); how many there are.
    pub fn carried(
        &self,
        model: &FrameModel,
        sent: &Channels,
        aborted: bool,
        values: &mut [u32; MAX_CHANNELS],
    ) -> usize {
        match self {
            WireFrame::Ppm(f) => f.carried(model, sent, aborted, values),
            WireFrame::Bytes(f) => {
                // What the receiver the values are encoded for reads of
                // the bytes sent.
                let mut read = [0u64; MAX_CHANNELS];
                let n = f.wire.reads(&f.bytes[..f.len], &mut read);
                for (v, r) in values.iter_mut().zip(&read[..n]) {
                    *v = *r as u32;
                }
                n
            }
        }
    }
}

/// A frame of bytes on the wire: its bytes, what its wire says of it, and
/// where it starts.
#[derive(Clone, Copy)]
pub(super) struct BytesFrame {
    bytes: [u8; MAX_FRAME_BYTES],
    len: usize,
    /// How long it takes on the wire.
    wire_ns: u64,
    /// See [`WireModel::late_margin_ns`].
    late_margin_ns: u64,
    wire: WireModel,
    start: u64,
}

/// A PPM frame on the wire: its edge schedule and how far it is written.
#[derive(Clone, Copy)]
pub(super) struct PpmFrame {
    schedule: EdgeSchedule,
    /// Where the frame starts.
    start: u64,
    /// The next edge to write, counting the lead-in pulse's two first.
    next: usize,
    /// How long before `start` the lead-in pulse starts (0: none).
    lead_in_ns: u64,
    /// Where the line's previous pulse started when the frame was decided.
    before_pulse: Option<u64>,
    /// How late each of the frame's own timed edges written so far reached
    /// the line (the lead-in's apart), ns.
    timed_err: [u64; MAX_CHANNELS + 1],
    /// How many of them were written.
    timed: usize,
    /// Aborted inside a pulse (idle high): the one edge left, back to the
    /// idle level, and when.
    tail: Option<u64>,
}

impl PpmFrame {
    /// The frame `schedule`, not placed yet.
    fn new(schedule: EdgeSchedule) -> PpmFrame {
        PpmFrame {
            schedule,
            start: 0,
            next: 0,
            lead_in_ns: 0,
            before_pulse: None,
            timed_err: [0; MAX_CHANNELS + 1],
            timed: 0,
            tail: None,
        }
    }

    /// The last pulse's start: the one before the closing sync.
    fn last_pulse(&self) -> u64 {
        let edges = self.schedule.edges();
        edges[edges.len() - 2].at_ns
    }

    /// Edges before the frame's own: the lead-in pulse's two, or none.
    fn pre(&self) -> usize {
        if self.lead_in_ns > 0 {
            2
        } else {
            0
        }
    }

    /// Every edge to write, the lead-in pulse's included.
    fn len(&self) -> usize {
        self.pre() + self.schedule.edges().len()
    }

    /// The next edge: when and to which level.
    fn edge(&self) -> (u64, Level) {
        match self.tail {
            Some(t) => (
                t,
                self.schedule.edges()[self.schedule.edges().len() - 1].level,
            ),
            None => self.edge_at(self.next),
        }
    }

    /// Edge `k`: when and to which level. The lead-in pulse is the frame's
    /// first pulse, `lead_in_ns` earlier.
    fn edge_at(&self, k: usize) -> (u64, Level) {
        let e = self.schedule.edges();
        match k.checked_sub(self.pre()) {
            Some(i) => (self.start + e[i].at_ns, e[i].level),
            None => (self.start - self.lead_in_ns + e[k].at_ns, e[k].level),
        }
    }

    /// A whole-frame line (SPI) times a frame's edges itself, exactly; the
    /// loop only starts the transfer. Started at `now`, the frame must still
    /// end the sync before it inside every receiver's window (a frame with a
    /// lead-in pulse carries its own sync).
    fn sync_overrun(&self, model: &FrameModel, now: u64) -> bool {
        let (_, sync_max) = model.sync_window_ns();
        self.lead_in_ns == 0 && self.before_pulse.is_some_and(|b| now - b > sync_max)
    }

    /// The rest of the frame, from its next edge due at `due`, in `buf`.
    fn whole<'b>(
        &self,
        due: u64,
        buf: &'b mut [FrameEdge; MAX_EDGES + 2],
    ) -> (WholeFrame<'b>, usize) {
        let n = self.len() - self.next;
        for (k, e) in buf.iter_mut().enumerate().take(n) {
            let (at, level) = self.edge_at(self.next + k);
            *e = FrameEdge {
                at_ns: at - due,
                level,
            };
        }
        let frame = WholeFrame::Ppm {
            edges: &buf[..n],
            due_ns: due,
        };
        (frame, n)
    }

    /// The last timed edge of the rest: a whole-frame line's bits are
    /// exact, its edges as scheduled.
    fn last_timed(&self, model: &FrameModel) -> Option<u64> {
        (self.next..self.len())
            .rev()
            .map(|k| self.edge_at(k))
            .find(|e| model.timed(e.1))
            .map(|e| e.0)
    }

    fn timed_written(&mut self, late_ns: u64) -> bool {
        if self.tail.is_some() {
            return false;
        }
        if self.next >= self.pre() {
            self.timed_err[self.timed] = late_ns;
            self.timed += 1;
        }
        true
    }

    fn advance(&mut self, whole: bool) -> bool {
        if self.tail.is_some() {
            // The line is back at its idle level: the aborted frame ends.
            return true;
        }
        self.next = if whole { self.len() } else { self.next + 1 };
        self.next == self.len()
    }

    /// With idle low the line is idle (the late edge starts a pulse) and
    /// the frame ends here. With idle high the late edge ends a pulse: the
    /// line goes back to idle with one edge a shortest sync after the last
    /// timed edge (or at once, when that has passed, but out of the gaps a
    /// trainer input reads as a channel when its timer wraps), which
    /// receivers read as a sync, never as a value.
    fn abort(&mut self, model: &FrameModel, at: u64, timed_ns: Option<u64>) -> bool {
        let in_pulse = self.edge().1 == model.idle_level();
        if !in_pulse {
            return true;
        }
        let sync_min = model.sync_window_ns().0;
        let tail = timed_ns.map_or(at, |t| at.max(t + sync_min));
        self.tail = Some(tail + alias_later(timed_ns, tail));
        false
    }

    /// The channels the line carried whole (between consecutive timed
    /// edges), each moved by the lateness of its two edges.
    fn carried(
        &self,
        model: &FrameModel,
        sent: &Channels,
        aborted: bool,
        values: &mut [u32; MAX_CHANNELS],
    ) -> usize {
        let carried = if aborted {
            self.timed.saturating_sub(1)
        } else {
            model.channels()
        };
        for (i, v) in values.iter_mut().enumerate().take(carried) {
            let given = sent.as_ns().get(i).copied().unwrap_or(model.default_ns(i));
            // The value sent, moved by the difference of its two edges'
            // lateness, to the microsecond receivers resolve.
            let moved = self.timed_err[i + 1] as i64 - self.timed_err[i] as i64;
            *v = (model.clamp(i, given).0 as i64 + round_us(moved)).max(0) as u32;
        }
        carried
    }
}

/// Rounds a signed ns difference to whole microseconds, in ns.
fn round_us(ns: i64) -> i64 {
    (ns + if ns < 0 { -500 } else { 500 }) / 1_000 * 1_000
}
