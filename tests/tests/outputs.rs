//! Several outputs from one ppmd: `[[outputs]]` with two simulated lines of
//! different PPM settings, each fed by its own `udp-ingress --name NAME` on
//! its own port, all edges from one timing thread. Each line's trace is
//! decoded on its own with transmitter semantics and must carry exactly its
//! own commands, on its own frame grid; each output publishes its own
//! timing, which its ingress's status reply shows.

use ppm_shared::framelog::{self, Status};
use ppm_tests::{
    at_50hz, bin, free_udp_port, read_trace, start_outputs, status, stop_all, two_outputs, Sandbox,
    Sender,
};
use std::net::SocketAddr;
use std::path::Path;
use std::process::Command;
use std::time::Duration;

const SECOND: Duration = Duration::from_secs(1);

/// Output b of the two: 6 channels TAER at 20 ms with a unit range on
/// aileron and failsafe `hold` (a: 8 channels AETR at 22.5 ms).
const B: &str = r#"
[outputs.ppm]
channels = 6
order = "TAER"
frame_us = 20000.0
[outputs.ppm.channel.ail]
unit_min = -10.0
unit_max = 10.0
[outputs.failsafe]
action = "hold"
"#;

/// Every frame of the trace at `path`, as whole microseconds, with the
/// scheduled frame starts: whole, or cut short at a late edge (then with the
/// channels before it, exact).
fn frames(path: &Path) -> Vec<(u64, Vec<u64>)> {
    read_trace(path)
        .decode(false)
        .iter()
        .map(|f| (f.start_ns, f.channels_us()))
        .collect()
}

#[test]
fn one_ppmd_drives_two_outputs_each_with_its_own_commands() {
    let sb = Sandbox::new("outputs");
    let port_b = free_udp_port();
    let (cfg_path, [name_a, name_b]) = two_outputs(&sb, port_b, B);
    let cfg = cfg_path.to_str().unwrap();
    // An ingress must say which output it feeds.
    let out = Command::new(bin("udp-ingress"))
        .args(["--config", cfg])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("2 outputs") && err.contains(&name_a) && err.contains("--name"),
        "{err}"
    );

    let (mut ppmd, mut ings) = start_outputs(&sb, &cfg_path, &[&name_a, &name_b]);

    let (to_a, to_b) = (sb.addr(), SocketAddr::from(([127, 0, 0, 1], port_b)));
    let (send_a, send_b) = (Sender::new(to_a), Sender::new(to_b));
    let mut statuses = Vec::new();
    at_50hz(100, |i| {
        send_a.send(b"[1100, 1200, 1300, 1400]");
        // b is TAER (throttle first), its values normalised on 1000..2000 us.
        send_b.send(br#"{"norm": {"thr": 0.8, "ail": 0.5, "ele": -0.4, "rud": 0.2, "aux1": -1}}"#);
        if i == 80 {
            statuses = vec![status(to_a), status(to_b)];
        }
    });
    let [a, b] = &mut ings[..] else {
        unreachable!()
    };
    stop_all(&mut ppmd, &mut [a, b]);

    // Each line carries its own commands, decoded on its own.
    let log = ppmd.log_text();
    let summary = |name: &str| -> String {
        log.lines()
            .find(|l| l.contains(&format!("{name}: stopped")))
            .unwrap_or_else(|| panic!("no summary for {name}:\n{log}"))
            .to_string()
    };
    let late_frames = |name: &str| -> usize {
        let line = summary(name);
        let before = line.split(" late frames").next().unwrap();
        before.rsplit(' ').next().unwrap().parse().unwrap()
    };
    // What each line lost to late edges, in every run's output: on a
    // loaded machine ppmd (a debug build here) cuts frames short at a late
    // edge, which the checks below allow for.
    for name in [&name_a, &name_b] {
        eprintln!("{}", summary(name));
    }
    for (trace, name, want, frame_ns) in [
        (
            "a.trace",
            &name_a,
            vec![1100, 1200, 1300, 1400, 1500, 1500, 1500, 1500],
            22_500_000,
        ),
        (
            "b.trace",
            &name_b,
            vec![1900, 1750, 1300, 1600, 1000, 1500],
            20_000_000,
        ),
    ] {
        let got = frames(&sb.dir.join(trace));
        // Every frame, whole or cut short, carries exactly this output's
        // command (the channels before the cut), never the other's.
        for (start, ch) in &got {
            assert_eq!(ch[..], want[..ch.len()], "{trace}: frame at {start}");
        }
        // One whole frame proves the command flew; how many more a busy
        // machine manages is the benchmarks' business.
        let whole = got.iter().filter(|f| f.1.len() == want.len()).count();
        assert!(
            whole >= 1,
            "{trace}: no whole frame of {}\n{log}",
            got.len()
        );
        // On the output's own grid, but for frames moved late (counted).
        let starts: Vec<u64> = got.iter().map(|f| f.0).collect();
        let on = |grid: u64| {
            starts
                .iter()
                .filter(|&&s| s.abs_diff(grid).is_multiple_of(frame_ns))
                .count()
        };
        let grid = *starts.iter().max_by_key(|&&s| on(s)).unwrap();
        let off = starts.len() - on(grid);
        let late = late_frames(name);
        assert!(
            off <= late,
            "{trace}: {off} frames off the grid, {late} late\n{log}"
        );
    }
    for name in [&name_a, &name_b] {
        let line = summary(name);
        assert!(line.contains(" 0 write errors"), "{line}");
        assert!(line.contains(" 0 mismatched"), "{line}");
    }
    // Each output's timing reaches its own ingress.
    for (s, name) in statuses.iter().zip([&name_a, &name_b]) {
        let p = s.ppmd.as_ref().expect("ppmd's timing");
        assert_eq!(p.state, "active", "{name}: {s}");
        assert!(p.frames > 0, "{name}: {s}");
    }
    // The frame log belongs to output a alone, and says what a's line
    // carried: each frame it logs whole carries a's command, each value
    // moved at most by the 20 us guard (the lateness of its edges).
    let rows = framelog::read_frames(&sb.dir.join("a.jsonl")).unwrap_or_else(|e| panic!("{e}"));
    let logged_whole: Vec<&Vec<f64>> = rows
        .iter()
        .filter(|r| r.status == Status::Whole)
        .map(|r| &r.ch_us)
        .collect();
    assert!(!logged_whole.is_empty(), "{rows:?}");
    let want_a = [
        1100.0, 1200.0, 1300.0, 1400.0, 1500.0, 1500.0, 1500.0, 1500.0,
    ];
    let near = |ch: &&Vec<f64>| {
        ch.len() == want_a.len() && ch.iter().zip(want_a).all(|(v, w)| (v - w).abs() <= 20.0)
    };
    assert!(logged_whole.iter().all(near), "{logged_whole:?}");
    assert!(!sb.dir.join("b.jsonl").exists());
}

