//! The timing loop. Once per frame, [`DECIDE_NS`] before the frame's first
//! edge (woken as precisely as for an edge), it takes the newest command,
//! decides what the frame carries (the command, or the failsafe action when
//! the command is too old), encodes it and emits every edge at its scheduled
//! time through an [`EdgeTimer`]: an absolute sleep until a margin before the
//! edge, a spin on CLOCK_MONOTONIC, then one write. So a command is at most
//! about `DECIDE_NS` old when its frame starts, whatever the spin margin.
//!
//! Frames sit on a fixed grid (`start_k = start_0 + k * frame`), so a late
//! edge never shifts later ones. When a frame's start has already passed, the
//! frame is moved later as a whole if the sync gaps on both sides stay within
//! what transmitters accept (counted as a late frame: its channel values stay
//! exact); otherwise it is skipped (counted as an overrun), and the frame
//! after it gets the lead-in pulse a frame after silence gets. Nothing inside the
//! loop allocates, logs or takes a lock; it updates atomic counters in
//! [`Stats`] and histograms in a [`Meter`].

use crate::clock::{self, EdgeTimer, Margin, Readable, Wake};
use crate::framelog::{self, CommandInfo, Record};
use crate::meter::Meter;
use crate::output::{Bank, FrameEdge, Output};
use crate::source::CommandSource;
use ppm_shared::config::{
    FailsafeAction, Timing, FOLLOW_SYNC_CEILING_US, SYNC_MAX_US, SYNC_MIN_US,
};
use ppm_shared::frame::{
    us_to_ns, Channels, EdgeSchedule, FrameModel, Level, MAX_CHANNELS, MAX_EDGES,
};
use ppm_shared::ipc::CommandSample;
use ppm_shared::trace::TraceEdge;
use std::os::fd::RawFd;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering::Relaxed};

/// How long before a frame's start its lane takes the newest command and
/// encodes the frame; with several lanes, [`DECIDE_SLOT_NS`] more per further
/// lane, so lanes that share a frame start all decide before it.
pub const DECIDE_NS: u64 = 150_000;
/// Time from the end of a decision to the frame's first edge that the loop
/// needs at least; a frame decided later than that is moved (a late frame).
pub const READY_NS: u64 = 20_000;
/// After silence, how long before the first frame a lone pulse goes out: a
/// sync period (4..19 ms) before the frame, so a transmitter reads that first
/// frame instead of waiting for the second.
pub const LEAD_IN_NS: u64 = 5_000_000;
/// How often the loop looks for a command while the line is silent.
pub const IDLE_POLL_NS: u64 = 2_000_000;
/// How often a follow lane whose source has no wake fd looks for a command
/// while it waits for one.
pub const FOLLOW_POLL_NS: u64 = 200_000;
/// An edge written later than this after its scheduled time counts as late.
pub const LATE_EDGE_NS: u64 = 10_000;

/// Settings of the loop, resolved from the configuration.
#[derive(Debug, Clone, Copy)]
pub struct EmitterConfig {
    /// How far before each edge the loop stops sleeping and spins.
    pub margin: Margin,
    /// A command older than this (by its ingress receive time) is not fresh.
    pub failsafe_after_ns: u64,
    /// What to emit when the newest command is not fresh.
    pub failsafe_action: FailsafeAction,
    /// What to emit before the first command (`Silence` or `Default`).
    pub startup: FailsafeAction,
}

pub use ppm_shared::line::LineState;

/// Counters the loop updates and other threads read.
#[derive(Debug, Default)]
pub struct Stats {
    /// Frames emitted.
    pub frames: AtomicU64,
    /// Edges written.
    pub edges: AtomicU64,
    /// Commands taken from the source.
    pub commands: AtomicU64,
    /// Samples whose channel count did not match this daemon's configuration.
    pub mismatched: AtomicU64,
    /// Frames skipped because their start had passed beyond what moving them allows.
    pub overruns: AtomicU64,
    /// Frames moved later as a whole because their start had passed.
    pub late_frames: AtomicU64,
    /// Edges written more than [`LATE_EDGE_NS`] after their time.
    pub late_edges: AtomicU64,
    /// Largest edge error seen (actual minus scheduled), ns.
    pub max_edge_error_ns: AtomicU64,
    /// Output writes that failed.
    pub write_errors: AtomicU64,
    /// Times the loop went from fresh commands to the failsafe action.
    pub failsafe_entries: AtomicU64,
    /// Follow: frames that repeated the last command (or the failsafe
    /// action's) because no fresh command came before the longest sync.
    pub repeats: AtomicU64,
    /// Follow: times a command's wake-up woke the loop.
    pub wakes: AtomicU64,
    /// Follow: wake fds that broke (the lane then polls for commands).
    pub wake_errors: AtomicU64,
    /// Times the loop decided this lane's next frame (or that the line
    /// stays silent a while longer): at least once a frame while the loop
    /// runs. ppmd pets systemd's watchdog only while it advances.
    pub decisions: AtomicU64,
    /// Current spin margin, ns.
    pub margin_ns: AtomicU64,
    /// Total time spent spinning, ns.
    pub spin_ns: AtomicU64,
    /// The current [`LineState`].
    state: AtomicU8,
}

impl Stats {
    /// The current line state.
    pub fn state(&self) -> LineState {
        LineState::from_code(self.state.load(Relaxed) as u32).unwrap_or(LineState::Silent)
    }
}

fn add(c: &AtomicU64, n: u64) {
    c.fetch_add(n, Relaxed);
}

/// Most outputs (lanes) one loop drives.
pub const MAX_LANES: usize = ppm_shared::config::MAX_OUTPUTS;

/// Time kept free for one decision (take the command, encode the frame), at
/// least; the loop widens it to a decaying peak of the decision times it
/// measures plus a quarter of this. A decision is made only when it can end
/// before the next edge of any lane; when its time falls on an edge, it is
/// made early, before the edge.
pub const DECIDE_SLOT_NS: u64 = 50_000;

/// Where a lane's edges go.
pub enum Sink<'a> {
    /// A line of its own.
    Line(&'a mut dyn Output),
    /// Line `bit` of bank `bank` (several lines of one GPIO chip in one
    /// request): edges of a bank's lanes due at the same time are written
    /// together, in one call.
    Bank {
        /// Index into the banks given to [`run_lanes`].
        bank: usize,
        /// The line's index within the bank.
        bit: u32,
    },
}

/// One output of the loop: its frame model, failsafe settings, commands,
/// line, counters and histograms.
pub struct Lane<'a> {
    /// The frame this output emits.
    pub model: &'a FrameModel,
    /// Failsafe settings (the loop's spin margin is the first lane's).
    pub cfg: EmitterConfig,
    /// Where its commands come from.
    pub source: &'a mut dyn CommandSource,
    /// Where its edges go.
    pub sink: Sink<'a>,
    /// Its counters.
    pub stats: &'a Stats,
    /// Its histograms.
    pub meter: &'a mut Meter,
    /// Its frame log, if any.
    pub log: Option<&'a mut framelog::Producer>,
}

/// Runs one output until `stop` is set, then finishes the frame in progress
/// and leaves the line at its idle level. With a frame log, every emitted
/// frame and every line-state change is queued to it.
#[allow(clippy::too_many_arguments)]
pub fn run(
    model: &FrameModel,
    cfg: &EmitterConfig,
    source: &mut dyn CommandSource,
    out: &mut dyn Output,
    stop: &AtomicBool,
    stats: &Stats,
    meter: &mut Meter,
    log: Option<&mut framelog::Producer>,
) {
    let mut lanes = [Lane {
        model,
        cfg: *cfg,
        source,
        sink: Sink::Line(out),
        stats,
        meter,
        log,
    }];
    run_lanes(&mut lanes, &mut [], stop);
}

/// A frame being emitted.
#[derive(Clone, Copy)]
struct Frame {
    schedule: EdgeSchedule,
    /// The next edge to write, counting the lead-in pulse's two first.
    next: usize,
    /// How long before `start` the lead-in pulse starts (0: none).
    lead_in_ns: u64,
    start: u64,
    start_real_ns: u64,
    channels: Channels,
    state: LineState,
    command: Option<CommandInfo>,
    spun: u64,
}

impl Frame {
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
        self.edge_at(self.next)
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

    fn due(&self) -> u64 {
        self.edge().0
    }
}

