//! The capture decoder: an input line's edges in, whole PPM frames out,
//! every frame it refuses counted by reason.
//!
//! # What EdgeTX's trainer input accepts (read from EdgeTX's sources)
//!
//! - `radio/src/targets/common/arm/stm32/trainer_driver.cpp`,
//!   `capture_pulse`: one edge direction is input-captured by a 16-bit timer
//!   at 2 MHz and the difference to the previous capture, halved, is a
//!   period in whole microseconds. `val > 4000 && val < 19000` is a sync
//!   (strict bounds) and starts channel 0; after that, `val < 800 ||
//!   val > 2200` is an invalid period that stops the frame until the next
//!   sync (so a channel is 800..=2200 us, inclusive); a valid period is
//!   stored as the next channel at once, up to `MAX_TRAINER_CHANNELS`, and
//!   later periods are ignored until the next sync. The capture channel is
//!   set up by `stm32_pulse_config_input`
//!   (`radio/src/targets/common/arm/stm32/stm32_pulse_driver.cpp`) with a
//!   hardware input filter of 8 timer-clock samples: only sub-microsecond
//!   glitches are filtered there.
//! - `radio/src/dataconstants.h`: `MAX_TRAINER_CHANNELS` is 16.
//! - `radio/src/trainer.cpp`: `TRAINER_IN_VALID_TIMEOUT` is 100 ticks of
//!   `per10ms()` (`radio/src/edgetx.cpp`), 1 s: `trainerResetTimer()` is
//!   called for every valid channel and `isTrainerValid()` holds while the
//!   timer has not run down ("trainer lost" after 1 s without one).
//! - `radio/src/pulses/ppm.cpp` and `radio/src/myeeprom.h`
//!   (`GET_MODULE_PPM_DELAY`, `GET_TRAINER_PPM_DELAY`): a radio's own PPM
//!   output has separator pulses of `delay * 50 + 300` us, `delay` in
//!   -4..=10 (`model_setup.cpp`): 100..=800 us, 300 us by default.
//!
//! # What this decoder does
//!
//! The same windows, at the nanosecond the kernel stamped the edges with
//! instead of EdgeTX's whole microseconds ([`CHANNEL_MIN_NS`]..=
//! [`CHANNEL_MAX_NS`] for a channel, strictly between [`SYNC_MIN_NS`] and
//! [`SYNC_MAX_NS`] for a sync), but stricter about what it hands on, since
//! a frame read back is evidence of what a radio transmits:
//!
//! - Only the edges that leave the idle level (*leading edges*) are timed;
//!   a channel is the period between two leading edges. (EdgeTX times the
//!   rising edge at the pin whatever the idle level; with a constant pulse
//!   width, as every PPM source sends, the periods are the same.)
//! - A frame is handed on only whole: it began at the leading edge that
//!   ended a sync, every period in it is a channel, it has at most 16
//!   channels, a sync closed it, its channel count is the configured or
//!   locked one, and nothing went wrong inside it (no lost event, no runt,
//!   no noise). EdgeTX instead uses each channel as it arrives and ignores
//!   a 17th; here a frame is never guessed or repaired, and its values are
//!   the exact leading-edge-to-leading-edge periods in ns.
//! - A leading edge is used only once its pulse has ended and proved not to
//!   be a runt (shorter than [`RUNT_NS`]), so a frame is handed on at the
//!   trailing edge of the pulse that ended its closing sync (a pulse width,
//!   typically 300 us, after [`ReadFrame::end_ns`]). A runt is no timing
//!   reference: the periods around it are measured from the real pulses.
//! - Validity: [`Capture::valid_at`] holds for [`INPUT_VALID_NS`] (1 s, as
//!   `TRAINER_IN_VALID_TIMEOUT`) after the last whole frame (EdgeTX counts
//!   from the last valid channel).
//!
//! # Refusals
//!
//! A frame begins at every sync. A frame in progress that goes wrong is
//! dropped and counted once, under the first reason that hit it (see
//! [`CaptureCounts`]); the decoder then waits for the next sync, and what
//! it sees until then belongs to no frame and is counted under
//! [`CaptureCounts::unsynced`] (so are the periods before the first sync).
//! Two syncs in a row (a frame of no channel) are no frame and not counted.