#[test]
fn output_arguments_make_outputs_and_bad_ones_are_refused() {
    let sb = Sandbox::new("outputs-cli");
    let cfg_path = sb.config("");
    let cfg = cfg_path.to_str().unwrap();
    // --output NAME=SPEC twice: two outputs from the file's settings.
    let mut ppmd = sb.spawn(
        "ppmd",
        &[
            "--config",
            cfg,
            "--output",
            "x=sim:x.trace",
            "--output",
            "y=sim:y.trace",
        ],
        "ppmd",
    );
    ppmd.wait_for_log("y: 8 channels", 30 * SECOND);
    let mut ing = sb.spawn("udp-ingress", &["--config", cfg, "--name", "y"], "ing");
    ing.wait_for_log("listening on", 30 * SECOND);
    let sender = Sender::new(sb.addr());
    for _ in 0..30 {
        sender.send(b"[1234]");
        std::thread::sleep(Duration::from_millis(20));
    }
    stop_all(&mut ppmd, &mut [&mut ing]);
    let y = frames(&sb.dir.join("y.trace"));
    // One frame proves y's command flew; every frame carries it.
    assert!(!y.is_empty(), "no frame on y");
    assert!(y.iter().all(|f| f.1.first().is_none_or(|&v| v == 1234)));
    assert!(
        frames(&sb.dir.join("x.trace")).is_empty(),
        "x got no command"
    );

    for (args, says) in [
        (&["--output", "sim", "--output", "z=sim"][..], "not both"),
        (
            &[
                "--output",
                "x=sim:same.trace",
                "--output",
                "y=sim:same.trace",
            ][..],
            "--output y=sim:same.trace",
        ),
        (
            &[
                "--output",
                "x=sim",
                "--output",
                "y=sim",
                "--frame-log",
                "f.jsonl",
            ][..],
            "--frame-log with several outputs",
        ),
    ] {
        let out = Command::new(bin("ppmd"))
            .args(["--config", cfg])
            .args(args)
            .current_dir(&sb.dir)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(err.contains(says), "{args:?}: {err}");
    }
}

/// Two `[[outputs]]` on one listen address: ppmd and udp-ingress (either
/// output's) refuse the file alike, naming the key and the other output.
#[test]
fn a_listen_address_shared_by_two_outputs_is_refused_by_ppmd_and_udp_ingress() {
    let sb = Sandbox::new("outputs-listen");
    let (cfg_path, [name_a, name_b]) = two_outputs(&sb, sb.port, "");
    let cfg = cfg_path.to_str().unwrap();
    let want = format!(
        "config key `outputs[1].ingress.listen`: 127.0.0.1:{} is the same address (each output has its own udp-ingress and port), as output `{name_a}` (outputs[0])",
        sb.port
    );
    let runs: [(&str, Vec<&str>); 3] = [
        ("ppmd", vec!["--config", cfg]),
        ("udp-ingress", vec!["--config", cfg, "--name", &name_a]),
        ("udp-ingress", vec!["--config", cfg, "--name", &name_b]),
    ];
    for (program, args) in runs {
        let out = Command::new(bin(program))
            .args(&args)
            .current_dir(&sb.dir)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{program} {args:?} started: {err}");
        let line = err
            .lines()
            .find_map(|l| {
                l.split_once(" ERROR ")
                    .and_then(|(_, r)| r.split_once("] "))
            })
            .map(|(_, msg)| msg);
        assert_eq!(line, Some(want.as_str()), "{program} {args:?}: {err}");
    }
}
