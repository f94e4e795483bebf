//! The loop on grid timing, and how its frames leave: edge by edge on a
//! line of its own or of a bank, or whole; late edges, skipped and late
//! frames, the failsafe, the automatic margin, the frame log.

use super::*;

#[test]
fn frames_carry_the_command_then_fall_silent() {
    let mut out = Recorder::default();
    let (sim, stats) = run_once(LineRef::Edges(&mut out), FailsafeAction::Silence, 100, 300);
    let edges = out.edges;
    let s0 = first_start(&edges);
    // The command (stamped at the start) is fresh for 100 ms: frame k is
    // decided DECIDE_NS before s0 + k frames, and fresh while that is
    // within 100 ms of the start: 5 frames. Then silence.
    let fresh = frames_before_stop(s0, FRAME_NS, LEAD_1, 100);
    assert_eq!(fresh, 5);
    assert_eq!(stats.frames.load(Relaxed), fresh);
    assert_eq!(edges.len() as u64, fresh * 18 + 2);
    assert_eq!(stats.edges.load(Relaxed), edges.len() as u64);
    let frames = channels_of(&scheduled(&edges));
    assert_eq!(frames, vec![CMD_US.to_vec(); 5]);
    // Every frame on the grid, every edge written after its time and
    // within the spin's resolution of it.
    let starts = starts_of(&scheduled(&edges));
    for (k, s) in starts.iter().enumerate() {
        assert_eq!(*s, s0 + k as u64 * FRAME_NS);
    }
    for e in &edges {
        assert!(e.actual_ns >= e.scheduled_ns, "never early");
    }
    assert!(stats.max_edge_error_ns.load(Relaxed) < 1_000, "{stats:?}");
    assert_eq!(stats.late_edges.load(Relaxed), 0);
    assert_eq!(stats.late_frames.load(Relaxed), 0);
    assert_eq!(stats.overruns.load(Relaxed), 0);
    assert_eq!(stats.commands.load(Relaxed), 1);
    assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
    assert_eq!(stats.state(), LineState::Silent);
    assert_eq!(stats.margin_ns.load(Relaxed), 100_000, "the fixed margin");
    // Each edge: a sleep to 100 us before it, then a spin.
    assert!(
        sim.sleeps() >= edges.len() as u64,
        "{} sleeps",
        sim.sleeps()
    );
}

/// Idle low: the loop held up 50 us just before the pulse that ends
/// the second frame's second channel. That pulse and the rest of the
/// frame are not written; the next frame keeps its grid start and, the
/// gap before it being longer than a sync, gets a lead-in pulse. EdgeTX
/// reads the cut frame as one of 1 channel (the first, exact), the
/// flight controllers drop it; no receiver reads a value not commanded.
#[test]
fn a_timed_edge_found_late_is_not_written_and_its_frame_ends_there() {
    let model = grid_model();
    let (clean, _) = stalled_run(&model, None, 800);
    // The lead-in pulse's two edges, then 18 per frame.
    let frame2 = 2 + 18;
    let due = clean[frame2 + 4].scheduled_ns;
    assert_eq!(clean[frame2 + 4].level, Level::High);
    let (edges, stats) = stalled_run(&model, Some((due - 5_000, 50_000)), 800);
    assert_eq!(stats.aborted_frames.load(Relaxed), 1, "{stats:?}");
    assert_eq!(stats.glitched_frames.load(Relaxed), 0);
    let s3 = clean[frame2 + 18].scheduled_ns;
    // Up to the aborted frame's second pulse, as without the stall.
    assert_eq!(
        scheduled(&edges[..frame2 + 4]),
        scheduled(&clean[..frame2 + 4])
    );
    // A lead-in pulse LEAD_IN_NS before the next frame, then the rest.
    assert_eq!(
        scheduled(&edges[frame2 + 4..frame2 + 6]),
        [
            (s3 - LEAD_IN_NS, Level::High),
            (s3 - LEAD_IN_NS + 300_000, Level::Low)
        ]
    );
    assert_eq!(
        scheduled(&edges[frame2 + 6..]),
        scheduled(&clean[frame2 + 18..])
    );
    assert!(edges.iter().all(|e| e.actual_ns - e.scheduled_ns < 1_000));
    assert_eq!(stats.frames.load(Relaxed), (clean.len() as u64 - 2) / 18);
    read_cut_after_its_first_channel(&edges, clean[frame2].scheduled_ns);
    // The newest frame on the line is the last one, whole: its number,
    // start and values.
    let last = stats.last_frame.load().expect("a frame went out whole");
    assert_eq!(last.frame, stats.frames.load(Relaxed));
    assert_eq!(last.start_mono_ns, edges[edges.len() - 18].scheduled_ns);
    let us: Vec<u64> = last.values_ns[..last.channels as usize]
        .iter()
        .map(|&v| v as u64 / 1_000)
        .collect();
    assert_eq!(us, CMD_US);
    assert_eq!(last.state, LineState::Active as u32);
}

