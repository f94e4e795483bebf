//! The loop on follow timing: frames that start as soon as a fresh command
//! comes, repeats at the longest sync, wake-ups, and the lead-in pulse
//! after silence.

use super::*;

#[test]
fn follow_frames_carry_each_command_as_it_comes() {
    let model = follow_model("");
    for with_fd in [true, false] {
        // 25 ms apart: each command finds the line free (a frame of these
        // values and its shortest sync take 15.5 ms; a repeat would come
        // only 28.5 ms after a frame's start).
        let sim = Sim::new();
        let mut src = Feed::paced(&sim, &model, 16, 25);
        src.with_fd = with_fd;
        let made = src.made();
        let (edges, stats) = run_follow(&sim, &model, &mut src, FailsafeAction::Silence, 160);
        let frames = check_follow(&edges, &model, &made, &stats, LEAD_1);
        assert_eq!(stats.commands.load(Relaxed), 16, "with_fd {with_fd}");
        // Each command is on the line in its own frame: at once with a
        // wake fd, within FOLLOW_POLL_NS without.
        let firsts: Vec<u32> = frames.iter().map(|f| f.first_us).collect();
        let want: Vec<u32> = made.iter().map(|m| m.1).collect();
        assert_eq!(firsts[..16], want[..], "with_fd {with_fd}");
        for (f, m) in frames.iter().zip(&made) {
            let after = f.start - m.0;
            let within = if with_fd { 0 } else { FOLLOW_POLL_NS };
            let first = if m.0 == made[0].0 { LEAD_IN_NS } else { 0 };
            assert!(
                after >= READY_NS + first && after <= READY_NS + first + within + 10_000,
                "with_fd {with_fd}: {after} ns after its command"
            );
        }
        // Then repeats of the last at the longest sync until 100 ms
        // after it, then silence.
        assert!(
            frames[16..].iter().all(|f| f.first_us == want[15]),
            "{frames:?}"
        );
        assert_eq!(stats.repeats.load(Relaxed), frames.len() as u64 - 16);
        assert_eq!(stats.failsafe_entries.load(Relaxed), 1);
        assert_eq!(stats.wake_errors.load(Relaxed), 0);
        assert_eq!(stats.late_frames.load(Relaxed), 0);
        assert_eq!(stats.overruns.load(Relaxed), 0);
        // With the fd, each command but the first (the line was silent:
        // it waits in its idle look) woke the waiting output.
        let wakes = stats.wakes.load(Relaxed);
        if with_fd {
            assert_eq!(wakes, 16, "{stats:?}");
        } else {
            assert_eq!(wakes, 0);
        }
    }
}

#[test]
fn follow_repeats_at_the_longest_sync_then_acts_as_failsafe() {
    let model = follow_model("");
    let (min, max) = model.follow_sync_ns();
    for action in [FailsafeAction::Hold, FailsafeAction::Silence] {
        // 60 ms apart: a frame and its longest sync (28.5 ms) come and go
        // before the next command, and the next one, and so on.
        let sim = Sim::new();
        let mut src = Feed::paced(&sim, &model, 5, 60);
        let made = src.made();
        let (edges, stats) = run_follow(&sim, &model, &mut src, action, 250);
        let frames = check_follow(&edges, &model, &made, &stats, LEAD_1);
        let repeats = frames
            .windows(2)
            .filter(|w| w[0].first_us == w[1].first_us)
            .count() as u64;
        assert_eq!(stats.repeats.load(Relaxed), repeats, "{action:?}");
        assert_eq!(stats.failsafe_entries.load(Relaxed), 1, "{action:?}");
        assert_eq!(stats.late_frames.load(Relaxed), 0);
        let last = frames.last().unwrap();
        assert_eq!(last.first_us, made[4].1, "{action:?}");
        // A command's frame starts READY_NS after it (the first one's
        // after a lead-in); then repeats, a frame and the longest sync
        // apart, for as long as they are decided (DECIDE_NS before
        // their start) before the next command, or the stop (Hold), or
        // until the command is 100 ms old (Silence).
        let ends: Vec<u64> = made[1..]
            .iter()
            .map(|m| m.0)
            .chain([match action {
                FailsafeAction::Hold => src.last_at() + 250 * MS,
                _ => src.last_at() + 100 * MS,
            }])
            .collect();
        for (k, m) in made.iter().enumerate() {
            let first = frames.iter().find(|f| f.start > m.0).unwrap();
            let lead_in = if k == 0 { LEAD_IN_NS } else { 0 };
            // Or at the shortest sync after a frame still running.
            let free = frames
                .iter()
                .rfind(|f| f.start < m.0)
                .map_or(0, |p| p.last_pulse + min);
            let at = (m.0 + READY_NS + lead_in).max(free);
            assert!(first.start.abs_diff(at) < 1_000, "{action:?} command {k}");
            let period = first.last_pulse - first.start + max;
            let want = (0..)
                .take_while(|j| first.start + j * period - LEAD_1 < ends[k])
                .count();
            let got = frames.iter().filter(|f| f.first_us == m.1).count();
            assert_eq!(got, want, "{action:?} after command {k}");
            assert!(want >= 2, "a repeat at least");
        }
    }
}

#[test]
fn a_broken_wake_fd_is_counted_and_the_output_polls() {
    let model = follow_model("");
    for clear_fails in [false, true] {
        let sim = Sim::new();
        let mut src = Feed::paced(&sim, &model, 8, 25);
        if clear_fails {
            // The wake-ups cannot be cleared: the fd stays readable.
            src.broken_clear = true;
        } else {
            // No such file descriptor: every wait would end at once.
            src.fake_fd = Some(999_999);
        }
        let made = src.made();
        let (edges, stats) = run_follow(&sim, &model, &mut src, FailsafeAction::Silence, 40);
        let frames = check_follow(&edges, &model, &made, &stats, LEAD_1);
        assert_eq!(stats.wake_errors.load(Relaxed), 1, "{clear_fails}");
        assert_eq!(stats.commands.load(Relaxed), 8);
        // Every command still on the line, found by polling.
        let firsts: Vec<u32> = frames.iter().map(|f| f.first_us).collect();
        for m in &made {
            assert!(firsts.contains(&m.1), "{clear_fails}: {firsts:?}");
        }
    }
}

