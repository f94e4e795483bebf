//! The loopback's pure parts: the sweep, the ring and the recording line,
//! the pairing of read edges with written ones, the frame comparison, the
//! checks, and the plan's checks of the options.

use super::analysis::{self, compare_frames, match_edges, Frame, TimeMap, EARLY_NS};
use super::report::{self, Thresholds};
use super::ring::{self, Recorder};
use super::sweep::{Sweep, SweepSource, HI_US, LO_US, STEP_US};
use super::*;
use ppm_shared::frame::Channels;
use ppm_shared::receiver::Receiver;
use ppm_shared::trace::TraceEdge;
use ppmd::source::CommandSource;

const US: u64 = 1_000;
const MS: u64 = 1_000_000;

fn edge(at: u64, level: Level) -> TraceEdge {
    TraceEdge {
        scheduled_ns: at,
        actual_ns: at,
        level,
    }
}

fn event(at_ns: u64, level: Level, seq: u64) -> EdgeEvent {
    EdgeEvent { at_ns, level, seq }
}

/// The read copies of `written`, each `late` ns after its scheduled time,
/// numbered from 1.
fn copies(written: &[TraceEdge], late: u64) -> Vec<EdgeEvent> {
    written
        .iter()
        .enumerate()
        .map(|(i, e)| event(e.scheduled_ns + late, e.level, i as u64 + 1))
        .collect()
}

/// Pulses of 300 us starting every ms from 1 s, idle low: `n` pulses.
fn pulses(n: u64) -> Vec<TraceEdge> {
    (0..n)
        .flat_map(|i| {
            let t = 1_000 * MS + i * MS;
            [edge(t, Level::High), edge(t + 300 * US, Level::Low)]
        })
        .collect()
}

#[test]
fn the_sweep_covers_the_range_with_different_values_on_every_channel() {
    let s = Sweep::new(8);
    assert_eq!(s.steps(), 101);
    assert_eq!((LO_US, HI_US, STEP_US), (1_000, 2_000, 10));
    for k in 0..2 * s.steps() {
        let f = s.frame_us(k);
        assert_eq!(f.len(), 8);
        assert!(f.iter().all(|v| (LO_US..=HI_US).contains(v)), "{f:?}");
        let mut distinct = f.clone();
        distinct.sort_unstable();
        distinct.dedup();
        assert_eq!(distinct.len(), 8, "frame {k}: {f:?}");
        // One step a frame, around the range.
        assert_eq!(f, s.frame_us(k + s.steps()));
    }
    // Every channel takes every value, the ends included.
    for ch in 0..8 {
        let mut seen: Vec<u32> = (0..s.steps()).map(|k| s.value_us(k, ch)).collect();
        seen.sort_unstable();
        assert_eq!(seen.first(), Some(&LO_US));
        assert_eq!(seen.last(), Some(&HI_US));
        seen.dedup();
        assert_eq!(seen.len(), s.steps(), "channel {ch}");
    }
    assert_eq!(
        s.frame_us(0),
        [1000, 1120, 1250, 1370, 1500, 1630, 1750, 1880]
    );
    assert_eq!(s.value_us(1, 0), 1_010);
    assert_eq!(s.value_us(100, 0), 2_000);
}

#[test]
fn a_frame_is_known_as_its_step_of_the_sweep() {
    let s = Sweep::new(6);
    for k in 0..s.steps() {
        let ns: Vec<u64> = s.frame_us(k).iter().map(|&v| u64::from(v) * US).collect();
        assert_eq!(s.step_of(&ns), Some(k));
        // One value off by a nanosecond, a channel missing, channels
        // swapped: no step.
        let mut off = ns.clone();
        off[3] += 1;
        assert_eq!(s.step_of(&off), None);
        assert_eq!(s.step_of(&ns[..5]), None);
        let mut swapped = ns.clone();
        swapped.swap(1, 2);
        assert_eq!(s.step_of(&swapped), None);
    }
    assert_eq!(s.step_of(&[999 * US; 6]), None);
}

