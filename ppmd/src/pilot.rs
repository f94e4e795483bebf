//! The pilot's radio as a takeover input: a radio's trainer signal (PPM,
//! from `ppmd.pilot`, read as the read-back reads a radio) whose takeover
//! switch (`pilot.switch_channel`) gives its pilot the controls.
//!
//! - [`PilotState`]: who flies: the groundstation, the pilot, or nobody
//!   can tell ([`PilotState::NoInput`]).
//! - [`PilotSlot`]: the state and the newest pilot frame ([`PilotFrame`]),
//!   written by the pilot thread and read by the timing loop without ever
//!   waiting (a sequence count, as [`crate::emitter::Stats::last_frame`]).
//! - [`Opened`], [`Pilot`]: the pilot thread of one output. Its input is
//!   opened at start (a fault stops ppmd there), the thread started once
//!   the loop runs. It decodes the frames ([`Capture`]), judges the switch
//!   in each whole frame, fills the slot and publishes the state on the
//!   output's read-back service (`ppm/NAME/readback`, a [`ReadbackSample`]:
//!   `following` while the groundstation flies, `overridden` while the
//!   pilot does, `no_input`), which udp-ingress, ppm-status and ppm-web
//!   already show.
//! - [`PilotMux`]: the loop's command source of an output with a pilot's
//!   radio: the groundstation's commands or the pilot's frames, by the
//!   state.
//!
//! The safety rule: the groundstation flies only while a pilot who can
//! take over is there. While the pilot's radio is not read (no whole frame
//! for a second, frames without the switch channel, the thread not yet
//! started or stopped) no command goes out at all, the groundstation's
//! included: the loop's failsafe (or its startup action) applies.
//!
//! The thread runs at normal priority, never on the timing thread's CPU,
//! and blocks only on its input, as the read-back's does
//! ([`crate::readback`]).

use crate::input::{self, EdgeSource};
use crate::readback::{avoid, real_of, refused};
use crate::source::CommandSource;
use anyhow::{Context, Result};
use ppm_shared::capture::{Capture, CaptureSettings, EdgeEvent, ReadFrame, ReadbackState};
use ppm_shared::config::PilotPlan;
use ppm_shared::frame::{FrameModel, MAX_CHANNELS};
use ppm_shared::ipc::{self, CommandSample, ReadbackSample};
use ppm_shared::logging::Chain;
use ppm_shared::time::now_ns;
use std::os::fd::RawFd;
use std::path::Path;
use std::sync::atomic::{
    fence, AtomicBool, AtomicU32, AtomicU64, AtomicU8,
    Ordering::{Acquire, Relaxed, Release},
};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// How long the thread waits for edges before it looks at the time again
/// (the one-second loss rule, the publishing).
pub const POLL: Duration = crate::readback::POLL;
/// A pilot's radio whose newest frame ended longer ago than this is taken
/// as not read by the loop, whatever the slot's state says: the thread
/// that judges it (1 s without a whole frame) has stopped or hangs.
pub const STALE_NS: u64 = 1_500_000_000;
/// Frames in a row that must read the switch off before the pilot gives
/// the controls back (one is enough to take them).
pub const RELEASE_FRAMES: u32 = 2;
/// How often the state is published while nothing changes.
const PUBLISH_EVERY_NS: u64 = 100_000_000;
/// Edges read in one go.
const BATCH: usize = 256;

/// Who flies, by the pilot's radio.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[repr(u8)]
pub enum PilotState {
    /// The pilot's radio is not read: no whole frame for a second (or none
    /// yet), or its frames do not carry the switch channel. Nothing goes
    /// out from the groundstation.
    #[default]
    NoInput = 0,
    /// The takeover switch is off: the groundstation's commands go out.
    Groundstation = 1,
    /// The takeover switch is on: the pilot's channels go out.
    Pilot = 2,
}

impl PilotState {
    /// Its name in logs.
    pub fn name(self) -> &'static str {
        match self {
            PilotState::NoInput => "no_input",
            PilotState::Groundstation => "groundstation",
            PilotState::Pilot => "pilot",
        }
    }

    /// The read-back state it is published as: `following` while the
    /// groundstation flies, `overridden` while the pilot does.
    pub fn readback(self) -> ReadbackState {
        match self {
            PilotState::NoInput => ReadbackState::NoInput,
            PilotState::Groundstation => ReadbackState::Following,
            PilotState::Pilot => ReadbackState::Overridden,
        }
    }

    /// The state of code `code` (`as u8`); an unknown code is `NoInput`.
    fn from_code(code: u8) -> PilotState {
        match code {
            1 => PilotState::Groundstation,
            2 => PilotState::Pilot,
            _ => PilotState::NoInput,
        }
    }
}

/// One whole frame read from the pilot's radio.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PilotFrame {
    /// Its number among the whole frames read (1, 2, ...).
    pub frame: u64,
    /// When it was known whole ([`ReadFrame::end_ns`]), CLOCK_MONOTONIC ns.
    pub end_mono_ns: u64,
    /// The same time on CLOCK_REALTIME, ns since the Unix epoch.
    pub end_real_ns: u64,
    /// The state this frame put the pilot's radio in.
    pub state: PilotState,
    /// Channels read.
    pub channels: u8,
    /// Channel periods, ns; the first `channels` are the frame's.
    pub values_ns: [u32; MAX_CHANNELS],
}

impl PilotFrame {
    /// The frame's channels, ns.
    pub fn values(&self) -> &[u32] {
        &self.values_ns[..(self.channels as usize).min(MAX_CHANNELS)]
    }
}

/// The pilot's radio as the timing loop sees it: the state, and the newest
/// whole frame as a sequence-counted copy. One writer (the pilot thread);
/// readers never wait and never allocate: a read that meets a write
/// returns `None` and the loop looks again at its next frame.
#[derive(Debug, Default)]
pub struct PilotSlot {
    state: AtomicU8,
    /// Odd while the frame is being written.
    version: AtomicU64,
    frame: AtomicU64,
    end_mono_ns: AtomicU64,
    end_real_ns: AtomicU64,
    frame_state: AtomicU8,
    channels: AtomicU8,
    values_ns: [AtomicU32; MAX_CHANNELS],
}

impl PilotSlot {
    /// The state.
    pub fn state(&self) -> PilotState {
        PilotState::from_code(self.state.load(Acquire))
    }

