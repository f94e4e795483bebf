//! The emission of a due step: a [`Frame`] in progress, and
//! [`emit_due`], which waits for the next edge and writes every output's
//! edge due then, the way each output's frames leave ([`LineRef`]): edge by
//! edge on a line of its own or of a bank, or whole at the frame's start.
//! What a write is, and which rules it answers to, is the frame's
//! [`WireFrame`]'s to say.

use super::module::ModuleTiming;
use super::record::{add, Recording};
use super::wire::{WholeBuf, WireFrame};
use super::{LineRef, Output, Progress, MAX_OUTPUTS};
use crate::clock::{Clock, EdgeTimer, Readable, Wake};
use crate::framelog::CommandInfo;
use crate::line::{Bank, FrameLine, Line, WholeFrame};
use ppm_shared::crsf::module::MODEL_ID_FRAME_LEN;
use ppm_shared::frame::{Channels, FrameModel, Level};
use ppm_shared::line::LineState;
use ppm_shared::trace::TraceEdge;
use ppm_shared::wire::{WireModel, MAX_FRAME_BYTES};
use std::os::fd::RawFd;

/// A frame being emitted: its form on the wire and what the loop records
/// of it.
#[derive(Clone, Copy)]
pub(super) struct Frame {
    /// What it is on the wire, and how far it is written.
    pub wire: WireFrame,
    pub start: u64,
    pub start_real_ns: u64,
    pub channels: Channels,
    pub state: LineState,
    pub command: Option<CommandInfo>,
    pub spun: u64,
    /// A timed write reached the line later than the guard.
    pub glitched: bool,
    /// A timed write was found later than the guard before it was made:
    /// it and the writes after it are not made.
    pub aborted: bool,
    /// How late the latest of its timed writes reached the line, ns.
    pub late_ns: u64,
    /// Aborted: how late its write was found, ns.
    pub found_late_ns: u64,
}

impl Frame {
    /// A frame of `channels`, `wire` on the wire, placed at `start`
    /// (`start_real_ns` on the wall clock); nothing of it written yet.
    pub fn new(
        wire: WireFrame,
        channels: Channels,
        (start, start_real_ns): (u64, u64),
        (state, command): (LineState, Option<CommandInfo>),
    ) -> Frame {
        Frame {
            wire,
            start,
            start_real_ns,
            channels,
            state,
            command,
            spun: 0,
            glitched: false,
            aborted: false,
            late_ns: 0,
            found_late_ns: 0,
        }
    }

    /// When its next write is due.
    pub fn due(&self) -> u64 {
        self.wire.due()
    }
}

/// What became of an output's due edge.
enum Wrote {
    /// Found too late: the frame is aborted there, the edge not written.
    Aborted,
    /// The edge, written; the reading after the write.
    Edge(u64),
    /// The whole rest of the frame, written; the reading after the write.
    Frame(u64),
}

/// Waits for `due` and writes every output's edge due then: lines one by
/// one, each bank's lines in one call. Each edge's error is measured just
/// before its own write. Returns without writing when one of `fds` became
/// readable during the sleep (the loop then decides for the output woken
/// first).
///
/// Right before an edge receivers time is written, its lateness is checked:
/// found later than the model's guard, the edge is not written and its
/// frame is aborted (see [`abort_frame`]). Other edges are written however
/// late. After each write, the time it took decides how late the edge
/// reached the line (see [`wrote`]).
pub(super) fn emit_due<C: Clock + ?Sized>(
    clk: &C,
    due: u64,
    outputs: &mut [Output],
    prog: &mut [Progress],
    banks: &mut [&mut dyn Bank],
    timer: &mut EdgeTimer,
    fds: &[RawFd],
) -> Option<Readable> {
    let w = match timer.wait_or_readable(clk, due, fds) {
        Wake::Due(w) => w,
        Wake::Readable(r) => return Some(r),
    };
    let mut round = Round::new(due, prog, w.now_ns);
    write_lines(clk, &mut round, outputs, prog);
    write_banks(clk, &mut round, outputs, prog, banks);
    // One wait served them all: its figures go to the first output.
    let first = round.due_mask.trailing_zeros() as usize;
    if let Some(late) = w.woke_late_ns {
        outputs[first].rec.meter.wake(late);
    }
    if let Some(f) = prog[first].frame.as_mut() {
        f.spun += w.spun_ns;
    }
    advance(&round, outputs, prog, timer.margin_ns());
    None
}

/// One round of writes, of the edges due at one time: which outputs are
/// in it and what became of their edges.
struct Round {
    due: u64,
    /// The outputs with an edge due now (bit i: output i).
    due_mask: u32,
    /// Outputs whose line took the whole frame.
    whole: u32,
    /// Outputs whose frame is aborted at this edge, and when that was
    /// found.
    aborted: u32,
    found_at: [u64; MAX_OUTPUTS],
    /// The latest reading of the time: the one before the next write.
    before: u64,
}

