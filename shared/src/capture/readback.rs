//! Read-back: does the radio transmit ppm's values? Each frame read from the
//! radio's PPM output is compared with the frames ppm's line carried shortly
//! before it, channel by channel; enough frames in a row that agree (or
//! not) make the state `following` (or `overridden`), and no whole frame for
//! [`INPUT_VALID_NS`](super::decode::INPUT_VALID_NS) makes it `no_input`.
//!
//! A channel of a frame read matches when some frame ppm's line carried
//! that began within the window before the read frame ended (`window_ns`
//! before its start, up to its end) carried that channel within
//! `tolerance_ns`, or the newest frame the line carried before it ended,
//! if that began within [`HELD_NS`] (1 s): a radio keeps relaying the last
//! trainer values it read until its input times out, so a line whose
//! frames were cut short for a while is still followed. Channels are
//! matched one by one, not frame by frame,
//! because a radio (EdgeTX, OpenTX) uses each trainer channel as it
//! arrives: one frame it transmits may mix channels of two frames ppm sent.
//! Only the channels both frames have are compared (a radio sending 8
//! channels relays ppm's 4 in its first 4). A frame read while ppm's line
//! carried nothing for a second does not match: the radio transmits its
//! own.

use super::decode::ReadFrame;
use crate::signal::MAX_CHANNELS;

/// Whether the radio transmits ppm's values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[repr(u32)]
pub enum ReadbackState {
    /// No whole frame read for a second (or none yet).
    #[default]
    NoInput = 0,
    /// The radio transmits ppm's values, within the tolerance.
    Following = 1,
    /// The radio transmits something else: the instructor has control.
    Overridden = 2,
}

impl ReadbackState {
    /// Its name in status replies, events and logs.
    pub fn name(self) -> &'static str {
        match self {
            ReadbackState::NoInput => "no_input",
            ReadbackState::Following => "following",
            ReadbackState::Overridden => "overridden",
        }
    }

    /// The state of code `code` ([`ReadbackState`] `as u32`).
    pub fn from_code(code: u32) -> Option<ReadbackState> {
        [
            ReadbackState::NoInput,
            ReadbackState::Following,
            ReadbackState::Overridden,
        ]
        .into_iter()
        .find(|s| *s as u32 == code)
    }
}

/// How frames read are judged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MatchSettings {
    /// Largest difference, per channel, between a value read and one ppm
    /// carried that still matches, ns.
    pub tolerance_ns: u32,
    /// How long before a read frame's start a frame ppm carried may have
    /// begun and still be what the radio relays, ns (the radio's own
    /// latency: its mixer and its module's frame).
    pub window_ns: u64,
    /// Frames read in a row that must agree before the state changes.
    pub frames: u8,
}

impl Default for MatchSettings {
    fn default() -> Self {
        MatchSettings {
            tolerance_ns: 10_000,
            window_ns: 100_000_000,
            frames: 2,
        }
    }
}

/// One frame ppm's line carried.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Carried {
    /// CLOCK_MONOTONIC time of its first edge, ns.
    pub start_ns: u64,
    /// Channels carried.
    pub count: u8,
    /// The values carried, ns.
    pub values_ns: [u32; MAX_CHANNELS],
}

/// What one frame read came to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Verdict {
    /// It carried ppm's values.
    pub matched: bool,
    /// Largest difference, over its channels, to the nearest value ppm
    /// carried in the window, ns (`u32::MAX` when ppm carried nothing).
    pub max_diff_ns: u32,
    /// The state change it made, if any: `(from, to)`.
    pub changed: Option<(ReadbackState, ReadbackState)>,
}

/// How long a radio keeps relaying the last trainer values it read:
/// EdgeTX's trainer input is valid 1 s after the last good frame.
pub const HELD_NS: u64 = 1_000_000_000;

/// Frames of ppm's line kept: `readback.window_ms` at its largest (2 s)
/// of the shortest PPM frames (one channel of 800 us and a 4 ms sync,
/// 4.8 ms), and the held second besides.
pub const HISTORY: usize = 512;

/// The comparison of frames read with frames carried, and the state.
#[derive(Debug, Clone)]
pub struct Matcher {
    settings: MatchSettings,
    history: [Carried; HISTORY],
    /// Next slot to write; `len` slots are valid.
    next: usize,
    len: usize,
    state: ReadbackState,
    /// The verdict of the frames read in a row, and how many.
    run: Option<(bool, u32)>,
}