    /// Sets the state (the pilot thread, after the frame that made it).
    pub fn set_state(&self, s: PilotState) {
        self.state.store(s as u8, Release);
    }

    /// Stores `f` as the newest frame. Only one thread may write.
    pub fn store(&self, f: &PilotFrame) {
        let v = self.version.load(Relaxed);
        self.version.store(v.wrapping_add(1), Relaxed);
        fence(Release);
        self.frame.store(f.frame, Relaxed);
        self.end_mono_ns.store(f.end_mono_ns, Relaxed);
        self.end_real_ns.store(f.end_real_ns, Relaxed);
        self.frame_state.store(f.state as u8, Relaxed);
        self.channels.store(f.channels, Relaxed);
        for (a, &v) in self.values_ns.iter().zip(&f.values_ns) {
            a.store(v, Relaxed);
        }
        self.version.store(v.wrapping_add(2), Release);
    }

    /// The newest frame stored; `None` before the first, or when this read
    /// met a write (one try: no waiting, no spinning).
    pub fn frame(&self) -> Option<PilotFrame> {
        let v1 = self.version.load(Acquire);
        if v1 & 1 == 1 {
            return None;
        }
        let mut f = PilotFrame {
            frame: self.frame.load(Relaxed),
            end_mono_ns: self.end_mono_ns.load(Relaxed),
            end_real_ns: self.end_real_ns.load(Relaxed),
            state: PilotState::from_code(self.frame_state.load(Relaxed)),
            channels: self.channels.load(Relaxed),
            values_ns: [0; MAX_CHANNELS],
        };
        for (v, a) in f.values_ns.iter_mut().zip(&self.values_ns) {
            *v = a.load(Relaxed);
        }
        fence(Acquire);
        (self.version.load(Relaxed) == v1 && f.frame != 0).then_some(f)
    }
}

/// The loop's command source of an output with a pilot's radio: wraps the
/// groundstation's source and hands on, by the [`PilotSlot`]'s state:
///
/// - [`PilotState::Groundstation`]: the groundstation's newest command when
///   one came; on the first call after the state became `Groundstation`,
///   the last one kept (the loop's failsafe judges its age).
/// - [`PilotState::Pilot`]: each new pilot frame once, as a command of the
///   output's model: pilot channel `i` is output channel `i`, clamped to
///   its limits, channels the pilot's radio does not send at their
///   defaults. No new frame: nothing (the loop repeats the last one, and
///   its failsafe takes over if the pilot's frames stop).
/// - [`PilotState::NoInput`]: nothing, ever, and the source is
///   [withdrawn](CommandSource::withdrawn) (the safety rule: no pilot who
///   could take over, so no command goes out at all, not the last one
///   held, not the failsafe's defaults: the line is silent). So is it when
///   the newest pilot frame is [`STALE_NS`] old, whatever the state: the
///   thread that judges the pilot's radio has stopped or hangs.
///
/// The groundstation's source is drained at every call, whatever the
/// state. [`CommandSource::newest`] neither blocks nor allocates.
pub struct PilotMux {
    inner: Box<dyn CommandSource>,
    slot: Arc<PilotSlot>,
    channels: usize,
    min_ns: [u32; MAX_CHANNELS],
    max_ns: [u32; MAX_CHANNELS],
    default_ns: [u32; MAX_CHANNELS],
    fingerprint: u64,
    /// The groundstation's newest command.
    kept: Option<CommandSample>,
    /// The state at the previous call.
    seen: PilotState,
    /// The newest pilot frame handed out.
    handed: u64,
    /// When the newest pilot frame seen ended (0: none yet).
    last_end: u64,
}

impl PilotMux {
    /// Wraps the groundstation's source `inner`; the pilot's frames become
    /// commands of `model`.
    pub fn new(
        inner: Box<dyn CommandSource>,
        slot: Arc<PilotSlot>,
        model: &FrameModel,
    ) -> PilotMux {
        let channels = model.channels().min(MAX_CHANNELS);
        let per = |f: &dyn Fn(usize) -> u32| {
            let mut a = [0; MAX_CHANNELS];
            for (i, v) in a.iter_mut().enumerate().take(channels) {
                *v = f(i);
            }
            a
        };
        PilotMux {
            inner,
            slot,
            channels,
            min_ns: per(&|i| model.min_ns(i)),
            max_ns: per(&|i| model.max_ns(i)),
            default_ns: per(&|i| model.default_ns(i)),
            fingerprint: model.fingerprint(),
            kept: None,
            seen: PilotState::NoInput,
            handed: 0,
            last_end: 0,
        }
    }

    /// The pilot's frame `f` as a command of the output's model.
    fn command(&self, f: &PilotFrame) -> CommandSample {
        let mut values_ns = [0; MAX_CHANNELS];
        let mut clamped = 0;
        let read = f.values();
        for (i, v) in values_ns.iter_mut().enumerate().take(self.channels) {
            *v = match read.get(i) {
                Some(&r) => {
                    let c = r.clamp(self.min_ns[i], self.max_ns[i]);
                    clamped += u32::from(c != r);
                    c
                }
                None => self.default_ns[i],
            };
        }
        CommandSample {
            ingress_seq: f.frame,
            seq: 0,
            recv_mono_ns: f.end_mono_ns,
            recv_real_ns: f.end_real_ns,
            ingress_pid: 0,
            has_seq: 0,
            channel_count: self.channels as u32,
            clamped,
            values_ns,
            model: self.fingerprint,
        }
    }
}

impl CommandSource for PilotMux {
    fn newest(&mut self) -> Option<CommandSample> {
        let came = self.inner.newest();
        if came.is_some() {
            self.kept = came;
        }
        let state = self.slot.state();
        let became = state != self.seen;
        self.seen = state;
        match state {
            PilotState::NoInput => None,
            PilotState::Groundstation => came.or(if became { self.kept } else { None }),
            PilotState::Pilot => {
                // A frame stored before the state left `Pilot` may be read
                // here after it did: only a frame that itself said `Pilot`
                // is handed out.
                let f = self.slot.frame()?;
                if f.frame <= self.handed || f.state != PilotState::Pilot {
                    return None;
                }
                self.handed = f.frame;
                Some(self.command(&f))
            }
        }
    }