/// Idle high: the rising edge receivers time ends each pulse. Held up
/// inside the second frame's third pulse, the loop cannot leave the
/// line in the pulse: it ends it a shortest sync (4500 us) after the
/// last timed edge that reached the line, which every receiver reads
/// as a sync. The next frame keeps its grid start (no lead-in: the gap
/// is a sync).
#[test]
fn idle_high_a_pulse_held_up_ends_a_sync_after_the_last_timed_edge() {
    let model = timed_model(false, "idle_level = 'high'");
    let (clean, _) = stalled_run(&model, None, 800);
    let frame2 = 2 + 18;
    // Pulse 2 of frame 2: its start (falling), then its end (rising).
    assert_eq!(clean[frame2 + 5].level, Level::High);
    let due = clean[frame2 + 5].scheduled_ns;
    let (edges, stats) = stalled_run(&model, Some((due - 5_000, 50_000)), 800);
    assert_eq!(stats.aborted_frames.load(Relaxed), 1, "{stats:?}");
    assert_eq!(
        scheduled(&edges[..frame2 + 5]),
        scheduled(&clean[..frame2 + 5])
    );
    let last_timed = edges[frame2 + 3].actual_ns;
    let tail = &edges[frame2 + 5];
    assert_eq!(tail.level, Level::High);
    assert_eq!(tail.scheduled_ns, last_timed + 4_500_000);
    assert_eq!(
        scheduled(&edges[frame2 + 6..]),
        scheduled(&clean[frame2 + 18..])
    );
    // The receivers time the pulses' ends, 300 us after their starts.
    read_cut_after_its_first_channel(&edges, clean[frame2].scheduled_ns + 300_000);
}

/// Every receiver reads more than 5 frames from `edges`, each the
/// command, but the one starting at `cut` (as the receivers time it),
/// which was aborted at its second channel: the trainer inputs read its
/// first channel, exact; the flight controllers drop it.
fn read_cut_after_its_first_channel(edges: &[TraceEdge], cut: u64) {
    for r in Receiver::ALL {
        let (read, _) = decode_as(r, scheduled(edges), Level::High);
        assert!(read.len() > 5, "{r:?} read {} frames", read.len());
        for f in &read {
            let v = f.channels_us();
            if f.start_ns == cut {
                assert!(matches!(r, Receiver::EdgeTx | Receiver::OpenTx), "{r:?}");
                assert_eq!(v, [1_100], "{r:?}: the channel before the abort");
            } else {
                assert_eq!(v, CMD_US, "{r:?} at {}", f.start_ns);
            }
        }
    }
}