#[test]
fn a_follow_output_and_a_grid_output_share_the_loop() {
    let sim = Sim::new();
    let grid = grid_model();
    let follow = follow_model("channels = 6\norder = 'TAER'");
    let mut src_f = Feed::paced(&sim, &follow, 20, 23);
    let made = src_f.made();
    let until_ms = (src_f.last_at() - START_NS) / MS + 60;
    let mut src_g = Fresh::new(&sim, &grid, CMD);
    let (mut out_g, mut out_f) = (Recorder::default(), Recorder::default());
    let silence = cfg(100, FailsafeAction::Silence);
    let (stats_g, stats_f) = run_two(
        &sim,
        (&grid, silence, &mut src_g, LineRef::Edges(&mut out_g)),
        (&follow, silence, &mut src_f, LineRef::Edges(&mut out_f)),
        until_ms,
    );
    let lead = DECIDE_NS + DECIDE_SLOT_NS;
    let frames = check_follow(&out_f.edges, &follow, &made, &stats_f, lead);
    let firsts: Vec<u32> = frames.iter().map(|f| f.first_us).collect();
    for m in &made {
        assert!(firsts.contains(&m.1), "{firsts:?}");
    }
    // The grid output keeps its grid.
    let edges = scheduled(&out_g.edges);
    assert_edges_add_up(edges.len(), &stats_g, 18);
    let starts = starts_of(&edges);
    let n = frames_before_stop(starts[0], FRAME_NS, lead, until_ms);
    assert_eq!(starts.len() as u64, n);
    for (k, s) in starts.iter().enumerate() {
        assert_eq!(*s, starts[0] + k as u64 * FRAME_NS, "on the grid");
    }
    assert_eq!(channels_of(&edges), vec![CMD_US.to_vec(); n as usize]);
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
    let sim = Sim::new();
    let mut src = Feed::paced(&sim, &model, 60, 7);
    let made = src.made();
    let (edges, stats) = run_follow(&sim, &model, &mut src, FailsafeAction::Silence, 40);
    let frames = check_follow(&edges, &model, &made, &stats, LEAD_1);
    let (min, _) = model.follow_sync_ns();
    // While commands come, every frame follows the one before at the
    // shortest sync.
    let while_commands: Vec<&Sent> = frames
        .iter()
        .filter(|f| f.start <= made[59].0 + READY_NS)
        .collect();
    assert!(
        while_commands.len() >= 25,
        "{} frames",
        while_commands.len()
    );
    for w in while_commands.windows(2) {
        assert_eq!(w[1].start - w[0].last_pulse, min, "{w:?}");
    }
    assert_eq!(stats.late_frames.load(Relaxed), 0);
    assert_eq!(stats.overruns.load(Relaxed), 0);
}

/// A command after silence whose lead-in pulse would fall 1.5 ms past
/// four wraps of a trainer input's 16-bit counter after the line's last
/// pulse (EdgeTX and OpenTX would read that gap as a 9th channel of
/// 1500 us): the pulse moves later, out of the gaps read as a channel,
/// and they read exactly the 8 channels of every frame.
#[test]
fn a_lead_in_pulse_keeps_out_of_gaps_a_trainer_reads_as_a_channel() {
    let model = follow_model("");
    let run = |second: Option<u64>| {
        let sim = Sim::new();
        let mut cmds = vec![(START_NS + 20 * MS, "[1100, 1900]")];
        if let Some(at) = second {
            cmds.push((at, "[1200, 1900]"));
        }
        let mut src = Feed::new(&sim, &model, &cmds);
        let mut out = Recorder::default();
        let stats = run_one(
            &sim,
            &model,
            cfg(100, FailsafeAction::Silence),
            &mut src,
            LineRef::Edges(&mut out),
            400,
        );
        (out.edges, stats)
    };
    let rising = |edges: &[TraceEdge]| -> Vec<u64> {
        edges
            .iter()
            .filter(|e| e.level == Level::High)
            .map(|e| e.scheduled_ns)
            .collect()
    };
    let (alone, _) = run(None);
    let last = *rising(&alone).last().unwrap();
    let at = last + 4 * TRAINER_WRAP_NS + 1_500_000 - READY_NS;
    let (edges, stats) = run(Some(at));
    let pulses = rising(&edges);
    let lone = *pulses.iter().find(|&&t| t > last).unwrap();
    let gap = lone - last;
    let m = gap % TRAINER_WRAP_NS;
    assert!(m > 2_400_000 && m < 2_500_000, "the gap reads as {m} ns");
    assert!(lone - (at + READY_NS) <= ALIAS_SHIFT_MAX_NS);
    assert_eq!(stats.commands.load(Relaxed), 2);
    let frames = sent_frames(&edges, model.channels());
    assert!(frames.iter().all(|f| !f.aborted));
    assert_eq!(frames.last().unwrap().first_us, 1_200);
    for r in [Receiver::EdgeTx, Receiver::OpenTx] {
        let (read, _) = decode_as(r, scheduled(&edges), Level::High);
        assert_eq!(read.len(), frames.len(), "{r:?}");
        for f in &read {
            assert_eq!(f.channels_us().len(), 8, "{r:?}: {:?}", f.channels_us());
        }
    }
}
