//! The decision of an output's next frame: take its newest command, decide
//! what the frame carries (the command, or the failsafe action when it is
//! not fresh), encode it, and have its [`Pace`] place it.

use super::emit::Frame;
use super::pace::{place_follow, place_grid, Pace};
use super::record::add;
use super::wire::WireFrame;
use super::{EmitterConfig, Output, Progress, FOLLOW_POLL_NS, IDLE_POLL_NS};
use crate::clock::Clock;
use crate::framelog::CommandInfo;
use ppm_shared::config::FailsafeAction;
use ppm_shared::frame::{Channels, FrameModel};
use ppm_shared::line::LineState;

/// Takes the output's newest command, decides what its next frame carries
/// and schedules it (or goes silent). A follow output that finds no fresh
/// command before its longest sync is up schedules nothing and waits for
/// one. `anchor`: a grid point of another grid output of the same frame
/// length, which a grid output starting its frames joins.
pub(super) fn decide_frame<C: Clock + ?Sized>(
    clk: &C,
    out: &mut Output,
    p: &mut Progress,
    lead: u64,
    anchor: Option<u64>,
) {
    let model = out.model;
    let cfg = out.cfg;
    let stats = out.rec.stats;
    let frame_ns = model.frame_ns();
    let now = clk.now_ns();
    add(&stats.decisions, 1);
    out.rec.meter.maybe_hand_over(now);
    // Follow: a look at the earliest start (not a wake-up, not a poll while
    // waiting) should have found the line free for a command it finds.
    let mut at_earliest = false;
    if let Some(f) = p.pace.follow() {
        at_earliest = !f.woken && !f.armed;
        if f.woken {
            add(&stats.wakes, 1);
        }
        // Before looking: a command published from now on wakes the loop.
        f.woken = false;
        if !out.source.clear_wake() && f.wake_fd.take().is_some() {
            // It might stay readable and end every wait at once.
            add(&stats.wake_errors, 1);
        }
    }
    let arrived = take_newest(out, p, now);
    if out.source.withdrawn(now) {
        // Nobody could take over: silence, whatever the failsafe says, and
        // only a command that comes after this may fly.
        p.newest = None;
        out.rec
            .transition(now, || clk.realtime_ns(), p.state, LineState::Silent);
        p.state = LineState::Silent;
        if let Some(f) = p.pace.follow() {
            f.armed = false;
        }
        p.pace.stop();
        p.poll_at = now + IDLE_POLL_NS;
        return;
    }
    let fresh = p
        .newest
        .filter(|(s, _)| s.fresh(p.started, now, cfg.failsafe_after_ns))
        .map(|(_, ch)| ch);
    // Follow: a fresh command starts a frame at once; without one, the last
    // frame repeats only when the longest sync is up.
    let mut fresh_arrived = false;
    if let Some(f) = p.pace.follow() {
        let retry = std::mem::take(&mut f.retry);
        fresh_arrived = (arrived || retry) && fresh.is_some();
        if f.last_pulse.is_some() && !fresh_arrived && now + lead < f.deadline(model) {
            f.armed = true;
            p.poll_at = now + FOLLOW_POLL_NS;
            return;
        }
    }
    let last = p.newest.map(|(_, ch)| ch);
    let (channels, new_state, flagged) = carries(&cfg, model, fresh, last);
    out.rec
        .transition(now, || clk.realtime_ns(), p.state, new_state);
    p.state = new_state;
    if let Some(f) = p.pace.follow() {
        f.armed = false;
    }
    let Some(channels) = channels else {
        p.pace.stop();
        p.poll_at = now + IDLE_POLL_NS;
        return;
    };
    let mut wire = WireFrame::encode(model, &channels, flagged);
    let last_pulse = wire.last_pulse();
    let prev_pulse = p.prev_pulse;
    let placed = match &mut p.pace {
        Pace::Follow(f) => {
            place_follow(clk, f, prev_pulse, model, stats, fresh_arrived, at_earliest)
        }
        Pace::Grid(g) => place_grid(
            clk,
            g,
            prev_pulse,
            model,
            stats,
            lead,
            anchor,
            frame_ns - last_pulse,
        ),
    };
    let Some((start, lead_in_ns)) = placed else {
        return;
    };
    // Where the frame starts on the wall clock, from one pair of readings.
    let start_real_ns = clk.realtime_ns() + start.saturating_sub(clk.now_ns());
    let from_command = p.state == LineState::Active || cfg.failsafe_action == FailsafeAction::Hold;
    let command = p.newest.filter(|_| from_command).map(|(s, _)| CommandInfo {
        seq: s.seq(),
        ingress_seq: s.ingress_seq,
        recv_mono_ns: s.recv_mono_ns,
        recv_real_ns: s.recv_real_ns,
    });
    wire.place(start, lead_in_ns, p.prev_pulse);
    p.frame = Some(Frame::new(
        wire,
        channels,
        (start, start_real_ns),
        (p.state, command),
    ));
    p.prev_pulse = Some(start + last_pulse);
    match &mut p.pace {
        Pace::Follow(f) => f.last_pulse = Some(start + last_pulse),
        Pace::Grid(g) => g.placed(
            model,
            stats,
            (start, last_pulse),
            out.sync.map(|s| (s, clk.now_ns())),
        ),
    }
}

/// What a frame carries, the line's state with it, and whether it carries
/// SBUS's failsafe flag: the `fresh` command; else, before any command,
/// what `failsafe.startup` says; else the failsafe action (holding the
/// `last` command, the defaults, or the defaults flagged). `None`: silence.
fn carries(
    cfg: &EmitterConfig,
    model: &FrameModel,
    fresh: Option<Channels>,
    last: Option<Channels>,
) -> (Option<Channels>, LineState, bool) {
    let action = match (fresh, last) {
        (Some(ch), _) => return (Some(ch), LineState::Active, false),
        // Nothing to hold before the first command.
        (None, None) if cfg.startup == FailsafeAction::Hold => FailsafeAction::Silence,
        (None, None) => cfg.startup,
        (None, Some(_)) => cfg.failsafe_action,
    };
    match (action, last) {
        (FailsafeAction::Silence, _) => (None, LineState::Silent, false),
        (FailsafeAction::Hold, Some(last)) => (Some(last), LineState::Failsafe, false),
        (FailsafeAction::Hold, None) => (None, LineState::Silent, false),
        (FailsafeAction::Default, _) => (Some(model.defaults()), LineState::Failsafe, false),
        (FailsafeAction::Flag, _) => (Some(model.defaults()), LineState::Failsafe, true),
    }
}

/// Takes the output's newest command from its source, if it has one: kept
/// as `p.newest` when fresh and of the output's channels (true), counted
/// as expired or mismatched otherwise.
fn take_newest(out: &mut Output, p: &mut Progress, now: u64) -> bool {
    let Some(sample) = out.source.newest() else {
        return false;
    };
    let stats = out.rec.stats;
    // Only a command seen arriving while the loop runs, and fresh, ever
    // flies: a sample from before the start (a service's history of a
    // previous run) or already past failsafe.after_ms is refused, so the
    // line does what `failsafe.startup` says until a fresh one comes.
    match sample.channels(out.model) {
        Some(_) if !sample.fresh(p.started, now, out.cfg.failsafe_after_ns) => {
            add(&stats.expired, 1)
        }
        Some(ch) => {
            add(&stats.commands, 1);
            p.newest = Some((sample, ch));
            return true;
        }
        None => add(&stats.mismatched, 1),
    }
    false
}
