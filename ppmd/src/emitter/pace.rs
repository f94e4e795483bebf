//! When an output's next frame starts: its frame timing, [`Pace`], is a
//! fixed grid ([`Grid`]) or follows the commands ([`Follow`]); each keeps
//! its own state, places a decided frame and says when the next decision is
//! due. The lead-in pulse after silence and the gaps it keeps out of are
//! here too.

use super::module::{ModuleTiming, Taken, PERIOD_MAX_NS, STALE_NS};
use super::record::{add, Stats};
use super::{Progress, LEAD_IN_NS, READY_NS, TRAINER_WRAP_NS};
use crate::clock::Clock;
use ppm_shared::config::{Timing, FOLLOW_SYNC_CEILING_US};
use ppm_shared::frame::{us_to_ns, FrameKind, FrameModel};
use std::os::fd::RawFd;

/// Gaps (modulo [`TRAINER_WRAP_NS`]) a lead-in pulse keeps out of.
const ALIASED_NS: std::ops::RangeInclusive<u64> = 600_000..=2_400_000;
/// Gaps longer than this are left as they come: the receiver's clock
/// (within 50 ppm of ours) makes where they fall uncertain by the margin.
const ALIAS_HORIZON_NS: u64 = 2_000_000_000;

/// Where the gap from the line's previous pulse `prev` to a pulse at `at`
/// falls in the trainer's counter, if that reads as a channel.
fn aliased(prev: Option<u64>, at: u64) -> Option<u64> {
    let gap = at.checked_sub(prev?)?;
    let m = gap % TRAINER_WRAP_NS;
    (gap <= ALIAS_HORIZON_NS && ALIASED_NS.contains(&m)).then_some(m)
}

/// How much later than `at` a lead-in pulse goes so that the gap before
/// it reads as no channel (0: it reads as none at `at`).
pub(super) fn alias_later(prev: Option<u64>, at: u64) -> u64 {
    aliased(prev, at).map_or(0, |m| ALIASED_NS.end() + 1 - m)
}

/// How much earlier than `at` a lead-in pulse goes for the same.
fn alias_earlier(prev: Option<u64>, at: u64) -> u64 {
    aliased(prev, at).map_or(0, |m| m + 1 - ALIASED_NS.start())
}

/// The first point at or after `t` on the grid through `anchor` with period
/// `period` (just `t` without an anchor).
pub(crate) fn align(t: u64, anchor: Option<u64>, period: u64) -> u64 {
    match anchor {
        None => t,
        Some(a) if a >= t => a - (a - t) / period * period,
        Some(a) => a + (t - a).div_ceil(period) * period,
    }
}

/// An output's frame timing and what it keeps between frames.
#[derive(Clone, Copy)]
pub(super) enum Pace {
    /// Frames on a fixed grid.
    Grid(Grid),
    /// Frames that start as soon as a fresh command comes.
    Follow(Follow),
}

/// Grid timing's state.
#[derive(Clone, Copy, Default)]
pub(super) struct Grid {
    /// Grid start of the next frame, while frames are running.
    pub next_start: Option<u64>,
    /// Gap from the previous frame's last pulse to `next_start`; 0 when
    /// the frame there follows silence or skipped frames (it gets a lead-in).
    pub prev_sync_ns: u64,
    /// A module's newest timing correction the grid follows.
    pub correction: Option<Taken>,
    /// What is left of its offset to add to coming periods, ns.
    pub lag_ns: i64,
}

/// Follow timing's state.
#[derive(Clone, Copy, Default)]
pub(super) struct Follow {
    /// When the previous frame's last pulse starts, while frames are
    /// running (the next frame starts a shortest sync after it at the
    /// earliest, a longest sync after it at the latest).
    pub last_pulse: Option<u64>,
    /// The output looked for a command at the earliest start and found
    /// none; it now waits for one (woken through its source's wake fd) or
    /// for the longest sync.
    pub armed: bool,
    /// Its wake fd became readable; it decides at once.
    pub woken: bool,
    /// Its source's wake fd, while it works.
    pub wake_fd: Option<RawFd>,
    /// The previous frame was aborted; its command goes out again at the
    /// shortest sync, as a fresh one would.
    pub retry: bool,
}