fn model(channels: usize) -> FrameModel {
    model_for(channels, None, 3.0).unwrap().0
}

#[test]
fn the_sweep_source_hands_out_one_step_a_frame_then_stops_the_loop() {
    let s = Sweep::new(8);
    let m = model(8);
    let stop = Arc::new(AtomicBool::new(false));
    let mut src = SweepSource::new(&s, &m, 3, stop.clone()).unwrap();
    for k in 0..3 {
        assert!(!src.done());
        let sample = src.newest().unwrap();
        let ch = sample.channels(&m).expect("made under the model");
        let want: Vec<u32> = s.frame_us(k).iter().map(|v| v * 1_000).collect();
        assert_eq!(ch.as_ns(), want);
        assert!(sample.recv_mono_ns > 0, "stamped");
        assert!(!stop.load(Relaxed));
    }
    assert!(src.done());
    src.newest().unwrap();
    assert!(stop.load(Relaxed), "asked to stop once the frames are out");
    // Another channel count than the model's: no source.
    assert!(SweepSource::new(&Sweep::new(6), &m, 3, stop).is_none());
}

#[test]
fn the_ring_hands_over_every_edge_in_order_and_counts_what_did_not_fit() {
    let (mut tx, mut rx) = ring::ring(4);
    let mut out = vec![];
    for round in 0..5u64 {
        for i in 0..3 {
            assert!(tx.push(&edge(round * 10 + i, Level::from_bit(i % 2 == 0))));
        }
        assert_eq!(rx.drain(&mut out), 3);
    }
    assert_eq!(out.len(), 15);
    for (i, e) in out.iter().enumerate() {
        let (round, k) = (i as u64 / 3, i as u64 % 3);
        assert_eq!(*e, edge(round * 10 + k, Level::from_bit(k % 2 == 0)));
    }
    for i in 0..4 {
        assert!(tx.push(&edge(i, Level::High)));
    }
    assert!(!tx.push(&edge(9, Level::High)), "full");
    assert_eq!(rx.dropped(), 1);
    out.clear();
    assert_eq!(rx.drain(&mut out), 4);
    assert_eq!(out.last().unwrap().scheduled_ns, 3);
}

#[test]
fn the_ring_takes_a_concurrent_writer() {
    let (mut tx, mut rx) = ring::ring(64);
    let writer = std::thread::spawn(move || {
        let mut i = 0;
        while i < 100_000u64 {
            if tx.push(&TraceEdge {
                scheduled_ns: i,
                actual_ns: i * 2,
                level: Level::from_bit(i % 2 == 1),
            }) {
                i += 1;
            }
        }
    });
    let mut out = vec![];
    while out.len() < 100_000 {
        rx.drain(&mut out);
    }
    writer.join().unwrap();
    for (i, e) in out.iter().enumerate() {
        let i = i as u64;
        assert_eq!((e.scheduled_ns, e.actual_ns), (i, 2 * i));
        assert_eq!(e.level, Level::from_bit(i % 2 == 1));
    }
}

/// A line that refuses every third write and says whether it is stamped.
struct Flaky {
    writes: u64,
    parked: Option<Level>,
}

impl Line for Flaky {
    fn write(&mut self, _edge: &TraceEdge) -> Result<(), ppmd::line::LineError> {
        self.writes += 1;
        if self.writes.is_multiple_of(3) {
            Err(ppmd::line::LineError::BufferFull)
        } else {
            Ok(())
        }
    }

    fn park(&mut self, level: Level) -> Result<(), ppmd::line::LineError> {
        self.parked = Some(level);
        Ok(())
    }

    fn stamped(&self) -> bool {
        true
    }
}

