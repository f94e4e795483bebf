//! The whole pipeline with the real binaries as separate processes:
//! UDP datagrams in, udp-ingress, shared memory, ppmd, the simulated line's
//! trace out, decoded with transmitter semantics.

use nix::sys::signal::Signal;
use ppm_shared::framelog::{self, Row, Status};
use ppm_shared::line::LineState;
use ppm_shared::time::now_ns;
use ppm_tests::{at_50hz, read_trace, stop_all, Sandbox, Sender};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

const FRAME_NS: u64 = 22_500_000;
const SECOND: Duration = Duration::from_secs(1);

fn start_pipeline(
    sb: &Sandbox,
    extra_config: &str,
    trace: &str,
) -> (ppm_tests::Proc, ppm_tests::Proc) {
    let cfg = sb.config(extra_config);
    (sb.start_ppmd(&cfg, trace), sb.start_ingress(&cfg, &[]))
}

#[test]
fn commands_reach_the_line_and_malformed_datagrams_change_nothing() {
    let sb = Sandbox::new("e2e");
    let (mut ppmd, mut ingress) = start_pipeline(&sb, "", "line.trace");
    let malformed: [(&[u8], &str); 8] = [
        (b"\xff\xfe[1500]", "invalid_utf8"),
        (b"[1000, 1200", "invalid_json"),
        (br#"[1000, "1200"]"#, "not_a_number"),
        (b"[1000, 1200, 2600]", "out_of_range"),
        (
            b"[1500,1500,1500,1500,1500,1500,1500,1500,1500]",
            "too_many_values",
        ),
        (br#"{"yaw": 1500}"#, "unknown_channel"),
        (b"{}", "bad_shape"),
        (b"1500", "bad_shape"),
    ];
    let sender = Sender::new(sb.addr());
    let first = now_ns();
    let mut bad_sent = 0;
    at_50hz(75, |i| {
        sender.send(b"[1000,1200,1700,2000]");
        if i % 3 == 1 {
            sender.send(malformed[bad_sent % malformed.len()].0);
            bad_sent += 1;
        }
    });
    let last = now_ns();
    std::thread::sleep(Duration::from_millis(100));
    stop_all(&mut ppmd, &mut [&mut ingress]);

    let trace = read_trace(&sb.dir.join("line.trace"));
    let all = trace.decode(false);
    let want_ns: Vec<u64> = [1000, 1200, 1700, 2000, 1500, 1500, 1500, 1500]
        .iter()
        .map(|us| us * 1_000)
        .collect();
    // ppmd runs here without real-time priority: on a loaded machine a few
    // frames are aborted at a late edge (cut short, never a wrong value).
    // A frame cut short carries the channels before the late edge, exact.
    for f in all.iter().filter(|f| f.channels_ns.len() < 8) {
        assert_eq!(
            f.channels_ns,
            want_ns[..f.channels_ns.len()],
            "a short frame"
        );
    }
    // Frames cut short before the first whole one (each on its grid point).
    let cut_first = all.iter().take_while(|f| f.channels_ns.len() < 8).count() as u64;
    let frames: Vec<_> = all.iter().filter(|f| f.channels_ns.len() == 8).collect();
    // 1.5 s of commands: about 66 frames, whole or cut short. One whole
    // frame is what the checks of the first readable frame below need (and
    // shows the command flew, exact); how many a loaded machine cuts short
    // is its business.
    assert!(!frames.is_empty(), "no whole frame");
    // The first is readable: a lone pulse a sync period before it stands in
    // for the previous frame's last pulse (unless that first frame was
    // aborted: then a later one on its grid).
    let after_lead_in =
        frames[0].start_ns - (trace.edges[0].scheduled_ns + ppmd::emitter::LEAD_IN_NS);
    assert_eq!(
        after_lead_in % FRAME_NS,
        0,
        "the first frame follows the lead-in pulse, on the grid"
    );
    // Within two frames of the first datagram, or one more for each frame
    // cut short before it.
    assert!(
        frames[0].start_ns <= first + (2 + cut_first) * FRAME_NS,
        "first readable frame starts {} ms after the first datagram ({cut_first} cut short before it)",
        (frames[0].start_ns as i64 - first as i64) / 1_000_000
    );
    for (k, f) in frames.iter().enumerate() {
        // Scheduled times are exact: compare to the nanosecond (well within 1 us).
        assert_eq!(f.channels_ns, want_ns, "frame {k} at {}", f.start_ns);
    }
    // The line carries the command to the end: within two frames of the
    // last datagram, a frame that carried it (whole, or cut short at a late
    // edge: exact; a loaded machine can cut every frame there short).
    let last_carried = all
        .iter()
        .rev()
        .find(|f| !f.channels_ns.is_empty())
        .expect("a frame with a channel");
    assert!(
        last_carried.start_ns >= last - 2 * FRAME_NS,
        "the last frame with a channel starts {} ms before the last datagram",
        (last as i64 - last_carried.start_ns as i64) / 1_000_000
    );
    // The line ends at its idle level (low).
    assert_eq!(trace.edges.last().unwrap().level.as_u8(), 0);

    // Every malformed datagram was counted under its reason.
    let log = ingress.log_text();
    let summary = log
        .lines()
        .find(|l| l.contains("stopped:"))
        .expect("ingress summary");
    assert!(
        summary.contains(&format!("rejected {bad_sent} ")),
        "{summary}"
    );
    for (_, reason) in &malformed[..bad_sent.min(malformed.len())] {
        assert!(
            summary.contains(&format!("{reason}=")),
            "{reason} missing: {summary}"
        );
    }
    assert!(summary.contains("received 100 "), "{summary}");
}

#[test]
fn stale_seq_never_reaches_the_line() {
    let sb = Sandbox::new("stale");
    let (mut ppmd, _ingress) = start_pipeline(&sb, "", "line.trace");
    let sender = Sender::new(sb.addr());
    at_50hz(50, |i| {
        sender.send(format!(r#"{{"ch": [1100], "seq": {}}}"#, 100 + i).as_bytes());
        sender.send(br#"{"ch": [1900], "seq": 50}"#);
    });
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    // Only the numbered commands fly, never the stale one: every frame that
    // carried channel 1 carries 1100, and one such frame shows it flew at
    // all (how many a loaded machine cuts short is its business).
    let ch1 = ppm_tests::channel_of_frames(&read_trace(&sb.dir.join("line.trace")), 0);
    assert!(!ch1.is_empty(), "the command never flew");
    assert!(ch1.iter().all(|&v| v == 1100), "{ch1:?}");
}

/// Without a key, one datagram with the largest `seq` locks numbered
/// commands out for `failsafe.after_ms` (200 ms) at most; it used to be
/// until udp-ingress restarted.
#[test]
fn one_huge_seq_locks_numbered_commands_out_for_the_failsafe_interval_only() {
    let sb = Sandbox::new("hugeseq");
    let (mut ppmd, ingress) = start_pipeline(&sb, "", "line.trace");
    let sender = Sender::new(sb.addr());
    at_50hz(20, |i| {
        sender.send(format!(r#"{{"ch": [1100], "seq": {}}}"#, 100 + i).as_bytes());
    });
    sender.send(br#"{"ch": [1900], "seq": 18446744073709551615}"#);
    at_50hz(60, |i| {
        sender.send(format!(r#"{{"ch": [1300], "seq": {}}}"#, 200 + i).as_bytes());
    });
    let status = ppm_tests::status(sb.addr());
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    drop(ingress);
    assert_eq!(status.datagrams.seq_resets, 1, "{status}");
    let stale = status.datagrams.stale;
    assert!(
        (5..=12).contains(&stale),
        "200 ms of 20 ms commands: {status}"
    );
    let ch1 = ppm_tests::channel_of_frames(&read_trace(&sb.dir.join("line.trace")), 0);
    let first_1300 = ch1.iter().position(|&v| v == 1300).expect("1300 applied");
    assert!(ch1[..first_1300].contains(&1900), "{ch1:?}");
    assert!(ch1[first_1300..].iter().all(|&v| v == 1300), "{ch1:?}");
    assert_eq!(ch1.last(), Some(&1300), "{ch1:?}");
}

#[test]
fn either_start_order_and_restarts_of_either_process() {
    let sb = Sandbox::new("restart");
    let cfg = sb.config("");
    let cfg = cfg.to_str().unwrap();
    // Ingress first, with commands already flowing before ppmd exists.
    let mut ingress = sb.spawn("udp-ingress", &["--config", cfg], "ingress1");
    ingress.wait_for_log("listening on", 30 * SECOND);
    let value = Arc::new(AtomicU64::new(1100));
    let stop = Arc::new(AtomicBool::new(false));
    let feeder = {
        let (value, stop, addr) = (value.clone(), stop.clone(), sb.addr());
        std::thread::spawn(move || {
            let s = Sender::new(addr);
            while !stop.load(Ordering::Relaxed) {
                s.send(format!("[{}]", value.load(Ordering::Relaxed)).as_bytes());
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };
    std::thread::sleep(Duration::from_millis(300));
    let sim = |n: u32| format!("sim:{}", sb.dir.join(format!("line{n}.trace")).display());
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg, "--output", &sim(1)], "ppmd1");
    std::thread::sleep(Duration::from_millis(700));

    // Ingress crashes; ppmd goes silent but keeps running; a new ingress resumes it.
    ingress.kill();
    std::thread::sleep(Duration::from_millis(500));
    value.store(1300, Ordering::Relaxed);
    let ingress2 = sb.spawn("udp-ingress", &["--config", cfg], "ingress2");
    ingress2.wait_for_log("listening on", 30 * SECOND);
    std::thread::sleep(Duration::from_millis(700));

    // ppmd crashes (SIGKILL) and restarts; the new one cleans what the dead
    // one left in shared memory and takes the newest command from the
    // running ingress.
    ppmd.kill();
    value.store(1700, Ordering::Relaxed);
    let mut ppmd2 = sb.spawn("ppmd", &["--config", cfg, "--output", &sim(2)], "ppmd2");
    std::thread::sleep(Duration::from_millis(700));
    assert!(ppmd2
        .signal_and_wait(Signal::SIGTERM, 10 * SECOND)
        .success());
    stop.store(true, Ordering::Relaxed);
    feeder.join().unwrap();

    let first = read_trace(&sb.dir.join("line1.trace")).decode(false);
    let ch1 = ppm_tests::channel_of_frames(&read_trace(&sb.dir.join("line1.trace")), 0);
    let gap = first
        .windows(2)
        .position(|w| w[1].start_ns - w[0].start_ns > FRAME_NS);
    // 1100 first, 1300 last, nothing else: one frame at each end is all
    // the order needs (how many a loaded machine cuts short is its
    // business).
    assert_eq!(ch1.first(), Some(&1100), "{ch1:?}");
    assert!(
        gap.is_some(),
        "the line fell silent while no ingress ran: {ch1:?}"
    );
    assert_eq!(ch1.last(), Some(&1300), "{ch1:?}");
    assert!(ch1.iter().all(|&v| v == 1100 || v == 1300), "{ch1:?}");

    // After the ppmd restart only the newest command: one frame carrying it
    // shows it flew.
    let second = ppm_tests::channel_of_frames(&read_trace(&sb.dir.join("line2.trace")), 0);
    assert!(!second.is_empty(), "nothing flew after the ppmd restart");
    assert!(second.iter().all(|&v| v == 1700), "{second:?}");
}

#[test]
fn bad_config_stops_both_at_start_naming_the_key() {
    let sb = Sandbox::new("badcfg");
    for (extra, key) in [
        ("[ppm]\nframe_us = 19000", "ppm.frame_us"),
        ("[ppm]\nchanels = 8", "chanels"),
        ("[ppm.channel.thr]\nmax_us = 2400", "ppm.channel.thr.max_us"),
    ] {
        let cfg = sb.config(extra);
        let cfg = cfg.to_str().unwrap();
        for bin in ["ppmd", "udp-ingress"] {
            let mut p = sb.spawn(bin, &["--config", cfg], bin);
            let status = p.wait(10 * SECOND);
            assert!(!status.success(), "{bin} accepted {extra:?}");
            let log = p.log_text();
            assert!(log.contains(key), "{bin} did not name {key}: {log}");
        }
    }
}

#[test]
fn frame_log_rows_match_the_decoded_line() {
    let sb = Sandbox::new("framelog");
    let cfg = sb.config("");
    let cfg = cfg.to_str().unwrap();
    let log_path = sb.dir.join("frames.jsonl");
    let output = format!("sim:{}", sb.dir.join("line.trace").display());
    let mut ppmd = sb.spawn(
        "ppmd",
        &[
            "--config",
            cfg,
            "--output",
            &output,
            "--frame-log",
            log_path.to_str().unwrap(),
        ],
        "ppmd",
    );
    let _ingress = sb.spawn("udp-ingress", &["--config", cfg], "ingress");
    ppmd.wait_for_log("commands from", 30 * SECOND);
    let sender = Sender::new(sb.addr());
    at_50hz(60, |i| {
        let v = 1000 + 10 * i;
        sender.send(format!(r#"{{"ch": [{v}, 1500.5, 1200], "seq": {}}}"#, i + 1).as_bytes());
    });
    std::thread::sleep(Duration::from_millis(400));
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());

    let rows = framelog::read(&log_path).unwrap_or_else(|e| panic!("{e}"));
    let frames: Vec<_> = rows.iter().filter_map(Row::as_frame).collect();
    let transitions: Vec<_> = rows
        .iter()
        .filter_map(Row::as_transition)
        .map(|t| (t.from, t.to))
        .collect();
    assert_eq!(
        transitions,
        [
            (LineState::Silent, LineState::Active),
            (LineState::Active, LineState::Silent)
        ]
    );
    let trace = read_trace(&sb.dir.join("line.trace"));
    let decoded = trace.decode(false);
    // As the line carried them: the times the edges were written.
    let carried = trace.decode(true);
    assert_eq!(carried.len(), decoded.len());
    // 60 commands at 50 Hz, then the failsafe: about 60 frames logged,
    // whole or cut short; fewer only show a loaded machine (frames
    // skipped). That the log keeps up is checked frame by frame below:
    // every frame on the line has its row. Two rows are what the numbering
    // check needs.
    assert!(frames.len() >= 2, "{} frames logged", frames.len());
    assert!(!decoded.is_empty(), "no frame decoded");
    // The line carries the commands as sent (exact, by scheduled time):
    // channel 1 one of the ramp's values (1000 + 10 i), never an older one
    // than the frame before; channels 2 and 3 as sent.
    let ch1 = ppm_tests::channel_of_frames(&trace, 0);
    assert!(
        ch1.iter()
            .all(|&v| (1_000..1_600).contains(&v) && v % 10 == 0),
        "{ch1:?}"
    );
    assert!(ch1.windows(2).all(|w| w[1] >= w[0]), "{ch1:?}");
    for f in &decoded {
        let ch = &f.channels_ns;
        for (i, want) in [(1, 1_500_500), (2, 1_200_000)] {
            assert!(
                ch.get(i).is_none_or(|&v| v == want),
                "frame at {}: {ch:?}",
                f.start_ns
            );
        }
    }
    // Every frame on the line is in the log, at its start time, with the
    // values the line carried (the log has them to the microsecond); a
    // frame aborted at a late edge (ppmd runs here without real-time
    // priority) with the channels it carried.
    for (f, real) in decoded.iter().zip(&carried) {
        let row = frames
            .iter()
            .find(|r| r.mono_ns == f.start_ns)
            .unwrap_or_else(|| panic!("no log row for the frame at {}", f.start_ns));
        let logged = row.ch_ns();
        assert_eq!(
            logged.len(),
            real.channels_ns.len(),
            "frame at {}",
            f.start_ns
        );
        for (l, r) in logged.iter().zip(&real.channels_ns) {
            assert!(
                l.abs_diff(*r) <= 500,
                "frame at {}: {logged:?} {real:?}",
                f.start_ns
            );
        }
        if logged.len() < 8 {
            assert_eq!(row.status, Status::Aborted, "{row:?}");
        }
        assert_eq!(row.state, LineState::Active);
        assert!(row.seq.is_some() && row.recv_mono_ns.unwrap() < f.start_ns);
    }
    // (The other way round is not checked: a frame cut short before its
    // first channel leaves a gap longer than a sync, after which the decoder
    // drops the frame before it, which a trainer input has already used
    // channel by channel.)
    // Frame numbers count up without gaps.
    for w in frames.windows(2) {
        assert_eq!(w[1].frame, w[0].frame + 1);
    }
    // The documentation's example rows have the keys of real rows.
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/programs.md"))
            .unwrap();
    let block = readme
        .split("### The frame log")
        .nth(1)
        .and_then(|s| s.split("```\n").nth(1))
        .expect("docs/programs.md's frame log example");
    let keys = |v: &serde_json::Value| {
        let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
        k.sort();
        k
    };
    for line in block.lines() {
        let doc = Row::parse(line).unwrap_or_else(|e| panic!("README row {line}: {e}"));
        let real = rows
            .iter()
            .find(|r| std::mem::discriminant(*r) == std::mem::discriminant(&doc))
            .unwrap();
        let real = serde_json::to_value(real).unwrap();
        let doc: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(keys(&doc), keys(&real), "README row {line}");
    }
}