impl Matcher {
    /// A matcher in state `no_input`, with nothing carried yet.
    pub fn new(settings: MatchSettings) -> Matcher {
        Matcher {
            settings,
            history: [Carried::default(); HISTORY],
            next: 0,
            len: 0,
            state: ReadbackState::NoInput,
            run: None,
        }
    }

    /// The state.
    pub fn state(&self) -> ReadbackState {
        self.state
    }

    /// Notes a frame ppm's line carried (in the order they went out).
    pub fn carried(&mut self, c: Carried) {
        self.history[self.next] = c;
        self.next = (self.next + 1) % HISTORY;
        self.len = (self.len + 1).min(HISTORY);
    }

    /// Judges frame `f`, read from the radio, and moves the state.
    pub fn read(&mut self, f: &ReadFrame) -> Verdict {
        let max_diff_ns = self.max_diff(f);
        let matched = max_diff_ns <= self.settings.tolerance_ns;
        let run = match self.run {
            Some((m, n)) if m == matched => n.saturating_add(1),
            _ => 1,
        };
        self.run = Some((matched, run));
        let to = if matched {
            ReadbackState::Following
        } else {
            ReadbackState::Overridden
        };
        let changed =
            (to != self.state && run >= self.settings.frames.max(1) as u32).then(|| self.set(to));
        Verdict {
            matched,
            max_diff_ns,
            changed,
        }
    }

    /// The input gave no whole frame for a second: state `no_input`.
    pub fn input_lost(&mut self) -> Option<(ReadbackState, ReadbackState)> {
        self.run = None;
        (self.state != ReadbackState::NoInput).then(|| self.set(ReadbackState::NoInput))
    }

    fn set(&mut self, to: ReadbackState) -> (ReadbackState, ReadbackState) {
        let from = std::mem::replace(&mut self.state, to);
        (from, to)
    }