impl Round {
    /// The round of `prog`'s edges due at `due`, the time read at `now`.
    fn new(due: u64, prog: &[Progress], now: u64) -> Round {
        let mut due_mask = 0u32;
        for (i, p) in prog.iter().enumerate() {
            if p.frame.is_some_and(|f| f.due() == due) {
                due_mask |= 1 << i;
            }
        }
        Round {
            due,
            due_mask,
            whole: 0,
            aborted: 0,
            found_at: [0; MAX_OUTPUTS],
            before: now,
        }
    }

    fn is_due(&self, i: usize) -> bool {
        self.due_mask & (1 << i) != 0
    }

    /// Output `i`'s edge was found too late, now.
    fn abort(&mut self, i: usize) {
        self.aborted |= 1 << i;
        self.found_at[i] = self.before;
    }
}

/// Writes the round's edges on lines of their own, one by one, and hands
/// whole-frame lines their frames.
fn write_lines<C: Clock + ?Sized>(
    clk: &C,
    round: &mut Round,
    outputs: &mut [Output],
    prog: &mut [Progress],
) {
    let (due, before) = (round.due, &mut round.before);
    for (i, (out, p)) in outputs.iter_mut().zip(prog.iter_mut()).enumerate() {
        let Some(f) = p.frame.filter(|_| round.due_mask & (1 << i) != 0) else {
            continue;
        };
        let model = out.model;
        let sync = out.sync;
        let done = match &mut out.line {
            LineRef::Whole(line) => send_whole(
                clk,
                &mut **line,
                (model, sync),
                &mut out.rec,
                p,
                &f,
                due,
                *before,
            ),
            LineRef::Edges(line) => {
                write_edge(clk, &mut **line, model, &mut out.rec, p, &f, due, *before)
            }
            // Checked and written at the bank's write.
            LineRef::Banked { .. } => continue,
        };
        match done {
            Wrote::Aborted => {
                round.aborted |= 1 << i;
                round.found_at[i] = *before;
            }
            Wrote::Edge(written) => *before = written,
            Wrote::Frame(written) => {
                round.whole |= 1 << i;
                *before = written;
            }
        }
    }
}

/// Writes the round's edges on each bank's lines, in one call per bank.
fn write_banks<C: Clock + ?Sized>(
    clk: &C,
    round: &mut Round,
    outputs: &mut [Output],
    prog: &mut [Progress],
    banks: &mut [&mut dyn Bank],
) {
    let due = round.due;
    for (b, bank) in banks.iter_mut().enumerate() {
        let (mut mask, mut levels) = (0u64, 0u64);
        for (i, (out, p)) in outputs.iter().zip(prog.iter()).enumerate() {
            let LineRef::Banked { bank, bit } = out.line else {
                continue;
            };
            let Some(f) = p.frame.filter(|_| bank == b && round.is_due(i)) else {
                continue;
            };
            if f.wire.guarded(out.model, due, round.before) {
                round.abort(i);
                continue;
            }
            mask |= 1 << bit;
            levels |= (f.wire.level() == Level::High) as u64 * (1 << bit);
        }
        if mask == 0 {
            continue;
        }
        let before = round.before;
        let failed = bank.write(due, mask, levels).is_err();
        let written = clk.now_ns();
        for (out, p) in outputs.iter_mut().zip(prog.iter_mut()) {
            let LineRef::Banked { bank, bit } = out.line else {
                continue;
            };
            if bank != b || mask & (1 << bit) == 0 {
                continue;
            }
            if failed {
                add(&out.rec.stats.write_errors, 1);
            }
            out.rec.edge(before - due, written - before);
            wrote(out.model, p, due, before, written - before);
        }
        round.before = written;
    }
}

/// After the round's writes: each of its frames moves on to its next edge,
/// or ends (its last edge written, or aborted).
fn advance(round: &Round, outputs: &mut [Output], prog: &mut [Progress], margin_ns: u64) {
    for (i, (out, p)) in outputs.iter_mut().zip(prog.iter_mut()).enumerate() {
        if !round.is_due(i) {
            continue;
        }
        if round.aborted & (1 << i) != 0 {
            abort_frame(out.model, &mut out.rec, p, round.found_at[i], margin_ns);
            continue;
        }
        let Some(f) = p.frame.as_mut() else {
            continue;
        };
        if f.wire.advance(round.whole & (1 << i) != 0) {
            out.rec.finish_frame(out.model, p, margin_ns);
        }
    }
}