#[test]
fn the_recorder_forwards_every_call_and_records_the_edges_that_went_out() {
    let (tx, mut rx) = ring::ring(16);
    let mut rec = Recorder::new(
        Box::new(Flaky {
            writes: 0,
            parked: None,
        }),
        tx,
    );
    assert!(rec.stamped(), "the loop sees the line's own stamping");
    let results: Vec<bool> = (0..6)
        .map(|i| rec.write(&edge(i, Level::High)).is_ok())
        .collect();
    assert_eq!(results, [true, true, false, true, true, false]);
    rec.park(Level::Low).unwrap();
    let mut out = vec![];
    rx.drain(&mut out);
    let at: Vec<u64> = out.iter().map(|e| e.scheduled_ns).collect();
    assert_eq!(at, [0, 1, 3, 4], "only the writes the line took");
}

#[test]
fn read_edges_pair_with_the_written_ones_in_order() {
    let written = pulses(10);
    let read = copies(&written, 7 * US);
    let m = match_edges(&written, &read);
    assert_eq!(m.pairs.len(), 20);
    assert!(m.pairs.iter().all(|(r, w)| r == w));
    assert_eq!((m.lost, m.missed, m.unexpected, m.before), (0, 0, 0, 0));
    // A stall: edges 4..8 all read 2.5 ms late, in order, each after the
    // next one was due: still each its own copy.
    let mut late = copies(&written, US);
    for e in &mut late[4..8] {
        e.at_ns = 1_000 * MS + 5_500 * US + e.seq;
    }
    let m = match_edges(&written, &late);
    assert!(m.pairs.iter().all(|(r, w)| r == w), "{:?}", m.pairs);
    assert_eq!((m.lost, m.missed, m.unexpected), (0, 0, 0));
}

#[test]
fn lost_missed_unexpected_and_early_edges_are_told_apart() {
    let written = pulses(6);
    // The kernel lost edges 3 and 4 (its sequence numbers skip them).
    let mut read = copies(&written, 2 * US);
    read.drain(3..5);
    let m = match_edges(&written, &read);
    assert_eq!((m.lost, m.missed, m.unexpected), (2, 0, 0));
    assert_eq!(m.pairs.len(), 10);
    assert!(m
        .pairs
        .iter()
        .all(|&(r, w)| w == if r < 3 { r } else { r + 2 }));
    // An edge never came (no gap in the numbers: it was not on the line).
    let mut read = copies(&written, 2 * US);
    read.remove(5);
    for (i, e) in read.iter_mut().enumerate() {
        e.seq = i as u64 + 1;
    }
    let m = match_edges(&written, &read);
    assert_eq!((m.lost, m.missed, m.unexpected), (0, 1, 0));
    assert_eq!(m.pairs.len(), 11);
    // A glitch (a spike of two edges inside a pulse) and a set-up edge
    // before the first written one: neither moves the pairs of the rest.
    let mut read = copies(&written, 2 * US);
    let t = read[0].at_ns;
    read.insert(1, event(t + 100 * US, Level::Low, 0));
    read.insert(2, event(t + 101 * US, Level::High, 0));
    read.insert(0, event(900 * MS, Level::Low, 0));
    for (i, e) in read.iter_mut().enumerate() {
        e.seq = i as u64 + 1;
    }
    let m = match_edges(&written, &read);
    assert_eq!((m.lost, m.missed, m.unexpected, m.before), (0, 0, 2, 1));
    assert_eq!(m.pairs.len(), 12);
    let errors: Vec<i64> = m
        .pairs
        .iter()
        .map(|&(r, w)| read[r].at_ns as i64 - written[w].scheduled_ns as i64)
        .collect();
    assert!(errors.iter().all(|&e| e == 2_000), "{errors:?}");
    // An edge read a little early (the clocks' business, a finding) is
    // still its edge's copy; one far earlier is not.
    let mut read = copies(&written, 0);
    read[4].at_ns -= EARLY_NS;
    let m = match_edges(&written, &read);
    assert_eq!((m.pairs.len(), m.unexpected), (12, 0));
    read[4].at_ns -= 1;
    let m = match_edges(&written, &read);
    assert_eq!((m.pairs.len(), m.unexpected, m.missed), (11, 1, 1));
    // Nothing read: every written edge missed.
    let m = match_edges(&written, &[]);
    assert_eq!((m.pairs.len(), m.missed), (0, 12));
}