    /// No pilot's radio read: its state says so, or its newest frame is
    /// [`STALE_NS`] old (or there is none), so the thread that would say
    /// so has stopped or hangs.
    fn withdrawn(&mut self, now_ns: u64) -> bool {
        if let Some(f) = self.slot.frame() {
            self.last_end = self.last_end.max(f.end_mono_ns);
        }
        self.seen == PilotState::NoInput
            || self.last_end == 0
            || now_ns.saturating_sub(self.last_end) > STALE_NS
    }

    fn errors(&self) -> u64 {
        self.inner.errors()
    }

    fn wake_fd(&self) -> Option<RawFd> {
        self.inner.wake_fd()
    }

    fn clear_wake(&mut self) -> bool {
        self.inner.clear_wake()
    }
}

/// The decoding and judging of the pilot's frames, apart from the input
/// and the publisher (so tests drive it with edges).
struct Tracker {
    tag: String,
    capture: Capture,
    /// `pilot.switch_channel`, 0-based.
    switch_channel: usize,
    switch_above_ns: u64,
    state: PilotState,
    /// Whether frames without the switch channel were warned about.
    warned_short: bool,
    /// Frames in a row, while the pilot flies, that read the switch off.
    off_frames: u32,
    /// The sample published last, updated as frames are read.
    sample: ReadbackSample,
    slot: Arc<PilotSlot>,
}

impl Tracker {
    fn new(tag: String, settings: &Settings, slot: Arc<PilotSlot>) -> Tracker {
        Tracker {
            tag,
            capture: Capture::new(settings.capture),
            switch_channel: settings.switch_channel,
            switch_above_ns: settings.switch_above_ns,
            state: PilotState::NoInput,
            warned_short: false,
            off_frames: 0,
            sample: ReadbackSample::default(),
            slot,
        }
    }

    /// Feeds one edge; a whole frame read is judged and stored.
    fn edge(&mut self, e: EdgeEvent) {
        let Some(f) = self.capture.push(e) else {
            return;
        };
        let mut state = self.judge(&f);
        // The pilot gets the controls at the first frame that says so, and
        // gives them back only when RELEASE_FRAMES frames in a row do: one
        // frame misread (noise on the switch channel) never hands a pilot's
        // vehicle back to the groundstation.
        if self.state == PilotState::Pilot && state == PilotState::Groundstation {
            self.off_frames += 1;
            if self.off_frames < RELEASE_FRAMES {
                state = PilotState::Pilot;
            }
        } else {
            self.off_frames = 0;
        }
        let s = &mut self.sample;
        s.frames += 1;
        match state {
            PilotState::Groundstation => s.matched += 1,
            PilotState::Pilot => s.mismatched += 1,
            PilotState::NoInput => {}
        }
        s.start_mono_ns = f.start_ns;
        s.channels = u32::from(f.count);
        s.values_ns = f.values_ns;
        self.slot.store(&PilotFrame {
            frame: s.frames,
            end_mono_ns: f.end_ns,
            end_real_ns: real_of(f.end_ns),
            state,
            channels: f.count,
            values_ns: f.values_ns,
        });
        self.change(f.end_ns, state, &f);
    }

    /// The state frame `f` says.
    fn judge(&mut self, f: &ReadFrame) -> PilotState {
        let Some(&v) = f.values().get(self.switch_channel) else {
            if !self.warned_short {
                self.warned_short = true;
                log::warn!(
                    "{}pilot.switch_channel is {}, but the pilot's radio sends {} channels: set pilot.switch_channel to the channel of its takeover switch, or have the radio send that channel",
                    self.tag,
                    self.switch_channel + 1,
                    f.count
                );
            }
            return PilotState::NoInput;
        };
        if u64::from(v) > self.switch_above_ns {
            PilotState::Pilot
        } else {
            PilotState::Groundstation
        }
    }

    /// At `now`: the input is lost when no whole frame came for a second.
    fn tick(&mut self, now: u64) {
        if self.state != PilotState::NoInput && !self.capture.valid_at(now) {
            self.slot.set_state(PilotState::NoInput);
            self.changed(
                now,
                PilotState::NoInput,
                "no whole frame from the pilot's radio for 1 s",
            );
        }
    }

    /// Frame `f`, known whole at `at`, says `to`.
    fn change(&mut self, at: u64, to: PilotState, f: &ReadFrame) {
        self.slot.set_state(to);
        if to == self.state {
            return;
        }
        let why = match f.values().get(self.switch_channel) {
            Some(&v) => format!(
                "switch channel {} reads {:.1} us",
                self.switch_channel + 1,
                f64::from(v) / 1e3
            ),
            None => format!(
                "frames of {} channels, no switch channel {}",
                f.count,
                self.switch_channel + 1
            ),
        };
        self.changed(at, to, &why);
    }

    fn changed(&mut self, at: u64, to: PilotState, why: &str) {
        let (tag, from) = (&self.tag, self.state.name());
        match to {
            PilotState::Pilot => {
                log::warn!("{tag}pilot: {from} -> pilot ({why}): the pilot flies")
            }
            PilotState::Groundstation => {
                log::info!("{tag}pilot: {from} -> groundstation ({why}): the groundstation flies")
            }
            PilotState::NoInput => log::warn!(
                "{tag}pilot: {from} -> no_input ({why}): no command goes out until the pilot's radio reads again; the failsafe applies"
            ),
        }
        self.state = to;
        self.sample.changes += 1;
        self.sample.changed_mono_ns = at;
    }

    /// The sample to publish at `now`.
    fn publish_at(&mut self, now: u64) -> ReadbackSample {
        let counts = self.capture.counts();
        let s = &mut self.sample;
        s.state = self.state.readback() as u32;
        s.edges = counts.edges;
        s.refused = refused(&counts);
        s.published_mono_ns = now;
        // Nothing is compared with what the line carried.
        s.max_diff_ns = 0;
        *s
    }
}

/// What the tracker is told.
struct Settings {
    capture: CaptureSettings,
    switch_channel: usize,
    switch_above_ns: u64,
}

/// A pilot's radio whose input is open, its thread not yet started.
pub struct Opened {
    name: String,
    tag: String,
    source: Box<dyn EdgeSource>,
    settings: Settings,
}