/// What the loop keeps per lane.
#[derive(Clone, Copy)]
struct Progress {
    newest: Option<(CommandSample, Channels)>,
    /// Grid: grid start of the next frame, while frames are running.
    next_start: Option<u64>,
    /// Grid: gap from the previous frame's last pulse to `next_start`; 0 when
    /// the frame there follows silence or skipped frames (it gets a lead-in).
    prev_sync_ns: u64,
    /// Follow: when the previous frame's last pulse starts, while frames are
    /// running (the next frame starts a shortest sync after it at the
    /// earliest, a longest sync after it at the latest).
    last_pulse: Option<u64>,
    /// Follow: the lane looked for a command at the earliest start and found
    /// none; it now waits for one (woken through its source's wake fd) or
    /// for the longest sync.
    armed: bool,
    /// Follow: its wake fd became readable; it decides at once.
    woken: bool,
    /// Follow: its source's wake fd, while it works.
    wake_fd: Option<RawFd>,
    state: LineState,
    frame_no: u64,
    /// When to look for a command again while silent (and, without a wake
    /// fd, while armed).
    poll_at: u64,
    frame: Option<Frame>,
}

impl Progress {
    /// When this lane next needs a decision (it has no frame in progress),
    /// and whether that time matters to the microsecond (a frame follows,
    /// rather than a look for a command).
    fn decide_at(&self, model: &FrameModel, lead: u64) -> Option<(u64, bool)> {
        if self.frame.is_some() {
            return None;
        }
        if self.woken {
            return Some((0, false));
        }
        let running = match model.timing() {
            Timing::Grid => self.next_start,
            Timing::Follow => self.last_pulse,
        };
        match (model.timing(), running) {
            (_, None) => Some((self.poll_at, false)),
            (Timing::Grid, Some(s)) => Some((s.saturating_sub(lead + self.lead_in_ns()), true)),
            (Timing::Follow, Some(last)) if !self.armed => {
                let earliest = last + model.follow_sync_ns().0;
                Some((earliest.saturating_sub(lead), true))
            }
            (Timing::Follow, Some(_)) => {
                let deadline = self.follow_deadline(model).saturating_sub(lead);
                match self.wake_fd {
                    Some(_) => Some((deadline, true)),
                    None if self.poll_at < deadline => Some((self.poll_at, false)),
                    None => Some((deadline, true)),
                }
            }
        }
    }

    /// Follow: when the next frame must start at the latest (the previous
    /// frame's last pulse plus the longest sync).
    fn follow_deadline(&self, model: &FrameModel) -> u64 {
        self.last_pulse.unwrap_or(0) + model.follow_sync_ns().1
    }

    /// Follow: the lane sleeps until its wake fd is readable (it waits for a
    /// command, armed or silent).
    fn watches(&self) -> Option<RawFd> {
        let waiting =
            self.frame.is_none() && !self.woken && (self.armed || self.last_pulse.is_none());
        self.wake_fd.filter(|_| waiting)
    }

    /// The lead-in the frame at `next_start` needs. A transmitter reads a
    /// frame only after a sync period (4..19 ms), so after silence or skipped
    /// frames (a gap of a sync plus at least a frame before it) a lone pulse
    /// LEAD_IN_NS before the frame provides one. The gap before that pulse is
    /// over 3.8 ms (a sync plus a 4.8 ms frame, the shortest valid, less
    /// LEAD_IN_NS): never read as a channel.
    fn lead_in_ns(&self) -> u64 {
        if self.prev_sync_ns == 0 {
            LEAD_IN_NS
        } else {
            0
        }
    }
}