#[test]
fn read_frames_are_compared_with_the_sent_frame_they_began_at() {
    let written = pulses(4);
    let read = copies(&written, 3 * US);
    let m = match_edges(&written, &read);
    let map = TimeMap::new(&m, &written, &read);
    assert_eq!(map.scheduled(1_000 * MS + 3 * US), Some(1_000 * MS));
    assert_eq!(map.scheduled(1_000 * MS), None);
    let at = |i: usize| written[2 * i].scheduled_ns;
    let sent = vec![
        Frame {
            start_ns: at(0),
            values_ns: vec![1_500 * US, 1_200 * US],
        },
        Frame {
            start_ns: at(2),
            values_ns: vec![1_000 * US, 2_000 * US],
        },
    ];
    let read_frames = vec![
        // As sent.
        Frame {
            start_ns: at(0) + 3 * US,
            values_ns: vec![1_499 * US, 1_201 * US],
        },
        // Off by 4 us on one channel.
        Frame {
            start_ns: at(2) + 3 * US,
            values_ns: vec![1_000 * US, 2_004 * US],
        },
        // Begun at an edge that began no frame sent.
        Frame {
            start_ns: at(1) + 3 * US,
            values_ns: vec![1_000 * US, 2_000 * US],
        },
        // Begun at no read edge at all.
        Frame {
            start_ns: 5,
            values_ns: vec![1_000 * US, 2_000 * US],
        },
    ];
    let t = compare_frames(&sent, &read_frames, &map);
    assert_eq!((t.sent, t.read, t.matched, t.exact), (2, 4, 2, 1));
    assert_eq!((t.not_sent(), t.max_error_ns), (2, 4 * US));
    assert!(
        !t.all_read_within(20 * US),
        "frames read that were not sent"
    );
    let t = compare_frames(&sent, &read_frames[..2], &map);
    assert!(t.all_read_within(4 * US));
    assert!(!t.all_read_within(3 * US));
    // Another channel count than the frame sent: not that frame.
    let short = [Frame {
        start_ns: at(0) + 3 * US,
        values_ns: vec![1_500 * US],
    }];
    assert_eq!(compare_frames(&sent, &short, &map).matched, 0);
}

/// `frames` frames of the sweep as the loop writes them on a grid, after
/// a lead-in pulse: each edge written `late` ns after its time.
fn sweep_written(model: &FrameModel, sweep: &Sweep, frames: usize, late: u64) -> Vec<TraceEdge> {
    let t0 = 1_000 * MS;
    let mut out = vec![
        TraceEdge {
            scheduled_ns: t0 - 5 * MS,
            actual_ns: t0 - 5 * MS + late,
            level: Level::High,
        },
        TraceEdge {
            scheduled_ns: t0 - 5 * MS + 300 * US,
            actual_ns: t0 - 5 * MS + 300 * US + late,
            level: Level::Low,
        },
    ];
    for k in 0..frames {
        let ns: Vec<u32> = sweep.frame_us(k).iter().map(|v| v * 1_000).collect();
        let start = t0 + k as u64 * model.frame_ns();
        for e in model.encode(&Channels::from_ns(&ns)).edges() {
            out.push(TraceEdge {
                scheduled_ns: start + e.at_ns,
                actual_ns: start + e.at_ns + late,
                level: e.level,
            });
        }
    }
    out
}

fn thresholds() -> Thresholds {
    Thresholds {
        max_p999_ns: 10 * US,
        max_value_error_ns: 20 * US,
    }
}

