//! Follow timing with the real binaries: frames start when commands come,
//! every frame on the simulated line (follow, and grid beside it) is read by
//! EdgeTX, OpenTX, Betaflight and ArduPilot as their firmware decodes PPM,
//! and the frame log, the exit summary and the status reply say the timing. How soon a command reaches
//! the line is measured by `ppm-bench --only e2e`, not here.

use ppm_shared::framelog::{self, FrameRow, Status};
use ppm_shared::receiver::{decode_as, Receiver};
use ppm_shared::signal::Timing;
use ppm_shared::trace::Trace;
use ppm_shared::Level;
use ppm_tests::{
    at_50hz, carries, channel_of_frames, free_udp_port, read_trace, start_outputs, status,
    stop_all, two_outputs, Sandbox, Sender, StatusReply,
};
use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

const MS: u64 = 1_000_000;

/// The frames of a frame log.
fn logged_frames(path: &Path) -> Vec<FrameRow> {
    framelog::read_frames(path).unwrap_or_else(|e| panic!("{e}"))
}

/// Aborted at a late edge: `ch_us` holds what it carried.
fn aborted(l: &FrameRow) -> bool {
    l.status == Status::Aborted
}

/// The number before `what` in ppmd's summary line for the output (`12
/// overruns`); with several outputs, `NAME: ` first.
fn summary_count(log: &str, what: &str) -> u64 {
    output_count(log, "", what)
}

fn output_count(log: &str, output: &str, what: &str) -> u64 {
    let line = log
        .lines()
        .find(|l| l.contains(&format!("{output}stopped")))
        .unwrap_or_else(|| panic!("no summary:\n{log}"));
    let words: Vec<&str> = line.split([' ', ',', '(', ')', ';']).collect();
    let at = words
        .iter()
        .position(|w| *w == what)
        .unwrap_or_else(|| panic!("no `{what}` in {line}"));
    words[at - 1].parse().unwrap()
}

/// The fewest logged frames that let every receiver hand one on: the
/// slowest to lock (Betaflight) reads its warm-up frames, then one more,
/// which the sync after it closes. Fewer, and its check reads nothing.
fn frames_to_lock() -> usize {
    let warmup = Receiver::ALL.iter().map(|r| r.warmup_frames()).max();
    warmup.unwrap_or(0) + 2
}

/// Checks that every receiver hands on every logged frame as the line
/// carried it (decoding the times the edges were written), with the values
/// the log has (to the receiver's 1 us truncation), but the frames it reads
/// while it locks on, and, for those that hand a frame on at the sync after
/// it, the last one; and that nothing else is read. A frame aborted at a
/// late edge (ppmd runs here without real-time priority) is logged with the
/// channels it carried: the trainer inputs read it short, Betaflight drops
/// it, ArduPilot takes it from 5 channels.
fn assert_every_receiver_reads(trace: &Trace, logged: &[FrameRow], overruns: u64) {
    let leading = trace.idle_level.unwrap_or(Level::Low).opposite();
    let channels = logged.iter().map(|l| l.ch_us.len()).max().unwrap_or(0);
    let aborted = logged.iter().filter(|l| aborted(l)).count();
    for r in Receiver::ALL {
        let (read, stats) = decode_as(
            r,
            trace.edges.iter().map(|e| (e.actual_ns, e.level)),
            leading,
        );
        let trainer = matches!(r, Receiver::EdgeTx | Receiver::OpenTx);
        let read: Vec<_> = read.iter().filter(|f| f.complete || trainer).collect();
        for f in &read {
            // The logged frame whose first edge was due last before.
            let l = logged
                .iter()
                .rev()
                .find(|l| l.mono_ns <= f.start_ns)
                .unwrap_or_else(|| panic!("{r:?} read a frame at {} not logged", f.start_ns));
            let got = f.channels_us();
            assert_eq!(
                got.len(),
                l.ch_us.len(),
                "{r:?} at {}: {got:?} {l:?}",
                f.start_ns
            );
            for (g, w) in got.iter().zip(&l.ch_us) {
                assert!(
                    (*g as f64 - w).abs() <= 1.0,
                    "{r:?} at {}: {got:?} {l:?}",
                    f.start_ns
                );
            }
        }
        let takes = |l: &&FrameRow| match r {
            Receiver::EdgeTx | Receiver::OpenTx => !l.ch_us.is_empty(),
            Receiver::Betaflight => l.ch_us.len() == channels,
            Receiver::ArduPilot => l.ch_us.len() >= 5,
        };
        let taken = logged.iter().filter(takes).count();
        // The last frame taken is closed by a sync unless it is the last.
        let open = !trainer && logged.last().is_some_and(|l| takes(&l));
        let closed = taken - open as usize;
        let want = closed.saturating_sub(r.warmup_frames());
        // A lead-in pulse after an overrun (a stall of this shared machine)
        // or an aborted frame makes Betaflight count its frames again
        // before it locks.
        let slack = (overruns as usize + aborted) * (r.warmup_frames() + 1);
        assert!(
            read.len() <= want && read.len() + slack >= want,
            "{r:?} read {} of {} frames ({overruns} overruns, {aborted} aborted, {stats:?})",
            read.len(),
            logged.len()
        );
        if trainer {
            // The gap before a lead-in pulse may be longer than a sync.
            assert!(
                stats.invalid_periods <= overruns + aborted as u64,
                "{r:?}: {stats:?}"
            );
        }
    }
}

