//! PPM input as real receivers decode it: the trainer input of EdgeTX and
//! OpenTX transmitters and the PPM receivers of Betaflight and ArduPilot
//! flight controllers, each modelled on its firmware's decoder (the file and
//! function are named on each [`Receiver`]).
//!
//! All of them time one direction of edges only ([`TIMED_EDGE`], the rising
//! edge at the pin: with the line idle high, the edge that ends a pulse; the
//! decoders here take it as their `leading` level), as periods of their
//! capture clock, and
//! find frames by their sync period alone: none looks at the frame length.
//! They differ in the capture resolution, in whether the bounds are strict,
//! in the channel counts they take, in what an invalid period does and in
//! when they hand a frame on. [`ReceiverDecoder`] reproduces each, including
//! the capture clock's truncation and EdgeTX's 16-bit timer wrap, so a
//! waveform that decodes here decodes there.

use crate::decode::{DecodedFrame, LeadingEdges};
use crate::signal::{Level, CHANNEL_MAX_US, CHANNEL_MIN_US, SYNC_MAX_US, SYNC_MIN_US};
use serde::Deserialize;

/// The edge every modelled receiver times: rising at the pin, whatever the
/// line's idle level.
pub const TIMED_EDGE: Level = Level::High;

/// A receiver whose PPM decoding is modelled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Receiver {
    /// EdgeTX 2.10 and later, trainer input
    /// (`radio/src/targets/common/arm/stm32/trainer_driver.cpp`,
    /// `capture_pulse`): rising edges captured at 2 MHz by a 16-bit timer,
    /// periods truncated to whole us; sync 4000 < v < 19000 us; channels
    /// 800 <= v <= 2200 us; up to 16 channels (more are ignored); each
    /// channel is used as it arrives; an invalid period drops the rest of
    /// the frame.
    EdgeTx,
    /// OpenTX and EdgeTX up to 2.9, trainer input (`radio/src/trainer.h`,
    /// `captureTrainerPulses`): as EdgeTX 2.10 but channels strictly inside
    /// 800 < v < 2200 us.
    OpenTx,
    /// Betaflight's PPM receiver (`src/main/drivers/rx/rx_pwm.c`,
    /// `ppmEdgeCallback`): rising edges at 1 MHz; sync v > 2700 us, no upper
    /// bound; channels 750 < v < 2250 us; 4..=12 channels, the same count in
    /// every frame (13 or more: every frame dropped); a frame is handed on
    /// at the sync that ends it, once 25 frames of one count have locked
    /// that count (the 27th frame after the first sync is the first one).
    Betaflight,
    /// ArduPilot's PPMSum decoder
    /// (`libraries/AP_RCProtocol/AP_RCProtocol_PPMSum.cpp`, `process_pulse`):
    /// periods at 1 MHz; sync v >= 2700 us, no upper bound; channels
    /// 700 < v < 2300 us, other periods skipped (later channels move down
    /// one); a frame of 5..=18 channels is handed on at its sync (at once on
    /// the 18th channel); the protocol locks on its 3rd frame.
    ArduPilot,
}

impl Receiver {
    /// Every modelled receiver.
    pub const ALL: [Receiver; 4] = [
        Receiver::EdgeTx,
        Receiver::OpenTx,
        Receiver::Betaflight,
        Receiver::ArduPilot,
    ];

    /// The name used in configuration and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Receiver::EdgeTx => "edgetx",
            Receiver::OpenTx => "opentx",
            Receiver::Betaflight => "betaflight",
            Receiver::ArduPilot => "ardupilot",
        }
    }

    /// Complete frames of a steady stream this receiver reads but does not
    /// hand on before it locks: Betaflight 26, ArduPilot 2, the trainer
    /// inputs none.
    pub fn warmup_frames(self) -> usize {
        match self {
            Receiver::EdgeTx | Receiver::OpenTx => 0,
            Receiver::Betaflight => BETAFLIGHT_STABLE_FRAMES as usize + 1,
            Receiver::ArduPilot => 2,
        }
    }

    /// Capture clock period, ns.
    fn tick_ns(self) -> u64 {
        match self {
            Receiver::EdgeTx | Receiver::OpenTx => 500,
            Receiver::Betaflight | Receiver::ArduPilot => 1_000,
        }
    }
}

