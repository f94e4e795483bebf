//! Tests of the capture decoder: every refusal reason with exact counts,
//! the idle level and channel count found from the signal, and property
//! tests on streams made by ppm's own encoder, on noise and on glitches.

use super::*;
use crate::frame::{Channels, FrameModel, PpmSection};
use crate::receiver::{Receiver, ReceiverChoice};
use crate::signal::Timing;
use proptest::prelude::*;

const US: u64 = 1_000;
const MS: u64 = 1_000_000;
const LOW: Level = Level::Low;
const HIGH: Level = Level::High;
const PULSE: u64 = 300 * US;
const CH3: &[u64] = &[1_000 * US, 1_500 * US, 2_000 * US];

/// The edges of pulses `width` ns long starting at `starts`, on a line
/// idle at `idle`: `(time, level after)`.
fn pulses(idle: Level, width: u64, starts: &[u64]) -> Vec<(u64, Level)> {
    starts
        .iter()
        .flat_map(|&t| [(t, idle.opposite()), (t + width, idle)])
        .collect()
}

/// The edges as events, sequence numbers from `seq0` on.
fn events(edges: &[(u64, Level)], seq0: u64) -> Vec<EdgeEvent> {
    edges
        .iter()
        .enumerate()
        .map(|(i, &(at_ns, level))| EdgeEvent {
            at_ns,
            level,
            seq: seq0.wrapping_add(i as u64),
        })
        .collect()
}

fn decode(c: &mut Capture, evs: &[EdgeEvent]) -> Vec<ReadFrame> {
    evs.iter().filter_map(|&e| c.push(e)).collect()
}

fn frame(start_ns: u64, end_ns: u64, values: &[u64]) -> ReadFrame {
    let mut values_ns = [0; MAX_CHANNELS];
    for (v, &c) in values_ns.iter_mut().zip(values) {
        *v = c as u32;
    }
    ReadFrame {
        start_ns,
        end_ns,
        count: values.len() as u8,
        values_ns,
    }
}

/// Pulse starts: a lone pulse at `t0`, then every frame of `frames` after
/// a sync of `sync` ns, then the pulse that ends the last sync; and the
/// frames as read whole.
fn train(t0: u64, sync: u64, frames: &[&[u64]]) -> (Vec<u64>, Vec<ReadFrame>) {
    let mut t = t0;
    let mut starts = vec![t];
    let mut read = vec![];
    for ch in frames {
        t += sync;
        let start = t;
        starts.push(t);
        for &c in *ch {
            t += c;
            starts.push(t);
        }
        read.push(frame(start, t + sync, ch));
    }
    starts.push(t + sync);
    (starts, read)
}

fn configured(idle: Level, channels: u8) -> Capture {
    Capture::new(CaptureSettings {
        idle: Some(idle),
        channels: Some(channels),
    })
}

/// The default 3-frame train of [`CH3`] frames, its edges idle low with a
/// `pulse`, and the frames.
fn three_frames() -> (Vec<u64>, Vec<(u64, Level)>, Vec<ReadFrame>) {
    let (starts, want) = train(5 * MS, 10 * MS, &[CH3, CH3, CH3]);
    let edges = pulses(LOW, PULSE, &starts);
    (starts, edges, want)
}

/// Adds a pulse of `width` at `at` to `edges`, in time order.
fn with_pulse(mut edges: Vec<(u64, Level)>, at: u64, width: u64) -> Vec<(u64, Level)> {
    edges.extend([(at, HIGH), (at + width, LOW)]);
    edges.sort_by_key(|e| e.0);
    edges
}

#[test]
fn limits_are_edgetx_2_10s() {
    assert_eq!(CHANNEL_MIN_NS, 800_000);
    assert_eq!(CHANNEL_MAX_NS, 2_200_000);
    assert_eq!(SYNC_MIN_NS, 4_000_000);
    assert_eq!(SYNC_MAX_NS, 19_000_000);
    assert_eq!(INPUT_VALID_NS, 1_000_000_000);
    // A runt is shorter than any pulse ppm sends; noise shorter than any channel.
    assert!(RUNT_NS * 2 <= crate::frame::us_to_ns(crate::frame::PULSE_MIN_US));
    assert_eq!(NOISE_NS * 2, CHANNEL_MIN_NS);
}