#[test]
fn follow_frames_start_with_the_commands_and_every_receiver_reads_them() {
    let sb = Sandbox::new("follow");
    let log_path = sb.dir.join("frames.jsonl");
    let cfg = sb.config(&format!(
        "[ppm]\ntiming = \"follow\"\n[ppmd]\nframe_log = \"{}\"\n",
        log_path.display()
    ));
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    assert!(ppmd
        .log_text()
        .contains("follow timing, sync 5000..18000 us"));
    let sender = Sender::new(sb.addr());
    let mut reply = None;
    at_50hz(100, |i| {
        let ail = 1_000 + 3 * i;
        sender.send(format!(r#"{{"ch": [{ail}, 1900], "seq": {i}}}"#).as_bytes());
        if i == 80 {
            reply = Some(status(sb.addr()));
        }
    });
    // Past the failsafe (200 ms): the repeats, then silence.
    std::thread::sleep(Duration::from_millis(400));
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let log = ppmd.log_text();
    let (late, overruns, repeats) = (
        summary_count(&log, "late"),
        summary_count(&log, "overruns"),
        summary_count(&log, "repeats"),
    );

    let reply = reply.expect("a status reply at the 80th command");
    let p = reply.ppmd.as_ref();
    assert_eq!(p.map(|p| p.timing.as_str()), Some("follow"), "{reply}");
    assert_eq!(p.map(|p| p.state.as_str()), Some("active"), "{reply}");

    let logged = logged_frames(&log_path);
    // Enough for every receiver to lock (about 100 on an idle machine,
    // those aborted at a late edge logged too).
    assert!(logged.len() >= frames_to_lock(), "{} frames", logged.len());
    assert!(logged.iter().all(|l| l.timing == Timing::Follow));
    let trace = read_trace(&sb.dir.join("line.trace"));
    assert_every_receiver_reads(&trace, &logged, overruns);

    // Frame to frame (scheduled times, exact): a frame starts after its
    // command was received, never carries an older one than the frame
    // before, leaves the follow syncs between frames, and repeats the
    // previous command only at the longest sync (or late, counted).
    let leading: std::collections::BTreeSet<u64> = trace
        .edges
        .iter()
        .filter(|e| e.level == Level::High)
        .map(|e| e.scheduled_ns)
        .collect();
    let mut late_repeats = 0;
    let mut counted_repeats = 0;
    for w in logged.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        assert!(b.recv_mono_ns.unwrap() <= b.mono_ns, "{b:?}");
        assert!(b.ingress_seq >= a.ingress_seq, "{a:?} then {b:?}");
        if aborted(a) {
            // Its command goes out again a shortest sync after the last
            // pulse it carried (an earlier frame's, when none).
            continue;
        }
        // Its last pulse as scheduled: the logged values are the line's,
        // each moved by its edges' lateness (up to the guard), so their sum
        // is not the schedule's to the ns.
        let a_last = *leading
            .range(a.mono_ns..)
            .nth(a.ch_us.len())
            .unwrap_or_else(|| panic!("{a:?} has no last pulse in the trace"));
        let sync = b.mono_ns - a_last;
        if sync >= 18_500_000 {
            assert!(
                leading.contains(&(b.mono_ns - 5 * MS)),
                "a long gap before {} without a lead-in pulse",
                b.mono_ns
            );
            continue;
        }
        assert!(sync >= 5 * MS, "{sync} ns before {b:?}");
        if a.ingress_seq == b.ingress_seq {
            counted_repeats += 1;
            late_repeats += (sync != 18 * MS) as u64;
        }
    }
    assert!(
        late_repeats <= late,
        "{late_repeats} late repeats, {late} late frames"
    );
    // After the last command the frame repeats at the longest sync until the
    // failsafe (200 ms) silences it: the newest command goes out in two
    // frames at the least, and one repeat counted above (its sync checked)
    // shows the sync. About six on an idle machine; one after a frame
    // aborted at a late edge is not counted.
    let newest = logged.iter().filter_map(|l| l.ingress_seq).max();
    let with_newest = logged.iter().filter(|l| l.ingress_seq == newest).count();
    assert!(
        with_newest >= 2,
        "the newest command in {with_newest} frames"
    );
    assert!(counted_repeats >= 1, "{counted_repeats} repeats");
    assert!(repeats >= counted_repeats, "{repeats} counted by ppmd");
    // Commands reach the line as sent: every frame that carried the
    // aileron carries one sent (1000 + 3 i), never an older one than the
    // frame before, with 1900 beside it. Two commands on the line show it
    // follows them (how many, and how soon, is ppm-bench's part).
    let ail = channel_of_frames(&trace, 0);
    assert!(
        ail.iter()
            .all(|&v| (1_000..1_300).contains(&v) && (v - 1_000) % 3 == 0),
        "{ail:?}"
    );
    assert!(ail.windows(2).all(|w| w[1] >= w[0]), "{ail:?}");
    let second = channel_of_frames(&trace, 1);
    assert!(second.iter().all(|&v| v == 1_900), "{second:?}");
    let carried: std::collections::BTreeSet<u64> =
        logged.iter().filter_map(|l| l.ingress_seq).collect();
    assert!(carried.len() >= 2, "{} of 100 commands", carried.len());
}

#[test]
fn a_follow_output_runs_beside_a_grid_output() {
    let sb = Sandbox::new("follow-outputs");
    let port_b = free_udp_port();
    let b = "frame_log = \"b.jsonl\"\n[outputs.ppm]\nchannels = 6\norder = \"TAER\"\ntiming = \"follow\"";
    let (cfg_path, [name_a, name_b]) = two_outputs(&sb, port_b, b);
    let (mut ppmd, mut ings) = start_outputs(&sb, &cfg_path, &[&name_a, &name_b]);
    let to_b = SocketAddr::from(([127, 0, 0, 1], port_b));
    let (send_a, send_b) = (Sender::new(sb.addr()), Sender::new(to_b));
    let mut replies = Vec::new();
    at_50hz(75, |i| {
        send_a.send(b"[1100, 1200, 1300, 1400]");
        send_b.send(format!("[{}, 1200, 1300]", 1_000 + 4 * i).as_bytes());
        if i == 60 {
            replies = vec![status(sb.addr()), status(to_b)];
        }
    });
    let [a, b] = &mut ings[..] else {
        unreachable!()
    };
    stop_all(&mut ppmd, &mut [a, b]);
    let timing = |r: &StatusReply| r.ppmd.as_ref().map(|p| p.timing.clone());
    assert_eq!(timing(&replies[0]).as_deref(), Some("grid"));
    assert_eq!(timing(&replies[1]).as_deref(), Some("follow"));
    let log = ppmd.log_text();
    assert!(log.contains(&format!("{name_b}: stopped")) && log.contains("repeats)"));
    for (file, timing, trace, name) in [
        ("a.jsonl", Timing::Grid, "a.trace", &name_a),
        ("b.jsonl", Timing::Follow, "b.trace", &name_b),
    ] {
        let logged = logged_frames(&sb.dir.join(file));
        // Every receiver reads either line, grid or follow.
        let overruns = output_count(&log, &format!("{name}: "), "overruns");
        let whole = read_trace(&sb.dir.join(trace));
        assert_every_receiver_reads(&whole, &logged, overruns);
        // Enough for every receiver to lock (about 70 on an idle machine,
        // those aborted at a late edge logged too).
        assert!(
            logged.len() >= frames_to_lock(),
            "{file}: {} frames",
            logged.len()
        );
        assert!(logged.iter().all(|l| l.timing == timing), "{file}");
        // Every whole frame on the line (scheduled times, exact) is a
        // logged one, at its start.
        let trace = read_trace(&sb.dir.join(trace));
        let whole: Vec<_> = logged.iter().filter(|l| !aborted(l)).collect();
        let frames = trace.decode(false);
        let frames: Vec<_> = frames
            .iter()
            .filter(|f| f.channels_us().len() == whole[0].ch_us.len())
            .collect();
        assert_eq!(frames.len(), whole.len(), "{file}");
        for (f, l) in frames.iter().zip(&whole) {
            assert_eq!(f.start_ns, l.mono_ns);
        }
    }
    // What the lines carry, every frame that carried it (whole, or cut
    // short after it: exact): a's command; b's first channel (throttle,
    // TAER) one sent (1000 + 4 i), never an older one than the frame
    // before, with b's other two beside it.
    let a_line = read_trace(&sb.dir.join("a.trace"));
    assert!(a_line
        .decode(false)
        .iter()
        .all(|f| carries(f, &[1100, 1200, 1300, 1400])));
    let b_line = read_trace(&sb.dir.join("b.trace"));
    let thr = channel_of_frames(&b_line, 0);
    assert!(
        thr.iter()
            .all(|&v| (1_000..1_300).contains(&v) && (v - 1_000) % 4 == 0),
        "{thr:?}"
    );
    assert!(thr.windows(2).all(|w| w[1] >= w[0]), "{thr:?}");
    for (i, want) in [(1, 1_200), (2, 1_300)] {
        let got = channel_of_frames(&b_line, i);
        assert!(got.iter().all(|&v| v == want), "b's channel {i}: {got:?}");
    }
    // The follow line carries its commands: two on the line show it
    // follows them (how many, and how soon, is ppm-bench's part).
    let b = logged_frames(&sb.dir.join("b.jsonl"));
    let carried: std::collections::BTreeSet<u64> = b.iter().filter_map(|l| l.ingress_seq).collect();
    assert!(carried.len() >= 2, "{} of 75 commands", carried.len());
}