impl std::str::FromStr for Receiver {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Receiver::ALL
            .into_iter()
            .find(|r| r.name() == s)
            .ok_or_else(|| {
                format!("`{s}` is not a receiver: use edgetx, opentx, betaflight or ardupilot")
            })
    }
}

/// The receiver a configuration is for (`ppm.receiver`): one of them, or
/// `any`, what every one of them accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(try_from = "String")]
pub enum ReceiverChoice {
    /// Every modelled receiver.
    Any,
    /// This one.
    One(Receiver),
}

impl std::str::FromStr for ReceiverChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "any" => Ok(ReceiverChoice::Any),
            _ => s.parse().map(ReceiverChoice::One).map_err(|_| {
                format!("`{s}` is not a receiver: use any, edgetx, opentx, betaflight or ardupilot")
            }),
        }
    }
}

impl TryFrom<String> for ReceiverChoice {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl ReceiverChoice {
    /// The name used in configuration and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ReceiverChoice::Any => "any",
            ReceiverChoice::One(r) => r.name(),
        }
    }

    /// The receivers this choice covers.
    pub fn receivers(self) -> Vec<Receiver> {
        match self {
            ReceiverChoice::Any => Receiver::ALL.to_vec(),
            ReceiverChoice::One(r) => vec![r],
        }
    }

    /// What ppm may send: the tightest of each bound over the receivers
    /// covered, each with the rule it comes from.
    pub fn rules(self) -> Rules {
        let all: Vec<Rules> = self.receivers().into_iter().map(Receiver::rules).collect();
        let pick = |better: fn(&Rules, &Rules) -> bool| {
            *all.iter()
                .reduce(|a, b| if better(b, a) { b } else { a })
                .expect("a receiver")
        };
        Rules {
            min_channels: pick(|a, b| a.min_channels.0 > b.min_channels.0).min_channels,
            max_channels: pick(|a, b| a.max_channels.0 < b.max_channels.0).max_channels,
            channel_min_us: pick(|a, b| a.channel_min_us.0 > b.channel_min_us.0).channel_min_us,
            channel_max_us: pick(|a, b| a.channel_max_us.0 < b.channel_max_us.0).channel_max_us,
            sync_min_us: pick(|a, b| a.sync_min_us.0 > b.sync_min_us.0).sync_min_us,
            sync_max_us: pick(|a, b| a.sync_max_us.0 < b.sync_max_us.0).sync_max_us,
        }
    }
}

/// Margin kept inside a receiver's channel window: a channel's period is
/// the time between two edges, each of which may come a little late (the
/// tail of ppmd's edge error on a loaded real-time board: p99.9 under 10 us
/// in most runs, now and then tens of us), and the trainer inputs truncate
/// to whole microseconds.
pub const CHANNEL_MARGIN_US: f64 = 20.0;

/// Margin kept inside a receiver's sync window: one late edge (the frame's
/// first, or the previous frame's last) lengthens or shortens the sync by
/// its lateness; a tuned PREEMPT_RT Raspberry Pi wakes at most 100-190 us
/// late, and ppmd spins the last part of every wait on top of that.
pub const SYNC_MARGIN_US: f64 = 500.0;

/// The longest period a 16-bit capture timer at 1 MHz measures, us
/// (Betaflight's and ArduPilot's): their only bound on a sync.
const CAPTURE_16_BIT_US: f64 = 65_536.0;