/// When an output next needs a decision, and whether that time matters to
/// the microsecond (a frame follows, rather than a look for a command).
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(super) struct DecideAt {
    /// When.
    pub at: u64,
    /// A frame follows closely: wake as precisely as for an edge.
    pub precise: bool,
}

impl Pace {
    /// The state a `timing` starts from.
    pub fn new(timing: Timing) -> Pace {
        match timing {
            Timing::Grid => Pace::Grid(Grid::default()),
            Timing::Follow => Pace::Follow(Follow::default()),
        }
    }

    /// Grid timing's state, if that is the timing.
    pub fn grid(&self) -> Option<&Grid> {
        match self {
            Pace::Grid(g) => Some(g),
            Pace::Follow(_) => None,
        }
    }

    /// Follow timing's state, if that is the timing.
    pub fn follow(&mut self) -> Option<&mut Follow> {
        match self {
            Pace::Follow(f) => Some(f),
            Pace::Grid(_) => None,
        }
    }

    /// The line goes silent: no frame is running any more.
    pub fn stop(&mut self) {
        match self {
            Pace::Grid(g) => g.next_start = None,
            Pace::Follow(f) => f.last_pulse = None,
        }
    }
}

impl Grid {
    /// The lead-in the frame at `next_start` needs. A transmitter reads a
    /// frame only after a sync period (4..19 ms), so after silence or skipped
    /// frames (a gap of a sync plus at least a frame before it) a lone pulse
    /// LEAD_IN_NS before the frame provides one, or up to
    /// [`super::ALIAS_SHIFT_MAX_NS`] earlier where the gap before it (from
    /// the line's previous pulse `prev_pulse`) would read as a channel on a
    /// trainer input (see [`TRAINER_WRAP_NS`]). Unwrapped, that gap is over
    /// 3.8 ms (a sync plus a 4.8 ms frame, the shortest valid, less
    /// LEAD_IN_NS).
    /// A frame of bytes ([`FrameKind::Bytes`], SBUS) needs none: its
    /// receivers find frames by the idle line before them, which any
    /// silence is.
    pub fn lead_in_ns(&self, model: &FrameModel, prev_pulse: Option<u64>) -> u64 {
        if model.wire().kind() == FrameKind::Bytes {
            return 0;
        }
        match (self.prev_sync_ns, self.next_start) {
            (0, Some(s)) => LEAD_IN_NS + alias_earlier(prev_pulse, s - LEAD_IN_NS),
            (0, None) => LEAD_IN_NS,
            _ => 0,
        }
    }
}

impl Follow {
    /// When the next frame must start at the latest (the previous frame's
    /// last pulse plus the longest sync).
    pub fn deadline(&self, model: &FrameModel) -> u64 {
        self.last_pulse.unwrap_or(0) + model.follow_sync_ns().1
    }
}

impl Progress {
    /// When this output next needs a decision (it has no frame in progress).
    pub(super) fn decide_at(&self, model: &FrameModel, lead: u64) -> Option<DecideAt> {
        if self.frame.is_some() {
            return None;
        }
        let poll = DecideAt {
            at: self.poll_at,
            precise: false,
        };
        let precise = |at: u64| DecideAt { at, precise: true };
        match &self.pace {
            Pace::Grid(g) => Some(match g.next_start {
                None => poll,
                Some(s) => precise(s.saturating_sub(lead + g.lead_in_ns(model, self.prev_pulse))),
            }),
            Pace::Follow(f) if f.woken => Some(DecideAt {
                at: 0,
                precise: false,
            }),
            Pace::Follow(f) => match f.last_pulse {
                None => Some(poll),
                Some(last) if !f.armed => {
                    let earliest = last + model.follow_sync_ns().0;
                    Some(precise(earliest.saturating_sub(lead)))
                }
                Some(_) => {
                    let deadline = f.deadline(model).saturating_sub(lead);
                    match f.wake_fd {
                        Some(_) => Some(precise(deadline)),
                        None if self.poll_at < deadline => Some(poll),
                        None => Some(precise(deadline)),
                    }
                }
            },
        }
    }