use super::EdgeEvent;
use crate::signal::{
    Level, CHANNEL_MAX_US, CHANNEL_MIN_US, MAX_CHANNELS, SYNC_MAX_US, SYNC_MIN_US,
};

/// Shortest channel period, ns (inclusive): EdgeTX 2.10's 800 us.
pub const CHANNEL_MIN_NS: u64 = (CHANNEL_MIN_US * 1e3) as u64;
/// Longest channel period, ns (inclusive): EdgeTX 2.10's 2200 us.
pub const CHANNEL_MAX_NS: u64 = (CHANNEL_MAX_US * 1e3) as u64;
/// A sync is longer than this, ns (strict): EdgeTX's 4000 us.
pub const SYNC_MIN_NS: u64 = (SYNC_MIN_US * 1e3) as u64;
/// A sync is shorter than this, ns (strict): EdgeTX's 19000 us.
pub const SYNC_MAX_NS: u64 = (SYNC_MAX_US * 1e3) as u64;

/// An active pulse (the line away from its idle level) shorter than this,
/// ns, is a runt: a spike, not a pulse. 25 us is half of the shortest pulse
/// ppm itself sends ([`crate::frame::PULSE_MIN_US`], 50 us), a quarter of
/// the shortest a radio sends (EdgeTX: 100 us) and a twelfth of the usual
/// 300-400 us; the spikes interference, ringing or contact bounce make last
/// nanoseconds to a few microseconds. The margin below 50 us leaves room for
/// the interrupt latency that shortens a pulse's kernel timestamps.
pub const RUNT_NS: u64 = 25_000;

/// A period between leading edges shorter than this, ns, is noise: half of
/// the shortest channel, far shorter than anything a PPM source sends even
/// with its timing error, and what a floating pin or interference makes
/// (bursts of edges microseconds apart). Longer periods that are neither a
/// channel nor a sync (400 us..800 us, 2200..=4000 us, 19 ms and more) are
/// [`CaptureCounts::out_of_window`]: a radio with extended limits (EdgeTX
/// sends down to about 730 us) makes those, not noise.
pub const NOISE_NS: u64 = 400_000;

/// Consecutive whole frames of one channel count that lock it when the
/// count is not configured (they are not handed on).
pub const LOCK_FRAMES: u8 = 2;
/// Consecutive whole frames of one other count that relock to it (they
/// are not handed on).
pub const RELOCK_FRAMES: u8 = 3;

/// How long the input stays valid after a whole frame, ns: 1 s, as
/// EdgeTX's `TRAINER_IN_VALID_TIMEOUT` (`radio/src/trainer.cpp`).
pub const INPUT_VALID_NS: u64 = 1_000_000_000;

/// Number of refusal reasons [`CaptureCounts::reasons`] gives.
pub const REASONS: usize = 8;

/// What the decoder is told; `None` is found from the signal.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CaptureSettings {
    /// The line's idle level (the level during the sync gap); `None`: found
    /// from the signal.
    pub idle: Option<Level>,
    /// Channels in a frame (1..=16); `None`: found from the signal.
    pub channels: Option<u8>,
}

/// One whole frame read from the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadFrame {
    /// The leading edge that began the first channel (ended the sync
    /// before it), CLOCK_MONOTONIC ns.
    pub start_ns: u64,
    /// The leading edge that ended the sync after the last channel: when
    /// the frame was known whole, CLOCK_MONOTONIC ns.
    pub end_ns: u64,
    /// Channels read.
    pub count: u8,
    /// Channel periods, ns (leading edge to leading edge); the first
    /// `count` are the frame's.
    pub values_ns: [u32; MAX_CHANNELS],
}

impl ReadFrame {
    /// The frame's channels, ns.
    pub fn values(&self) -> &[u32] {
        &self.values_ns[..(self.count as usize).min(MAX_CHANNELS)]
    }

    /// The sync that closed the frame, ns: from the last channel's end to
    /// [`ReadFrame::end_ns`].
    pub fn sync_ns(&self) -> u64 {
        let sum: u64 = self.values().iter().map(|&v| u64::from(v)).sum();
        self.end_ns
            .saturating_sub(self.start_ns)
            .saturating_sub(sum)
    }
}