/// Hands the rest of frame `f` (from its first edge, due at `due`, found
/// at `before`) to a whole-frame `line` in one call, timed by the line's
/// own clock from here.
#[allow(clippy::too_many_arguments)]
fn send_whole<C: Clock + ?Sized>(
    clk: &C,
    line: &mut dyn FrameLine,
    (model, module): (&FrameModel, Option<&ModuleTiming>),
    rec: &mut Recording,
    p: &mut Progress,
    f: &Frame,
    due: u64,
    before: u64,
) -> Wrote {
    if f.wire.sync_overrun(model, before) {
        return Wrote::Aborted;
    }
    let mut buf = WholeBuf::new();
    let (frame, n) = f.wire.whole(due, &mut buf);
    // A transmitter module that came (back) gets its model ID command
    // right before this frame, in the same write.
    let mut joined = [0u8; MODEL_ID_FRAME_LEN + MAX_FRAME_BYTES];
    let frame = match (module, frame) {
        (Some(m), WholeFrame::Bytes { bytes, due_ns }) => match model.wire() {
            WireModel::Crsf(c) if m.take_model_id() => match c.model_id_frame() {
                Some(id) => {
                    let len = id.len() + bytes.len();
                    joined[..id.len()].copy_from_slice(&id);
                    joined[id.len()..len].copy_from_slice(bytes);
                    WholeFrame::Bytes {
                        bytes: &joined[..len],
                        due_ns,
                    }
                }
                None => WholeFrame::Bytes { bytes, due_ns },
            },
            _ => WholeFrame::Bytes { bytes, due_ns },
        },
        (_, frame) => frame,
    };
    if line.write_frame(frame).is_err() {
        add(&rec.stats.write_errors, 1);
    }
    let written = clk.now_ns();
    // The frame's start error and how long the transfer took: what can be
    // known of a line timed by its own clock.
    rec.edge(before - due, written - before);
    add(&rec.stats.edges, n as u64 - 1);
    // What it carries is exact: as scheduled.
    if let Some(pf) = p.frame.as_mut() {
        pf.wire.sent_whole(model);
    }
    p.timed_ns = f.wire.last_timed(model);
    // Where the frame ends at the latest (SBUS), for the idle line before
    // the next one.
    if let Some(end) = f.wire.ends_by(due, written) {
        p.prev_pulse = p.prev_pulse.max(Some(end));
        if let Some(fl) = p.pace.follow() {
            fl.last_pulse = fl.last_pulse.max(Some(end));
        }
    }
    Wrote::Frame(written)
}

/// Writes frame `f`'s next edge, due at `due` and found at `before`, to a
/// `line` of its own, unless it is one receivers time found too late.
#[allow(clippy::too_many_arguments)]
fn write_edge<C: Clock + ?Sized>(
    clk: &C,
    line: &mut dyn Line,
    model: &FrameModel,
    rec: &mut Recording,
    p: &mut Progress,
    f: &Frame,
    due: u64,
    before: u64,
) -> Wrote {
    if f.wire.guarded(model, due, before) {
        return Wrote::Aborted;
    }
    let edge = TraceEdge {
        scheduled_ns: due,
        actual_ns: before,
        level: f.wire.level(),
    };
    if line.write(&edge).is_err() {
        add(&rec.stats.write_errors, 1);
    }
    let written = clk.now_ns();
    let took = if line.stamped() { 0 } else { written - before };
    rec.edge(before - due, written - before);
    wrote(model, p, due, before, took);
    Wrote::Edge(written)
}

/// After the write of the output's next edge, from the reading `before` it
/// and how long it `took` (0 for a stamped line): when a write takes
/// longer than the shortest one seen, the thread was held up in it, and the
/// edge may have reached the line that much later. That latest time is the
/// edge's time for the frame log and the next frame's sync; a timed edge
/// later than the guard makes the frame glitched.
fn wrote(model: &FrameModel, p: &mut Progress, due: u64, before: u64, took: u64) {
    p.write_floor_ns = p.write_floor_ns.min(took);
    let Some(f) = p.frame.as_mut() else {
        return;
    };
    if !f.wire.timed(model) {
        return;
    }
    let late = before - due + (took - p.write_floor_ns);
    p.timed_ns = Some(due + late);
    if !f.wire.timed_written(late) {
        return;
    }
    f.late_ns = f.late_ns.max(late);
    if late > model.late_edge_guard_ns() {
        f.glitched = true;
    }
}

/// Aborts the output's frame at its next write, found late at `at`: that
/// write and the ones after it are not made. The frame ends here, or after
/// the one write its wire form needs to leave the line idle (see
/// [`WireFrame::abort`]).
fn abort_frame(model: &FrameModel, rec: &mut Recording, p: &mut Progress, at: u64, margin_ns: u64) {
    let Some(f) = p.frame.as_mut() else {
        return;
    };
    f.aborted = true;
    f.found_late_ns = at - f.due();
    if !f.wire.abort(model, at, p.timed_ns) {
        return;
    }
    rec.finish_frame(model, p, margin_ns);
}