    /// Follow: the wake fd to sleep on while the output waits for a command
    /// (armed or silent).
    pub(super) fn watches(&self) -> Option<RawFd> {
        let Pace::Follow(f) = &self.pace else {
            return None;
        };
        let waiting = self.frame.is_none() && !f.woken && (f.armed || f.last_pulse.is_none());
        f.wake_fd.filter(|_| waiting)
    }

    /// Grid's next grid start, while frames are running.
    pub(super) fn next_start(&self) -> Option<u64> {
        self.pace.grid().and_then(|g| g.next_start)
    }

    /// Where the output goes on after an aborted frame whose last timed
    /// pulse started at `last`. That is where the receivers' sync is
    /// measured from. Grid: the next grid frame, with a lead-in pulse when
    /// the gap up to it is longer than a sync (and the one after, counted
    /// as an overrun, when it is shorter). Follow: a shortest sync after it,
    /// carrying the command again (or with a lead-in when none was ever
    /// written).
    pub(super) fn resume_after_abort(
        &mut self,
        model: &FrameModel,
        stats: &Stats,
        last: Option<u64>,
    ) {
        self.prev_pulse = last;
        match &mut self.pace {
            Pace::Follow(f) => {
                f.last_pulse = last;
                f.retry = true;
                f.armed = false;
                if last.is_none() {
                    self.poll_at = 0;
                }
            }
            Pace::Grid(g) => {
                let Some(mut s) = g.next_start else {
                    return;
                };
                let (sync_min, sync_max) = model.sync_window_ns();
                loop {
                    let gap = last.map_or(u64::MAX, |l| s.saturating_sub(l));
                    if gap >= sync_min {
                        g.prev_sync_ns = if gap <= sync_max { gap } else { 0 };
                        break;
                    }
                    add(&stats.overruns, 1);
                    s += model.frame_ns();
                }
                g.next_start = Some(s);
            }
        }
    }
}

/// Grid: the frame's start and lead-in (`None`: skipped). The frame sits at
/// its grid start (a late frame moves off it, the next one returns to it);
/// on return `g.next_start` is that grid start. After silence or skipped
/// frames, a lone pulse LEAD_IN_NS before the frame gives it the sync before
/// it that a transmitter needs to read it (see [`Grid::lead_in_ns`]).
/// `anchor`: a grid point of another output of the same frame length, to
/// join; `sync_ns`: the frame's own sync, after its last pulse.
#[allow(clippy::too_many_arguments)]
pub(super) fn place_grid<C: Clock + ?Sized>(
    clk: &C,
    g: &mut Grid,
    prev_pulse: Option<u64>,
    model: &FrameModel,
    stats: &Stats,
    lead: u64,
    anchor: Option<u64>,
    sync_ns: u64,
) -> Option<(u64, u64)> {
    if model.wire().kind() == FrameKind::Bytes {
        return Some(place_grid_bytes(
            clk, g, prev_pulse, model, stats, lead, anchor,
        ));
    }
    let frame_ns = model.frame_ns();
    let (sync_min_ns, sync_max_ns) = model.sync_window_ns();
    let now = clk.now_ns();
    let (grid_start, lead_in_ns) = match g.next_start {
        Some(s) => (s, g.lead_in_ns(model, prev_pulse)),
        None => {
            g.prev_sync_ns = 0;
            match anchor {
                // Joining a running grid costs up to one frame, once; a
                // grid point is taken while its lead-in pulse is still twice
                // READY_NS away.
                Some(_) => {
                    let mut s = align(now + LEAD_IN_NS + 2 * READY_NS, anchor, frame_ns);
                    loop {
                        let li = LEAD_IN_NS + alias_earlier(prev_pulse, s - LEAD_IN_NS);
                        if s - li >= now + 2 * READY_NS {
                            break (s, li);
                        }
                        s += frame_ns;
                    }
                }
                None => {
                    let lone = now + lead;
                    let lone = lone + alias_later(prev_pulse, lone);
                    (lone + LEAD_IN_NS, LEAD_IN_NS)
                }
            }
        }
    };
    g.next_start = Some(grid_start);
    let mut start = grid_start;
    let ready = clk.now_ns() + READY_NS;
    if ready > start - lead_in_ns {
        // Moving the frame later by `late` lengthens the gap before it and
        // shortens the one after it: both must stay sync periods (a lead-in
        // pulse moves with its frame).
        let mut late = ready - (start - lead_in_ns);
        if lead_in_ns > 0 {
            late += alias_later(prev_pulse, ready);
        }
        let fits_after = sync_ns >= sync_min_ns + late;
        let fits_before = lead_in_ns > 0 || g.prev_sync_ns + late <= sync_max_ns;
        if fits_after && fits_before {
            add(&stats.late_frames, 1);
            start += late;
        } else {
            // Skip to the first frame whose lead-in can still be decided in
            // time (the gap it follows is too long to be a sync).
            let mut missed = (ready + lead + LEAD_IN_NS - start).div_ceil(frame_ns);
            loop {
                let s = start + missed * frame_ns;
                let li = LEAD_IN_NS + alias_earlier(prev_pulse, s - LEAD_IN_NS);
                if s - li >= ready + lead {
                    break;
                }
                missed += 1;
            }
            add(&stats.overruns, missed);
            g.next_start = Some(start + missed * frame_ns);
            g.prev_sync_ns = 0;
            return None;
        }
    }
    Some((start, lead_in_ns))
}