/// A whole-frame line (SPI) times the frame's edges itself: no guard
/// inside a frame. A transfer started late only lengthens the sync
/// before it; started so late that the sync would pass the receivers'
/// window (18500 us), it is not started: the frame is aborted and the
/// next one gets a lead-in pulse.
#[test]
fn a_whole_frame_output_starts_no_frame_past_the_longest_sync() {
    let model = grid_model();
    let run = |stall: Option<(u64, u64)>| {
        let sim = Sim::new();
        if let Some((at, ns)) = stall {
            sim.stall_at(at, ns);
        }
        let mut src = Fresh::new(&sim, &model, CMD);
        let mut out = WholeFrames {
            sim: Some(sim.clone()),
            ..WholeFrames::default()
        };
        let stats = run_one(
            &sim,
            &model,
            cfg(100, FailsafeAction::Silence),
            &mut src,
            LineRef::Whole(&mut out),
            200,
        );
        (out, stats)
    };
    let (clean, _) = run(None);
    // Frame 2's start; frame 1's last pulse 11000 us after its start
    // (the command's values), so a sync of 11500 us before frame 2.
    let s2 = clean.started[1];
    let last1 = clean.started[0] + LEAD_IN_NS + 11_000_000;
    assert_eq!(s2 - last1, 11_500_000);
    // Almost 7 ms late: a sync just under 18.5 ms, the longest; written.
    let (late, stats) = run(Some((s2 - 5_000, 6_990_000)));
    assert_eq!(stats.aborted_frames.load(Relaxed), 0, "{stats:?}");
    let sync = late.started[1] - last1;
    assert!((18_480_000..=18_500_000).contains(&sync), "{sync}");
    assert_eq!(late.frames.len(), clean.frames.len());
    // Later: not started; the next frame, at its grid start, has a
    // lead-in pulse.
    let (cut, stats) = run(Some((s2 - 5_000, 7_010_000)));
    assert_eq!(stats.aborted_frames.load(Relaxed), 1, "{stats:?}");
    assert_eq!(cut.frames.len(), clean.frames.len() - 1);
    assert_eq!(cut.frames[1].len(), 18 + 2, "a lead-in pulse first");
    assert_eq!(cut.frames[1][2].at_ns, LEAD_IN_NS);
    assert_eq!(cut.started[1] + LEAD_IN_NS, clean.started[2]);
}

/// A whole-frame line gets each frame once, at its first edge, with
/// every edge relative to it (the first frame's lead-in pulse
/// included), and no single edge; the counters count every edge.
#[test]
fn whole_frame_outputs_get_each_frame_in_one_call() {
    let mut out = WholeFrames::default();
    let line = LineRef::Whole(&mut out);
    let (_, stats) = run_once(line, FailsafeAction::Silence, 100, 300);
    assert_eq!(stats.frames.load(Relaxed), 5);
    assert_eq!(out.frames.len(), 5);
    let edges: usize = out.frames.iter().map(Vec::len).sum();
    assert_eq!(edges, 5 * 18 + 2);
    assert_eq!(
        stats.edges.load(Relaxed),
        edges as u64,
        "every edge counted"
    );
    for (k, edges) in out.frames.iter().enumerate() {
        assert_eq!(edges[0].at_ns, 0);
        assert_eq!(edges[0].level, Level::High);
        // 18 edges of 9 pulses, and the lead-in pulse's 2 first.
        let lead = if k == 0 { 2 } else { 0 };
        assert_eq!(edges.len(), 18 + lead, "frame {k}");
        if lead == 2 {
            assert_eq!(edges[2].at_ns, LEAD_IN_NS, "the lead-in pulse first");
        }
        // Pulse starts in the frame give the channels exactly.
        let starts: Vec<u64> = edges[lead..]
            .iter()
            .filter(|e| e.level == Level::High)
            .map(|e| e.at_ns)
            .collect();
        let got: Vec<u64> = starts.windows(2).map(|w| (w[1] - w[0]) / 1_000).collect();
        assert_eq!(got, CMD_US, "frame {k}");
    }
}

#[test]
fn a_silent_line_reports_its_margin() {
    let sim = Sim::new();
    let model = grid_model();
    let mut src = Feed::new(&sim, &model, &[]);
    let mut out = Recorder::default();
    let cfg = Settings {
        margin: Margin::Fixed(70_000),
        ..cfg(100, FailsafeAction::Silence)
    };
    let stats = run_one(&sim, &model, cfg, &mut src, LineRef::Edges(&mut out), 51);
    assert!(out.edges.is_empty());
    assert_eq!(stats.frames.load(Relaxed), 0);
    assert_eq!(stats.margin_ns.load(Relaxed), 70_000);
    // It looked for a command every IDLE_POLL_NS, from the start.
    assert_eq!(
        stats.decisions.load(Relaxed),
        51 * MS / IDLE_POLL_NS + 1,
        "{stats:?}"
    );
}