#[test]
fn whole_frames_are_handed_on_with_exact_periods() {
    let ch: &[u64] = &[1_000 * US, 1_500_123, 2_000 * US + 1];
    let (starts, want) = train(5 * MS, 10 * MS, &[ch, ch, ch]);
    for idle in [LOW, HIGH] {
        let evs = events(&pulses(idle, PULSE, &starts), 1);
        let mut c = configured(idle, 3);
        let mut got = vec![];
        for e in &evs {
            if let Some(f) = c.push(*e) {
                // Handed on at the end of the pulse that ended its sync.
                assert_eq!(e.at_ns, f.end_ns + PULSE);
                got.push(f);
            }
        }
        assert_eq!(got, want, "idle {idle:?}");
        assert_eq!(got[1].values(), [1_000_000, 1_500_123, 2_000_001]);
        assert_eq!(got[1].start_ns, 5 * MS + 10 * MS + 4_500_124 + 10 * MS);
        assert_eq!(got[1].sync_ns(), 10 * MS);
        assert_eq!(
            c.counts(),
            CaptureCounts {
                edges: 28,
                frames: 3,
                ..Default::default()
            }
        );
        assert_eq!(c.idle_level(), Some(idle));
        assert_eq!(c.channels(), Some(3));
    }
}

#[test]
fn channel_window_is_800_to_2200_us_inclusive() {
    for (v, read) in [
        (800_000, true),
        (2_200_000, true),
        (799_999, false),
        (2_200_001, false),
    ] {
        let ch: &[u64] = &[1_500 * US, v, 1_500 * US];
        let (starts, want) = train(5 * MS, 10 * MS, &[ch, ch]);
        let evs = events(&pulses(LOW, PULSE, &starts), 1);
        let mut c = configured(LOW, 3);
        let got = decode(&mut c, &evs);
        if read {
            assert_eq!(got, want, "{v}");
            assert_eq!(c.counts().frames, 2);
        } else {
            assert!(got.is_empty(), "{v}: {got:?}");
            // Each frame refused once; its last channel belongs to no frame.
            assert_eq!(
                c.counts(),
                CaptureCounts {
                    edges: 20,
                    out_of_window: 2,
                    unsynced: 2,
                    ..Default::default()
                },
                "{v}"
            );
        }
    }
}

#[test]
fn sync_is_strictly_between_4_and_19_ms() {
    let ch: &[u64] = &[MS, MS];
    for (sync, read) in [
        (4_000_001, true),
        (18_999_999, true),
        (4_000_000, false),
        (19_000_000, false),
    ] {
        let (starts, want) = train(5 * MS, sync, &[ch, ch, ch]);
        let evs = events(&pulses(LOW, PULSE, &starts), 1);
        let mut c = configured(LOW, 2);
        let got = decode(&mut c, &evs);
        if read {
            assert_eq!(got, want, "{sync}");
        } else {
            assert!(got.is_empty(), "{sync}: {got:?}");
            // Never synchronised: all 10 periods belong to no frame.
            assert_eq!(
                c.counts(),
                CaptureCounts {
                    edges: 22,
                    unsynced: 10,
                    ..Default::default()
                },
                "{sync}"
            );
        }
    }
}

#[test]
fn a_runt_refuses_its_frame_and_is_no_timing_reference() {
    let (starts, edges, want) = three_frames();
    let s1 = starts[5];
    // In frame 1's first channel: 24.999 us is a runt, 25 us a pulse (and
    // then the 600 us period before it is out of the window).
    for (width, runts, out_of_window) in [(RUNT_NS - 1, 1, 0), (RUNT_NS, 0, 1)] {
        let evs = events(&with_pulse(edges.clone(), s1 + 600 * US, width), 1);
        let mut c = configured(LOW, 3);
        assert_eq!(decode(&mut c, &evs), [want[0], want[2]], "{width}");
        // Frame 1's three channels (or the 400 us left of its first and
        // its last two) belong to no frame.
        assert_eq!(
            c.counts(),
            CaptureCounts {
                edges: 30,
                frames: 2,
                runts,
                out_of_window,
                unsynced: 3,
                ..Default::default()
            },
            "{width}"
        );
    }
    // In the sync gap after frame 0: frame 0 is refused, frame 1 is not
    // (its sync is measured from the real pulses: from the runt, 3 ms).
    let evs = events(&with_pulse(edges.clone(), starts[4] + 7 * MS, 2 * US), 1);
    let mut c = configured(LOW, 3);
    assert_eq!(decode(&mut c, &evs), [want[1], want[2]]);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 30,
            frames: 2,
            runts: 1,
            ..Default::default()
        }
    );
    // Before the first sync: no frame in progress.
    let evs = events(&with_pulse(edges, starts[0] + 2 * MS, 1), 1);
    let mut c = configured(LOW, 3);
    assert_eq!(decode(&mut c, &evs), want);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 30,
            frames: 3,
            unsynced: 1,
            ..Default::default()
        }
    );
}