/// What the decoder saw and refused, by reason.
///
/// A frame in progress is counted once, under the first reason that hit
/// it; `lost_events` counts events, `unsynced` what belonged to no frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CaptureCounts {
    /// Edges pushed.
    pub edges: u64,
    /// Whole frames handed on.
    pub frames: u64,
    /// Events the kernel lost: the gaps in the events' sequence numbers
    /// (an event whose `seq` is not the previous one's + 1).
    pub lost_events: u64,
    /// Frames in progress dropped because events were lost (or the
    /// sequence numbers went backwards) inside them.
    pub lost_frames: u64,
    /// Frames in progress with a runt: an active pulse shorter than
    /// [`RUNT_NS`].
    pub runts: u64,
    /// Frames in progress with noise: a period between leading edges
    /// shorter than [`NOISE_NS`], an edge not later than the one before it
    /// (time going backwards, or an equal timestamp), or two edges to the
    /// same level in a row (an edge missed).
    pub noise: u64,
    /// Frames in progress with a period neither a channel nor a sync (and
    /// not noise); and, while the idle level is being found, a frame in
    /// progress when the level taken as active is held longer than any
    /// channel (the idle level found changes: see `idle_changes`).
    pub out_of_window: u64,
    /// Frames in progress with a 17th channel before their sync.
    pub too_many_channels: u64,
    /// Whole frames whose channel count is not the configured or locked
    /// one, including those read while a count is being locked
    /// ([`LOCK_FRAMES`], [`RELOCK_FRAMES`]).
    pub wrong_count: u64,
    /// What belonged to no frame: periods other than a sync, runts and
    /// noisy edges seen while no frame was in progress (before the first
    /// sync, or after a refusal until the next sync).
    pub unsynced: u64,
    /// Times the idle level found from the signal changed (not a refusal
    /// reason: the frame in progress it drops is counted under
    /// `out_of_window`).
    pub idle_changes: u64,
}

impl CaptureCounts {
    /// The refusal reasons, snake_case names and counts, always in this
    /// order: `lost_events`, `lost_frames`, `runts`, `noise`,
    /// `out_of_window`, `too_many_channels`, `wrong_count`, `unsynced`.
    pub fn reasons(&self) -> [(&'static str, u64); REASONS] {
        [
            ("lost_events", self.lost_events),
            ("lost_frames", self.lost_frames),
            ("runts", self.runts),
            ("noise", self.noise),
            ("out_of_window", self.out_of_window),
            ("too_many_channels", self.too_many_channels),
            ("wrong_count", self.wrong_count),
            ("unsynced", self.unsynced),
        ]
    }
}

/// Why a frame in progress was dropped.
#[derive(Debug, Clone, Copy)]
enum Refusal {
    Lost,
    Runt,
    Noise,
    OutOfWindow,
    TooMany,
}

/// The frame in progress: begun at a sync, channels so far.
#[derive(Debug, Clone, Copy)]
struct Progress {
    start_ns: u64,
    count: u8,
    values_ns: [u32; MAX_CHANNELS],
}

/// The streaming capture decoder.
///
/// Allocation-free: its state is a few fixed-size fields, and
/// [`Capture::push`] does a constant amount of work per edge.
#[derive(Debug, Clone)]
pub struct Capture {
    settings: CaptureSettings,
    counts: CaptureCounts,
    /// `seq` of the previous event.
    seq: Option<u64>,
    /// Time of the previous event.
    last_at: Option<u64>,
    /// The line's level after the previous event (`None` after lost events).
    level: Option<Level>,
    /// When the line went to `level`, if that edge was a clean one.
    since: Option<u64>,
    /// The idle level found from the signal.
    found_idle: Option<Level>,
    /// A leading edge whose pulse has not ended yet.
    pending: Option<u64>,
    /// The last leading edge used: the start of the next period.
    last_lead: Option<u64>,
    /// The frame in progress; `None` while waiting for a sync.
    frame: Option<Progress>,
    /// The channel count locked on, when not configured.
    locked: Option<u8>,
    /// The count of the latest whole frames not of the locked count, and
    /// how many of them came in a row.
    candidate: Option<u8>,
    streak: u8,
    /// `end_ns` of the last frame handed on.
    last_end: Option<u64>,
}

impl Capture {
    /// A decoder with `settings`.
    pub fn new(settings: CaptureSettings) -> Capture {
        Capture {
            settings,
            counts: CaptureCounts::default(),
            seq: None,
            last_at: None,
            level: None,
            since: None,
            found_idle: None,
            pending: None,
            last_lead: None,
            frame: None,
            locked: None,
            candidate: None,
            streak: 0,
            last_end: None,
        }
    }