    /// Largest, over `f`'s channels, of the smallest difference to a value
    /// ppm carried in the window.
    fn max_diff(&self, f: &ReadFrame) -> u32 {
        let from = f.start_ns.saturating_sub(self.settings.window_ns);
        // The newest frame carried before the read frame ended: a radio
        // keeps the last trainer values it read until its input times out
        // (1 s), so it is what the radio relays when the line carried
        // nothing newer (a line whose frames were cut short a while).
        let newest = self
            .history
            .iter()
            .take(self.len)
            .filter(|c| c.start_ns <= f.end_ns && c.count > 0)
            .max_by_key(|c| c.start_ns)
            .filter(|c| c.start_ns >= f.start_ns.saturating_sub(HELD_NS))
            .map(|c| c.start_ns);
        let mut window = self
            .history
            .iter()
            .take(self.len)
            .filter(|c| {
                c.start_ns <= f.end_ns
                    && c.count > 0
                    && (c.start_ns >= from || Some(c.start_ns) == newest)
            })
            .peekable();
        if window.peek().is_none() {
            return u32::MAX;
        }
        let mut nearest = [u32::MAX; MAX_CHANNELS];
        let mut compared = [false; MAX_CHANNELS];
        for c in window {
            for (i, &read) in f.values().iter().enumerate().take(c.count as usize) {
                compared[i] = true;
                nearest[i] = nearest[i].min(read.abs_diff(c.values_ns[i]));
            }
        }
        nearest
            .iter()
            .zip(compared)
            .filter(|(_, c)| *c)
            .map(|(d, _)| *d)
            .max()
            .unwrap_or(u32::MAX)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn carried(start_ns: u64, us: &[u32]) -> Carried {
        let mut values_ns = [0; MAX_CHANNELS];
        for (v, u) in values_ns.iter_mut().zip(us) {
            *v = u * 1_000;
        }
        Carried {
            start_ns,
            count: us.len() as u8,
            values_ns,
        }
    }

    fn read(start_ns: u64, ns: &[u32]) -> ReadFrame {
        let mut values_ns = [0; MAX_CHANNELS];
        values_ns[..ns.len()].copy_from_slice(ns);
        ReadFrame {
            start_ns,
            end_ns: start_ns + 20 * MS,
            count: ns.len() as u8,
            values_ns,
        }
    }

    #[test]
    fn a_relayed_frame_follows_after_two_and_another_overrides_after_two() {
        let mut m = Matcher::new(MatchSettings::default());
        m.carried(carried(0, &[1500, 1000, 2000, 1500]));
        // Within 10 us of what ppm carried, one channel 10 us off.
        let relay = read(30 * MS, &[1_500_000, 1_010_000, 1_999_500, 1_500_000]);
        let v = m.read(&relay);
        assert_eq!((v.matched, v.max_diff_ns, v.changed), (true, 10_000, None));
        let v = m.read(&relay);
        assert_eq!(
            v.changed,
            Some((ReadbackState::NoInput, ReadbackState::Following))
        );
        // The instructor moves one stick 11 us away: overridden on the second.
        let other = read(50 * MS, &[1_500_000, 1_011_000, 2_000_000, 1_500_000]);
        let v = m.read(&other);
        assert_eq!((v.matched, v.max_diff_ns, v.changed), (false, 11_000, None));
        // One frame that agrees again starts the count anew.
        assert!(m.read(&relay).matched);
        assert_eq!(m.read(&other).changed, None);
        assert_eq!(
            m.read(&other).changed,
            Some((ReadbackState::Following, ReadbackState::Overridden))
        );
        assert_eq!(m.state(), ReadbackState::Overridden);
        assert_eq!(
            m.input_lost(),
            Some((ReadbackState::Overridden, ReadbackState::NoInput))
        );
        assert_eq!(m.input_lost(), None);
    }

    #[test]
    fn channels_match_one_by_one_within_the_window_only() {
        let mut m = Matcher::new(MatchSettings {
            frames: 1,
            ..MatchSettings::default()
        });
        m.carried(carried(0, &[1000, 1000]));
        m.carried(carried(20 * MS, &[2000, 2000]));
        // Channel 1 from the first frame, channel 2 from the second.
        let mixed = read(40 * MS, &[1_000_000, 2_000_000]);
        assert!(m.read(&mixed).matched);
        // At 110 ms the first frame is out of the 100 ms window.
        let late = read(110 * MS, &[1_000_000, 2_000_000]);
        let v = m.read(&late);
        assert_eq!((v.matched, v.max_diff_ns), (false, 1_000_000));
        // The newest frame carried stays what the radio may relay for 1 s
        // (the line carried nothing newer), not longer.
        let held = read(900 * MS, &[2_000_000, 2_000_000]);
        assert_eq!(m.read(&held).max_diff_ns, 0);
        let gone = read(1_100 * MS, &[2_000_000, 2_000_000]);
        assert_eq!(m.read(&gone).max_diff_ns, u32::MAX);
        // A frame ppm sends after the read frame ended is not what it relays.
        let mut m = Matcher::new(MatchSettings::default());
        m.carried(carried(100 * MS, &[1000, 1000]));
        let v = m.read(&read(0, &[1_000_000, 1_000_000]));
        assert_eq!((v.matched, v.max_diff_ns), (false, u32::MAX));
    }

    #[test]
    fn only_the_channels_both_have_are_compared() {
        let mut m = Matcher::new(MatchSettings::default());
        m.carried(carried(0, &[1200, 1300]));
        // The radio sends 4 channels; its last 2 are its own.
        let v = m.read(&read(20 * MS, &[1_200_000, 1_300_000, 900_000, 2_100_000]));
        assert_eq!((v.matched, v.max_diff_ns), (true, 0));
        // ppm sends 2, the radio 1.
        assert!(m.read(&read(20 * MS, &[1_200_000])).matched);
    }

    #[test]
    fn the_history_keeps_the_newest_frames() {
        let mut m = Matcher::new(MatchSettings {
            window_ns: u64::MAX,
            tolerance_ns: 0,
            frames: 2,
        });
        for i in 0..(HISTORY as u64 + 5) {
            m.carried(carried(i * MS, &[1000 + i as u32]));
        }
        // The first five went out of the history.
        let end = HISTORY as u64 + 10;
        assert!(!m.read(&read(end * MS, &[1_000_000])).matched);
        assert!(m.read(&read(end * MS, &[1_005_000])).matched);
        assert!(
            m.read(&read(end * MS, &[(1000 + end as u32 - 6) * 1_000]))
                .matched
        );
    }

    #[test]
    fn codes_and_names() {
        for s in [
            ReadbackState::NoInput,
            ReadbackState::Following,
            ReadbackState::Overridden,
        ] {
            assert_eq!(ReadbackState::from_code(s as u32), Some(s));
        }
        assert_eq!(ReadbackState::from_code(3), None);
        assert_eq!(ReadbackState::Overridden.name(), "overridden");
    }
}