#[test]
fn a_period_under_400_us_is_noise() {
    let (starts, edges, want) = three_frames();
    let s1 = starts[5];
    for (at, noise, out_of_window) in [(350 * US, 1, 0), (NOISE_NS - 1, 1, 0), (NOISE_NS, 0, 1)] {
        let evs = events(&with_pulse(edges.clone(), s1 + at, 30 * US), 1);
        let mut c = configured(LOW, 3);
        assert_eq!(decode(&mut c, &evs), [want[0], want[2]], "{at}");
        assert_eq!(
            c.counts(),
            CaptureCounts {
                edges: 30,
                frames: 2,
                noise,
                out_of_window,
                unsynced: 3,
                ..Default::default()
            },
            "{at}"
        );
    }
}

#[test]
fn time_going_backwards_equal_times_and_missed_edges_are_noise() {
    let (starts, edges, want) = three_frames();
    // Frame 1's second pulse starts at edge 12.
    let p1 = starts[6];
    assert_eq!(edges[12], (p1, HIGH));
    for bad in [p1, p1 - US, 0] {
        let mut e = edges.clone();
        e.insert(13, (bad, LOW));
        let evs = events(&e, 1);
        let mut c = configured(LOW, 3);
        assert_eq!(decode(&mut c, &evs), [want[0], want[2]], "{bad}");
        // The real end of the pulse is then a second edge to low (no
        // frame in progress any more); the next pulse is the first
        // reference again, and the period after it belongs to no frame.
        assert_eq!(
            c.counts(),
            CaptureCounts {
                edges: 29,
                frames: 2,
                noise: 1,
                unsynced: 2,
                ..Default::default()
            },
            "{bad}"
        );
    }
    // The end of frame 1's second pulse missed (no sequence gap): two
    // rising edges in a row.
    let mut e = edges.clone();
    e.remove(13);
    let mut c = configured(LOW, 3);
    assert_eq!(decode(&mut c, &events(&e, 1)), [want[0], want[2]]);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 27,
            frames: 2,
            noise: 1,
            ..Default::default()
        }
    );
}

#[test]
fn lost_events_drop_the_frame_and_wait_for_a_sync() {
    let (_, edges, want) = three_frames();
    // Frame 1's second pulse (edges 12 and 13) lost.
    let mut evs = events(&edges, 1);
    evs.drain(12..14);
    let mut c = configured(LOW, 3);
    assert_eq!(decode(&mut c, &evs), [want[0], want[2]]);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 26,
            frames: 2,
            lost_events: 2,
            lost_frames: 1,
            unsynced: 1,
            ..Default::default()
        }
    );
    // A sequence number repeated: nothing lost, but the frame is dropped.
    let mut evs = events(&edges, 1);
    for e in &mut evs[12..] {
        e.seq -= 1;
    }
    let mut c = configured(LOW, 3);
    assert_eq!(decode(&mut c, &evs), [want[0], want[2]]);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 28,
            frames: 2,
            lost_frames: 1,
            unsynced: 2,
            ..Default::default()
        }
    );
    // An event lost before the first sync: no frame in progress.
    let mut evs = events(&edges, 1);
    evs.remove(1);
    let mut c = configured(LOW, 3);
    assert_eq!(decode(&mut c, &evs), [want[1], want[2]]);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 27,
            frames: 2,
            lost_events: 1,
            unsynced: 3,
            ..Default::default()
        }
    );
    // The first sequence number is taken as given, and may wrap.
    let mut c = configured(LOW, 3);
    assert_eq!(decode(&mut c, &events(&edges, u64::MAX - 5)), want);
    assert_eq!(c.counts().lost_events, 0);
}

