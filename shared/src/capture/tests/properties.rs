//! Property tests of the capture decoder: streams made by ppm's own
//! encoder decode exactly, configured or not; glitched frames are never
//! handed on; a floating pin, a stream without a sync and arbitrary events
//! never yield a frame that is not whole.

use super::*;
use crate::frame::{Channels, FrameModel, PpmSection};
use crate::receiver::{Receiver, ReceiverChoice};
use crate::signal::Timing;
use proptest::prelude::*;

/// An accepted ppm configuration and what a stream of it carries, as raw
/// seeds (the model's ranges are applied in [`build`]).
#[derive(Debug, Clone)]
struct Config {
    n: usize,
    idle: Level,
    min_us: u32,
    max_us: u32,
    pulse_ns: u64,
    /// Grid timing's frame length (where the channel range allows one),
    /// else follow timing.
    frame_us: Option<u64>,
    frames: usize,
    values: Vec<[u32; MAX_CHANNELS]>,
    syncs: Vec<u64>,
    base: u64,
    seq0: u64,
}

fn config() -> impl Strategy<Value = Config> {
    (
        1usize..=16,
        any::<bool>(),
        (820u32..=2_180, any::<u32>(), any::<u32>()),
        proptest::option::of(any::<u64>()),
        4usize..=8,
        proptest::collection::vec(proptest::array::uniform16(any::<u32>()), 9),
        proptest::collection::vec(any::<u64>(), 9),
        0u64..1 << 50,
        any::<u64>(),
    )
        .prop_map(
            |(n, high, (min_us, max_seed, pulse_seed), grid, frames, values, syncs, base, seq0)| {
                let max_us = min_us + max_seed % (2_180 - min_us + 1);
                let min_ns = u64::from(min_us) * US;
                let pulse_ns = 50_000 + u64::from(pulse_seed) % (min_ns - 50_000);
                // EdgeTX's rules less ppm's margin: a sync of 4500..=18500 us
                // with every channel at its maximum and at its minimum.
                let lo = (n as u64 * u64::from(max_us) * US + 4_500 * US).div_ceil(US);
                let hi = (n as u64 * u64::from(min_us) * US + 18_500 * US) / US;
                let frame_us = grid.filter(|_| lo <= hi).map(|s| lo + s % (hi - lo + 1));
                Config {
                    n,
                    idle: Level::from_bit(high),
                    min_us,
                    max_us,
                    pulse_ns,
                    frame_us,
                    frames,
                    values,
                    syncs,
                    base,
                    seq0,
                }
            },
        )
}

/// ppm's frame model of `c` (EdgeTX 2.10's rules: 1..=16 channels).
fn model(c: &Config) -> FrameModel {
    let ppm = PpmSection {
        channels: Some(c.n as u32),
        frame_us: c.frame_us.map(|f| f as f64),
        pulse_us: c.pulse_ns as f64 / 1e3,
        idle_level: Some(c.idle),
        default_us: f64::from(c.min_us + c.max_us) / 2.0,
        min_us: c.min_us.into(),
        max_us: c.max_us.into(),
        receiver: ReceiverChoice::One(Receiver::EdgeTx),
        timing: match c.frame_us {
            Some(_) => Timing::Grid,
            None => Timing::Follow,
        },
        follow_sync_min_us: Some(4_500.0),
        follow_sync_max_us: Some(18_500.0),
        ..PpmSection::default()
    };
    FrameModel::build(&ppm).unwrap_or_else(|e| panic!("{c:?}: {e}"))
}

/// Something wrong in one frame.
#[derive(Debug, Clone)]
enum Glitch {
    /// A runt (1 ns..RUNT_NS) in the idle time after pulse `gap` (modulo
    /// the pulses; the sync gap where it does not fit).
    Runt { gap: usize, pos: u64, width: u64 },
    /// `count` events from the frame's `from`th (modulo its events) lost:
    /// the sequence numbers jump.
    Drop { from: usize, count: usize },
    /// One more channel of `v` ns before the sync.
    Extra { v: u64 },
}

fn glitch() -> impl Strategy<Value = Glitch> {
    prop_oneof![
        (any::<usize>(), any::<u64>(), 1..RUNT_NS).prop_map(|(gap, pos, width)| Glitch::Runt {
            gap,
            pos,
            width
        }),
        (any::<usize>(), 1usize..=3).prop_map(|(from, count)| Glitch::Drop { from, count }),
        (CHANNEL_MIN_NS..=CHANNEL_MAX_NS).prop_map(|v| Glitch::Extra { v }),
    ]
}

