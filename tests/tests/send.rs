//! `ppm-send` against real udp-ingress and ppmd instances: one command fanned
//! out to two vehicles' lines, a swept channel, standard-input streaming to
//! every target, signed sending, and `--status` of each target.

use nix::sys::signal::Signal;
use ppm_shared::protocol::RejectReason;
use ppm_tests::{bin, handed_over, read_trace, status, Proc, Sandbox, StatusReply, GENTLE_RT};
use std::io::Write;
use std::net::UdpSocket;
use std::process::{Command, Output, Stdio};
use std::time::Duration;

const SECOND: Duration = Duration::from_secs(1);

/// One vehicle: its sandbox, ingress and (optionally) ppmd on a sim line.
struct Vehicle {
    sb: Sandbox,
    ppmd: Option<Proc>,
    _ingress: Proc,
}

impl Vehicle {
    fn start(label: &str, with_ppmd: bool, ingress_args: &[&str]) -> Vehicle {
        let sb = Sandbox::new(label);
        let cfg = sb.config(GENTLE_RT);
        let ppmd = with_ppmd.then(|| sb.start_ppmd(&cfg, "line.trace"));
        let ingress = sb.start_ingress(&cfg, ingress_args);
        Vehicle {
            sb,
            ppmd,
            _ingress: ingress,
        }
    }

    fn to(&self) -> String {
        self.sb.addr().to_string()
    }

    fn status(&self) -> StatusReply {
        status(self.sb.addr())
    }