#[test]
fn a_17th_channel_is_too_many() {
    let ch16 = [1_000 * US; 16];
    let ch17 = [1_000 * US; 17];
    let (starts, want) = train(5 * MS, 10 * MS, &[&ch16[..], &ch17[..], &ch16[..]]);
    let mut c = configured(LOW, 16);
    let got = decode(&mut c, &events(&pulses(LOW, PULSE, &starts), 1));
    assert_eq!(got, [want[0], want[2]]);
    assert_eq!(got[0].values(), [1_000_000; 16]);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 2 * (1 + 17 + 18 + 17 + 1),
            frames: 2,
            too_many_channels: 1,
            ..Default::default()
        }
    );
}

#[test]
fn a_frame_of_another_count_than_configured_is_dropped() {
    let ch4 = [1_200 * US; 4];
    let (starts, want) = train(5 * MS, 10 * MS, &[CH3, &ch4[..], CH3]);
    let mut c = configured(LOW, 3);
    assert_eq!(
        decode(&mut c, &events(&pulses(LOW, PULSE, &starts), 1)),
        [want[0], want[2]]
    );
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 2 * (1 + 4 + 5 + 4 + 1),
            frames: 2,
            wrong_count: 1,
            ..Default::default()
        }
    );
}

#[test]
fn count_locks_after_two_frames_and_relocks_after_three() {
    let c4 = [1_100 * US; 4];
    let c5 = [1_200 * US; 5];
    let c6 = [1_300 * US; 6];
    let mut frames: Vec<&[u64]> = vec![];
    frames.extend([&c4[..]; 5]);
    frames.push(&c5);
    frames.extend([&c4[..]; 4]);
    frames.extend([&c6[..]; 4]);
    frames.extend([&c4[..]; 2]);
    let (starts, want) = train(5 * MS, 8 * MS, &frames);
    let evs = events(&pulses(HIGH, PULSE, &starts), 1);
    let mut c = Capture::new(CaptureSettings {
        idle: Some(HIGH),
        channels: None,
    });
    let mut locked = vec![];
    let mut got = vec![];
    for e in &evs {
        got.extend(c.push(*e));
        locked.push(c.channels());
    }
    let handed: Vec<ReadFrame> = [2, 3, 4, 6, 7, 8, 9, 13].iter().map(|&i| want[i]).collect();
    assert_eq!(got, handed);
    // 2 locking 4, the 5, 3 relocking to 6, the last two 4s.
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: evs.len() as u64,
            frames: 8,
            wrong_count: 8,
            ..Default::default()
        }
    );
    assert_eq!(c.channels(), Some(6));
    // No count until the end of the second frame (its sync's pulse).
    let second_end = evs.iter().position(|e| e.at_ns == want[1].end_ns + PULSE);
    let second_end = second_end.unwrap();
    assert_eq!(locked[second_end - 1], None);
    assert_eq!(locked[second_end], Some(4));
}

#[test]
fn a_refused_frame_breaks_a_run_of_whole_frames() {
    let (starts, want) = train(5 * MS, 10 * MS, &[CH3; 5]);
    let edges = with_pulse(pulses(LOW, PULSE, &starts), starts[5] + 500 * US, US);
    let mut c = Capture::new(CaptureSettings {
        idle: Some(LOW),
        channels: None,
    });
    // Frame 0 starts a run, the runt in frame 1 breaks it, frames 2 and 3
    // lock the count.
    assert_eq!(decode(&mut c, &events(&edges, 1)), [want[4]]);
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 2 * (1 + 20 + 1) + 2,
            frames: 1,
            runts: 1,
            wrong_count: 3,
            unsynced: 3,
            ..Default::default()
        }
    );
}

#[test]
fn idle_level_is_found_from_the_sync_gap() {
    let (starts, want) = train(5 * MS, 10 * MS, &[CH3; 6]);
    for idle in [LOW, HIGH] {
        let evs = events(&pulses(idle, PULSE, &starts), 7);
        let mut c = Capture::new(CaptureSettings {
            idle: None,
            channels: Some(3),
        });
        assert_eq!(c.push(evs[0]), None);
        assert_eq!(c.push(evs[1]), None);
        assert_eq!(c.idle_level(), None);
        // The first pulse of frame 0 ends the first long hold.
        assert_eq!(c.push(evs[2]), None);
        assert_eq!(c.idle_level(), Some(idle));
        let got = decode(&mut c, &evs[3..]);
        // Frame 0 had no timed sync before it: its channels belong to no frame.
        assert_eq!(got, want[1..], "{idle:?}");
        assert_eq!(
            c.counts(),
            CaptureCounts {
                edges: evs.len() as u64,
                frames: 5,
                unsynced: 3,
                ..Default::default()
            }
        );
        // And with the channel count to find as well: two more frames.
        let mut c = Capture::new(CaptureSettings::default());
        assert_eq!(decode(&mut c, &evs), want[3..], "{idle:?}");
        assert_eq!(
            c.counts(),
            CaptureCounts {
                edges: evs.len() as u64,
                frames: 3,
                wrong_count: 2,
                unsynced: 3,
                ..Default::default()
            }
        );
        assert_eq!((c.idle_level(), c.channels()), (Some(idle), Some(3)));
    }
}