/// Grid, a frame of bytes (SBUS): the frame's start (never a lead-in, never skipped). The frame
/// sits at its grid start unless that has passed, or the previous frame
/// ends (`prev_end`, as measured after its write) less than the receivers'
/// least idle line before it: then it starts as soon as both allow, counted
/// as a late frame. How far the grid moves on after it is
/// [`Grid::placed`]'s.
fn place_grid_bytes<C: Clock + ?Sized>(
    clk: &C,
    g: &mut Grid,
    prev_end: Option<u64>,
    model: &FrameModel,
    stats: &Stats,
    lead: u64,
    anchor: Option<u64>,
) -> (u64, u64) {
    let grid_start = match g.next_start {
        Some(s) => s,
        None => align(clk.now_ns() + lead, anchor, model.frame_ns()),
    };
    g.next_start = Some(grid_start);
    let ready = clk.now_ns() + READY_NS;
    let earliest = prev_end.map_or(0, |e| e + model.sync_window_ns().0);
    let start = grid_start.max(ready).max(earliest);
    if start > grid_start {
        add(&stats.late_frames, 1);
    }
    (start, 0)
}

impl Grid {
    /// After a frame from grid start `next_start` was placed at `start`,
    /// its last pulse `last_pulse` after that: the next grid start, and the
    /// sync before it. A frame of bytes (SBUS) moved so late that the next grid start
    /// would leave less than the receivers' least idle line after it skips
    /// grid starts (counted as overruns) instead of sending frames closer.
    ///
    /// An output that drives a transmitter module (`module`: its
    /// corrections, and the time now) steps by [`Grid::period_ns`].
    pub fn placed(
        &mut self,
        model: &FrameModel,
        stats: &Stats,
        (start, last_pulse): (u64, u64),
        module: Option<(&ModuleTiming, u64)>,
    ) {
        let grid_start = self.next_start.expect("placed on the grid");
        let step = self.period_ns(model, module);
        let mut next = grid_start + step;
        let end = start + last_pulse;
        if model.wire().kind() == FrameKind::Bytes {
            while next < end + model.sync_window_ns().0 {
                next += step;
                add(&stats.overruns, 1);
            }
        }
        self.next_start = Some(next);
        self.prev_sync_ns = next - end;
    }
}