/// What ppm may send to a receiver, each bound with the rule it comes from
/// (for error messages). Channel and sync bounds are the receiver's own
/// less [`CHANNEL_MARGIN_US`] and [`SYNC_MARGIN_US`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rules {
    /// Fewest channels in a frame.
    pub min_channels: (usize, &'static str),
    /// Most channels in a frame.
    pub max_channels: (usize, &'static str),
    /// Lowest channel value, us.
    pub channel_min_us: (f64, &'static str),
    /// Highest channel value, us.
    pub channel_max_us: (f64, &'static str),
    /// Shortest sync gap, us.
    pub sync_min_us: (f64, &'static str),
    /// Longest sync gap, us.
    pub sync_max_us: (f64, &'static str),
}

impl Receiver {
    /// What ppm may send to this receiver.
    pub fn rules(self) -> Rules {
        const TRAINER_SYNC_MIN: &str =
            "EdgeTX and OpenTX read a sync strictly between 4000 and 19000 us (capture_pulse, captureTrainerPulses)";
        const TRAINER_MAX: &str =
            "EdgeTX and OpenTX read at most 16 channels (MAX_TRAINER_CHANNELS)";
        const EDGETX_CHANNEL: &str = "EdgeTX 2.10 reads a channel of 800..=2200 us (capture_pulse)";
        const OPENTX_CHANNEL: &str = "OpenTX and EdgeTX before 2.10 read a channel strictly between 800 and 2200 us (captureTrainerPulses)";
        const BETAFLIGHT_CHANNEL: &str = "Betaflight takes a channel of 885..=2115 us as valid (rx_min_usec and rx_max_usec, their defaults)";
        const PPM_RANGE: &str = "ppm sends channels of 800..=2200 us";
        let c = CHANNEL_MARGIN_US;
        let sync = |us: f64| us + SYNC_MARGIN_US;
        match self {
            Receiver::EdgeTx => Rules {
                min_channels: (1, "EdgeTX reads a frame of any channel count"),
                max_channels: (16, TRAINER_MAX),
                channel_min_us: (CHANNEL_MIN_US + c, EDGETX_CHANNEL),
                channel_max_us: (CHANNEL_MAX_US - c, EDGETX_CHANNEL),
                sync_min_us: (sync(SYNC_MIN_US), TRAINER_SYNC_MIN),
                sync_max_us: (SYNC_MAX_US - SYNC_MARGIN_US, TRAINER_SYNC_MIN),
            },
            Receiver::OpenTx => Rules {
                min_channels: (1, "OpenTX reads a frame of any channel count"),
                max_channels: (16, TRAINER_MAX),
                channel_min_us: (801.0 + c, OPENTX_CHANNEL),
                channel_max_us: (2_199.0 - c, OPENTX_CHANNEL),
                sync_min_us: (sync(SYNC_MIN_US), TRAINER_SYNC_MIN),
                sync_max_us: (SYNC_MAX_US - SYNC_MARGIN_US, TRAINER_SYNC_MIN),
            },
            Receiver::Betaflight => Rules {
                min_channels: (4, "Betaflight decodes 4..=12 channels (rx_pwm.c, PPM_IN_MIN_NUM_CHANNELS)"),
                max_channels: (12, "Betaflight decodes 4..=12 channels and drops every frame of 13 or more (rx_pwm.c, PPM_IN_MAX_NUM_CHANNELS)"),
                channel_min_us: (885.0 + c, BETAFLIGHT_CHANNEL),
                channel_max_us: (2_115.0 - c, BETAFLIGHT_CHANNEL),
                sync_min_us: (sync(2_700.0), "Betaflight reads a sync only above 2700 us (rx_pwm.c, PPM_IN_MIN_SYNC_PULSE_US)"),
                sync_max_us: (CAPTURE_16_BIT_US - SYNC_MARGIN_US, "Betaflight's 16-bit capture timer at 1 MHz measures a gap only up to 65536 us (rx_pwm.c, PPM_TIMER_PERIOD)"),
            },
            Receiver::ArduPilot => Rules {
                min_channels: (5, "ArduPilot drops a frame of fewer than 5 channels (AP_RCProtocol_PPMSum.cpp, MIN_RCIN_CHANNELS)"),
                max_channels: (16, "ppm sends at most 16 channels"),
                // Its window (701..=2299 us) holds ppm's whole range.
                channel_min_us: (800.0, PPM_RANGE),
                channel_max_us: (2_200.0, PPM_RANGE),
                sync_min_us: (sync(2_700.0), "ArduPilot reads a sync only from 2700 us (AP_RCProtocol_PPMSum.cpp)"),
                sync_max_us: (CAPTURE_16_BIT_US - SYNC_MARGIN_US, "ArduPilot's 16-bit input capture at 1 MHz measures a gap only up to 65536 us"),
            },
        }
    }
}

/// What a receiver threw away.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReceiverStats {
    /// Timed edges seen.
    pub edges: u64,
    /// Periods that were neither a channel nor a sync where one was expected
    /// (EdgeTX/OpenTX, Betaflight: the frame is lost; ArduPilot: skipped).
    pub invalid_periods: u64,
    /// Frames ended by a sync but not handed on (a channel count the
    /// receiver does not take, or before it locked).
    pub unused_frames: u64,
}

/// Streaming decoder with one receiver's rules: feed the line's level
/// changes in time order with [`ReceiverDecoder::push`].
#[derive(Debug, Clone)]
pub struct ReceiverDecoder {
    receiver: Receiver,
    edges: LeadingEdges,
    /// Capture of the previous timed edge, in ticks.
    last_tick: Option<u64>,
    /// Channels of the frame in progress, us; `None` while not synchronised.
    frame: Option<Vec<u64>>,
    /// Start of the frame in progress, ns.
    start_ns: u64,
    /// Betaflight: channel count of the previous frame, frames seen with it,
    /// the locked count.
    prev_count: Option<usize>,
    stable: u32,
    locked: Option<usize>,
    /// Betaflight: channels read when an invalid period stopped the frame.
    cut: usize,
    /// ArduPilot: frames accepted so far (it locks on the third).
    accepted: u32,
    stats: ReceiverStats,
}

/// Betaflight's frames of one count needed to lock that count
/// (`PPM_STABLE_FRAMES_REQUIRED_COUNT`).
const BETAFLIGHT_STABLE_FRAMES: u32 = 25;

impl ReceiverDecoder {
    /// A decoder timing the edges after which the line is at `leading`.
    pub fn new(receiver: Receiver, leading: Level) -> ReceiverDecoder {
        ReceiverDecoder {
            receiver,
            edges: LeadingEdges::new(leading),
            last_tick: None,
            frame: None,
            start_ns: 0,
            prev_count: None,
            stable: 0,
            locked: None,
            cut: 0,
            accepted: 0,
            stats: ReceiverStats::default(),
        }
    }

    /// The receiver modelled.
    pub fn receiver(&self) -> Receiver {
        self.receiver
    }

    /// What was thrown away so far.
    pub fn stats(&self) -> ReceiverStats {
        self.stats
    }

    /// Feeds the line's level after a change at `at_ns`; returns a frame
    /// when the receiver hands one on (EdgeTX and OpenTX use each channel as
    /// it arrives: their frames are returned at the sync or invalid period
    /// that ends them, `complete` false when an invalid period cut them).
    pub fn push(&mut self, at_ns: u64, level: Level) -> Option<DecodedFrame> {
        if !self.edges.timed(level) {
            return None;
        }
        self.stats.edges += 1;
        let tick = at_ns / self.receiver.tick_ns();
        let prev = self.last_tick.replace(tick)?;
        match self.receiver {
            Receiver::EdgeTx | Receiver::OpenTx => {
                // A 16-bit timer at 2 MHz, halved: whole microseconds.
                let v = (tick.wrapping_sub(prev) as u16 / 2) as u64;
                self.trainer(at_ns, v)
            }
            Receiver::Betaflight => self.betaflight(at_ns, tick - prev),
            Receiver::ArduPilot => self.ardupilot(at_ns, tick - prev),
        }
    }

    /// Ends the input: EdgeTX/OpenTX's channels of an unfinished frame (they
    /// are in use already); the others hand nothing on without a sync.
    pub fn finish(&mut self) -> Option<DecodedFrame> {
        match self.receiver {
            Receiver::EdgeTx | Receiver::OpenTx => {
                let ch = self.frame.take()?;
                self.emit(ch, false)
            }
            _ => None,
        }
    }

    fn emit(&self, channels_us: Vec<u64>, complete: bool) -> Option<DecodedFrame> {
        (!channels_us.is_empty()).then(|| DecodedFrame {
            start_ns: self.start_ns,
            channels_ns: channels_us.iter().map(|us| us * 1_000).collect(),
            complete,
        })
    }

    fn trainer(&mut self, at_ns: u64, v: u64) -> Option<DecodedFrame> {
        if v > 4_000 && v < 19_000 {
            let done = self
                .frame
                .replace(Vec::new())
                .and_then(|ch| self.emit(ch, true));
            self.start_ns = at_ns;
            return done;
        }
        let full = self.frame.as_ref()?.len() >= 16;
        if full {
            // The 17th channel and on are ignored until the next sync.
            return None;
        }
        let channel = if self.receiver == Receiver::EdgeTx {
            (800..=2_200).contains(&v)
        } else {
            v > 800 && v < 2_200
        };
        if channel {
            self.frame.as_mut().expect("synchronised").push(v);
            None
        } else {
            self.stats.invalid_periods += 1;
            let cut = self.frame.take().expect("synchronised");
            self.emit(cut, false)
        }
    }

    fn betaflight(&mut self, at_ns: u64, v: u64) -> Option<DecodedFrame> {
        if v > 2_700 {
            // The count seen is where the frame stopped (a frame cut by an
            // invalid period stopped early).
            let (count, tracking, channels) = match self.frame.take() {
                Some(ch) => (ch.len(), true, ch),
                None => (self.cut, false, Vec::new()),
            };
            self.cut = 0;
            let seen = self.prev_count.is_some();
            if seen && Some(count) == self.prev_count && (4..=12).contains(&count) {
                if self.stable < BETAFLIGHT_STABLE_FRAMES {
                    self.stable += 1;
                } else {
                    self.locked = Some(count);
                }
            } else {
                self.stable = 0;
            }
            let handed = tracking && self.locked == Some(count);
            if seen && !handed && count > 0 {
                self.stats.unused_frames += 1;
            }
            let out = if handed {
                self.emit(channels, true)
            } else {
                None
            };
            self.prev_count = Some(count);
            self.frame = Some(Vec::new());
            self.start_ns = at_ns;
            return out;
        }
        let frame = self.frame.as_mut()?;
        if v > 750 && v < 2_250 && frame.len() < 12 {
            frame.push(v);
        } else {
            self.stats.invalid_periods += 1;
            self.cut = frame.len();
            self.frame = None;
        }
        None
    }

    fn ardupilot(&mut self, at_ns: u64, v: u64) -> Option<DecodedFrame> {
        if v >= 2_700 {
            let out = match self.frame.replace(Vec::new()) {
                Some(ch) if ch.len() >= 5 => self.accept(ch),
                Some(ch) if !ch.is_empty() => {
                    self.stats.unused_frames += 1;
                    None
                }
                _ => None,
            };
            self.start_ns = at_ns;
            return out;
        }
        let frame = self.frame.as_mut()?;
        if v > 700 && v < 2_300 {
            frame.push(v);
        } else {
            self.stats.invalid_periods += 1;
        }
        if frame.len() >= 18 {
            let ch = self.frame.take().expect("synchronised");
            return self.accept(ch);
        }
        None
    }

    /// ArduPilot: a frame of 5..=18 channels; handed on from the third.
    fn accept(&mut self, ch: Vec<u64>) -> Option<DecodedFrame> {
        self.accepted += 1;
        if self.accepted < 3 {
            self.stats.unused_frames += 1;
            return None;
        }
        self.emit(ch, true)
    }
}

/// Decodes a whole waveform, given as `(time_ns, level_after)` changes, as
/// `receiver` does: the frames it hands on, and what it threw away.
pub fn decode_as(
    receiver: Receiver,
    edges: impl IntoIterator<Item = (u64, Level)>,
    leading: Level,
) -> (Vec<DecodedFrame>, ReceiverStats) {
    let mut d = ReceiverDecoder::new(receiver, leading);
    let mut frames: Vec<DecodedFrame> = edges
        .into_iter()
        .filter_map(|(t, l)| d.push(t, l))
        .collect();
    frames.extend(d.finish());
    (frames, d.stats())
}

#[cfg(test)]
mod tests {
    use super::*;

    const PULSE: u64 = 300_000;

    /// A waveform of pulses starting at `starts` (ns), idle `idle`.
    fn pulses(starts: &[u64], idle: Level) -> Vec<(u64, Level)> {
        starts
            .iter()
            .flat_map(|&t| [(t, idle.opposite()), (t + PULSE, idle)])
            .collect()
    }

    /// Leading-edge times of `frames` frames, each a sync of `sync_ns` then
    /// the channel periods `ch_ns`, after one first lone pulse.
    fn train(frames: usize, sync_ns: u64, ch_ns: &[u64]) -> Vec<u64> {
        let mut t = 1_000_000;
        let mut starts = vec![t];
        for _ in 0..frames {
            t += sync_ns;
            starts.push(t);
            for c in ch_ns {
                t += c;
                starts.push(t);
            }
        }
        // The sync that ends the last frame.
        starts.push(t + sync_ns);
        starts
    }

    fn decoded(r: Receiver, starts: &[u64]) -> (Vec<Vec<u64>>, ReceiverStats) {
        let (frames, stats) = decode_as(r, pulses(starts, Level::Low), Level::High);
        let complete = frames
            .iter()
            .filter(|f| f.complete)
            .map(|f| f.channels_us())
            .collect();
        (complete, stats)
    }

    const US: u64 = 1_000;

    #[test]
    fn trainer_sync_is_strictly_between_4_and_19_ms() {
        let ch = [1_500 * US; 8];
        for r in [Receiver::EdgeTx, Receiver::OpenTx] {
            for (sync, read) in [
                (4_000 * US, false),
                (4_001 * US, true),
                (18_999 * US + 500, true),
                (19_000 * US, false),
            ] {
                let (frames, _) = decoded(r, &train(3, sync, &ch));
                // The first frame follows the lone pulse's gap, a sync too.
                let want = if read { 3 } else { 0 };
                assert_eq!(frames.len(), want, "{r:?} sync {sync} ns: {frames:?}");
            }
        }
    }

    #[test]
    fn trainer_channel_bounds() {
        for (r, v, read) in [
            (Receiver::EdgeTx, 800, true),
            (Receiver::EdgeTx, 2_200, true),
            (Receiver::EdgeTx, 799, false),
            (Receiver::EdgeTx, 2_201, false),
            (Receiver::OpenTx, 800, false),
            (Receiver::OpenTx, 2_200, false),
            (Receiver::OpenTx, 801, true),
            (Receiver::OpenTx, 2_199, true),
        ] {
            let ch = [1_500 * US, v * US, 1_500 * US];
            let (frames, stats) = decoded(r, &train(2, 10_000 * US, &ch));
            if read {
                assert_eq!(frames, vec![vec![1_500, v, 1_500]; 2], "{r:?} {v}");
                assert_eq!(stats.invalid_periods, 0);
            } else {
                assert!(frames.is_empty(), "{r:?} {v}: {frames:?}");
                assert_eq!(stats.invalid_periods, 2, "{r:?} {v}");
            }
        }
    }

    #[test]
    fn trainer_truncates_to_whole_microseconds() {
        // 2200.9 us is 4401 ticks of 0.5 us: 2200 us, read by EdgeTX 2.10.
        let ch = [2_200 * US + 900, 1_000 * US + 499];
        let (frames, _) = decoded(Receiver::EdgeTx, &train(1, 8_000 * US, &ch));
        assert_eq!(frames, vec![vec![2_200, 1_000]]);
    }

    #[test]
    fn trainer_takes_16_channels_and_ignores_more() {
        let (frames, _) = decoded(Receiver::EdgeTx, &train(2, 6_000 * US, &[1_000 * US; 17]));
        assert_eq!(frames, vec![vec![1_000; 16]; 2]);
        let (frames, _) = decoded(Receiver::EdgeTx, &train(2, 6_000 * US, &[1_000 * US; 1]));
        assert_eq!(frames, vec![vec![1_000]; 2], "no minimum");
    }

    #[test]
    fn trainer_timer_wraps_every_32768_us() {
        // A silence of 32.768 ms plus 5 ms reads as a 5 ms sync.
        let starts = [0, 37_768 * US, 38_768 * US, 40_768 * US, 47_000 * US];
        let (frames, _) = decoded(Receiver::EdgeTx, &starts);
        assert_eq!(frames, vec![vec![1_000, 2_000]]);
    }

    #[test]
    fn betaflight_locks_a_count_of_4_to_12_after_26_frames() {
        for n in [3, 4, 12, 13] {
            let ch = vec![1_200 * US; n];
            let (frames, stats) = decoded(Receiver::Betaflight, &train(40, 3_000 * US, &ch));
            if (4..=12).contains(&n) {
                // Frames 27..=40 of the 40.
                assert_eq!(frames, vec![vec![1_200; n]; 14], "{n} channels");
                assert_eq!(stats.unused_frames, 26, "{n}");
                assert_eq!(Receiver::Betaflight.warmup_frames(), 26);
            } else {
                assert!(frames.is_empty(), "{n} channels: {frames:?}");
            }
        }
    }

    #[test]
    fn betaflight_bounds_are_strict_and_sync_has_no_maximum() {
        for (sync, v, read) in [
            (2_700, 1_500, false),
            (2_701, 1_500, true),
            (60_000, 1_500, true),
            (5_000, 750, false),
            (5_000, 751, true),
            (5_000, 2_249, true),
            (5_000, 2_250, false),
        ] {
            let ch = [v * US, 1_500 * US, 1_500 * US, 1_500 * US];
            let (frames, _) = decoded(Receiver::Betaflight, &train(30, sync * US, &ch));
            assert_eq!(!frames.is_empty(), read, "sync {sync}, channel {v}");
        }
    }

    #[test]
    fn ardupilot_takes_5_to_18_channels_from_its_third_frame() {
        for (n, want) in [(4, 0), (5, 5), (18, 18), (19, 18)] {
            let ch = vec![1_100 * US; n];
            let (frames, _) = decoded(Receiver::ArduPilot, &train(6, 2_700 * US, &ch));
            if want == 0 {
                assert!(frames.is_empty(), "{n}: {frames:?}");
            } else {
                assert_eq!(frames, vec![vec![1_100; want]; 4], "{n} channels");
                assert_eq!(Receiver::ArduPilot.warmup_frames(), 6 - 4);
            }
        }
    }

    #[test]
    fn ardupilot_skips_a_period_outside_its_window() {
        // 2400 us is neither a channel nor a sync: skipped, the next channel
        // takes its place.
        let ch = [
            1_000 * US,
            2_400 * US,
            1_200 * US,
            1_300 * US,
            1_400 * US,
            1_500 * US,
        ];
        let (frames, stats) = decoded(Receiver::ArduPilot, &train(4, 5_000 * US, &ch));
        assert_eq!(frames, vec![vec![1_000, 1_200, 1_300, 1_400, 1_500]; 2]);
        assert_eq!(stats.invalid_periods, 4);
        for (v, read) in [(700, false), (701, true), (2_299, true), (2_300, false)] {
            let ch = [v * US, 1_500 * US, 1_500 * US, 1_500 * US, 1_500 * US];
            let (frames, _) = decoded(Receiver::ArduPilot, &train(4, 5_000 * US, &ch));
            // Skipped, it leaves 4 channels: too few, no frame.
            assert_eq!(frames.first().map(Vec::len), read.then_some(5), "{v}");
        }
    }

    #[test]
    fn either_polarity_times_the_edges_that_leave_idle() {
        let starts = train(
            30,
            9_000 * US,
            &[1_100 * US, 1_900 * US, 1_300 * US, 1_700 * US, 1_500 * US],
        );
        for r in Receiver::ALL {
            let low = decode_as(r, pulses(&starts, Level::Low), Level::High).0;
            let high = decode_as(r, pulses(&starts, Level::High), Level::Low).0;
            assert!(!low.is_empty(), "{r:?}");
            assert_eq!(low, high, "{r:?}");
            assert_eq!(low[0].channels_us(), [1_100, 1_900, 1_300, 1_700, 1_500]);
            // A frame starts at its first pulse, after the sync.
            let first = 1_000_000
                + (r.warmup_frames() as u64 + 1) * 9_000_000
                + r.warmup_frames() as u64 * 7_500_000;
            assert_eq!(low[0].start_ns, first, "{r:?}");
        }
    }

    #[test]
    fn names_round_trip() {
        for r in Receiver::ALL {
            assert_eq!(r.name().parse::<Receiver>(), Ok(r));
        }
        assert!("spektrum".parse::<Receiver>().is_err());
    }
}