/// A stream of `c`'s frames made by ppm's encoder, after a lone pulse and
/// closed by one, with `glitches` (one per frame at most) in it.
struct Built {
    events: Vec<EdgeEvent>,
    /// Every frame as it would be read whole.
    frames: Vec<ReadFrame>,
    /// The values asked of the encoder, per frame.
    asked: Vec<Vec<u32>>,
    /// Frames a glitch touched: one falls between their first leading edge
    /// and the end of the pulse that ends their sync.
    touched: Vec<bool>,
    /// Events left out.
    dropped: u64,
}

fn build(m: &FrameModel, c: &Config, glitches: &[Option<Glitch>]) -> Built {
    let idle = m.idle_level();
    let active = idle.opposite();
    let pulse = m.pulse_ns();
    let (smin, smax) = m.follow_sync_ns();
    let sync = |seed: u64| smin + seed % (smax - smin + 1);
    let glitch = |k: usize| glitches.get(k).cloned().flatten();
    let mut edges = vec![(c.base, active), (c.base + pulse, idle)];
    let mut t = c.base + sync(c.syncs[0]);
    let (mut frames, mut asked, mut ranges, mut hits) = (vec![], vec![], vec![], vec![]);
    for k in 0..c.frames {
        let vals: Vec<u32> = (0..c.n)
            .map(|i| m.min_ns(i) + c.values[k][i] % (m.max_ns(i) - m.min_ns(i) + 1))
            .collect();
        let schedule = m.encode(&Channels::from_ns(&vals));
        let mut own: Vec<(u64, Level)> = schedule
            .edges()
            .iter()
            .map(|e| (t + e.at_ns, e.level))
            .collect();
        let leads: Vec<u64> = own.iter().filter(|e| e.1 == active).map(|e| e.0).collect();
        let mut last = *leads.last().unwrap();
        let next = match (glitch(k), c.frame_us) {
            (Some(Glitch::Extra { v }), _) => {
                last += v;
                own.extend([(last, active), (last + pulse, idle)]);
                hits.push((last, last + pulse));
                last + sync(c.syncs[k + 1])
            }
            (_, Some(f)) => t + f * US,
            (_, None) => last + sync(c.syncs[k + 1]),
        };
        if let Some(Glitch::Runt { gap, pos, width }) = glitch(k) {
            let g = gap % (c.n + 1);
            let (mut lo, mut hi) = match leads.get(g + 1) {
                Some(&b) => (leads[g] + pulse, b),
                None => (last + pulse, next),
            };
            if hi - lo < width + 2 {
                (lo, hi) = (last + pulse, next);
            }
            let s = lo + 1 + pos % (hi - lo - width - 1);
            own.extend([(s, active), (s + width, idle)]);
            own.sort_by_key(|e| e.0);
            hits.push((s, s + width));
        }
        ranges.push(edges.len()..edges.len() + own.len());
        edges.extend(own);
        let values: Vec<u64> = leads.windows(2).map(|w| w[1] - w[0]).collect();
        frames.push(frame(leads[0], next, &values));
        asked.push(vals);
        t = next;
    }
    edges.extend([(t, active), (t + pulse, idle)]);
    let mut events = events(&edges, c.seq0);
    let mut dropped = 0;
    // From the last frame back, so earlier indices stay.
    for k in (0..c.frames).rev() {
        if let Some(Glitch::Drop { from, count }) = glitch(k) {
            let r = ranges[k].clone();
            let from = r.start + from % r.len();
            let to = (from + count).min(r.end);
            // The event after the gap is where it is seen.
            hits.push((events[from].at_ns, events[to].at_ns));
            events.drain(from..to);
            dropped += (to - from) as u64;
        }
    }
    let touched = frames
        .iter()
        .map(|f| {
            hits.iter()
                .any(|&(a, b)| a <= f.end_ns + pulse && b >= f.start_ns)
        })
        .collect();
    Built {
        events,
        frames,
        asked,
        touched,
        dropped,
    }
}

/// Settings with the idle level and the channel count configured or not.
fn settings(c: &Config, idle_known: bool, count_known: bool) -> CaptureSettings {
    CaptureSettings {
        idle: idle_known.then_some(c.idle),
        channels: count_known.then_some(c.n as u8),
    }
}