#[test]
fn the_frame_after_skipped_ones_is_read_too() {
    // The third frame's last edge (after the first lead-in pulse) holds
    // the loop up for 50 ms: the next frame's start passes, by more than
    // its sync can absorb, and frames are skipped.
    let stall_after = 2 + 3 * 18;
    let sim = Sim::new();
    let mut out = Recorder {
        stall: Some((stall_after, 50 * MS, sim.clone())),
        ..Recorder::default()
    };
    let model = grid_model();
    let mut src = Feed::new(&sim, &model, &[(START_NS, CMD)]);
    let stats = run_one(
        &sim,
        &model,
        cfg(10_000, FailsafeAction::Silence),
        &mut src,
        LineRef::Edges(&mut out),
        200,
    );
    let edges = out.edges;
    let s0 = first_start(&edges);
    // Frame 2's last pulse ends 11.6 ms in, so the loop is back 39.1 ms
    // past frame 3's start: with the 5 ms lead-in frame 5 needs, frames
    // 3 and 4 are skipped.
    assert_eq!(stats.overruns.load(Relaxed), 2, "{stats:?}");
    assert_eq!(stats.late_frames.load(Relaxed), 0);
    // A lone pulse 5 ms before frame 5, as after silence...
    let lead_in = &edges[stall_after..stall_after + 3];
    assert_eq!(lead_in[2].scheduled_ns, s0 + 5 * FRAME_NS);
    assert_eq!(
        lead_in[2].scheduled_ns - lead_in[0].scheduled_ns,
        LEAD_IN_NS
    );
    // ...so a transmitter reads every frame sent, that one included:
    // frames 0..=8 are decided before the stop at 200 ms, less 3 and 4.
    let n = frames_before_stop(s0, FRAME_NS, LEAD_1, 200) - 2;
    assert_eq!(n, 7);
    assert_eq!(stats.frames.load(Relaxed), n);
    assert_eq!(edges.len() as u64, n * 18 + 4, "two lead-in pulses");
    let starts = starts_of(&scheduled(&edges));
    let want: Vec<u64> = [0, 1, 2, 5, 6, 7, 8]
        .iter()
        .map(|k| s0 + k * FRAME_NS)
        .collect();
    assert_eq!(starts, want);
    assert_eq!(channels_of(&scheduled(&edges)), vec![CMD_US.to_vec(); 7]);
}

/// A stall short enough that the frame can move later as a whole: the
/// sync before it grows, the one after it shrinks, both stay valid, and
/// the frame after returns to the grid.
#[test]
fn a_frame_decided_late_moves_and_the_next_returns_to_the_grid() {
    let sim = Sim::new();
    let model = grid_model();
    let mut src = Feed::new(&sim, &model, &[(START_NS, CMD)]);
    let mut out = Recorder::default();
    // Frame 2 is decided at s0 + 2 frames - DECIDE_NS; a 3 ms stall just
    // before its decision makes it 2.85 ms late (less than its
    // predecessor's 10.9 ms sync less the 4 ms shortest).
    let s0_planned = START_NS + LEAD_1 + LEAD_IN_NS;
    sim.stall_at(s0_planned + 2 * FRAME_NS - LEAD_1 - 1_000, 3 * MS);
    let stats = run_one(
        &sim,
        &model,
        cfg(10_000, FailsafeAction::Silence),
        &mut src,
        LineRef::Edges(&mut out),
        100,
    );
    let edges = scheduled(&out.edges);
    let s0 = first_start(&out.edges);
    assert_eq!(stats.late_frames.load(Relaxed), 1, "{stats:?}");
    assert_eq!(stats.overruns.load(Relaxed), 0);
    let starts = starts_of(&edges);
    let n = frames_before_stop(s0, FRAME_NS, LEAD_1, 100);
    assert_eq!(starts.len() as u64, n);
    assert_eq!(n, 5);
    assert_eq!(starts[1], s0 + FRAME_NS);
    let moved = starts[2] - (s0 + 2 * FRAME_NS);
    assert!((2_800_000..3_000_000).contains(&moved), "moved {moved} ns");
    for (k, s) in starts.iter().enumerate().skip(3) {
        assert_eq!(*s, s0 + k as u64 * FRAME_NS, "back on the grid");
    }
    assert_eq!(channels_of(&edges), vec![CMD_US.to_vec(); 5]);
}