    /// Feeds one edge (in time order); returns a frame when this edge
    /// completes one.
    ///
    /// The edge that completes a frame is the trailing edge of the pulse
    /// whose leading edge ended the frame's closing sync
    /// ([`ReadFrame::end_ns`]): a leading edge counts only once its pulse
    /// is known not to be a runt. Never panics, whatever the input.
    pub fn push(&mut self, e: EdgeEvent) -> Option<ReadFrame> {
        bump(&mut self.counts.edges);
        // Events lost: nothing measured across the gap is trusted.
        if let Some(prev) = self.seq.replace(e.seq) {
            if e.seq != prev.wrapping_add(1) {
                let missing = if e.seq > prev { e.seq - prev - 1 } else { 0 };
                self.counts.lost_events = self.counts.lost_events.saturating_add(missing);
                self.refuse(Refusal::Lost);
                self.restart();
                self.level = None;
            }
        }
        let t = e.at_ns;
        let prev_at = self.last_at.replace(t);
        let prev_level = self.level.replace(e.level);
        if prev_at.is_some_and(|p| t <= p) || prev_level == Some(e.level) {
            // Time going backwards, an equal timestamp, or an edge missed.
            self.refuse(Refusal::Noise);
            self.restart();
            return None;
        }
        let since = self.since.replace(t);
        if self.settings.idle.is_none() {
            self.find_idle(prev_level, since, t);
        }
        let idle = self.idle_level()?;
        if e.level != idle {
            // A leading edge: used once its pulse ends.
            self.pending = Some(t);
            return None;
        }
        let lead = self.pending.take()?;
        if t.saturating_sub(lead) < RUNT_NS {
            // A spike: not a timing reference.
            self.refuse(Refusal::Runt);
            return None;
        }
        self.timed(lead)
    }

    /// What was seen and refused so far.
    pub fn counts(&self) -> CaptureCounts {
        self.counts
    }

    /// The settings the decoder was made with.
    pub fn settings(&self) -> CaptureSettings {
        self.settings
    }

    /// The idle level: configured, or found from the signal (`None` until
    /// then; nothing is handed on before).
    ///
    /// Found: a level held longer than the longest channel
    /// ([`CHANNEL_MAX_NS`]) is idle, since in PPM only the sync gap lasts
    /// that long (a pulse is shorter than a channel). When the other level
    /// is held that long later, it becomes the idle level (counted in
    /// [`CaptureCounts::idle_changes`]): a pull resistor's level before
    /// the source was plugged in is not mistaken for good.
    pub fn idle_level(&self) -> Option<Level> {
        self.settings.idle.or(self.found_idle)
    }

    /// Channels in a frame: configured, or locked on from the signal
    /// (`None` until then).
    ///
    /// Locked: after [`LOCK_FRAMES`] consecutive whole frames of one count
    /// (a frame refused between them, or one of the locked count, breaks
    /// the run, so glitches scattered over a noisy stretch never add up to
    /// a lock). Once locked, a whole frame of another count is dropped
    /// ([`CaptureCounts::wrong_count`]); after [`RELOCK_FRAMES`]
    /// consecutive whole frames of one new count the decoder relocks to it.
    /// The frames that lock or relock a count are not handed on.
    pub fn channels(&self) -> Option<u8> {
        self.settings.channels.or(self.locked)
    }

    /// Whether the input is valid at `now_ns` (CLOCK_MONOTONIC): a whole
    /// frame was handed on less than [`INPUT_VALID_NS`] before (or, with a
    /// `now_ns` read before the frame's edges were stamped, after).
    pub fn valid_at(&self, now_ns: u64) -> bool {
        self.last_end
            .is_some_and(|end| now_ns.saturating_sub(end) < INPUT_VALID_NS)
    }

    /// [`ReadFrame::end_ns`] of the last frame handed on.
    pub fn last_frame_end_ns(&self) -> Option<u64> {
        self.last_end
    }

    /// Forgets the timing: the next period starts at the next leading edge
    /// used, and a frame at the sync after it.
    fn restart(&mut self) {
        self.since = None;
        self.pending = None;
        self.last_lead = None;
    }