impl Opened {
    /// Opens output `name`'s pilot input (`ppmd.pilot`); `tag` goes before
    /// its log lines. Errors name `ppmd.pilot`.
    pub fn open(name: &str, tag: &str, plan: &PilotPlan) -> Result<Opened> {
        let source = input::open_as(&plan.input, input::PILOT_CONSUMER)
            .with_context(|| format!("{tag}ppmd.pilot: opening {}", plan.input))?;
        log::info!(
            "{tag}pilot's radio: {} (takeover switch: channel {}, on above {} us)",
            source.description(),
            plan.switch_channel + 1,
            plan.switch_above_ns as f64 / 1e3
        );
        let mut capture = plan.capture;
        if capture.idle.is_none() {
            capture.idle = source.idle_level();
        }
        Ok(Opened {
            name: name.to_owned(),
            tag: tag.to_owned(),
            source,
            settings: Settings {
                capture,
                switch_channel: plan.switch_channel,
                switch_above_ns: plan.switch_above_ns,
            },
        })
    }

    /// Starts the thread, which fills `slot`, publishes under the
    /// shared-memory `root` and stays off `avoid_cpu` (the timing thread's).
    /// Returns once it publishes, or why it cannot.
    pub fn start(
        self,
        root: &Path,
        slot: Arc<PilotSlot>,
        avoid_cpu: Option<usize>,
    ) -> Result<Pilot> {
        let stop = Arc::new(AtomicBool::new(false));
        let ctx = Ctx {
            tag: self.tag.clone(),
            source: self.source,
            tracker: Tracker::new(self.tag, &self.settings, slot.clone()),
            stop: stop.clone(),
        };
        let (name, root) = (self.name, root.to_owned());
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("ppmd-pilot".into())
            .spawn(move || {
                // However the thread ends, nobody is known to be able to
                // take over any more.
                let _no_input = NoInputOnExit(slot);
                avoid(avoid_cpu);
                let opened = (|| -> Result<_, ipc::IpcError> {
                    let node = ipc::create_node(&root, &format!("ppmd-{name}-pilot"))?;
                    let service = ipc::open_readback_service(&node, &name)?;
                    let publisher = service.publisher_builder().create().map_err(|e| {
                        ipc::IpcError::new(
                            format!("creating the pilot's read-back publisher of `{name}`"),
                            e,
                        )
                    })?;
                    // A follow output sleeps until a command's wake-up: the
                    // pilot's frames wake it as udp-ingress's commands do.
                    let wake = ipc::open_wake_service(&node, &name)
                        .and_then(|w| {
                            let n = w.notifier_builder().create().map_err(|e| {
                                ipc::IpcError::new(format!("creating the pilot's wake-up notifier of `{name}`"), e)
                            })?;
                            Ok((w, n))
                        })
                        .map_err(|e| {
                            log::warn!(
                                "the pilot's frames will not wake a follow output (it looks for them at its longest sync): {}",
                                Chain(&e)
                            )
                        })
                        .ok();
                    Ok((node, service, publisher, wake))
                })();
                match opened {
                    Ok((_node, _service, publisher, wake)) => {
                        let _ = ready_tx.send(Ok(()));
                        ctx.run(&publisher, wake.as_ref().map(|w| &w.1));
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                }
            })
            .context("spawning the pilot thread")?;
        let mut pilot = Pilot {
            stop,
            thread: Some(thread),
        };
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(pilot),
            Ok(Err(e)) => {
                pilot.finish();
                Err(e.into())
            }
            Err(_) => {
                pilot.finish();
                anyhow::bail!("the pilot thread stopped at start")
            }
        }
    }
}

/// Sets the slot's state to `NoInput` when dropped.
struct NoInputOnExit(Arc<PilotSlot>);

impl Drop for NoInputOnExit {
    fn drop(&mut self) {
        self.0.set_state(PilotState::NoInput);
    }
}