/// Checks every frame handed on is one sent, exactly, and untouched.
fn check_untouched(got: &[ReadFrame], b: &Built) -> Result<(), TestCaseError> {
    for f in got {
        let j = b.frames.iter().position(|e| e.start_ns == f.start_ns);
        prop_assert!(j.is_some(), "not a frame sent: {:?}", f);
        let j = j.unwrap();
        prop_assert!(!b.touched[j], "frame {} was touched: {:?}", j, f);
        prop_assert_eq!(f, &b.frames[j]);
    }
    Ok(())
}

/// Checks a frame handed on is whole by the windows.
fn check_whole(f: &ReadFrame) -> Result<(), TestCaseError> {
    prop_assert!((1..=MAX_CHANNELS).contains(&(f.count as usize)), "{f:?}");
    for &v in f.values() {
        prop_assert!(
            (CHANNEL_MIN_NS..=CHANNEL_MAX_NS).contains(&u64::from(v)),
            "{f:?}"
        );
    }
    let sync = f.sync_ns();
    prop_assert!(sync > SYNC_MIN_NS && sync < SYNC_MAX_NS, "{f:?}");
    prop_assert!(f.end_ns > f.start_ns);
    Ok(())
}

/// A line's level changes: the first to `first`, then alternating, each
/// held for its duration.
fn alternating(base: u64, first: Level, durations: &[u64]) -> Vec<(u64, Level)> {
    let (mut t, mut level) = (base, first);
    let mut edges = vec![];
    for &d in durations {
        edges.push((t, level));
        t += d;
        level = level.opposite();
    }
    edges
}