#[test]
fn default_action_emits_defaults_after_the_command() {
    let mut out = Recorder::default();
    let (_, stats) = run_once(LineRef::Edges(&mut out), FailsafeAction::Default, 60, 200);
    let s0 = first_start(&out.edges);
    let frames = channels_of(&scheduled(&out.edges));
    // Fresh for 60 ms: 3 frames carry it (decided at 5, 27.5 and 50 ms),
    // then the defaults until the stop.
    let fresh = frames_before_stop(s0, FRAME_NS, LEAD_1, 60) as usize;
    assert_eq!(fresh, 3);
    let all = frames_before_stop(s0, FRAME_NS, LEAD_1, 200) as usize;
    assert_eq!(frames.len(), all);
    assert_eq!(frames[..fresh], vec![CMD_US.to_vec(); fresh]);
    let defaults = [1500, 1500, 1000, 1500, 1500, 1500, 1500, 1500];
    assert_eq!(frames[fresh..], vec![defaults.to_vec(); all - fresh]);
    assert_eq!(stats.state(), LineState::Silent, "stopped");
    assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
}

#[test]
fn hold_repeats_the_last_command() {
    let mut out = Recorder::default();
    let (_, stats) = run_once(LineRef::Edges(&mut out), FailsafeAction::Hold, 30, 300);
    let s0 = first_start(&out.edges);
    let frames = channels_of(&scheduled(&out.edges));
    let all = frames_before_stop(s0, FRAME_NS, LEAD_1, 300) as usize;
    assert_eq!(all, 14);
    assert_eq!(frames, vec![CMD_US.to_vec(); all]);
    assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
    assert_eq!(stats.commands.load(Relaxed), 1);
}

/// The automatic margin learns how late sleeps end and covers it. The
/// first edge comes within the starting margin, so the loop spins to it
/// without a sleep and the margin halves (it dropped to its minimum once,
/// and the next sleep, 40 us late, wrote the lead-in pulse's end 20 us
/// late); the next edge's sleep, 40 us late, still ends before its edge:
/// no edge is late.
#[test]
fn the_automatic_margin_covers_the_wake_up_lateness() {
    let sim = Sim::new();
    sim.set_wake_late_ns(40_000);
    let model = grid_model();
    let mut src = Fresh::new(&sim, &model, CMD);
    let mut out = Recorder::default();
    let cfg = Settings {
        margin: Margin::Auto {
            min_ns: 20_000,
            max_ns: 500_000,
        },
        ..cfg(100, FailsafeAction::Silence)
    };
    let stats = run_one(&sim, &model, cfg, &mut src, LineRef::Edges(&mut out), 200);
    // 40 us late is bucket 40..45 us, plus 10 us of headroom.
    assert_eq!(stats.margin_ns.load(Relaxed), 55_000);
    assert_eq!(stats.late_edges.load(Relaxed), 0, "{stats:?}");
    let late: Vec<u64> = out
        .edges
        .iter()
        .map(|e| e.actual_ns - e.scheduled_ns)
        .collect();
    assert!(late.iter().all(|&l| l < 1_000), "{late:?}");
    // With a fixed margin below the lateness, every edge after a sleep
    // is late by the difference: within the guard (20 us here), written
    // so.
    let guard_20 = timed_model(false, "late_edge_guard_us = 20.0");
    let sim = Sim::new();
    sim.set_wake_late_ns(40_000);
    let mut src = Fresh::new(&sim, &guard_20, CMD);
    let mut out = Recorder::default();
    let fixed = Settings {
        margin: Margin::Fixed(25_000),
        ..cfg
    };
    let stats = run_one(
        &sim,
        &guard_20,
        fixed,
        &mut src,
        LineRef::Edges(&mut out),
        200,
    );
    let late = stats.late_edges.load(Relaxed);
    assert_eq!(late, stats.edges.load(Relaxed), "{stats:?}");
    assert!(late > 0);
    let max = stats.max_edge_error_ns.load(Relaxed);
    assert!((15_000..16_000).contains(&max), "{max} ns");
    assert_eq!(stats.aborted_frames.load(Relaxed), 0);
    // Later than the guard (25 us, the default guard 3 us): no rising
    // edge is written, every frame is aborted at its first pulse, and
    // the line stays idle.
    let sim = Sim::new();
    sim.set_wake_late_ns(40_000);
    let mut src = Fresh::new(&sim, &model, CMD);
    let mut out = Recorder::default();
    let fixed = Settings {
        margin: Margin::Fixed(15_000),
        ..cfg
    };
    let stats = run_one(&sim, &model, fixed, &mut src, LineRef::Edges(&mut out), 200);
    assert!(out.edges.is_empty(), "{:?}", out.edges);
    assert_eq!(stats.edges.load(Relaxed), 0);
    let frames = stats.frames.load(Relaxed);
    assert!(frames > 0);
    assert_eq!(stats.aborted_frames.load(Relaxed), frames, "{stats:?}");
    // No frame went out whole: none is reported as on the line.
    assert_eq!(stats.last_frame.load(), None);
}

