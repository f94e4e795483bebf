//! Tests of the capture decoder: every refusal reason with exact counts,
//! and the idle level and channel count found from the signal. The
//! property tests, on streams made by ppm's own encoder, on noise and on
//! glitches, are in `properties.rs`.

use super::*;

mod properties;

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