fn any_settings() -> impl Strategy<Value = CaptureSettings> {
    (
        proptest::option::of(any::<bool>().prop_map(Level::from_bit)),
        proptest::option::of(1u8..=16),
    )
        .prop_map(|(idle, channels)| CaptureSettings { idle, channels })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// ppm's own frames decode to exactly the encoded periods, configured
    /// or not. Not handed on: with the idle level to find, frame 0 (the
    /// leading edge that opens it is the first one known, so its sync is
    /// not timed); with the count to find, the next 2 (they lock it).
    #[test]
    fn ppm_streams_decode_exactly(
        c in config(),
        idle_known in any::<bool>(),
        count_known in any::<bool>(),
    ) {
        let m = model(&c);
        let b = build(&m, &c, &[]);
        for (f, asked) in b.frames.iter().zip(&b.asked) {
            prop_assert_eq!(f.values(), &asked[..]);
        }
        let skip = usize::from(!idle_known) + 2 * usize::from(!count_known);
        let mut cap = Capture::new(settings(&c, idle_known, count_known));
        let mut got = vec![];
        for e in &b.events {
            if let Some(f) = cap.push(*e) {
                prop_assert_eq!(e.at_ns, f.end_ns + m.pulse_ns());
                got.push(f);
            }
        }
        prop_assert_eq!(&got[..], &b.frames[skip..]);
        prop_assert_eq!(
            cap.counts(),
            CaptureCounts {
                edges: b.events.len() as u64,
                frames: (c.frames - skip) as u64,
                wrong_count: if count_known { 0 } else { 2 },
                unsynced: if idle_known { 0 } else { c.n as u64 },
                ..Default::default()
            }
        );
        prop_assert_eq!(cap.idle_level(), Some(c.idle));
        prop_assert_eq!(cap.channels(), Some(c.n as u8));
        prop_assert_eq!(cap.last_frame_end_ns(), b.frames.last().map(|f| f.end_ns));
    }

    /// Glitches in random frames, the channel count configured: every
    /// frame handed on is an untouched frame, exactly; and every untouched
    /// frame after an untouched one is handed on too (from frame 1 when
    /// the idle level is found).
    #[test]
    fn glitched_frames_are_never_handed_on(
        c in config(),
        glitches in proptest::collection::vec(proptest::option::weighted(0.4, glitch()), 8),
        idle_known in any::<bool>(),
    ) {
        let m = model(&c);
        let b = build(&m, &c, &glitches);
        let mut cap = Capture::new(settings(&c, idle_known, true));
        let got = decode(&mut cap, &b.events);
        check_untouched(&got, &b)?;
        prop_assert_eq!(cap.counts().frames, got.len() as u64);
        prop_assert_eq!(cap.counts().lost_events, b.dropped);
        let first = usize::from(!idle_known);
        for j in first..c.frames {
            if !b.touched[j] && (j == 0 || !b.touched[j - 1]) {
                prop_assert!(got.contains(&b.frames[j]), "frame {} lost", j);
            }
        }
    }

    /// The same with the idle level and the count to find, and glitches
    /// that leave no whole frame (runts, lost events): a run of frames with
    /// an extra channel is a channel count like any other, which the
    /// decoder follows (see `count_locks_after_two_frames_and_relocks_after_three`).
    #[test]
    fn glitched_frames_are_never_handed_on_while_counting(
        c in config(),
        glitches in proptest::collection::vec(
            proptest::option::weighted(
                0.4,
                glitch().prop_filter("no extra channel", |g| !matches!(g, Glitch::Extra { .. })),
            ),
            8,
        ),
    ) {
        let m = model(&c);
        let b = build(&m, &c, &glitches);
        let mut cap = Capture::new(settings(&c, false, false));
        let got = decode(&mut cap, &b.events);
        check_untouched(&got, &b)?;
        prop_assert_eq!(cap.counts().lost_events, b.dropped);
    }

    /// A floating pin (after a sync gap or not): every period between
    /// leading edges below the channel window. Never a frame.
    #[test]
    fn a_floating_pin_never_yields_a_frame(
        mut durations in proptest::collection::vec(0u64..400_000, 1..300),
        settle in any::<bool>(),
        first in any::<bool>(),
        s in any_settings(),
        base in 0u64..1 << 50,
        seq0 in any::<u64>(),
    ) {
        if settle {
            durations.insert(0, 10 * MS);
        }
        let evs = events(&alternating(base, Level::from_bit(first), &durations), seq0);
        let mut cap = Capture::new(s);
        prop_assert_eq!(decode(&mut cap, &evs), []);
        prop_assert_eq!(cap.counts().frames, 0);
        prop_assert_eq!(cap.counts().edges, evs.len() as u64);
        prop_assert!(!cap.valid_at(base + 50 * MS));
    }

    /// Every level held under 2 ms or 19 ms and more: no period between
    /// edges of one direction is a sync, whatever the idle level. Never a
    /// frame.
    #[test]
    fn a_stream_without_a_sync_never_yields_a_frame(
        durations in proptest::collection::vec(
            prop_oneof![4 => 0u64..2_000_000, 1 => 19_000_000u64..=40_000_000],
            1..300,
        ),
        first in any::<bool>(),
        s in any_settings(),
        base in 0u64..1 << 50,
        seq0 in any::<u64>(),
    ) {
        let evs = events(&alternating(base, Level::from_bit(first), &durations), seq0);
        let mut cap = Capture::new(s);
        prop_assert_eq!(decode(&mut cap, &evs), []);
        prop_assert_eq!(cap.counts().frames, 0);
    }

    /// Anything at all: no panic, and whatever is handed on is whole.
    #[test]
    fn arbitrary_events_never_panic(
        raw in proptest::collection::vec((any::<u64>(), any::<bool>(), any::<u64>()), 0..200),
        s in any_settings(),
    ) {
        let mut cap = Capture::new(s);
        for &(at_ns, high, seq) in &raw {
            if let Some(f) = cap.push(EdgeEvent { at_ns, level: Level::from_bit(high), seq }) {
                check_whole(&f)?;
            }
        }
        prop_assert_eq!(cap.counts().edges, raw.len() as u64);
        let _ = cap.valid_at(u64::MAX);
    }

    /// Random PPM-like timing with lost events, repeated levels and time
    /// going backwards: whatever is handed on is a whole frame of the
    /// expected count.
    #[test]
    fn whatever_is_handed_on_is_whole(
        steps in proptest::collection::vec(
            (
                prop_oneof![
                    50_000u64..=600_000,
                    700_000u64..=2_300_000,
                    3_900_000u64..=19_100_000,
                ],
                0u8..40,
            ),
            0..800,
        ),
        s in any_settings(),
    ) {
        let mut cap = Capture::new(s);
        let (mut at_ns, mut level, mut seq) = (1u64 << 40, Level::Low, 1u64);
        for &(d, r) in &steps {
            match r {
                0 => seq += 3,
                1 => at_ns -= d / 2,
                2 => level = level.opposite(),
                _ => at_ns += d,
            }
            level = level.opposite();
            seq += 1;
            if let Some(f) = cap.push(EdgeEvent { at_ns, level, seq }) {
                check_whole(&f)?;
                prop_assert_eq!(Some(f.count), cap.channels());
            }
        }
    }
}