#[test]
fn a_clean_loopback_reads_every_frame_on_every_receiver_and_passes() {
    let m = model(8);
    let s = Sweep::new(8);
    let written = sweep_written(&m, &s, 60, 40);
    let read = copies(&written, 2_345);
    let a = analysis::analyse(&written, &read, &s, Level::Low);
    assert_eq!(
        (a.written, a.read, a.matching.pairs.len()),
        (1082, 1082, 1082)
    );
    assert!(a.line_error.equivalent(a.line_error.min(), 2_345));
    assert!(a.line_error.equivalent(a.line_error.max(), 2_345));
    assert!(a.own_error.equivalent(a.own_error.max(), 40));
    // The last frame has no sync after it: no receiver hands it on.
    assert_eq!(a.sweep.whole, 59);
    assert_eq!(a.sweep.of_sweep, 59);
    let sent: Vec<(Receiver, usize)> = a
        .receivers
        .iter()
        .map(|(r, t)| (*r, t.unwrap().sent))
        .collect();
    assert_eq!(
        sent,
        [
            (Receiver::EdgeTx, 59),
            (Receiver::Betaflight, 59 - 26),
            (Receiver::ArduPilot, 59 - 2)
        ]
    );
    for (r, t) in &a.receivers {
        let t = t.unwrap();
        assert_eq!(
            (t.read, t.matched, t.exact),
            (t.sent, t.sent, t.sent),
            "{r:?}"
        );
    }
    assert_eq!(a.capture.read, a.capture.sent);
    assert!(a.capture.max_error_ns == 0, "{:?}", a.capture);
    let checks = report::checks(&a, 0, &thresholds());
    assert!(checks.iter().all(|c| c.ok), "{checks:?}");
    assert_eq!(report::verdict(&checks), "verdict: PASS");
}

#[test]
fn a_lost_edge_a_slow_line_or_a_wrong_value_fails_the_verdict() {
    let m = model(8);
    let s = Sweep::new(8);
    let written = sweep_written(&m, &s, 60, 40);
    let failed = |read: &[EdgeEvent], dropped: u64| -> Vec<&'static str> {
        let a = analysis::analyse(&written, read, &s, Level::Low);
        report::checks(&a, dropped, &thresholds())
            .into_iter()
            .filter(|c| !c.ok)
            .map(|c| c.name)
            .collect()
    };
    let clean = copies(&written, 1_000);
    assert!(failed(&clean, 0).is_empty());
    // An edge the ring could not record.
    assert_eq!(failed(&clean, 1), ["edges"]);
    // The kernel lost one edge (a timed one, inside frame 30): every
    // receiver misses that frame.
    let mut lost = clean.clone();
    lost.remove(2 + 30 * 18 + 6);
    assert_eq!(failed(&lost, 0), ["edges", "frames"]);
    // A line that carries every edge 12 us late: p99.9 over 10 us.
    assert_eq!(failed(&copies(&written, 12_000), 0), ["edge error"]);
    // One timed edge 25 us late: two values off by 25 us, beyond 20.
    let mut slow = clean.clone();
    slow[2 + 30 * 18 + 6].at_ns += 25 * US;
    assert_eq!(failed(&slow, 0), ["frames"]);
    let a = analysis::analyse(&written, &slow, &s, Level::Low);
    let (_, edgetx) = &a.receivers[0];
    assert_eq!(edgetx.unwrap().max_error_ns, 25 * US);
    assert_eq!(edgetx.unwrap().exact, edgetx.unwrap().read - 1);
}

#[test]
fn a_receiver_that_does_not_take_the_channel_count_is_left_out() {
    let m = model(4);
    let s = Sweep::new(4);
    let written = sweep_written(&m, &s, 40, 0);
    let a = analysis::analyse(&written, &copies(&written, 500), &s, Level::Low);
    let ardupilot = a.receivers.iter().find(|(r, _)| *r == Receiver::ArduPilot);
    assert!(ardupilot.unwrap().1.unwrap_err().contains("fewer than 5"));
    assert!(report::checks(&a, 0, &thresholds()).iter().all(|c| c.ok));
}