/// The frame log gets one row per frame sent, numbered from 1, with
/// its start on both clocks (as scheduled), its state, its values and
/// the command it carries (none for the failsafe defaults), and one
/// row per change of the line's state, at the decision that made it.
#[test]
fn the_frame_log_has_every_frame_and_change_as_sent() {
    let dir = std::env::temp_dir().join(format!("ppmd-emitter-log-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("frames.jsonl");
    let _ = std::fs::remove_file(&path);
    let (mut log, mut writer) = framelog::open(&path, 1 << 20).unwrap();
    let sim = Sim::new();
    let model = grid_model();
    let mut src = Feed::new(&sim, &model, &[(START_NS, CMD)]);
    let mut out = Recorder::default();
    let default = cfg(60, FailsafeAction::Default);
    let line = LineRef::Edges(&mut out);
    run_logged(&sim, &model, default, &mut src, line, &mut log, 150);
    drop(log);
    writer.finish();
    let rows = log_rows(&path);
    std::fs::remove_dir_all(&dir).unwrap();
    let starts = starts_of(&scheduled(&out.edges));
    // Frames decided at 5, 27.5 and 50 ms carry the command (60 ms
    // fresh), those at 72.5..=140 ms the defaults.
    assert_eq!(starts.len(), 7);
    let frames: Vec<&serde_json::Value> = rows.iter().filter(|r| r["type"] == "frame").collect();
    assert_eq!(frames.len(), 7);
    for (k, (f, start)) in frames.iter().zip(&starts).enumerate() {
        assert_eq!(f["frame"], k as u64 + 1);
        assert_eq!(f["mono_ns"], *start);
        assert_eq!(
            f["real_ns"],
            *start + crate::clock::sim::REALTIME_OFFSET_NS,
            "one pair of readings"
        );
        assert_eq!(f["timing"], "grid");
        if k < 3 {
            assert_eq!(f["state"], "active", "frame {k}");
            assert_eq!(f["ingress_seq"], 1);
            assert_eq!(f["recv_mono_ns"], START_NS);
            assert_eq!(f["ch_us"], serde_json::json!(CMD_US.map(|v| v as f64)));
        } else {
            assert_eq!(f["state"], "failsafe", "frame {k}");
            assert_eq!(f["ingress_seq"], serde_json::Value::Null);
            assert_eq!(
                f["ch_us"],
                serde_json::json!([1500.0, 1500.0, 1000.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0])
            );
        }
    }
    let changes: Vec<(&str, &str, u64)> = rows
        .iter()
        .filter(|r| r["type"] == "transition")
        .map(|r| {
            (
                r["from"].as_str().unwrap(),
                r["to"].as_str().unwrap(),
                r["mono_ns"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(changes.len(), 2, "{changes:?}");
    assert_eq!(changes[0].0..changes[0].1, "silent".."active");
    assert_eq!(changes[1].0..changes[1].1, "active".."failsafe");
    // At the first look (the start), and at the decision of frame 3,
    // DECIDE_NS before it.
    assert!(changes[0].2 - START_NS < 1_000, "{changes:?}");
    assert!(
        (starts[3] - LEAD_1).abs_diff(changes[1].2) < 1_000,
        "{changes:?}"
    );
    // A row per frame and per change, in time order.
    let times: Vec<u64> = rows
        .iter()
        .map(|r| r["mono_ns"].as_u64().unwrap())
        .collect();
    assert_eq!(rows.len(), 9);
    assert!(times.windows(2).all(|w| w[0] < w[1]), "{times:?}");
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
fn two_outputs_emit_their_own_frames_from_one_loop() {
    let sim = Sim::new();
    let a = grid_model();
    let b = timed_model(false, SIX_AT_20_MS);
    let mut src_a = Fresh::new(&sim, &a, CMD);
    let mut src_b = Fresh::new(&sim, &b, "[1900, 1800, 1700, 1600, 1500, 1000]");
    let (mut out_a, mut out_b) = (Recorder::default(), Recorder::default());
    let silence = cfg(100, FailsafeAction::Silence);
    let until_ms = 511;
    let (stats_a, stats_b) = run_two(
        &sim,
        (&a, silence, &mut src_a, LineRef::Edges(&mut out_a)),
        (&b, silence, &mut src_b, LineRef::Edges(&mut out_b)),
        until_ms,
    );
    // Two outputs decide DECIDE_NS + DECIDE_SLOT_NS ahead.
    let lead = DECIDE_NS + DECIDE_SLOT_NS;
    for (out, stats, frame_ns, per_frame, values) in [
        (&out_a, &stats_a, FRAME_NS, 18, CMD_US.to_vec()),
        (
            &out_b,
            &stats_b,
            20 * MS,
            14,
            vec![1900, 1800, 1700, 1600, 1500, 1000],
        ),
    ] {
        let edges = scheduled(&out.edges);
        assert_edges_add_up(edges.len(), stats, per_frame);
        assert!(
            out.edges.iter().all(|e| e.actual_ns >= e.scheduled_ns),
            "never early"
        );
        assert!(stats.max_edge_error_ns.load(Relaxed) < 1_000, "{stats:?}");
        let starts = starts_of(&edges);
        let n = frames_before_stop(starts[0], frame_ns, lead, until_ms);
        assert_eq!(starts.len() as u64, n, "{frame_ns}");
        assert_eq!(stats.frames.load(Relaxed), n);
        for (k, s) in starts.iter().enumerate() {
            assert_eq!(*s, starts[0] + k as u64 * frame_ns, "on the grid");
        }
        assert_eq!(channels_of(&edges), vec![values; n as usize]);
    }
    // Frames from about 5 ms on, decided before 511 ms: a's last at
    // 500 ms, b's at 505 ms.
    assert_eq!(stats_a.frames.load(Relaxed), 23);
    assert_eq!(stats_b.frames.load(Relaxed), 26);
}

#[test]
fn a_bank_writes_simultaneous_edges_in_one_call() {
    let sim = Sim::new();
    let model = grid_model();
    // Same values on lines 0 and 1: every edge coincides. Other values
    // on line 2: only its frame starts coincide (its grid joins line
    // 0's).
    let mut s0 = Fresh::new(&sim, &model, CMD);
    let mut s1 = Fresh::new(&sim, &model, CMD);
    let mut s2 = Fresh::new(&sim, &model, "[2000, 1000, 2000, 1000]");
    let mut bank = BankRecorder::default();
    let mut kits: [Kit; 3] = Default::default();
    {
        let silence = cfg(100, FailsafeAction::Silence);
        let sources: [&mut dyn CommandSource; 3] = [&mut s0, &mut s1, &mut s2];
        let mut outputs: Vec<Output> = sources
            .into_iter()
            .zip(kits.iter_mut())
            .enumerate()
            .map(|(i, (source, kit))| {
                let line = LineRef::Banked {
                    bank: 0,
                    bit: i as u32,
                };
                output(&model, silence, source, line, kit)
            })
            .collect();
        let mut banks: [&mut dyn Bank; 1] = [&mut bank];
        run_until(&sim, silence.margin, &mut outputs, &mut banks, 401);
    }
    let stats = kits.map(|k| k.stats);
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
    assert_eq!(l0.len(), 18, "{l0:?}");
    assert_eq!(l0, vec![CMD_US.to_vec(); 18]);
    assert_eq!(l1, l0);
    assert_eq!(
        l2,
        vec![vec![2000, 1000, 2000, 1000, 1500, 1500, 1500, 1500]; 18]
    );
    for (i, s) in stats.iter().enumerate() {
        assert_edges_add_up(line(i as u32).len(), s, 18);
    }
    // Never two writes for one time; lines 0 and 1 always together
    // (their lead-in pulses too); the frame starts of line 2 are those
    // of line 0.
    for w in writes.windows(2) {
        assert!(w[0].0 < w[1].0, "two writes for one time: {w:?}");
    }
    assert!(
        writes
            .iter()
            .all(|(_, m, _)| m & 0b11 != 0b01 && m & 0b11 != 0b10),
        "{writes:?}"
    );
    assert_eq!(starts_of(&line(2)), starts_of(&line(0)));
    let shared = starts_of(&line(0))
        .iter()
        .filter(|t| writes.iter().any(|(w, m, _)| w == *t && m & 0b111 == 0b111))
        .count();
    assert_eq!(shared, 18, "one write for the three frame starts");
}

/// A write held up 5 us before its edge reached the line (the check
/// before it found the edge on time): on a real line the frame is
/// glitched, and the log has the values the line carried (channel 2 5 us
/// longer, channel 3 5 us shorter); on a stamped line (the simulated
/// one) the edge is where the reading before the write put it, and the
/// frame is whole.
#[test]
fn a_write_held_up_glitches_its_frame_and_the_log_has_what_the_line_carried() {
    let model = grid_model();
    for stamped in [false, true] {
        let dir =
            std::env::temp_dir().join(format!("ppmd-glitch-{}-{stamped}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("frames.jsonl");
        let (mut log, mut writer) = framelog::open(&path, 1 << 20).unwrap();
        let sim = Sim::new();
        let mut src = Fresh::new(&sim, &model, CMD);
        // The lead-in pulse, frame 1, then frame 2's third pulse start.
        let mut wire = Wire {
            sim: sim.clone(),
            edges: Vec::new(),
            held: vec![(2 + 18 + 4, 5_000)],
            stamped,
        };
        let silence = cfg(100, FailsafeAction::Silence);
        let line = LineRef::Edges(&mut wire);
        let stats = run_logged(&sim, &model, silence, &mut src, line, &mut log, 100);
        drop(log);
        writer.finish();
        let rows: Vec<serde_json::Value> = log_rows(&path)
            .into_iter()
            .filter(|r| r["type"] == "frame")
            .collect();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(stats.aborted_frames.load(Relaxed), 0);
        assert!(rows.len() >= 3, "{} frames", rows.len());
        let us = |v: &[u64]| serde_json::json!(v.iter().map(|&u| u as f64).collect::<Vec<_>>());
        let late_us = [1100, 1205, 1295, 1400, 1500, 1500, 1500, 1500];
        for (k, row) in rows.iter().enumerate() {
            let (status, values) = if k == 1 && !stamped {
                ("glitched", us(&late_us))
            } else {
                ("whole", us(&CMD_US))
            };
            assert_eq!(row["status"], status, "frame {k}, stamped {stamped}");
            assert_eq!(row["glitched"], status == "glitched");
            assert_eq!(row["ch_us"], values, "frame {k}, stamped {stamped}");
        }
        assert_eq!(stats.glitched_frames.load(Relaxed), !stamped as u64);
        // What EdgeTX reads from the times the edges reached the line.
        let line = wire.edges.iter().map(|(e, real)| (*real, e.level));
        let (read, _) = decode_as(Receiver::EdgeTx, line, Level::High);
        let want: &[u64] = if stamped { &CMD_US } else { &late_us };
        assert_eq!(read[1].channels_us(), want, "stamped {stamped}");
    }
}