impl Grid {
    /// The step from this grid start to the next: `ppm.frame_us`; for an
    /// output that drives a transmitter module, the period its newest
    /// timing correction asks for (while the correction is under
    /// [`STALE_NS`] old), with the correction's offset added once, as
    /// EdgeTX does (`ModuleSyncStatus::getAdjustedRefreshRate`): a step is
    /// kept within the frame's time on the wire and its least idle line,
    /// and [`PERIOD_MAX_NS`], and what the bounds hold back of the offset
    /// is added to the steps after it. Reads the correction without
    /// waiting: one being written now is read at the next frame.
    pub fn period_ns(&mut self, model: &FrameModel, module: Option<(&ModuleTiming, u64)>) -> u64 {
        let Some((timing, now)) = module else {
            return model.frame_ns();
        };
        if let Some(t) = timing.get() {
            if self.correction.is_none_or(|c| c.number != t.number) {
                self.correction = Some(t);
                self.lag_ns = t.offset_ns;
            }
        }
        let least = model.wire().frame_wire_ns() + model.sync_window_ns().0;
        let rate = match self.correction {
            Some(c) if now.saturating_sub(c.at_ns) <= STALE_NS && c.rate_ns > 0 => {
                c.rate_ns.clamp(least, PERIOD_MAX_NS)
            }
            _ => {
                self.lag_ns = 0;
                return model.frame_ns();
            }
        };
        let step = (rate as i64 + self.lag_ns).clamp(least as i64, PERIOD_MAX_NS as i64);
        self.lag_ns -= step - rate as i64;
        step as u64
    }
}

/// Follow: the frame's start and lead-in. A fresh command's frame starts as
/// soon as the loop can write it, but not before the shortest sync after the
/// previous frame's last pulse; a repeat starts at the longest sync. A frame
/// decided too late for that moves later while the sync before it stays
/// under [`FOLLOW_SYNC_CEILING_US`] (counted as a late frame when it was
/// decided at its planned time, the earliest start or the longest sync, but
/// late); past that, it gets the lead-in pulse a frame after silence gets
/// (counted as an overrun).
pub(super) fn place_follow<C: Clock + ?Sized>(
    clk: &C,
    f: &Follow,
    prev_pulse: Option<u64>,
    model: &FrameModel,
    stats: &Stats,
    fresh_arrived: bool,
    at_earliest: bool,
) -> Option<(u64, u64)> {
    let (sync_min_ns, sync_max_ns) = model.follow_sync_ns();
    let ready = clk.now_ns() + READY_NS;
    if model.wire().kind() == FrameKind::Bytes {
        return Some(place_follow_bytes(
            f,
            prev_pulse,
            model,
            stats,
            ready,
            (fresh_arrived, at_earliest),
        ));
    }
    // A lead-in pulse as soon as it can be written, clear of the gaps a
    // trainer input reads as a channel.
    let lone = ready + alias_later(prev_pulse, ready);
    let Some(last) = f.last_pulse else {
        return Some((lone + LEAD_IN_NS, LEAD_IN_NS));
    };
    if !fresh_arrived {
        add(&stats.repeats, 1);
    }
    let want = last
        + if fresh_arrived {
            sync_min_ns
        } else {
            sync_max_ns
        };
    if ready <= want {
        return Some((want, 0));
    }
    if ready - last < us_to_ns(FOLLOW_SYNC_CEILING_US) {
        if !fresh_arrived || at_earliest {
            add(&stats.late_frames, 1);
        }
        return Some((ready, 0));
    }
    add(&stats.overruns, 1);
    Some((lone + LEAD_IN_NS, LEAD_IN_NS))
}

/// Follow, a frame of bytes (SBUS): a fresh command's frame starts as soon as the loop can
/// write it, but not before the shortest idle line after the previous
/// frame's end; a repeat at the longest. Never a lead-in: after silence, or
/// however late, a frame starts when it is ready (counted as a late frame
/// when it was decided at its planned time but late), and after silence no
/// earlier than the shortest idle line after the last frame there was
/// (`prev_end`).
fn place_follow_bytes(
    f: &Follow,
    prev_end: Option<u64>,
    model: &FrameModel,
    stats: &Stats,
    ready: u64,
    (fresh_arrived, at_earliest): (bool, bool),
) -> (u64, u64) {
    let (gap_min, gap_max) = model.follow_sync_ns();
    let Some(last) = f.last_pulse else {
        return (ready.max(prev_end.map_or(0, |e| e + gap_min)), 0);
    };
    if !fresh_arrived {
        add(&stats.repeats, 1);
    }
    let want = last + if fresh_arrived { gap_min } else { gap_max };
    if ready <= want {
        return (want, 0);
    }
    if !fresh_arrived || at_earliest {
        add(&stats.late_frames, 1);
    }
    (ready, 0)
}