    /// Stops ppmd and decodes its line: every frame's start (ns) and
    /// values (us), whole or cut short at a late edge (then with the
    /// channels before it, exact).
    fn frames(&mut self) -> Vec<(u64, Vec<u64>)> {
        let mut p = self.ppmd.take().expect("a ppmd");
        assert!(p.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
        read_trace(&self.sb.dir.join("line.trace"))
            .decode(false)
            .iter()
            .map(|f| (f.start_ns, f.channels_us()))
            .collect()
    }
}

fn ppm_send(args: &[&str], stdin: Option<&str>) -> Output {
    let mut child = Command::new(bin("ppm-send"))
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running ppm-send");
    let mut input = child.stdin.take().unwrap();
    if let Some(text) = stdin {
        input.write_all(text.as_bytes()).unwrap();
    }
    drop(input);
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "ppm-send {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

#[test]
fn one_command_fans_out_to_both_lines() {
    let mut a = Vehicle::start("fan-a", true, &[]);
    let mut b = Vehicle::start("fan-b", true, &[]);
    ppm_send(
        &[
            "--to",
            &a.to(),
            "--to",
            &b.to(),
            "--count",
            "75",
            "--seq",
            "[1000, 1200, 1700, 2000]",
        ],
        None,
    );
    for v in [&a, &b] {
        let s = v.status();
        assert_eq!(s.datagrams.received, 75, "{s}");
        assert_eq!(handed_over(&s), 75, "{s}");
        assert!(s.newest_seq.unwrap() > 1_700_000_000_000_000, "{s}");
    }
    std::thread::sleep(Duration::from_millis(100));
    for (name, v) in [("a", &mut a), ("b", &mut b)] {
        // About 60 frames, whole or cut short at a late edge: every one
        // carries the command, and one carrying a channel shows it reached
        // this line (how many a loaded machine cuts short is its business).
        let frames = v.frames();
        let want = [1000, 1200, 1700, 2000, 1500, 1500, 1500, 1500];
        assert!(
            frames.iter().any(|(_, f)| !f.is_empty()),
            "{name}: no frame with a channel"
        );
        for (_, f) in &frames {
            assert!(f.len() <= 8 && f[..] == want[..f.len()], "{name}: {f:?}");
        }
    }
}

#[test]
fn a_swept_channel_follows_a_triangle_and_the_others_their_defaults() {
    let mut v = Vehicle::start("sweep", true, &[]);
    ppm_send(
        &[
            "--to",
            &v.to(),
            "--duration",
            "2.5s",
            "--sweep",
            "3:1000:2000:1s",
        ],
        None,
    );
    std::thread::sleep(Duration::from_millis(50));
    // About 110 frames, whole or cut short at a late edge (then with the
    // channels before it, exact). The others at their defaults in every
    // frame; the throttle from every frame that carried it. The triangle's
    // two turns (checked below) need four such frames at the least; how
    // many more a loaded machine managed is its business.
    let line = v.frames();
    for (_, f) in &line {
        for (i, &us) in f.iter().enumerate() {
            assert!(i == 2 || us == 1500, "{f:?}");
        }
    }
    let frames: Vec<_> = line.into_iter().filter(|(_, f)| f.len() >= 3).collect();
    assert!(
        frames.len() >= 4,
        "{} frames with the throttle",
        frames.len()
    );
    let thr: Vec<u64> = frames.iter().map(|(_, f)| f[2]).collect();
    assert!(*thr.iter().min().unwrap() <= 1_050, "{thr:?}");
    assert!(*thr.iter().max().unwrap() >= 1_950, "{thr:?}");
    // The sweep rises 1000 us per 0.5 s (2 us per ms): between two of these
    // frames, at most that over the time between them (frames cut short
    // before the throttle are left out, many on a loaded machine) plus 300
    // us for the datagrams in flight and a late sender catching up.
    assert!(
        frames.windows(2).all(|w| {
            let ms = (w[1].0 - w[0].0) / 1_000_000;
            w[0].1[2].abs_diff(w[1].1[2]) <= 300 + 2 * ms
        }),
        "{thr:?}"
    );
    let turns = thr
        .windows(3)
        .filter(|w| (w[1] > w[0]) != (w[2] > w[1]) && w[0] != w[1] && w[1] != w[2])
        .count();
    assert!((2..=8).contains(&turns), "{turns} turns: {thr:?}");
}

#[test]
fn standard_input_lines_go_to_every_target() {
    let a = Vehicle::start("stdin-a", false, &[]);
    let b = Vehicle::start("stdin-b", false, &[]);
    let mut lines: String = (0..300)
        .map(|i| format!("{{\"ch\": [{}]}}\n", 1000 + i))
        .collect();
    lines.push_str("not json\n\n");
    let out = ppm_send(&["--to", &a.to(), "--to", &b.to(), "--seq"], Some(&lines));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("skipped") && err.contains("not json"), "{err}");
    for v in [&a, &b] {
        let s = v.status();
        assert_eq!(s.datagrams.received, 300, "{s}");
        assert_eq!(handed_over(&s), 300, "{s}");
        assert_eq!(s.datagrams.stale, 0, "{s}");
    }
    // Each target numbers on its own: both end on the same last seq.
    assert_eq!(a.status().newest_seq, b.status().newest_seq);

    // --count stops standard input too.
    ppm_send(&["--to", &a.to(), "--count", "10"], Some(&lines));
    assert_eq!(a.status().datagrams.received, 310);
}

#[test]
fn signed_sending_and_status_of_each_target() {
    let key_dir = Sandbox::new("send-key");
    let key = key_dir.write_file(
        "auth.key",
        "8f2a55e0c1d94b7e3a6f0b1c2d3e4f5061728394a5b6c7d8e9f0a1b2c3d4e5f6\n",
        0o600,
    );
    let key = key.to_str().unwrap();
    let a = Vehicle::start("signed-a", false, &["--auth-key", key]);
    let b = Vehicle::start("signed-b", false, &["--auth-key", key]);
    let (name_a, name_b) = (a.sb.name.as_str(), b.sb.name.as_str());
    // One key, two vehicles: each target's commands are signed for its own
    // output (--name once per --to, in order).
    ppm_send(
        &[
            "--to",
            &a.to(),
            "--to",
            &b.to(),
            "--name",
            name_a,
            "--name",
            name_b,
            "--auth-key",
            key,
            "--rate",
            "200",
            "--count",
            "20",
            "[1200]",
        ],
        None,
    );
    ppm_send(
        &["--to", &a.to(), "--name", name_a, "--auth-key", key],
        Some("[1300]\n{\"thr\": 1100}\n"),
    );
    // Signed for a, sent to b: refused as wrong_output.
    ppm_send(
        &["--to", &b.to(), "--name", name_a, "--auth-key", key],
        Some("[1500]\n[1500]\n"),
    );
    // A key without --name: refused before anything is sent.
    let out = Command::new(bin("ppm-send"))
        .args(["--to", &b.to(), "--auth-key", key, "[1500]"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("--auth-key needs --name NAME"),
        "{out:?}"
    );
    // Unsigned: refused by a keyed ingress.
    ppm_send(
        &["--to", &b.to(), "--count", "3", "--rate", "200", "[1400]"],
        None,
    );
    let (sa, sb) = (a.status(), b.status());
    assert_eq!(handed_over(&sa), 22, "{sa}");
    assert_eq!(handed_over(&sb), 20, "{sb}");
    let rejected = |r| sb.datagrams.rejected.count(r);
    assert_eq!(rejected(RejectReason::Unsigned), 3, "{sb}");
    assert_eq!(rejected(RejectReason::WrongOutput), 2, "{sb}");
    assert_eq!(rejected(RejectReason::Replay), 0, "{sb}");

    // --status asks each target and prints the replies readably.
    let out = ppm_send(&["--status", "--to", &a.to(), "--to", &b.to()], None);
    let text = String::from_utf8(out.stdout).unwrap();
    for line in [
        format!("== {} ==\n", a.to()),
        format!("== {} ==\n", b.to()),
        format!("udp-ingress `{}`, up ", a.sb.name),
        format!("udp-ingress `{}`, up ", b.sb.name),
        "datagrams: received 22, applied ".into(),
        "rejected: 5 (unsigned 3, wrong_output 2)\n".into(),
    ] {
        assert!(text.contains(&line), "`{line}` not in:\n{text}");
    }
    // A target that does not answer: said, and the exit status is 1.
    let silent = UdpSocket::bind("127.0.0.1:0").unwrap();
    let out = Command::new(bin("ppm-send"))
        .args(["--status", "--timeout", "300ms", "--to", &a.to()])
        .args(["--to", &silent.local_addr().unwrap().to_string()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stdout).contains(&format!("udp-ingress `{}`", a.sb.name)));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no reply from"));
}

/// ppm-send checks a command as udp-ingress reads it under any
/// configuration: one every udp-ingress refuses stops it before anything is
/// sent (exit 1, the reason the ingress would count), and from standard
/// input such a line is skipped and said while the good ones go out.
#[test]
fn ppm_send_refuses_what_every_ingress_refuses() {
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    socket
        .set_read_timeout(Some(std::time::Duration::from_millis(300)))
        .unwrap();
    let to = socket.local_addr().unwrap().to_string();
    for (command, reason) in [
        ("[3000]", "out_of_range"),
        (r#"[1500,"x"]"#, "not_a_number"),
        (r#"{"thr":1000,"thr":2000}"#, "duplicate_key"),
        (r#"{"yaw":1500}"#, "unknown_channel"),
        ("[1500, 1500", "invalid_json"),
    ] {
        let out = std::process::Command::new(ppm_tests::bin("ppm-send"))
            .args(["--to", &to, "--count", "3", command])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{command}: {err}");
        assert!(err.contains(reason), "{command}: {err}");
        let mut buf = [0u8; 512];
        assert!(socket.recv(&mut buf).is_err(), "{command} was sent");
    }
    // Standard input: the bad lines are skipped, the good ones sent.
    let mut child = std::process::Command::new(ppm_tests::bin("ppm-send"))
        .args(["--to", &to])
        .stdin(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    use std::io::Write;
    child
        .stdin
        .take()
        .unwrap()
        .write_all(b"[1100]\n[3000]\n{\"ail\":1,\"ail\":2}\n{\"ch\":[1200]}\n")
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("out_of_range") && err.contains("duplicate_key"),
        "{err}"
    );
    let mut got = Vec::new();
    let mut buf = [0u8; 512];
    while let Ok(n) = socket.recv(&mut buf) {
        got.push(String::from_utf8_lossy(&buf[..n]).to_string());
    }
    assert_eq!(got, ["[1100]", r#"{"ch":[1200]}"#], "{err}");
}