#[test]
fn idle_level_follows_the_signal() {
    // A pull-up holds the line high for 50 ms before the source (idle low)
    // is plugged in: high is taken as idle, until low is held 9 ms.
    let (starts, want) = train(60 * MS, 10 * MS, &[CH3; 3]);
    let mut edges = vec![(MS, HIGH), (51 * MS, LOW)];
    edges.extend(pulses(LOW, PULSE, &starts));
    let evs = events(&edges, 1);
    let mut c = Capture::new(CaptureSettings {
        idle: None,
        channels: Some(3),
    });
    assert_eq!(decode(&mut c, &evs[..2]), []);
    assert_eq!(c.idle_level(), Some(HIGH));
    assert_eq!(decode(&mut c, &evs[2..]), want);
    assert_eq!(c.idle_level(), Some(LOW));
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 30,
            frames: 3,
            idle_changes: 1,
            ..Default::default()
        }
    );

    // A 2.5 ms "pulse" inside frame 2 (it swallows the next pulse): the
    // active level held longer than any channel makes it the idle level,
    // dropping frame 2; the next sync gap turns it back.
    let (starts, want) = train(5 * MS, 10 * MS, &[CH3; 5]);
    let s2 = starts[9];
    let mut edges = pulses(LOW, PULSE, &starts);
    let i = edges.iter().position(|&e| e == (s2 + MS, HIGH)).unwrap();
    edges[i + 1].0 = s2 + 3_500 * US;
    assert_eq!(
        edges.drain(i + 2..i + 4).next(),
        Some((s2 + 2_500 * US, HIGH))
    );
    let mut c = Capture::new(CaptureSettings {
        idle: None,
        channels: Some(3),
    });
    assert_eq!(decode(&mut c, &events(&edges, 1)), [want[1], want[4]]);
    assert_eq!(c.idle_level(), Some(LOW));
    // Frames 0 and 3 each follow a newly found idle level.
    assert_eq!(
        c.counts(),
        CaptureCounts {
            edges: 42,
            frames: 2,
            out_of_window: 1,
            unsynced: 6,
            idle_changes: 2,
            ..Default::default()
        }
    );
}

#[test]
fn valid_for_a_second_after_the_last_whole_frame() {
    let (_, edges, want) = three_frames();
    let mut c = configured(LOW, 3);
    assert!(!c.valid_at(0));
    assert!(!c.valid_at(want[0].end_ns));
    assert_eq!(c.last_frame_end_ns(), None);
    decode(&mut c, &events(&edges, 1));
    let end = want[2].end_ns;
    assert_eq!(c.last_frame_end_ns(), Some(end));
    assert!(c.valid_at(end));
    assert!(
        c.valid_at(end - 1),
        "a now read before the edge was stamped"
    );
    assert!(c.valid_at(end + INPUT_VALID_NS - 1));
    assert!(!c.valid_at(end + INPUT_VALID_NS));
    assert!(!c.valid_at(u64::MAX));
}

#[test]
fn reasons_are_named_in_order() {
    let c = CaptureCounts {
        edges: 100,
        frames: 50,
        lost_events: 1,
        lost_frames: 2,
        runts: 3,
        noise: 4,
        out_of_window: 5,
        too_many_channels: 6,
        wrong_count: 7,
        unsynced: 8,
        idle_changes: 9,
    };
    assert_eq!(
        c.reasons(),
        [
            ("lost_events", 1),
            ("lost_frames", 2),
            ("runts", 3),
            ("noise", 4),
            ("out_of_window", 5),
            ("too_many_channels", 6),
            ("wrong_count", 7),
            ("unsynced", 8),
        ]
    );
}

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