/// A running pilot thread.
pub struct Pilot {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Pilot {
    /// Stops the thread and waits for it; the slot's state is `NoInput`
    /// after.
    pub fn finish(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Pilot {
    fn drop(&mut self) {
        self.finish();
    }
}

struct Ctx {
    tag: String,
    source: Box<dyn EdgeSource>,
    tracker: Tracker,
    stop: Arc<AtomicBool>,
}

impl Ctx {
    fn run(
        mut self,
        publisher: &ipc::Publisher<ReadbackSample>,
        wake: Option<&iceoryx2::port::notifier::Notifier<iceoryx2::service::ipc::Service>>,
    ) {
        let mut buf = [EdgeEvent {
            at_ns: 0,
            level: ppm_shared::Level::Low,
            seq: 0,
        }; BATCH];
        let mut published = 0u64;
        let mut failing = false;
        while !self.stop.load(Relaxed) {
            let n = match self.source.read(&mut buf, POLL) {
                Ok(n) => {
                    if failing {
                        log::info!("{}the pilot's input reads again", self.tag);
                        failing = false;
                    }
                    n
                }
                Err(e) => {
                    if !failing {
                        log::warn!("{}reading the pilot's input: {}", self.tag, Chain(&e));
                        failing = true;
                    }
                    std::thread::sleep(Duration::from_millis(100));
                    0
                }
            };
            let before = self.tracker.sample;
            for e in &buf[..n] {
                self.tracker.edge(*e);
            }
            let now = now_ns();
            self.tracker.tick(now);
            let s = self.tracker.sample;
            // A pilot's frame (or a change of who flies) the loop should
            // take now, not at its next look.
            let flying = self.tracker.slot.state() == PilotState::Pilot;
            if (s.frames != before.frames && flying) || s.changes != before.changes {
                if let Some(n) = wake {
                    if let Err(e) = n.notify() {
                        log::debug!("waking the timing loop: {e:?}");
                    }
                }
            }
            if s.frames != before.frames
                || s.changes != before.changes
                || now.saturating_sub(published) >= PUBLISH_EVERY_NS
            {
                let sample = self.tracker.publish_at(now);
                if let Err(e) = ipc::publish(publisher, sample) {
                    log::debug!("publishing the pilot's state: {}", Chain(&e));
                }
                published = now;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ppm_shared::config::Config;
    use ppm_shared::signal::Level;
    use std::cell::Cell;
    use std::rc::Rc;
    use std::sync::atomic::Ordering::Relaxed;

    /// The model of the mux tests: 6 channels AETR, 1000..2000 us, 1500 by
    /// default but the throttle (channel 3) at 1000, and aux2 (channel 6)
    /// limited to 1100..1800 with a default of 1200.
    fn model() -> FrameModel {
        Config::parse(
            "[ppm]\nchannels = 6\n[ppm.channel.aux2]\nmin_us = 1100\nmax_us = 1800\ndefault_us = 1200",
        )
        .unwrap()
        .validate()
        .unwrap()
    }

    /// The groundstation: hands out what the test put there, once; counts
    /// its calls.
    struct Ground {
        next: Rc<Cell<Option<CommandSample>>>,
        calls: Rc<Cell<u32>>,
        cleared: Rc<Cell<u32>>,
    }

    impl CommandSource for Ground {
        fn newest(&mut self) -> Option<CommandSample> {
            self.calls.set(self.calls.get() + 1);
            self.next.take()
        }
        fn errors(&self) -> u64 {
            7
        }
        fn wake_fd(&self) -> Option<RawFd> {
            Some(42)
        }
        fn clear_wake(&mut self) -> bool {
            self.cleared.set(self.cleared.get() + 1);
            false
        }
    }

    struct Rig {
        mux: PilotMux,
        slot: Arc<PilotSlot>,
        next: Rc<Cell<Option<CommandSample>>>,
        calls: Rc<Cell<u32>>,
        cleared: Rc<Cell<u32>>,
        model: FrameModel,
    }

    fn rig() -> Rig {
        let model = model();
        let (next, calls, cleared) = Default::default();
        let ground = Ground {
            next: Rc::clone(&next),
            calls: Rc::clone(&calls),
            cleared: Rc::clone(&cleared),
        };
        let slot = Arc::new(PilotSlot::default());
        let mux = PilotMux::new(Box::new(ground), slot.clone(), &model);
        Rig {
            mux,
            slot,
            next,
            calls,
            cleared,
            model,
        }
    }

    /// A groundstation command numbered `n`, all channels at `us`.
    fn command(model: &FrameModel, n: u64, us: u32) -> CommandSample {
        CommandSample {
            ingress_seq: n,
            seq: n,
            recv_mono_ns: 1_000 * n,
            recv_real_ns: 2_000 * n,
            ingress_pid: 99,
            has_seq: 1,
            channel_count: 6,
            clamped: 0,
            values_ns: [us * 1_000; MAX_CHANNELS],
            model: model.fingerprint(),
        }
    }

    /// Pilot frame `frame` with values `us`, in state `state`.
    fn frame(frame: u64, state: PilotState, us: &[u32]) -> PilotFrame {
        let mut values_ns = [0; MAX_CHANNELS];
        for (v, u) in values_ns.iter_mut().zip(us) {
            *v = u * 1_000;
        }
        PilotFrame {
            frame,
            end_mono_ns: 5_000_000 + frame,
            end_real_ns: 9_000_000 + frame,
            state,
            channels: us.len() as u8,
            values_ns,
        }
    }

    #[test]
    fn the_pilots_channels_go_out_clamped_and_filled_once_each() {
        let mut r = rig();
        // Four channels read: 2100 above the limit, 900 below, 1234.5 kept;
        // channel 5 at its default 1500, channel 6 at its own 1200.
        let mut f = frame(3, PilotState::Pilot, &[2100, 900, 1300, 1700]);
        f.values_ns[2] = 1_234_500;
        r.slot.store(&f);
        r.slot.set_state(PilotState::Pilot);
        let s = r.mux.newest().expect("the pilot's frame");
        assert_eq!(
            s.values_ns,
            [
                2_000_000, 1_000_000, 1_234_500, 1_700_000, 1_500_000, 1_200_000, 0, 0, 0, 0, 0, 0,
                0, 0, 0, 0
            ]
        );
        assert_eq!(s.clamped, 2);
        assert_eq!(s.channel_count, 6);
        assert_eq!((s.recv_mono_ns, s.recv_real_ns), (5_000_003, 9_000_003));
        assert_eq!(
            (s.ingress_seq, s.ingress_pid, s.has_seq, s.seq),
            (3, 0, 0, 0)
        );
        assert_eq!(s.model, r.model.fingerprint());
        // The loop takes it: its model, fresh from a start before it.
        let ch = s.channels(&r.model).expect("of the output's model");
        assert_eq!(ch.len(), 6);
        assert!(s.fresh(5_000_000, 5_000_003, 0));
        // The same frame is not handed out twice.
        assert_eq!(r.mux.newest(), None);
        assert_eq!(r.mux.newest(), None);
        // A new one is; channels beyond the model's are not carried, and
        // aux2's own limit clamps.
        r.slot.store(&frame(
            4,
            PilotState::Pilot,
            &[1500, 1500, 1500, 1500, 1500, 1900, 1500, 1500],
        ));
        let s = r.mux.newest().expect("the next frame");
        assert_eq!(s.ingress_seq, 4);
        assert_eq!(
            &s.values_ns[..7],
            &[1_500_000, 1_500_000, 1_500_000, 1_500_000, 1_500_000, 1_800_000, 0]
        );
        assert_eq!(s.clamped, 1);
        assert_eq!(r.calls.get(), 4, "the groundstation drained at every call");
    }

    #[test]
    fn no_input_lets_nothing_out_while_the_groundstation_sends() {
        let mut r = rig();
        for n in 1..=5 {
            r.next.set(Some(command(&r.model, n, 1600)));
            assert_eq!(r.mux.newest(), None, "command {n}");
        }
        // Frames stored with the state still NoInput do not go out either.
        r.slot.store(&frame(1, PilotState::NoInput, &[1500; 4]));
        r.next.set(Some(command(&r.model, 6, 1600)));
        assert_eq!(r.mux.newest(), None);
        assert_eq!(r.calls.get(), 6);
        // The pilot's radio reads: the kept (newest) command goes out once.
        r.slot.set_state(PilotState::Groundstation);
        assert_eq!(r.mux.newest(), Some(command(&r.model, 6, 1600)));
        assert_eq!(r.mux.newest(), None);
        r.next.set(Some(command(&r.model, 7, 1400)));
        assert_eq!(r.mux.newest(), Some(command(&r.model, 7, 1400)));
        // Lost again: nothing, whatever comes.
        r.slot.set_state(PilotState::NoInput);
        r.next.set(Some(command(&r.model, 8, 1400)));
        assert_eq!(r.mux.newest(), None);
    }

    #[test]
    fn switching_back_hands_the_kept_groundstation_command_once() {
        let mut r = rig();
        r.slot.set_state(PilotState::Groundstation);
        assert_eq!(r.mux.newest(), None, "no command yet");
        r.next.set(Some(command(&r.model, 1, 1300)));
        assert_eq!(r.mux.newest(), Some(command(&r.model, 1, 1300)));
        // The pilot takes over; the groundstation keeps sending.
        r.slot.store(&frame(1, PilotState::Pilot, &[1600; 6]));
        r.slot.set_state(PilotState::Pilot);
        r.next.set(Some(command(&r.model, 2, 1350)));
        let s = r.mux.newest().expect("the pilot's frame");
        assert_eq!(s.ingress_seq, 1);
        assert_eq!(s.values_ns[0], 1_600_000);
        r.next.set(Some(command(&r.model, 3, 1400)));
        assert_eq!(r.mux.newest(), None, "no new pilot frame");
        // A frame of the switch off, stored before the state says so, is
        // not the pilot's to fly.
        r.slot
            .store(&frame(2, PilotState::Groundstation, &[1000; 6]));
        assert_eq!(r.mux.newest(), None);
        // Given back: the newest groundstation command kept, once.
        r.slot.set_state(PilotState::Groundstation);
        assert_eq!(r.mux.newest(), Some(command(&r.model, 3, 1400)));
        assert_eq!(r.mux.newest(), None);
        assert_eq!(r.mux.newest(), None);
        // Given back with a command arriving at that call: that one.
        r.slot.store(&frame(3, PilotState::Pilot, &[1700; 6]));
        r.slot.set_state(PilotState::Pilot);
        assert_eq!(r.mux.newest().map(|s| s.ingress_seq), Some(3));
        r.slot.set_state(PilotState::Groundstation);
        r.next.set(Some(command(&r.model, 4, 1450)));
        assert_eq!(r.mux.newest(), Some(command(&r.model, 4, 1450)));
        assert_eq!(r.mux.newest(), None);
    }

    #[test]
    fn errors_and_wake_ups_are_the_groundstations() {
        let mut r = rig();
        assert_eq!(r.mux.errors(), 7);
        assert_eq!(r.mux.wake_fd(), Some(42));
        assert!(!r.mux.clear_wake());
        assert_eq!(r.cleared.get(), 1);
    }

    #[test]
    fn the_slot_reads_whole_frames_while_the_thread_writes() {
        let slot = Arc::new(PilotSlot::default());
        assert_eq!(slot.frame(), None, "no frame yet");
        assert_eq!(slot.state(), PilotState::NoInput);
        let writer = {
            let slot = slot.clone();
            std::thread::spawn(move || {
                for k in 1..=20_000u64 {
                    let n = (k % 16 + 1) as usize;
                    let state = [PilotState::Groundstation, PilotState::Pilot][(k % 2) as usize];
                    let mut f = frame(k, state, &vec![k as u32; n]);
                    f.values_ns[..n].fill(k as u32);
                    f.end_mono_ns = 3 * k;
                    f.end_real_ns = 5 * k;
                    slot.store(&f);
                    slot.set_state(state);
                }
            })
        };
        let (mut whole, mut met) = (0u64, 0u64);
        loop {
            let done = writer.is_finished();
            match slot.frame() {
                Some(f) => {
                    let k = f.frame;
                    assert_eq!((f.end_mono_ns, f.end_real_ns), (3 * k, 5 * k));
                    assert_eq!(f.channels as u64, k % 16 + 1);
                    assert!(f.values().iter().all(|&v| v as u64 == k), "{f:?}");
                    assert_eq!(f.state as u64, k % 2 + 1);
                    whole += 1;
                }
                None => met += 1,
            }
            if done {
                break;
            }
        }
        writer.join().unwrap();
        let last = slot.frame().unwrap();
        assert_eq!(last.frame, 20_000);
        assert_eq!(last.values()[..], [20_000; 1]);
        assert_eq!(slot.state(), PilotState::Groundstation);
        assert!(whole > 0, "{whole} whole reads, {met} met a write");
    }

    /// The line's edges, recorded.
    #[derive(Default)]
    struct Recorder(Vec<ppm_shared::trace::TraceEdge>);

    impl crate::line::Line for Recorder {
        fn write(
            &mut self,
            edge: &ppm_shared::trace::TraceEdge,
        ) -> Result<(), crate::line::LineError> {
            self.0.push(*edge);
            Ok(())
        }
        fn park(&mut self, _: Level) -> Result<(), crate::line::LineError> {
            Ok(())
        }
        fn stamped(&self) -> bool {
            true
        }
    }

    const MS: u64 = 1_000_000;

    /// On the simulated clock, ms after its start: the groundstation
    /// sends a fresh command at every look; the pilot's radio sends a
    /// frame every 25 ms from 100 ms (so each comes before a grid frame of
    /// its own), saying who flies as `script` says at its end (`None`: no
    /// frame); the slot says `NoInput` from `no_input_from`, as the
    /// pilot's thread does a second after the last frame.
    struct Scenario {
        sim: crate::clock::sim::Sim,
        slot: Arc<PilotSlot>,
        fingerprint: u64,
        script: fn(u64) -> Option<PilotState>,
        no_input_from: Option<u64>,
        /// Frame times passed, and pilot frames stored.
        ticks: u64,
        frames: u64,
        /// Groundstation commands sent while the state let them out.
        let_out: Rc<Cell<u64>>,
    }

    const GROUND_US: [u32; 4] = [1300, 1400, 1500, 1600];
    const PILOT_US: [u32; 4] = [2100, 1600, 1000, 1700];

    impl CommandSource for Scenario {
        fn newest(&mut self) -> Option<CommandSample> {
            use crate::clock::sim::START_NS;
            let now = self.sim.at();
            let ms = (now - START_NS) / MS;
            while START_NS + (100 + 25 * self.ticks) * MS <= now {
                let t = 100 + 25 * self.ticks;
                self.ticks += 1;
                if let Some(state) = (self.script)(t) {
                    self.frames += 1;
                    let mut f = frame(self.frames, state, &PILOT_US);
                    f.end_mono_ns = START_NS + t * MS;
                    self.slot.store(&f);
                    self.slot.set_state(state);
                }
            }
            if self.no_input_from.is_some_and(|m| ms >= m) {
                self.slot.set_state(PilotState::NoInput);
            }
            if self.slot.state() == PilotState::Groundstation {
                self.let_out.set(self.let_out.get() + 1);
            }
            let mut values_ns = [0; MAX_CHANNELS];
            for (v, us) in values_ns.iter_mut().zip(GROUND_US) {
                *v = us * 1_000;
            }
            Some(CommandSample {
                ingress_seq: 1,
                seq: 0,
                recv_mono_ns: now,
                recv_real_ns: 0,
                ingress_pid: 1,
                has_seq: 0,
                channel_count: 4,
                clamped: 0,
                values_ns,
                model: self.fingerprint,
            })
        }
    }

    /// Runs a grid output of 4 channels through a [`PilotMux`] on the
    /// simulated clock until `until_ms`, with failsafe `action` 100 ms
    /// after the last command: its counters, the groundstation commands
    /// let out, and the line's whole frames, runs of equal frames taken as
    /// one (start ms, values us).
    fn fly(
        script: fn(u64) -> Option<PilotState>,
        no_input_from: Option<u64>,
        action: ppm_shared::config::FailsafeAction,
        until_ms: u64,
    ) -> (crate::emitter::Stats, u64, Vec<(u64, Vec<u64>)>) {
        use crate::clock::sim::{Sim, START_NS};
        use crate::emitter::{run_outputs, EmitterConfig, LineRef, Output, Recording, Stats};
        use ppm_shared::config::FailsafeAction;
        let model = Config::parse("[ppm]\nchannels = 4\ntiming = \"grid\"\nreceiver = \"edgetx\"")
            .unwrap()
            .validate()
            .unwrap();
        let sim = Sim::new();
        let slot = Arc::new(PilotSlot::default());
        let let_out = Rc::new(Cell::new(0));
        let scenario = Scenario {
            sim: sim.clone(),
            slot: slot.clone(),
            fingerprint: model.fingerprint(),
            script,
            no_input_from,
            ticks: 0,
            frames: 0,
            let_out: let_out.clone(),
        };
        let mut mux = PilotMux::new(Box::new(scenario), slot, &model);
        let mut line = Recorder::default();
        let stats = Stats::default();
        let (mut meter, _reader) = crate::meter::meter(1_000_000_000);
        let stop = Arc::new(AtomicBool::new(false));
        sim.stop_at(START_NS + until_ms * MS, stop.clone());
        run_outputs(
            &sim,
            crate::clock::Margin::Fixed(100_000),
            &mut [Output {
                model: &model,
                cfg: EmitterConfig {
                    failsafe_after_ns: 100 * MS,
                    failsafe_action: action,
                    startup: FailsafeAction::Silence,
                },
                source: &mut mux,
                line: LineRef::Edges(&mut line),
                rec: Recording {
                    stats: &stats,
                    meter: &mut meter,
                    log: None,
                },
                sync: None,
            }],
            &mut [],
            &stop,
        );
        let trace = ppm_shared::trace::Trace {
            edges: line.0,
            idle_level: Some(Level::Low),
            ..Default::default()
        };
        let mut runs: Vec<(u64, Vec<u64>)> = vec![];
        for f in trace.decode(false).iter().filter(|f| f.complete) {
            if runs.last().is_none_or(|(_, v)| *v != f.channels_us()) {
                runs.push(((f.start_ns - START_NS) / MS, f.channels_us()));
            }
        }
        let last = trace_last_ms(&trace);
        runs.push((last, vec![]));
        (stats, let_out.get(), runs)
    }

    /// When the line's last edge was, ms after the simulation's start.
    fn trace_last_ms(trace: &ppm_shared::trace::Trace) -> u64 {
        trace
            .edges
            .last()
            .map_or(0, |e| (e.actual_ns - crate::clock::sim::START_NS) / MS)
    }

    #[test]
    fn the_loop_flies_the_groundstation_then_the_pilot_then_the_groundstation() {
        use ppm_shared::config::FailsafeAction;
        let script = |t: u64| {
            Some(match t {
                300..500 => PilotState::Pilot,
                _ => PilotState::Groundstation,
            })
        };
        let (stats, let_out, mut runs) = fly(script, None, FailsafeAction::Hold, 600);
        runs.pop();
        // Every command the loop took was its own and fresh: the pilot's
        // eight frames (300, 325, ... 475 ms), once each, and the
        // groundstation's let out.
        assert_eq!(stats.mismatched.load(Relaxed), 0);
        assert_eq!(stats.expired.load(Relaxed), 0);
        assert_eq!(stats.commands.load(Relaxed), let_out + 8);
        assert_eq!(stats.failsafe_entries.load(Relaxed), 0);
        // What the line carried: silence until the pilot's radio is read,
        // the groundstation, the pilot (clamped), the groundstation again.
        let values: Vec<&[u64]> = runs.iter().map(|(_, v)| v.as_slice()).collect();
        assert_eq!(
            values,
            [
                &[1300, 1400, 1500, 1600][..],
                &[2000, 1600, 1000, 1700],
                &[1300, 1400, 1500, 1600]
            ]
        );
        let at: Vec<u64> = runs.iter().map(|(t, _)| *t).collect();
        assert!(at[0] >= 100 && at[1] >= 300 && at[2] >= 500, "{at:?}");
        assert!(at[1] < 300 + 23 && at[2] < 500 + 23, "a frame late: {at:?}");
    }

    /// The pilot's radio goes quiet at 600 ms while the groundstation
    /// keeps sending: once the slot says `NoInput` (1600 ms, the thread's
    /// 1 s rule), the line is silent within a frame, neither holding the
    /// groundstation's command nor sending the failsafe's defaults.
    #[test]
    fn losing_the_pilots_radio_silences_the_line_whatever_the_failsafe() {
        use ppm_shared::config::FailsafeAction;
        let script = |t: u64| (t < 600).then_some(PilotState::Groundstation);
        for action in [FailsafeAction::Default, FailsafeAction::Hold] {
            let (stats, _, runs) = fly(script, Some(1_600), action, 3_000);
            let (last, _) = runs.last().unwrap();
            assert_eq!(runs.len(), 2, "{action:?}: {runs:?}");
            assert_eq!(runs[0].1, [1300, 1400, 1500, 1600], "{action:?}");
            // Flying until then (a frame is 22.5 ms), nothing a frame after.
            assert!(
                (1_600 - 45..1_600 + 23).contains(last),
                "{action:?}: the line's last edge at {last} ms"
            );
            assert_eq!(stats.failsafe_entries.load(Relaxed), 1, "{action:?}");
        }
    }

    /// The pilot's thread hangs at 600 ms, leaving `Groundstation` in the
    /// slot: 1.5 s after the newest frame ended (575 ms) the loop takes the
    /// pilot's radio as not read, and the line goes silent.
    #[test]
    fn a_hung_pilots_thread_silences_the_line() {
        use ppm_shared::config::FailsafeAction;
        let script = |t: u64| (t < 600).then_some(PilotState::Groundstation);
        let (_, _, runs) = fly(script, None, FailsafeAction::Default, 3_000);
        let (last, _) = runs.last().unwrap();
        assert_eq!(runs.len(), 2, "{runs:?}");
        let stale = 575 + STALE_NS / MS;
        assert!(
            (stale - 45..stale + 23).contains(last),
            "the line's last edge at {last} ms"
        );
    }

    /// A pulse's width, ns.
    const PULSE: u64 = 300_000;

    /// The edges of PPM pulses (idle low) starting at `leads`.
    fn pulses(leads: &[u64]) -> Vec<EdgeEvent> {
        leads
            .iter()
            .flat_map(|&t| [(t, Level::High), (t + PULSE, Level::Low)])
            .enumerate()
            .map(|(i, (at_ns, level))| EdgeEvent {
                at_ns,
                level,
                seq: i as u64 + 1,
            })
            .collect()
    }

    /// The leading edges of a lead-in pulse and `frames` frames of 22.5 ms
    /// from `start`, each of channels `us`, and the one closing the last.
    fn leads(start: u64, frames: &[&[u64]]) -> Vec<u64> {
        let mut out = vec![start - 10_000_000];
        let mut t = start;
        for f in frames {
            let mut c = t;
            out.push(c);
            for v in *f {
                c += v * 1_000;
                out.push(c);
            }
            t += 22_500_000;
        }
        out.push(t);
        out
    }

    fn tracker(channel: usize, slot: &Arc<PilotSlot>) -> Tracker {
        let settings = Settings {
            capture: CaptureSettings {
                idle: Some(Level::Low),
                channels: None,
            },
            switch_channel: channel,
            switch_above_ns: 1_500_000,
        };
        Tracker::new(String::new(), &settings, slot.clone())
    }

    #[test]
    fn the_switch_in_each_frame_says_who_flies() {
        let slot = Arc::new(PilotSlot::default());
        let mut t = tracker(4, &slot);
        let low: &[u64] = &[1100, 1200, 1300, 1400, 1000];
        let high: &[u64] = &[1100, 1200, 1300, 1400, 2000];
        let at: &[u64] = &[1100, 1200, 1300, 1400, 1500];
        let start = 1_000_000_000;
        let edges = pulses(&leads(start, &[low, low, low, low, high, high, at, at]));
        let mut states = vec![];
        for e in &edges {
            let before = slot.frame().map(|f| f.frame);
            t.edge(*e);
            if slot.frame().map(|f| f.frame) != before {
                states.push(slot.state());
            }
        }
        // Two frames lock the count of 5; then two low, two high and two
        // at the threshold (not above it): the first of those keeps the
        // pilot flying, the second gives the controls back.
        use PilotState::{Groundstation as G, Pilot as P};
        assert_eq!(states, [G, G, P, P, P, G]);
        let f = slot.frame().unwrap();
        assert_eq!(f.frame, 6);
        assert_eq!(
            f.values(),
            [1_100_000, 1_200_000, 1_300_000, 1_400_000, 1_500_000]
        );
        assert_eq!(f.end_mono_ns, start + 8 * 22_500_000);
        assert_eq!(f.state, PilotState::Groundstation);
        assert_eq!(slot.state(), PilotState::Groundstation);
        let s = t.publish_at(start + 9 * 22_500_000);
        assert_eq!((s.frames, s.matched, s.mismatched), (6, 3, 3));
        assert_eq!(s.state, ReadbackState::Following as u32);
        // no_input -> groundstation -> pilot -> groundstation
        assert_eq!(s.changes, 3);
        assert_eq!(s.changed_mono_ns, start + 8 * 22_500_000);
        assert_eq!(s.edges, edges.len() as u64);
        assert_eq!(s.channels, 5);
        assert_eq!(s.start_mono_ns, start + 7 * 22_500_000);
        assert_eq!(s.refused[6], 2, "the two frames that locked the count");
        // A second after the last frame: no input.
        let end = start + 8 * 22_500_000;
        t.tick(end + 999_999_999);
        assert_eq!(slot.state(), PilotState::Groundstation);
        t.tick(end + 1_000_000_000);
        assert_eq!(slot.state(), PilotState::NoInput);
        let s = t.publish_at(end + 1_000_000_000);
        assert_eq!((s.state, s.changes), (ReadbackState::NoInput as u32, 4));
        assert_eq!(s.changed_mono_ns, end + 1_000_000_000);
        t.tick(end + 2_000_000_000);
        assert_eq!(t.publish_at(0).changes, 4, "one change");
    }

    #[test]
    fn frames_without_the_switch_channel_are_no_input() {
        let slot = Arc::new(PilotSlot::default());
        let mut t = tracker(5, &slot);
        let high: &[u64] = &[1100, 1200, 1300, 1400, 2000];
        for e in pulses(&leads(1_000_000_000, &[high; 5])) {
            t.edge(e);
        }
        assert_eq!(slot.state(), PilotState::NoInput);
        let f = slot.frame().unwrap();
        assert_eq!((f.frame, f.state, f.channels), (3, PilotState::NoInput, 5));
        let s = t.publish_at(0);
        assert_eq!((s.frames, s.matched, s.mismatched, s.changes), (3, 0, 0, 0));
        assert!(t.warned_short);
    }
}