    /// Notes the previous level, held from `since` to `t`: held longer than
    /// any channel, it is the idle level.
    fn find_idle(&mut self, held: Option<Level>, since: Option<u64>, t: u64) {
        let (Some(held), Some(since)) = (held, since) else {
            return;
        };
        if t.saturating_sub(since) <= CHANNEL_MAX_NS || self.found_idle == Some(held) {
            return;
        }
        if self.found_idle.is_some() {
            bump(&mut self.counts.idle_changes);
            if self.drop_frame() {
                bump(&mut self.counts.out_of_window);
            }
            self.restart();
            // This edge itself is clean: the level it leaves was held.
            self.since = Some(t);
        }
        self.found_idle = Some(held);
    }

    /// Drops the frame in progress for `why` (counted once); without one,
    /// what was seen belonged to no frame.
    fn refuse(&mut self, why: Refusal) {
        if !self.drop_frame() {
            if !matches!(why, Refusal::Lost) {
                bump(&mut self.counts.unsynced);
            }
            return;
        }
        let c = &mut self.counts;
        bump(match why {
            Refusal::Lost => &mut c.lost_frames,
            Refusal::Runt => &mut c.runts,
            Refusal::Noise => &mut c.noise,
            Refusal::OutOfWindow => &mut c.out_of_window,
            Refusal::TooMany => &mut c.too_many_channels,
        });
    }

    /// Drops the frame in progress, if any (true then): it also breaks the
    /// run of whole frames of one count.
    fn drop_frame(&mut self) -> bool {
        if self.frame.take().is_none() {
            return false;
        }
        self.candidate = None;
        self.streak = 0;
        true
    }

    /// Uses the leading edge at `lead`: the period since the previous one.
    fn timed(&mut self, lead: u64) -> Option<ReadFrame> {
        let prev = self.last_lead.replace(lead)?;
        let p = lead.saturating_sub(prev);
        if p > SYNC_MIN_NS && p < SYNC_MAX_NS {
            let done = self.frame.replace(Progress {
                start_ns: lead,
                count: 0,
                values_ns: [0; MAX_CHANNELS],
            });
            return done.and_then(|f| self.close(f, lead));
        }
        let Some(f) = self.frame.as_mut() else {
            bump(&mut self.counts.unsynced);
            return None;
        };
        if (CHANNEL_MIN_NS..=CHANNEL_MAX_NS).contains(&p) {
            let i = f.count as usize;
            if i < MAX_CHANNELS {
                // At most CHANNEL_MAX_NS: fits.
                f.values_ns[i] = p as u32;
                f.count += 1;
                return None;
            }
            self.refuse(Refusal::TooMany);
        } else if p < NOISE_NS {
            self.refuse(Refusal::Noise);
        } else {
            self.refuse(Refusal::OutOfWindow);
        }
        None
    }

    /// The frame `f`, closed by a sync at `end_ns`: handed on if its count
    /// is the one expected.
    fn close(&mut self, f: Progress, end_ns: u64) -> Option<ReadFrame> {
        if f.count == 0 {
            return None;
        }
        let expected = match self.settings.channels {
            Some(c) => f.count == c,
            None => self.track_count(f.count),
        };
        if !expected {
            bump(&mut self.counts.wrong_count);
            return None;
        }
        bump(&mut self.counts.frames);
        self.last_end = Some(end_ns);
        Some(ReadFrame {
            start_ns: f.start_ns,
            end_ns,
            count: f.count,
            values_ns: f.values_ns,
        })
    }

    /// Locks the channel count on the whole frames' counts; true when a
    /// frame of `n` channels is of the locked count.
    fn track_count(&mut self, n: u8) -> bool {
        if self.locked == Some(n) {
            self.candidate = None;
            self.streak = 0;
            return true;
        }
        if self.candidate == Some(n) {
            self.streak = self.streak.saturating_add(1);
        } else {
            self.candidate = Some(n);
            self.streak = 1;
        }
        let needed = if self.locked.is_some() {
            RELOCK_FRAMES
        } else {
            LOCK_FRAMES
        };
        if self.streak >= needed {
            self.locked = Some(n);
            self.candidate = None;
            self.streak = 0;
        }
        false
    }
}

/// Adds one to a count (saturating: never overflows).
fn bump(n: &mut u64) {
    *n = n.saturating_add(1);
}

#[cfg(test)]
#[path = "tests/mod.rs"]
mod tests;