/// Runs every lane from one thread until `stop` is set: the edges of all
/// lanes are merged into one schedule and waited for by one [`EdgeTimer`];
/// edges due at the same time on the lines of one bank are written with one
/// call. Each lane keeps its own frame timing, failsafe, counters and frame
/// log. Grid lanes with equal frame lengths that start while another runs
/// join its grid, so their frame starts coincide. Follow lanes waiting for a
/// command sleep on their sources' wake fds along with every other wait.
/// When `stop` is set, frames in progress are finished and every line is
/// left at its idle level.
pub fn run_lanes(lanes: &mut [Lane], banks: &mut [&mut dyn Bank], stop: &AtomicBool) {
    assert!(
        (1..=MAX_LANES).contains(&lanes.len()),
        "1..={MAX_LANES} lanes"
    );
    let n = lanes.len();
    let mut timer = EdgeTimer::new(lanes[0].cfg.margin);
    let now = clock::now_ns();
    let mut prog = [Progress {
        newest: None,
        next_start: None,
        prev_sync_ns: 0,
        last_pulse: None,
        armed: false,
        woken: false,
        wake_fd: None,
        state: LineState::Silent,
        frame_no: 0,
        poll_at: now,
        frame: None,
    }; MAX_LANES];
    for (lane, p) in lanes.iter_mut().zip(prog.iter_mut()) {
        lane.meter.start(now);
        // Shown while the line is still silent; updated after every frame.
        lane.stats.margin_ns.store(timer.margin_ns(), Relaxed);
        if lane.model.timing() == Timing::Follow {
            p.wake_fd = lane.source.wake_fd();
        }
    }
    let mut decide_peak_ns = 0u64;
    let lead = DECIDE_NS + DECIDE_SLOT_NS * (n as u64 - 1);
    loop {
        let stopping = stop.load(Relaxed);
        let edge_due = prog[..n]
            .iter()
            .filter_map(|p| p.frame.map(|f| f.due()))
            .min();
        let decision = if stopping {
            None
        } else {
            (0..n)
                .filter_map(|i| {
                    prog[i]
                        .decide_at(lanes[i].model, lead)
                        .map(|(d, precise)| (d, i, precise))
                })
                .min()
        };
        // The wake fds of the lanes waiting for a command: any wait below
        // ends early when one is readable.
        let mut fds = [0 as RawFd; MAX_LANES];
        let mut fd_lane = [0usize; MAX_LANES];
        let mut watched = 0;
        if !stopping {
            for (i, p) in prog[..n].iter().enumerate() {
                if let Some(fd) = p.watches() {
                    fds[watched] = fd;
                    fd_lane[watched] = i;
                    watched += 1;
                }
            }
        }
        let fds = &fds[..watched];
        let slot = DECIDE_SLOT_NS.max(decide_peak_ns + DECIDE_SLOT_NS / 4);
        let decide = match (decision, edge_due) {
            (None, None) => break,
            (None, Some(_)) => None,
            (Some((at, i, precise)), None) => Some((at, i, true, precise)),
            (Some((at, i, precise)), Some(due)) => {
                // A decision made awake may use an edge's spin margin: it
                // only has to end before the edge.
                if at + slot <= due {
                    Some((at, i, true, precise))
                } else if at <= due && clock::now_ns() + slot <= due {
                    // Its time falls on an edge: decide now, before it.
                    Some((at, i, false, precise))
                } else {
                    None
                }
            }
        };
        let woke = match decide {
            Some((at, i, sleep, precise)) => {
                let woke = if sleep && (precise || edge_due.is_some()) {
                    // A frame or another line's edge follows closely: wake as
                    // precisely as for an edge.
                    match timer.wait_or_readable(at, fds) {
                        Wake::Due(_) => None,
                        Wake::Readable(r) => Some(r),
                    }
                } else if sleep {
                    let r = clock::sleep_until_or_readable(at, fds);
                    r.any().then_some(r)
                } else {
                    None
                };
                if woke.is_none() {
                    let took_from = clock::now_ns();
                    let frame_ns = lanes[i].model.frame_ns();
                    let anchor = (0..n)
                        .filter(|&j| {
                            j != i
                                && lanes[j].model.timing() == Timing::Grid
                                && lanes[j].model.frame_ns() == frame_ns
                        })
                        .find_map(|j| prog[j].next_start);
                    decide_frame(&mut lanes[i], &mut prog[i], lead, anchor);
                    // A decaying peak of the decision time sizes the slot.
                    let took = clock::now_ns() - took_from;
                    decide_peak_ns = took.max(decide_peak_ns - decide_peak_ns / 64);
                }
                woke
            }
            None => {
                let due = edge_due.expect("an edge is due");
                emit_due(due, lanes, &mut prog[..n], banks, &mut timer, fds)
            }
        };
        if let Some(r) = woke {
            for (k, &i) in fd_lane[..watched].iter().enumerate() {
                if r.readable & (1 << k) != 0 {
                    prog[i].woken = true;
                }
                if r.broken & (1 << k) != 0 {
                    // It would end every wait at once: look for commands
                    // every FOLLOW_POLL_NS instead.
                    prog[i].wake_fd = None;
                    prog[i].woken = true;
                    add(&lanes[i].stats.wake_errors, 1);
                }
            }
        }
    }
    for lane in lanes.iter_mut() {
        let idle = lane.model.idle_level();
        let parked = match &mut lane.sink {
            Sink::Line(out) => out.park(idle),
            Sink::Bank { bank, bit } => banks[*bank].park(*bit, idle),
        };
        if parked.is_err() {
            add(&lane.stats.write_errors, 1);
        }
        lane.stats.state.store(LineState::Silent as u8, Relaxed);
    }
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

/// Takes the lane's newest command, decides what its next frame carries and
/// schedules it (or goes silent). A follow lane that finds no fresh command
/// before its longest sync is up schedules nothing and waits for one.
fn decide_frame(lane: &mut Lane, p: &mut Progress, lead: u64, anchor: Option<u64>) {
    let model = lane.model;
    let cfg = &lane.cfg;
    let stats = lane.stats;
    let frame_ns = model.frame_ns();
    let follow = model.timing() == Timing::Follow;
    let now = clock::now_ns();
    add(&stats.decisions, 1);
    lane.meter.maybe_hand_over(now);
    // Follow: a look at the earliest start (not a wake-up, not a poll while
    // waiting) should have found the line free for a command it finds.
    let at_earliest = follow && !p.woken && !p.armed;
    if follow {
        if p.woken {
            add(&stats.wakes, 1);
        }
        // Before looking: a command published from now on wakes the loop.
        p.woken = false;
        if !lane.source.clear_wake() && p.wake_fd.take().is_some() {
            // It might stay readable and end every wait at once.
            add(&stats.wake_errors, 1);
        }
    }
    let mut arrived = false;
    if let Some(sample) = lane.source.newest() {
        match sample.channels(model) {
            Some(ch) => {
                add(&stats.commands, 1);
                p.newest = Some((sample, ch));
                arrived = true;
            }
            None => add(&stats.mismatched, 1),
        }
    }
    let fresh = p
        .newest
        .filter(|(s, _)| now.saturating_sub(s.recv_mono_ns) <= cfg.failsafe_after_ns)
        .map(|(_, ch)| ch);
    // Follow: a fresh command starts a frame at once; without one, the last
    // frame repeats only when the longest sync is up.
    let fresh_arrived = arrived && fresh.is_some();
    if follow && p.last_pulse.is_some() && !fresh_arrived {
        let deadline = p.follow_deadline(model);
        if now + lead < deadline {
            p.armed = true;
            p.poll_at = now + FOLLOW_POLL_NS;
            return;
        }
    }
    let (channels, new_state) = match (fresh, p.newest) {
        (Some(ch), _) => (Some(ch), LineState::Active),
        (None, None) => match cfg.startup {
            FailsafeAction::Default => (Some(model.defaults()), LineState::Failsafe),
            // Nothing to hold before the first command.
            _ => (None, LineState::Silent),
        },
        (None, Some((_, last))) => match cfg.failsafe_action {
            FailsafeAction::Silence => (None, LineState::Silent),
            FailsafeAction::Hold => (Some(last), LineState::Failsafe),
            FailsafeAction::Default => (Some(model.defaults()), LineState::Failsafe),
        },
    };
    if p.state == LineState::Active && new_state != LineState::Active {
        add(&stats.failsafe_entries, 1);
    }
    if new_state != p.state {
        if let Some(log) = lane.log.as_deref_mut() {
            log.push(Record::Transition {
                mono_ns: now,
                real_ns: clock::realtime_ns(),
                from: p.state,
                to: new_state,
            });
        }
    }
    p.state = new_state;
    stats.state.store(p.state as u8, Relaxed);
    p.armed = false;
    let Some(channels) = channels else {
        p.next_start = None;
        p.last_pulse = None;
        p.poll_at = now + IDLE_POLL_NS;
        return;
    };
    let schedule = model.encode(&channels);
    let edges = schedule.edges();
    let last_pulse = edges[edges.len() - 2].at_ns;
    let placed = if follow {
        place_follow(p, model, stats, fresh_arrived, at_earliest)
    } else {
        place_grid(p, model, stats, lead, anchor, frame_ns - last_pulse)
    };
    let Some((start, lead_in_ns)) = placed else {
        return;
    };
    // Where the frame starts on the wall clock, from one pair of readings.
    let start_real_ns = clock::realtime_ns() + start.saturating_sub(clock::now_ns());
    let from_command = p.state == LineState::Active || cfg.failsafe_action == FailsafeAction::Hold;
    p.frame = Some(Frame {
        schedule,
        next: 0,
        lead_in_ns,
        start,
        start_real_ns,
        channels,
        state: p.state,
        command: p.newest.filter(|_| from_command).map(|(s, _)| CommandInfo {
            seq: s.seq(),
            ingress_seq: s.ingress_seq,
            recv_mono_ns: s.recv_mono_ns,
            recv_real_ns: s.recv_real_ns,
        }),
        spun: 0,
    });
    if follow {
        p.last_pulse = Some(start + last_pulse);
    } else {
        let grid_start = p.next_start.expect("placed on the grid");
        p.next_start = Some(grid_start + frame_ns);
        p.prev_sync_ns = grid_start + frame_ns - (start + last_pulse);
    }
}

/// Grid: the frame's start and lead-in (`None`: skipped). The frame sits at
/// its grid start (a late frame moves off it, the next one returns to it);
/// on return `p.next_start` is that grid start. After silence or skipped
/// frames, a lone pulse LEAD_IN_NS before the frame gives it the sync before
/// it that a transmitter needs to read it (see `Progress::lead_in_ns`).
fn place_grid(
    p: &mut Progress,
    model: &FrameModel,
    stats: &Stats,
    lead: u64,
    anchor: Option<u64>,
    sync_ns: u64,
) -> Option<(u64, u64)> {
    let frame_ns = model.frame_ns();
    let (sync_min_ns, sync_max_ns) = (us_to_ns(SYNC_MIN_US), us_to_ns(SYNC_MAX_US));
    let now = clock::now_ns();
    let (grid_start, lead_in_ns) = match p.next_start {
        Some(s) => (s, p.lead_in_ns()),
        None => {
            p.prev_sync_ns = 0;
            // Joining a running grid costs up to one frame, once; a grid
            // point is taken while it is still twice READY_NS away.
            let start = match anchor {
                Some(_) => align(now + LEAD_IN_NS + 2 * READY_NS, anchor, frame_ns),
                None => now + lead + LEAD_IN_NS,
            };
            (start, LEAD_IN_NS)
        }
    };
    p.next_start = Some(grid_start);
    let mut start = grid_start;
    let ready = clock::now_ns() + READY_NS;
    if ready > start - lead_in_ns {
        // Moving the frame later by `late` lengthens the gap before it and
        // shortens the one after it: both must stay sync periods (a lead-in
        // pulse moves with its frame).
        let late = ready - (start - lead_in_ns);
        let fits_after = sync_ns >= sync_min_ns + late;
        let fits_before = lead_in_ns > 0 || p.prev_sync_ns + late <= sync_max_ns;
        if fits_after && fits_before {
            add(&stats.late_frames, 1);
            start += late;
        } else {
            // Skip to the first frame whose lead-in can still be decided in
            // time (the gap it follows is too long to be a sync).
            let missed = (ready + lead + LEAD_IN_NS - start).div_ceil(frame_ns);
            add(&stats.overruns, missed);
            p.next_start = Some(start + missed * frame_ns);
            p.prev_sync_ns = 0;
            return None;
        }
    }
    Some((start, lead_in_ns))
}

/// Follow: the frame's start and lead-in. A fresh command's frame starts as
/// soon as the loop can write it, but not before the shortest sync after the
/// previous frame's last pulse; a repeat starts at the longest sync. A frame
/// decided too late for that moves later while the sync before it stays
/// under [`FOLLOW_SYNC_CEILING_US`] (counted as a late frame when it was
/// decided at its planned time, the earliest start or the longest sync, but
/// late); past that, it gets the lead-in pulse a frame after silence gets
/// (counted as an overrun).
fn place_follow(
    p: &Progress,
    model: &FrameModel,
    stats: &Stats,
    fresh_arrived: bool,
    at_earliest: bool,
) -> Option<(u64, u64)> {
    let (sync_min_ns, sync_max_ns) = model.follow_sync_ns();
    let ready = clock::now_ns() + READY_NS;
    let Some(last) = p.last_pulse else {
        return Some((ready + LEAD_IN_NS, LEAD_IN_NS));
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
    Some((ready + LEAD_IN_NS, LEAD_IN_NS))
}

/// Waits for `due` and writes every lane's edge due then: lines one by one,
/// each bank's lines in one call. Each edge's error is measured just before
/// its own write. Returns without writing when one of `fds` became readable
/// during the sleep (the loop then decides for the lane woken first).
fn emit_due(
    due: u64,
    lanes: &mut [Lane],
    prog: &mut [Progress],
    banks: &mut [&mut dyn Bank],
    timer: &mut EdgeTimer,
    fds: &[RawFd],
) -> Option<Readable> {
    let w = match timer.wait_or_readable(due, fds) {
        Wake::Due(w) => w,
        Wake::Readable(r) => return Some(r),
    };
    // The lanes with an edge due now (bit i: lane i).
    let mut now_due = 0u32;
    for (i, p) in prog.iter().enumerate() {
        if p.frame.is_some_and(|f| f.due() == due) {
            now_due |= 1 << i;
        }
    }
    let is_due = |i: usize| now_due & (1 << i) != 0;
    let mut bank_mask = [0u64; MAX_LANES];
    let mut bank_levels = [0u64; MAX_LANES];
    // Lanes whose output took the whole frame at this edge.
    let mut whole = 0u32;
    let mut before = w.now_ns;
    for (i, (lane, p)) in lanes.iter_mut().zip(prog.iter()).enumerate() {
        let Some(f) = p.frame.filter(|_| is_due(i)) else {
            continue;
        };
        let level = f.edge().1;
        match &mut lane.sink {
            Sink::Line(out) if out.whole_frames() => {
                // The frame's first edge: every edge goes in one transfer,
                // timed by the output's clock from here.
                let mut edges = [FrameEdge {
                    at_ns: 0,
                    level: Level::Low,
                }; MAX_EDGES + 2];
                let n = f.len() - f.next;
                for (k, e) in edges.iter_mut().enumerate().take(n) {
                    let (at, level) = f.edge_at(f.next + k);
                    *e = FrameEdge {
                        at_ns: at - due,
                        level,
                    };
                }
                if out.write_frame(&edges[..n]).is_err() {
                    add(&lane.stats.write_errors, 1);
                }
                let written = clock::now_ns();
                // The frame's start error and how long the transfer took:
                // what can be known of an output timed by its own clock.
                record(lane, before - due, written - before);
                add(&lane.stats.edges, n as u64 - 1);
                whole |= 1 << i;
                before = written;
            }
            Sink::Line(out) => {
                let edge = TraceEdge {
                    scheduled_ns: due,
                    actual_ns: before,
                    level,
                };
                if out.write(&edge).is_err() {
                    add(&lane.stats.write_errors, 1);
                }
                let written = clock::now_ns();
                record(lane, before - due, written - before);
                before = written;
            }
            Sink::Bank { bank, bit } => {
                bank_mask[*bank] |= 1 << *bit;
                bank_levels[*bank] |= (level == Level::High) as u64 * (1 << *bit);
            }
        }
    }
    for (b, bank) in banks.iter_mut().enumerate() {
        if bank_mask[b] == 0 {
            continue;
        }
        let failed = bank.write(due, bank_mask[b], bank_levels[b]).is_err();
        let written = clock::now_ns();
        for (i, lane) in lanes.iter_mut().enumerate() {
            let Sink::Bank { bank, .. } = lane.sink else {
                continue;
            };
            if bank != b || !is_due(i) {
                continue;
            }
            if failed {
                add(&lane.stats.write_errors, 1);
            }
            record(lane, before - due, written - before);
        }
        before = written;
    }
    // One wait served them all: its figures go to the first lane.
    let first = now_due.trailing_zeros() as usize;
    if let Some(late) = w.woke_late_ns {
        lanes[first].meter.wake(late);
    }
    if let Some(f) = prog[first].frame.as_mut() {
        f.spun += w.spun_ns;
    }
    for (i, (lane, p)) in lanes.iter_mut().zip(prog.iter_mut()).enumerate() {
        let Some(f) = p.frame.as_mut().filter(|_| is_due(i)) else {
            continue;
        };
        f.next = if whole & (1 << i) != 0 {
            f.len()
        } else {
            f.next + 1
        };
        if f.next == f.len() {
            finish_frame(lane, p, timer.margin_ns());
        }
    }
    None
}

/// Counts one written edge of `lane`.
fn record(lane: &mut Lane, err: u64, write_ns: u64) {
    lane.meter.edge(err, write_ns);
    lane.stats.max_edge_error_ns.fetch_max(err, Relaxed);
    if err > LATE_EDGE_NS {
        add(&lane.stats.late_edges, 1);
    }
    add(&lane.stats.edges, 1);
}

/// Closes the lane's frame after its last edge: counters and frame log.
fn finish_frame(lane: &mut Lane, p: &mut Progress, margin_ns: u64) {
    let Some(f) = p.frame.take() else {
        return;
    };
    let (model, stats) = (lane.model, lane.stats);
    lane.meter.frame(f.spun);
    add(&stats.spin_ns, f.spun);
    add(&stats.frames, 1);
    stats.margin_ns.store(margin_ns, Relaxed);
    p.frame_no += 1;
    if let Some(log) = lane.log.as_deref_mut() {
        let mut values_ns = [0; MAX_CHANNELS];
        for (i, v) in values_ns.iter_mut().enumerate().take(model.channels()) {
            let given = f
                .channels
                .as_ns()
                .get(i)
                .copied()
                .unwrap_or(model.default_ns(i));
            *v = model.clamp(i, given).0;
        }
        log.push(Record::Frame {
            frame: p.frame_no,
            start_mono_ns: f.start,
            start_real_ns: f.start_real_ns,
            state: f.state,
            timing: model.timing(),
            command: f.command,
            channels: model.channels() as u8,
            values_ns,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::OutputError;
    use ppm_shared::config::Config;
    use ppm_shared::decode::{decode, DecoderLimits};
    use ppm_shared::frame::Level;
    use ppm_shared::protocol::parse;
    use ppm_shared::receiver::{decode_as, Receiver};
    use std::sync::Arc;

    /// Records edges in memory (allocation in a test backend is fine).
    #[derive(Default)]
    struct Recorder(Vec<TraceEdge>);

    impl Output for Recorder {
        fn write(&mut self, edge: &TraceEdge) -> Result<(), OutputError> {
            self.0.push(*edge);
            Ok(())
        }
        fn park(&mut self, _: Level) -> Result<(), OutputError> {
            Ok(())
        }
    }

    /// Hands out one command (stamped now) on the first poll, then `after`
    /// more frames' worth of polls with nothing, then asks the loop to stop.
    struct Script {
        cmd: Option<CommandSample>,
        polls_left: u32,
        stop: Arc<AtomicBool>,
    }

    impl CommandSource for Script {
        fn newest(&mut self) -> Option<CommandSample> {
            if self.polls_left == 0 {
                self.stop.store(true, Relaxed);
            } else {
                self.polls_left -= 1;
            }
            self.cmd.take().map(|mut c| {
                c.recv_mono_ns = clock::now_ns();
                c
            })
        }
    }

    /// Runs the loop on the default model into `out`: `cmd` (if any) is
    /// handed out on the first of `polls` decisions, then the loop stops.
    fn run_on(
        cmd: Option<&[u8]>,
        polls: u32,
        margin_ns: u64,
        failsafe_after_ns: u64,
        failsafe_action: FailsafeAction,
        out: &mut dyn Output,
    ) -> Stats {
        let model = Config::default().validate().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let mut src = Script {
            cmd: cmd.map(|c| {
                CommandSample::new(&parse(c, &model).unwrap(), model.fingerprint(), 1, 0, 0)
            }),
            polls_left: polls,
            stop: stop.clone(),
        };
        let cfg = EmitterConfig {
            margin: Margin::Fixed(margin_ns),
            failsafe_after_ns,
            failsafe_action,
            startup: FailsafeAction::Silence,
        };
        let stats = Stats::default();
        let (mut meter, _reader) = crate::meter::meter(1_000_000_000);
        run(&model, &cfg, &mut src, out, &stop, &stats, &mut meter, None);
        stats
    }

    fn run_script(action: FailsafeAction, after_ms: u64, polls: u32) -> (Vec<TraceEdge>, Stats) {
        let mut out = Recorder::default();
        let cmd = b"[1100, 1200, 1300, 1400]";
        let stats = run_on(
            Some(cmd),
            polls,
            100_000,
            after_ms * 1_000_000,
            action,
            &mut out,
        );
        (out.0, stats)
    }

    /// An output that takes frames whole (as the SPI output does): each
    /// call's edges.
    #[derive(Default)]
    struct WholeFrames {
        frames: Vec<Vec<FrameEdge>>,
        single_writes: usize,
    }

    impl Output for WholeFrames {
        fn write(&mut self, _: &TraceEdge) -> Result<(), OutputError> {
            self.single_writes += 1;
            Ok(())
        }
        fn park(&mut self, _: Level) -> Result<(), OutputError> {
            Ok(())
        }
        fn whole_frames(&self) -> bool {
            true
        }
        fn write_frame(&mut self, edges: &[FrameEdge]) -> Result<(), OutputError> {
            self.frames.push(edges.to_vec());
            Ok(())
        }
    }

    /// A whole-frame output gets each frame once, at its first edge, with
    /// every edge relative to it (a lead-in pulse, after silence or an
    /// overrun, included), and no single edge; the counters count every edge.
    #[test]
    fn whole_frame_outputs_get_each_frame_in_one_call() {
        let mut out = WholeFrames::default();
        let stats = run_on(
            Some(b"[1100, 1200, 1300, 1400]"),
            12,
            100_000,
            100_000_000,
            FailsafeAction::Silence,
            &mut out,
        );
        assert_eq!(out.single_writes, 0);
        let n = stats.frames.load(Relaxed);
        assert!(n >= 2, "{n} frames");
        assert_eq!(out.frames.len() as u64, n);
        let edges: usize = out.frames.iter().map(Vec::len).sum();
        assert_eq!(
            stats.edges.load(Relaxed),
            edges as u64,
            "every edge counted"
        );
        let want = [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500];
        for (k, edges) in out.frames.iter().enumerate() {
            assert_eq!(edges[0].at_ns, 0);
            assert_eq!(edges[0].level, Level::High);
            // 18 edges of 9 pulses, and 2 more for a lead-in pulse (the first
            // frame's, and any after an overrun).
            let lead = edges.len() - 18;
            assert!(lead == 0 || lead == 2, "frame {k}: {} edges", edges.len());
            assert!(k > 0 || lead == 2, "the first frame has its lead-in pulse");
            if lead == 2 {
                assert_eq!(
                    edges[2].at_ns, LEAD_IN_NS,
                    "frame {k}: the lead-in pulse first"
                );
            }
            // Pulse starts in the frame give the channels exactly.
            let starts: Vec<u64> = edges[lead..]
                .iter()
                .filter(|e| e.level == Level::High)
                .map(|e| e.at_ns)
                .collect();
            let got: Vec<u64> = starts.windows(2).map(|w| (w[1] - w[0]) / 1_000).collect();
            assert_eq!(got, want, "frame {k}");
        }
    }

    #[test]
    fn frames_carry_the_command_then_fall_silent() {
        let (edges, stats) = run_script(FailsafeAction::Silence, 100, 12);
        let frames = decode(
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
            DecoderLimits::default(),
        );
        assert!(!frames.is_empty());
        for f in &frames {
            assert_eq!(
                f.channels_us(),
                [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500]
            );
        }
        // 100 ms at 22.5 ms per frame: 5 frames, then silence.
        let n = stats.frames.load(Relaxed);
        assert!((4..=6).contains(&n), "{n} frames");
        assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
        assert_eq!(stats.margin_ns.load(Relaxed), 100_000, "the fixed margin");
        // Every frame's 18 edges, and the lead-in pulse before the first.
        assert_eq!(edges.len() as u64, n * 18 + 2);
        assert_eq!(edges[2].scheduled_ns - edges[0].scheduled_ns, LEAD_IN_NS);
        // So the decoder reads the first frame too.
        assert_eq!(frames[0].start_ns, edges[2].scheduled_ns);
        // Frames sit on one grid, but for those moved later as a whole.
        let starts: Vec<u64> = edges[2..]
            .iter()
            .step_by(18)
            .map(|e| e.scheduled_ns)
            .collect();
        let off_grid = starts
            .iter()
            .filter(|&&s| !(s - starts[0]).is_multiple_of(22_500_000))
            .count() as u64;
        assert!(
            off_grid <= stats.late_frames.load(Relaxed),
            "{off_grid} frames off the grid"
        );
        for e in &edges {
            assert!(e.actual_ns >= e.scheduled_ns, "never early");
        }
    }

    #[test]
    fn a_silent_line_reports_its_margin() {
        let mut out = Recorder::default();
        let stats = run_on(
            None,
            3,
            70_000,
            100_000_000,
            FailsafeAction::Silence,
            &mut out,
        );
        assert!(out.0.is_empty());
        assert_eq!(stats.frames.load(Relaxed), 0);
        assert_eq!(stats.margin_ns.load(Relaxed), 70_000);
    }

    /// Records edges, and stalls the loop once, in the `stall_after`th write.
    struct Stalling {
        rec: Recorder,
        stall_after: usize,
        stall: std::time::Duration,
    }

    impl Output for Stalling {
        fn write(&mut self, edge: &TraceEdge) -> Result<(), OutputError> {
            self.rec.write(edge)?;
            if self.rec.0.len() == self.stall_after {
                std::thread::sleep(self.stall);
            }
            Ok(())
        }
        fn park(&mut self, _: Level) -> Result<(), OutputError> {
            Ok(())
        }
    }

    #[test]
    fn the_frame_after_skipped_ones_is_read_too() {
        // The third frame's last edge (after the first lead-in pulse) stalls
        // the loop for 50 ms: the next frame's start passes, by more than its
        // sync can absorb, and frames are skipped.
        let stall_after = 2 + 3 * 18;
        let mut out = Stalling {
            rec: Recorder::default(),
            stall_after,
            stall: std::time::Duration::from_millis(50),
        };
        let cmd = b"[1100, 1200, 1300, 1400]";
        let stats = run_on(
            Some(cmd),
            8,
            100_000,
            10_000_000_000,
            FailsafeAction::Silence,
            &mut out,
        );
        let edges = out.rec.0;
        // 50 ms after a frame's last pulse (11.3 ms in) is at least 38.8 ms
        // past the next start; the frame after must also fit its lead-in.
        assert!(stats.overruns.load(Relaxed) >= 2, "{stats:?}");
        let gap = edges[stall_after].scheduled_ns - edges[stall_after - 1].scheduled_ns;
        assert!(gap > 40_000_000, "the stall left a {gap} ns gap");
        // A lone pulse 5 ms before the next frame, as after silence...
        let lead_in = &edges[stall_after..stall_after + 3];
        assert_eq!(
            lead_in[2].scheduled_ns - lead_in[0].scheduled_ns,
            LEAD_IN_NS
        );
        // ...so a transmitter reads every frame sent, that one included.
        let frames = decode(
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
            DecoderLimits::default(),
        );
        let n = stats.frames.load(Relaxed);
        // Two lead-in pulses at least: the first frame's and this one's (a
        // further stall on a loaded machine may add more).
        assert!(edges.len() as u64 >= n * 18 + 4, "{} edges", edges.len());
        assert_eq!(frames.len() as u64, n, "{frames:?}");
        assert!(frames.iter().any(|f| f.start_ns == lead_in[2].scheduled_ns));
        for f in &frames {
            assert_eq!(
                f.channels_us(),
                [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500]
            );
        }
    }

    #[test]
    fn default_action_emits_defaults_after_the_command() {
        let (edges, stats) = run_script(FailsafeAction::Default, 50, 30);
        let frames = decode(
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
            DecoderLimits::default(),
        );
        let last = frames.last().unwrap();
        assert_eq!(
            last.channels_us(),
            [1500, 1500, 1000, 1500, 1500, 1500, 1500, 1500]
        );
        assert_eq!(frames[0].channels_us()[0], 1100);
        assert_eq!(stats.state(), LineState::Silent, "stopped");
        assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
    }

    #[test]
    fn hold_repeats_the_last_command() {
        let (edges, _) = run_script(FailsafeAction::Hold, 30, 20);
        let frames = decode(
            edges.iter().map(|e| (e.scheduled_ns, e.level)),
            Level::High,
            DecoderLimits::default(),
        );
        assert!(frames.len() >= 10);
        assert!(frames
            .iter()
            .all(|f| f.channels_us()[..4] == [1100, 1200, 1300, 1400]));
    }

    /// Records bank writes: (scheduled, mask, levels).
    #[derive(Default)]
    struct BankRecorder(Vec<(u64, u64, u64)>);

    impl Bank for BankRecorder {
        fn write(&mut self, due: u64, mask: u64, levels: u64) -> Result<(), OutputError> {
            self.0.push((due, mask, levels));
            Ok(())
        }
        fn park(&mut self, _: u32, _: Level) -> Result<(), OutputError> {
            Ok(())
        }
    }

    fn repeat(
        cmd: &[u8],
        model: &FrameModel,
        frames: u64,
        stop: &Arc<AtomicBool>,
    ) -> crate::source::RepeatSource {
        crate::source::RepeatSource {
            sample: CommandSample::new(&parse(cmd, model).unwrap(), model.fingerprint(), 1, 0, 0),
            frames,
            stop: stop.clone(),
        }
    }

    fn lane_cfg() -> EmitterConfig {
        EmitterConfig {
            margin: Margin::Fixed(100_000),
            failsafe_after_ns: 100_000_000,
            failsafe_action: FailsafeAction::Silence,
            startup: FailsafeAction::Silence,
        }
    }

    fn channels_of(edges: &[(u64, Level)]) -> Vec<Vec<u64>> {
        decode(edges.iter().copied(), Level::High, DecoderLimits::default())
            .iter()
            .map(|f| f.channels_us().to_vec())
            .collect()
    }

    /// Where each frame a transmitter reads starts.
    fn starts_of(edges: &[(u64, Level)]) -> Vec<u64> {
        decode(edges.iter().copied(), Level::High, DecoderLimits::default())
            .iter()
            .map(|f| f.start_ns)
            .collect()
    }

    /// Checks a lane wrote its frames' edges plus a lead-in pulse before the
    /// first frame and at most one after each overrun (a stall of this
    /// shared machine can cause one).
    fn assert_edges_add_up(edges: usize, stats: &Stats, per_frame: u64) {
        let frames = stats.frames.load(Relaxed);
        let overruns = stats.overruns.load(Relaxed);
        let extra = edges as u64 - frames * per_frame;
        assert!(
            extra.is_multiple_of(2) && (2..=2 + 2 * overruns).contains(&extra),
            "{edges} edges for {frames} frames of {per_frame} and {overruns} overruns"
        );
    }

    #[test]
    fn align_finds_the_next_grid_point() {
        assert_eq!(align(1_000, None, 300), 1_000);
        assert_eq!(align(1_000, Some(1_000), 300), 1_000);
        assert_eq!(align(1_000, Some(100), 300), 1_000);
        assert_eq!(align(1_001, Some(100), 300), 1_300);
        assert_eq!(align(1_000, Some(1_050), 300), 1_050);
        assert_eq!(align(1_000, Some(1_900), 300), 1_000);
        assert_eq!(align(1_000, Some(1_901), 300), 1_001);
    }

    #[test]
    fn two_lanes_emit_their_own_frames_from_one_loop() {
        let a = Config::default().validate().unwrap();
        let mut cb = Config::default();
        cb.ppm.channels = 6;
        cb.ppm.order = "TAER".into();
        cb.ppm.frame_us = 20_000.0;
        let b = cb.validate().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let mut src_a = repeat(b"[1100, 1200, 1300, 1400]", &a, 20, &stop);
        let mut src_b = repeat(b"[1900, 1800, 1700, 1600, 1500, 1000]", &b, 1_000, &stop);
        let (mut out_a, mut out_b) = (Recorder::default(), Recorder::default());
        let (stats_a, stats_b) = (Stats::default(), Stats::default());
        let (mut meter_a, _ra) = crate::meter::meter(1_000_000_000);
        let (mut meter_b, _rb) = crate::meter::meter(1_000_000_000);
        let mut lanes = [
            Lane {
                model: &a,
                cfg: lane_cfg(),
                source: &mut src_a,
                sink: Sink::Line(&mut out_a),
                stats: &stats_a,
                meter: &mut meter_a,
                log: None,
            },
            Lane {
                model: &b,
                cfg: lane_cfg(),
                source: &mut src_b,
                sink: Sink::Line(&mut out_b),
                stats: &stats_b,
                meter: &mut meter_b,
                log: None,
            },
        ];
        run_lanes(&mut lanes, &mut [], &stop);
        let fa = channels_of(
            &out_a
                .0
                .iter()
                .map(|e| (e.scheduled_ns, e.level))
                .collect::<Vec<_>>(),
        );
        let fb = channels_of(
            &out_b
                .0
                .iter()
                .map(|e| (e.scheduled_ns, e.level))
                .collect::<Vec<_>>(),
        );
        assert!(fa.len() >= 15, "{} frames on a", fa.len());
        assert!(fb.len() >= 15, "{} frames on b", fb.len());
        assert!(
            fa.iter()
                .all(|f| f[..] == [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500]),
            "{fa:?}"
        );
        assert!(
            fb.iter()
                .all(|f| f[..] == [1900, 1800, 1700, 1600, 1500, 1000]),
            "{fb:?}"
        );
        for (out, stats, frame_ns, per_frame) in [
            (&out_a, &stats_a, 22_500_000, 18),
            (&out_b, &stats_b, 20_000_000, 14),
        ] {
            assert_eq!(out.0.len() as u64, stats.edges.load(Relaxed));
            assert_edges_add_up(out.0.len(), stats, per_frame);
            assert!(
                out.0.iter().all(|e| e.actual_ns >= e.scheduled_ns),
                "never early"
            );
            let edges: Vec<(u64, Level)> =
                out.0.iter().map(|e| (e.scheduled_ns, e.level)).collect();
            let starts = starts_of(&edges);
            assert_eq!(starts.len() as u64, stats.frames.load(Relaxed));
            let off_grid = starts
                .iter()
                .filter(|&&s| !(s - starts[0]).is_multiple_of(frame_ns))
                .count() as u64;
            assert!(
                off_grid <= stats.late_frames.load(Relaxed),
                "{off_grid} frames off the grid"
            );
        }
    }

    #[test]
    fn a_bank_writes_simultaneous_edges_in_one_call() {
        let model = Config::default().validate().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        // Same values on both: every edge coincides. Different values on the
        // third: only its frame starts coincide (its grid joins the others').
        let mut s0 = repeat(b"[1100, 1200, 1300, 1400]", &model, 20, &stop);
        let mut s1 = repeat(b"[1100, 1200, 1300, 1400]", &model, 1_000, &stop);
        let mut s2 = repeat(b"[2000, 1000, 2000, 1000]", &model, 1_000, &stop);
        let mut bank = BankRecorder::default();
        let stats: [Stats; 3] = Default::default();
        let (mut m0, _r0) = crate::meter::meter(1_000_000_000);
        let (mut m1, _r1) = crate::meter::meter(1_000_000_000);
        let (mut m2, _r2) = crate::meter::meter(1_000_000_000);
        let mut lanes = [
            Lane {
                model: &model,
                cfg: lane_cfg(),
                source: &mut s0,
                sink: Sink::Bank { bank: 0, bit: 0 },
                stats: &stats[0],
                meter: &mut m0,
                log: None,
            },
            Lane {
                model: &model,
                cfg: lane_cfg(),
                source: &mut s1,
                sink: Sink::Bank { bank: 0, bit: 1 },
                stats: &stats[1],
                meter: &mut m1,
                log: None,
            },
            Lane {
                model: &model,
                cfg: lane_cfg(),
                source: &mut s2,
                sink: Sink::Bank { bank: 0, bit: 2 },
                stats: &stats[2],
                meter: &mut m2,
                log: None,
            },
        ];
        {
            let mut banks: [&mut dyn Bank; 1] = [&mut bank];
            run_lanes(&mut lanes, &mut banks, &stop);
        }
        let writes = &bank.0;
        // Each line's waveform, decoded on its own.
        let line = |bit: u32| -> Vec<(u64, Level)> {
            writes
                .iter()
                .filter(|(_, m, _)| m & (1 << bit) != 0)
                .map(|&(t, _, l)| (t, Level::from_bit(l & (1 << bit) != 0)))
                .collect()
        };
        let (l0, l1, l2) = (
            channels_of(&line(0)),
            channels_of(&line(1)),
            channels_of(&line(2)),
        );
        assert!(l0.len() >= 15, "{l0:?}");
        assert!(l0
            .iter()
            .chain(&l1)
            .all(|f| f[..4] == [1100, 1200, 1300, 1400]));
        // The others may join line 0's grid a frame after its first (when
        // their lead-in no longer fits before it), and the stop comes from
        // line 0's source: they may miss its last frame.
        let late = |i: usize| stats[i].late_frames.load(Relaxed) as usize;
        let skipped = |i: usize| stats[i].overruns.load(Relaxed) as usize;
        for (i, s) in stats.iter().enumerate() {
            assert_edges_add_up(line(i as u32).len(), s, 18);
        }
        assert!(
            l1.len() + 2 + skipped(1) >= l0.len() && l2.len() + 2 + skipped(2) >= l0.len(),
            "{} {} {}: {:?}",
            l0.len(),
            l1.len(),
            l2.len(),
            &writes[..12]
        );
        assert!(
            l2.iter().all(|f| f[..4] == [2000, 1000, 2000, 1000]),
            "{l2:?}"
        );
        // Never two writes for one time, and the lines 0 and 1 always together.
        for w in writes.windows(2) {
            assert!(w[0].0 < w[1].0, "two writes for one time: {w:?}");
        }
        // A frame whose decision came late is moved off the grid (counted),
        // one after skipped frames (counted) gets a lead-in of its own; every
        // other edge of lines 0 and 1 is written in one call.
        let trouble = late(0) + late(1) + skipped(0) + skipped(1);
        let only = |bit: u64| writes.iter().filter(|(_, m, _)| m & 0b11 == bit).count();
        assert!(
            only(0b10) <= 2 + 20 * trouble,
            "line 1 alone: {} edges",
            only(0b10)
        );
        assert!(
            only(0b01) <= 2 + 20 * (trouble + 2),
            "line 0 alone: {} edges",
            only(0b01)
        );
        // Frame starts of line 2 coincide with those of line 0 while both run.
        let starts0 = starts_of(&line(0));
        let joined = starts0
            .iter()
            .filter(|t| writes.iter().any(|(w, m, _)| w == *t && m & 0b111 == 0b111))
            .count();
        assert!(
            joined + 3 + late(0) + late(2) + skipped(0) + skipped(2) >= starts0.len(),
            "{joined} of {} frame starts shared",
            starts0.len()
        );
        for s in &stats {
            assert_eq!(s.write_errors.load(Relaxed), 0);
        }
    }

    /// A follow-timing model: the defaults with `timing = "follow"`.
    fn follow_model(extra: &str) -> FrameModel {
        Config::parse(&format!("[ppm]\ntiming = 'follow'\n{extra}"))
            .unwrap()
            .validate()
            .unwrap()
    }

    /// Commands made available at set times, each followed by a wake-up on a
    /// socket (as udp-ingress's notification); records when each was there.
    struct Paced {
        slot: Arc<std::sync::Mutex<Option<CommandSample>>>,
        rx: std::os::unix::net::UnixDatagram,
        with_fd: bool,
        /// Hands out this fd number instead of its socket's.
        fake_fd: Option<std::os::fd::RawFd>,
        /// Clearing the wake-ups fails.
        broken_clear: bool,
        /// Per command: when it was surely available (its slot set), its
        /// first value in us, and its stamp (taken before the slot was set:
        /// it was not available earlier). The thread may be preempted
        /// between the two, for milliseconds on a loaded or emulated machine.
        made: Arc<std::sync::Mutex<Vec<(u64, u32, u64)>>>,
        feeder: Option<std::thread::JoinHandle<()>>,
        /// Set by the feeder `tail_ms` after the last command.
        stop: Arc<AtomicBool>,
    }

    impl Paced {
        /// Makes `count` commands `every_ms` apart (first value 1100 + 10 k
        /// us), then stops the loop `tail_ms` after the last.
        fn start(model: &FrameModel, count: u32, every_ms: u64, tail_ms: u64) -> Paced {
            let stop = Arc::new(AtomicBool::new(false));
            let (tx, rx) = std::os::unix::net::UnixDatagram::pair().unwrap();
            rx.set_nonblocking(true).unwrap();
            let slot = Arc::new(std::sync::Mutex::new(None));
            let made = Arc::new(std::sync::Mutex::new(Vec::new()));
            let feeder = {
                let (slot, made, stop, model) =
                    (slot.clone(), made.clone(), stop.clone(), model.clone());
                std::thread::spawn(move || {
                    let t0 = clock::now_ns() + 20_000_000;
                    for k in 0..count {
                        clock::sleep_until(t0 + k as u64 * every_ms * 1_000_000);
                        let v = 1_100 + 10 * k;
                        let cmd = parse(format!("[{v}, 1900]").as_bytes(), &model).unwrap();
                        let mut sample =
                            CommandSample::new(&cmd, model.fingerprint(), k as u64 + 1, 0, 0);
                        let stamp = clock::now_ns();
                        sample.recv_mono_ns = stamp;
                        *slot.lock().unwrap() = Some(sample);
                        made.lock().unwrap().push((clock::now_ns(), v, stamp));
                        let _ = tx.send(&[1]);
                    }
                    std::thread::sleep(std::time::Duration::from_millis(tail_ms));
                    stop.store(true, Relaxed);
                })
            };
            Paced {
                slot,
                rx,
                with_fd: true,
                fake_fd: None,
                broken_clear: false,
                made,
                feeder: Some(feeder),
                stop,
            }
        }

        fn made(&mut self) -> Vec<(u64, u32, u64)> {
            if let Some(f) = self.feeder.take() {
                f.join().unwrap();
            }
            self.made.lock().unwrap().clone()
        }
    }

    impl CommandSource for Paced {
        fn newest(&mut self) -> Option<CommandSample> {
            self.slot.lock().unwrap().take()
        }
        fn wake_fd(&self) -> Option<std::os::fd::RawFd> {
            use std::os::fd::AsRawFd;
            self.with_fd
                .then(|| self.fake_fd.unwrap_or(self.rx.as_raw_fd()))
        }
        fn clear_wake(&mut self) -> bool {
            if self.broken_clear {
                // Leaves the wake-up pending: the fd stays readable.
                return false;
            }
            let mut b = [0u8; 16];
            while self.rx.recv(&mut b).is_ok() {}
            true
        }
    }

    /// A lane of `model` into `out` from `source`.
    fn follow_lane<'a>(
        model: &'a FrameModel,
        source: &'a mut dyn CommandSource,
        out: &'a mut Recorder,
        stats: &'a Stats,
        meter: &'a mut Meter,
        action: FailsafeAction,
    ) -> Lane<'a> {
        Lane {
            model,
            cfg: EmitterConfig {
                failsafe_action: action,
                ..lane_cfg()
            },
            source,
            sink: Sink::Line(out),
            stats,
            meter,
            log: None,
        }
    }

    /// A frame as sent: its first edge, its last pulse and its first value.
    #[derive(Debug)]
    struct Sent {
        start: u64,
        last_pulse: u64,
        first_us: u32,
    }

    /// The frames in a recorded single-lane waveform of `channels` channels,
    /// from the scheduled edges, lead-in pulses left out.
    fn sent_frames(edges: &[TraceEdge], channels: usize) -> Vec<Sent> {
        let leading: Vec<u64> = edges
            .iter()
            .filter(|e| e.level == Level::High)
            .map(|e| e.scheduled_ns)
            .collect();
        let per = channels + 1;
        let mut frames = Vec::new();
        let mut i = 0;
        while i + per <= leading.len() {
            // A lead-in pulse is alone: the next leading edge is a sync away.
            if leading
                .get(i + 1)
                .is_some_and(|&n| n - leading[i] >= 2_500_000)
            {
                i += 1;
                continue;
            }
            frames.push(Sent {
                start: leading[i],
                last_pulse: leading[i + per - 1],
                first_us: ((leading[i + 1] - leading[i] + 500) / 1_000) as u32,
            });
            i += per;
        }
        frames
    }

    /// Checks that every receiver hands on every frame sent (but those it
    /// reads while it locks on), with its values to the microsecond.
    fn assert_read_by_every_receiver(edges: &[TraceEdge], frames: &[Sent]) {
        for r in Receiver::ALL {
            let (read, _) = decode_as(
                r,
                edges.iter().map(|e| (e.scheduled_ns, e.level)),
                Level::High,
            );
            // A trainer input uses channels as they come: the last frame
            // too, which no sync closes. The others hand a frame on at the
            // sync after it: not the last one.
            let trainer = matches!(r, Receiver::EdgeTx | Receiver::OpenTx);
            let read: Vec<_> = read.iter().filter(|f| f.complete || trainer).collect();
            let closed = frames.len() - !trainer as usize;
            let want = closed.saturating_sub(r.warmup_frames());
            assert_eq!(
                read.len(),
                want,
                "{r:?} read {} of {} frames",
                read.len(),
                frames.len()
            );
            for f in read {
                let sent = frames
                    .iter()
                    .find(|s| s.start == f.start_ns)
                    .expect("a frame sent");
                assert_eq!(f.channels_us()[0], sent.first_us as u64, "{r:?}");
                assert_eq!(f.channels_us()[1], 1_900, "{r:?}");
            }
        }
    }

    /// Checks what follow timing promises about a single lane's frames, on
    /// the scheduled edges: every receiver reads every frame;
    /// the sync before a frame is within the follow limits (or the frame had
    /// a lead-in); a frame that repeats its predecessor's command comes at the
    /// longest sync unless counted late; and each frame carries the newest
    /// command there was when the loop decided it (no later than its start
    /// less READY_NS, no earlier than its start less DECIDE_NS, after a
    /// lead-in no earlier than that less LEAD_IN_NS). `alone`: the lane is
    /// the loop's only one. With another lane, a decision whose time falls
    /// on that lane's edge is made earlier, before the edge, so when it was
    /// made is not known here: the newest-command and late-count checks,
    /// which need it, are left out.
    fn check_follow(
        edges: &[TraceEdge],
        model: &FrameModel,
        made: &[(u64, u32, u64)],
        stats: &Stats,
        alone: bool,
    ) -> Vec<Sent> {
        let frames = sent_frames(edges, model.channels());
        assert_eq!(frames.len() as u64, stats.frames.load(Relaxed));
        assert_read_by_every_receiver(edges, &frames);
        let (min, max) = model.follow_sync_ns();
        let mut late = 0;
        for (i, f) in frames.iter().enumerate() {
            let prev = i.checked_sub(1).map(|j| &frames[j]);
            let sync = prev.map(|p| f.start - p.last_pulse);
            let lead_in = sync.is_none_or(|s| s >= us_to_ns(FOLLOW_SYNC_CEILING_US));
            if let (Some(s), Some(p)) = (sync.filter(|_| !lead_in), prev) {
                assert!(s >= min, "frame {i}: sync {s} ns");
                if p.first_us == f.first_us {
                    // A repeat: at the longest sync, or late (counted).
                    late += (s != max) as u64;
                    assert!(s >= max, "frame {i}: repeat after {s} ns");
                } else {
                    // A command there before the look at the earliest start
                    // starts its frame then, or late (counted).
                    let waiting = made
                        .iter()
                        .find(|m| m.1 == f.first_us)
                        .is_some_and(|m| m.0 < p.last_pulse + min - DECIDE_NS);
                    late += (waiting && s != min) as u64;
                }
            }
            // Commands by index: the carried one was there at the decision,
            // and is not older than the newest there before it.
            let index_at = |t: u64| made.iter().rposition(|m| m.0 <= t);
            let carried = made
                .iter()
                .position(|m| m.1 == f.first_us)
                .expect("a command's value");
            assert!(
                made[carried].2 <= f.start - READY_NS,
                "frame {i} carries a command from after its decision"
            );
            if alone && !lead_in {
                assert!(
                    index_at(f.start - DECIDE_NS).is_none_or(|a| carried >= a),
                    "frame {i} at {} carries command {carried}, not the newest",
                    f.start
                );
            }
        }
        assert!(
            !alone || late <= stats.late_frames.load(Relaxed),
            "{late} late repeats"
        );
        frames
    }

    /// Runs one follow lane fed by `source` until it stops the loop.
    fn run_follow(
        model: &FrameModel,
        source: &mut Paced,
        action: FailsafeAction,
    ) -> (Vec<TraceEdge>, Stats, Vec<(u64, u32, u64)>) {
        let mut out = Recorder::default();
        let stats = Stats::default();
        let (mut meter, _r) = crate::meter::meter(1_000_000_000);
        let stop = source.stop.clone();
        {
            let mut lanes = [follow_lane(
                model, source, &mut out, &stats, &mut meter, action,
            )];
            run_lanes(&mut lanes, &mut [], &stop);
        }
        let made = source.made();
        (out.0, stats, made)
    }

    #[test]
    fn follow_frames_carry_each_command_as_it_comes() {
        let model = follow_model("");
        for with_fd in [true, false] {
            // 25 ms apart: each command finds the line free (a frame of these
            // values and its shortest sync take 15.5 ms; a repeat would come
            // only 28.5 ms after a frame's start).
            let mut src = Paced::start(&model, 16, 25, 160);
            src.with_fd = with_fd;
            let (edges, stats, made) = run_follow(&model, &mut src, FailsafeAction::Silence);
            let frames = check_follow(&edges, &model, &made, &stats, true);
            assert_eq!(stats.commands.load(Relaxed), 16, "with_fd {with_fd}");
            // Commands come slower than frames can go: they reach the line
            // (a stall of this shared machine may merge a few; how soon is
            // for ppm-bench to show).
            let carried: std::collections::BTreeSet<u32> =
                frames.iter().map(|f| f.first_us).collect();
            assert!(
                carried.len() >= 8,
                "with_fd {with_fd}: {} of 16 commands on the line, {stats:?}",
                carried.len()
            );
            assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
            assert_eq!(stats.wake_errors.load(Relaxed), 0);
            // The commands woke the loop (found the lane waiting), or it
            // looked for them every FOLLOW_POLL_NS.
            let wakes = stats.wakes.load(Relaxed);
            if with_fd {
                assert!(wakes >= 1, "{stats:?}");
            } else {
                assert_eq!(wakes, 0);
            }
        }
    }

    #[test]
    fn follow_repeats_at_the_longest_sync_then_acts_as_failsafe() {
        let model = follow_model("");
        for action in [FailsafeAction::Hold, FailsafeAction::Silence] {
            // 60 ms apart: a frame and its longest sync (28.5 ms) come and go
            // before the next command, and the next one, and so on.
            let mut src = Paced::start(&model, 5, 60, 250);
            let (edges, stats, made) = run_follow(&model, &mut src, action);
            let frames = check_follow(&edges, &model, &made, &stats, true);
            let repeats = frames
                .windows(2)
                .filter(|w| w[0].first_us == w[1].first_us)
                .count() as u64;
            assert!(repeats >= 5, "{action:?}: {repeats} repeats");
            assert_eq!(stats.repeats.load(Relaxed), repeats, "{action:?}");
            assert_eq!(stats.failsafe_entries.load(Relaxed), 1, "{action:?}");
            let last = frames.last().unwrap();
            assert_eq!(last.first_us, made.last().unwrap().1, "{action:?}");
            // Hold repeats the last command until the end (250 ms after it:
            // about 8 frames); silence stops 100 ms after it.
            let after: Vec<&Sent> = frames.iter().filter(|f| f.start > made[4].0).collect();
            match action {
                FailsafeAction::Hold => assert!(after.len() >= 6, "{after:?}"),
                _ => assert!((2..=5).contains(&after.len()), "{after:?}"),
            }
        }
    }

    #[test]
    fn a_broken_wake_fd_is_counted_and_the_lane_polls() {
        let model = follow_model("");
        for clear_fails in [false, true] {
            let mut src = Paced::start(&model, 8, 25, 40);
            if clear_fails {
                // The wake-ups cannot be cleared: the fd stays readable.
                src.broken_clear = true;
            } else {
                // No such file descriptor: every wait would end at once.
                src.fake_fd = Some(999_999);
            }
            let (edges, stats, made) = run_follow(&model, &mut src, FailsafeAction::Silence);
            check_follow(&edges, &model, &made, &stats, true);
            assert_eq!(stats.wake_errors.load(Relaxed), 1, "{clear_fails}");
            assert_eq!(stats.commands.load(Relaxed), 8);
        }
    }

    #[test]
    fn a_follow_lane_and_a_grid_lane_share_the_loop() {
        let grid = Config::default().validate().unwrap();
        let follow = follow_model("channels = 6\norder = 'TAER'");
        let mut src_f = Paced::start(&follow, 20, 23, 60);
        let stop = src_f.stop.clone();
        let mut src_g = repeat(b"[1100, 1200, 1300, 1400]", &grid, u64::MAX, &stop);
        let (mut out_g, mut out_f) = (Recorder::default(), Recorder::default());
        let (stats_g, stats_f) = (Stats::default(), Stats::default());
        let (mut meter_g, _rg) = crate::meter::meter(1_000_000_000);
        let (mut meter_f, _rf) = crate::meter::meter(1_000_000_000);
        {
            let mut lanes = [
                Lane {
                    model: &grid,
                    cfg: lane_cfg(),
                    source: &mut src_g,
                    sink: Sink::Line(&mut out_g),
                    stats: &stats_g,
                    meter: &mut meter_g,
                    log: None,
                },
                follow_lane(
                    &follow,
                    &mut src_f,
                    &mut out_f,
                    &stats_f,
                    &mut meter_f,
                    FailsafeAction::Silence,
                ),
            ];
            run_lanes(&mut lanes, &mut [], &stop);
        }
        let made = src_f.made();
        let frames = check_follow(&out_f.0, &follow, &made, &stats_f, false);
        assert!(frames.len() >= 10, "{} follow frames", frames.len());
        // The grid lane keeps its grid.
        let edges: Vec<(u64, Level)> = out_g.0.iter().map(|e| (e.scheduled_ns, e.level)).collect();
        let g = channels_of(&edges);
        assert!(g.len() >= 15, "{} grid frames", g.len());
        assert!(g
            .iter()
            .all(|f| f[..] == [1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500]));
        let starts = starts_of(&edges);
        let off_grid = starts
            .iter()
            .filter(|&&s| !(s - starts[0]).is_multiple_of(22_500_000))
            .count() as u64;
        assert!(off_grid <= stats_g.late_frames.load(Relaxed) + stats_g.overruns.load(Relaxed) * 3);
        assert_eq!(
            stats_g.repeats.load(Relaxed),
            0,
            "grid frames are not repeats"
        );
    }

    #[test]
    fn commands_faster_than_frames_take_the_newest_at_the_shortest_sync() {
        let model = follow_model("");
        // 7 ms apart: every frame (10.9..11.1 ms of channels, and 5 ms of
        // sync) finds a newer command waiting at its earliest start.
        let mut src = Paced::start(&model, 60, 7, 40);
        let (edges, stats, made) = run_follow(&model, &mut src, FailsafeAction::Silence);
        let frames = check_follow(&edges, &model, &made, &stats, true);
        let (min, _) = model.follow_sync_ns();
        // check_follow holds every frame to the rule (a waiting command starts
        // at the shortest sync, or the frame is counted late). How many made
        // it on time is the machine's: reported (under qemu-aarch64 in CI, 2
        // of 27 did), not asserted.
        let back_to_back = frames
            .windows(2)
            .filter(|w| w[1].start - w[0].last_pulse == min)
            .count();
        eprintln!(
            "{back_to_back} of {} frames at the shortest sync, {} late",
            frames.len(),
            stats.late_frames.load(Relaxed)
        );
        // 60 commands over 420 ms: frames enough to carry many of them.
        assert!(frames.len() >= 10, "{} frames", frames.len());
    }
}