fn args(cli: &[&str]) -> Result<LoopbackArgs, clap::Error> {
    #[derive(clap::Parser)]
    #[command(disable_help_flag = true)]
    struct Wrap {
        #[command(flatten)]
        args: LoopbackArgs,
    }
    use clap::Parser;
    Wrap::try_parse_from(std::iter::once("loopback").chain(cli.iter().copied())).map(|w| w.args)
}

#[test]
fn the_options_resolve_into_a_plan() {
    let a = args(&["--output", "sim:/t/a", "--input", "sim:/t/a"]).unwrap();
    let plan = Plan::resolve(&a).unwrap();
    assert_eq!(plan.drive, Drive::Sim("/t/a".into()));
    assert_eq!(plan.drive.to_string(), "sim:/t/a");
    assert_eq!(plan.model.frame_ns(), 22_500_000);
    assert_eq!(plan.frames, 1334, "30 s of 22.5 ms frames");
    assert_eq!(plan.lengthened_from, None);
    assert_eq!(plan.setup.priority, 80);
    assert_eq!(plan.thresholds, thresholds());
    let a = args(&[
        "--output",
        "gpio:GPIO18",
        "--input",
        "gpio:GPIO17",
        "--channels",
        "12",
        "-D",
        "2s",
        "--max-p999",
        "2.5",
    ])
    .unwrap();
    let plan = Plan::resolve(&a).unwrap();
    assert_eq!(
        plan.drive,
        Drive::Gpio {
            chip: String::new(),
            line: "GPIO18".into()
        }
    );
    assert_eq!(plan.drive.to_string(), "gpio:GPIO18");
    assert_eq!(plan.lengthened_from, Some(22_500.0));
    assert_eq!(plan.model.frame_ns(), 28_500_000, "12 x 2000 us + 4500 us");
    assert_eq!(plan.thresholds.max_p999_ns, 2_500);
    let refused = |cli: &[&str], says: &str| {
        let e = Plan::resolve(&args(cli).unwrap()).unwrap_err().to_string();
        assert!(e.contains(says), "{cli:?}: {e}");
    };
    refused(
        &["--output", "gpio:GPIO18", "--input", "gpio:GPIO18"],
        "the same line",
    );
    refused(
        &["--output", "sim:/t/a", "--input", "sim:/t/b"],
        "--input sim:/t/b: a sim output is read back through its own trace: --input sim:/t/a",
    );
    refused(
        &["--output", "sim:/t/a", "--input", "gpio:nochip:3"],
        "--input gpio:nochip:3",
    );
    refused(
        &["--output", "gpio:18", "--input", "sim:/t/a"],
        "--input sim:/t/a",
    );
    refused(&["--output", "sim", "--input", "sim:/t/a"], "sim:PATH");
    refused(
        &["--output", "spi:/dev/spidev0.0", "--input", "gpio:17"],
        "edge by edge",
    );
    refused(
        &["--output", "sim:/t/a", "--input", "sim:/t/a", "-D", "1s"],
        "at least 1.1 s",
    );
    refused(
        &[
            "--output", "sim:/t/a", "--input", "sim:/t/a", "--frame", "10000",
        ],
        "--frame 10000: config key `ppm.frame_us`",
    );
    assert!(args(&[
        "--output",
        "sim:/t/a",
        "--input",
        "sim:/t/a",
        "--channels",
        "15"
    ])
    .is_err());
    assert!(args(&["--output", "sim:/t/a", "--input", "nothing"]).is_err());
}

#[test]
fn every_channel_count_gets_a_frame_that_holds_the_sweep() {
    for n in 1..=14 {
        let (m, from) = model_for(n, None, 3.0).unwrap();
        assert_eq!(m.channels(), n);
        assert_eq!(from.is_some(), m.frame_ns() != 22_500_000, "{n}");
    }
    assert!(model_for(15, None, 3.0).is_err());
}
