//! Authenticated commands and the source allowlist against the real
//! udp-ingress and ppmd: signed commands fly the line, forged, unsigned and
//! replayed ones (also after an ingress restart or crash) never do; a key
//! file others can read stops the ingress at start; datagrams from outside
//! `ingress.allow` are dropped and counted. Two outputs sharing one key: a
//! copy of one's signed commands sent to the other is refused as
//! `wrong_output` and never flies it, nor locks out its own commands; a
//! keyed output left at the default name is warned about. Also
//! the test vector and the Python signed sender of docs/security.md.

use nix::sys::signal::Signal;
use ppm_shared::auth::AuthKey;
use ppm_shared::protocol::RejectReason::{self, *};
use ppm_tests::{
    free_udp_port, handed_over, python3, read_trace, rejected_total, start_outputs, stop_all, Proc,
    Sandbox, StatusReply, GENTLE_RT, PYTHON_PACKAGE,
};
use serde_json::{json, Value};
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

const SECOND: Duration = Duration::from_secs(1);
const KEY_HEX: &str = "8f2a55e0c1d94b7e3a6f0b1c2d3e4f5061728394a5b6c7d8e9f0a1b2c3d4e5f6";

fn key() -> AuthKey {
    AuthKey::from_hex(KEY_HEX).unwrap()
}

/// Sends from one socket and asks for status (unsigned) from it.
struct Client {
    socket: UdpSocket,
    to: SocketAddr,
}

impl Client {
    fn new(from: &str, to: SocketAddr) -> Client {
        let socket = UdpSocket::bind(format!("{from}:0")).unwrap();
        socket.set_read_timeout(Some(5 * SECOND)).unwrap();
        Client { socket, to }
    }

    fn send(&self, bytes: &[u8]) {
        self.socket.send_to(bytes, self.to).unwrap();
    }

    fn status(&self) -> StatusReply {
        self.send(br#"{"get":"status"}"#);
        let mut buf = [0u8; 65_536];
        let (n, _) = self.socket.recv_from(&mut buf).expect("a status reply");
        serde_json::from_slice(&buf[..n]).unwrap()
    }
}

/// Calls `send(i)` for i = 0..n at 50 Hz.
fn at_50hz(n: u64, mut send: impl FnMut(u64)) {
    let start = Instant::now();
    for i in 0..n {
        send(i);
        let next = start + Duration::from_millis(20 * (i + 1));
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
}

fn start_ingress(sb: &Sandbox, cfg: &str, log: &str) -> Proc {
    let p = sb.spawn("udp-ingress", &["--config", cfg], log);
    p.wait_for_log("listening on", 30 * SECOND);
    p
}

fn rejected(status: &StatusReply, reason: RejectReason) -> u64 {
    let name = reason.as_str();
    *status
        .datagrams
        .rejected
        .0
        .get(name)
        .unwrap_or_else(|| panic!("no counter {name}: {status}"))
}

#[test]
fn signed_commands_apply_and_forgeries_and_replays_do_not() {
    let sb = Sandbox::new("auth");
    let key_path = sb.write_file("auth.key", &format!("{KEY_HEX}\n"), 0o600);
    let cfg = sb.config_with_ingress(&format!("auth_key = {key_path:?}"), GENTLE_RT);
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let cfg = cfg.to_str().unwrap();
    let mut ingress = start_ingress(&sb, cfg, "ingress1");
    // Logged just after "listening on", which start_ingress waited for.
    ingress.wait_for_log("commands must be signed", 10 * SECOND);
    let k = key();
    let to = sb.name.as_str();
    let signed =
        |ch: u64, seq: u64| k.envelope(&json!({"ch": [ch], "seq": seq, "to": to}).to_string());
    let c = Client::new("127.0.0.1", sb.addr());

    // 1 s of signed commands (1100), with forgeries (1900) in between.
    let mut history: Vec<String> = vec![];
    at_50hz(50, |i| {
        let good = signed(1100, 1_000 + i);
        c.send(good.as_bytes());
        history.push(good);
        if i % 10 == 5 {
            // Unsigned, with a seq far ahead.
            c.send(
                json!({"ch": [1900], "seq": 9_000 + i})
                    .to_string()
                    .as_bytes(),
            );
            // The MAC changed.
            let forged = signed(1900, 9_100 + i);
            let at = forged.find("\"mac\":\"").unwrap() + 7;
            let flipped = if &forged[at..at + 1] == "0" { "1" } else { "0" };
            let mut bytes = forged.into_bytes();
            bytes[at] = flipped.as_bytes()[0];
            c.send(&bytes);
            // The msg changed, the MAC kept.
            c.send(signed(1100, 9_200 + i).replace("1100", "1900").as_bytes());
            // A replay of an earlier signed datagram.
            c.send(history[i as usize - 5].as_bytes());
            // Signed, but without a seq.
            c.send(
                k.envelope(&json!({"ch": [1900], "to": to}).to_string())
                    .as_bytes(),
            );
            // Signed with another key.
            let other = AuthKey::new([3; 32]);
            c.send(
                other
                    .envelope(&json!({"ch": [1900], "seq": 9900, "to": to}).to_string())
                    .as_bytes(),
            );
        }
    });
    // Status queries need no signature.
    let s = c.status();
    let d = &s.datagrams;
    assert_eq!(handed_over(&s), 50, "{s}");
    assert_eq!(
        (
            rejected(&s, Unsigned),
            rejected(&s, BadMac),
            rejected(&s, Replay),
            rejected(&s, NoSeq)
        ),
        (5, 15, 5, 5),
        "{s}"
    );
    assert_eq!(d.received, 50 + 5 * 6, "{s}");
    assert_eq!(s.newest_seq, Some(1_049));

    // A clean restart: the last accepted seq was kept, old datagrams stay refused.
    assert!(ingress
        .signal_and_wait(Signal::SIGTERM, 10 * SECOND)
        .success());
    let seq_file = sb.dir.join("ipc").join(format!("{}.last_seq", sb.name));
    assert_eq!(
        std::fs::read_to_string(&seq_file)
            .unwrap()
            .trim()
            .parse::<u64>(),
        Ok(1_049)
    );
    let mut ingress = start_ingress(&sb, cfg, "ingress2");
    ingress.wait_for_log("seq 1049 and below refused", 10 * SECOND);
    c.send(history[40].as_bytes());
    c.send(history[49].as_bytes());
    let s = c.status();
    assert_eq!(
        (rejected(&s, Replay), Some(s.datagrams.applied)),
        (2, Some(0)),
        "{s}"
    );

    // New commands apply; then a crash (SIGKILL) after a pause longer than the
    // save interval: the seq file has the last one, replays stay refused.
    let mut second: Vec<String> = vec![];
    at_50hz(25, |i| {
        let d = signed(1300, 2_000 + i);
        c.send(d.as_bytes());
        second.push(d);
    });
    std::thread::sleep(Duration::from_millis(400));
    ingress.kill();
    let ingress = start_ingress(&sb, cfg, "ingress3");
    ingress.wait_for_log("seq 2024 and below refused", 10 * SECOND);
    c.send(second[24].as_bytes());
    c.send(second[3].as_bytes());
    c.send(history[49].as_bytes());
    at_50hz(25, |i| c.send(signed(1300, 3_000 + i).as_bytes()));
    let s = c.status();
    assert_eq!(rejected(&s, Replay), 3, "{s}");
    assert_eq!(s.newest_seq, Some(3_024), "{s}");
    std::thread::sleep(Duration::from_millis(100));
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    drop(ingress);

    let ch1 = ppm_tests::channel_of_frames(&read_trace(&trace), 0);
    assert!(ch1.iter().all(|&v| v == 1100 || v == 1300), "{ch1:?}");
    // Each flew, 1100 then only 1300: one frame of each is all the order
    // needs (about 45 each on an idle machine; how many a loaded one cuts
    // short at a late edge is its business).
    assert!(ch1.contains(&1100), "{ch1:?}");
    let first_1300 = ch1.iter().position(|&v| v == 1300).expect("1300 flew");
    assert!(ch1[first_1300..].iter().all(|&v| v == 1300), "{ch1:?}");
}

#[test]
fn key_files_others_can_read_and_bad_settings_stop_the_ingress() {
    let sb = Sandbox::new("authkey");
    let cfg = sb.config(GENTLE_RT);
    let cfg = cfg.to_str().unwrap();
    let run = |args: &[&str], log: &str| {
        let mut p = sb.spawn("udp-ingress", args, log);
        let status = p.wait(10 * SECOND);
        assert!(!status.success(), "udp-ingress {args:?} started");
        p.log_text()
    };
    let open = sb.write_file("open.key", KEY_HEX, 0o644);
    let short = sb.write_file("short.key", &KEY_HEX[..63], 0o600);
    let missing = sb.dir.join("missing.key");
    for (key, says) in [
        (&open, "chmod 600"),
        (&short, "64 hex characters"),
        (&missing, "cannot read auth key file"),
    ] {
        let name = key.file_stem().unwrap().to_str().unwrap();
        let log = run(
            &["--config", cfg, "--auth-key", key.to_str().unwrap()],
            name,
        );
        assert!(
            log.contains(&key.display().to_string()) && log.contains(says),
            "{log}"
        );
    }

    // A key file that is a FIFO (it used to hang the ingress, silently), a
    // seq file that is /dev/zero (read until memory ran out) and a config
    // that is a FIFO: each stops the ingress at once, saying what it is.
    let fifo = sb.dir.join("fifo.key");
    nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
    let log = run(
        &["--config", cfg, "--auth-key", fifo.to_str().unwrap()],
        "fifo",
    );
    assert!(
        log.contains("fifo.key") && log.contains("a FIFO (named pipe), not a regular file"),
        "{log}"
    );
    let good = sb.write_file("good.key", KEY_HEX, 0o600);
    let zero = sb
        .config_with_ingress(
            &format!("auth_key = {good:?}\nseq_file = \"/dev/zero\""),
            GENTLE_RT,
        )
        .display()
        .to_string();
    let log = run(&["--config", &zero], "zero");
    assert!(
        log.contains("/dev/zero") && log.contains("a character device"),
        "{log}"
    );
    let log = run(&["--config", fifo.to_str().unwrap()], "fifoconfig");
    assert!(
        log.contains("cannot read config file") && log.contains("a FIFO (named pipe)"),
        "{log}"
    );

    // A bad address block, in the config (named by its key) and on the command line.
    let bad = sb
        .config_with_ingress("allow = [\"10.0.0.0/33\"]", GENTLE_RT)
        .display()
        .to_string();
    let log = run(&["--config", &bad], "badallow");
    assert!(
        log.contains("ingress.allow") && log.contains("10.0.0.0/33"),
        "{log}"
    );
    let out = std::process::Command::new(ppm_tests::bin("udp-ingress"))
        .args(["--allow", "localhost"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("localhost"));

    // ppm-send refuses the same key file.
    let out = std::process::Command::new(ppm_tests::bin("ppm-send"))
        .args([
            "--to",
            &sb.addr().to_string(),
            "--count",
            "1",
            "--name",
            "x",
        ])
        .args(["--auth-key", open.to_str().unwrap(), "[1500]"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("chmod 600"), "{err}");
}

#[test]
fn allowlist_drops_other_sources_before_parsing() {
    let sb = Sandbox::new("allow");
    let cfg = sb.config_with_ingress("allow = [\"127.0.0.2/32\"]", GENTLE_RT);
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let ingress = start_ingress(&sb, cfg.to_str().unwrap(), "ingress");
    // Logged just after "listening on", which start_ingress waited for.
    ingress.wait_for_log("taking datagrams only from 127.0.0.2/32", 10 * SECOND);
    let outsider = Client::new("127.0.0.1", sb.addr());
    let insider = Client::new("127.0.0.2", sb.addr());
    at_50hz(50, |i| {
        insider.send(json!({"ch": [1100], "seq": i + 1}).to_string().as_bytes());
        outsider.send(
            json!({"ch": [1900], "seq": 1_000 + i})
                .to_string()
                .as_bytes(),
        );
    });
    // The outsider's status query is dropped (and counted) too.
    outsider
        .socket
        .set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    outsider.send(br#"{"get":"status"}"#);
    assert!(outsider.socket.recv_from(&mut [0u8; 1024]).is_err());
    // Without a key a signed datagram is bad_shape.
    insider.send(key().envelope(r#"{"ch":[1900],"seq":5000}"#).as_bytes());
    let s = insider.status();
    assert_eq!(rejected(&s, NotAllowed), 51, "{s}");
    assert_eq!(rejected(&s, BadShape), 1, "{s}");
    assert_eq!(handed_over(&s), 50, "{s}");
    assert_eq!(s.newest_seq, Some(50));
    std::thread::sleep(Duration::from_millis(100));
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    // Only the insider's command flies: every frame that carried channel 1
    // carries it, and one such frame shows it flew at all (how many a
    // loaded machine cuts short is its business).
    let ch1 = ppm_tests::channel_of_frames(&read_trace(&trace), 0);
    assert!(!ch1.is_empty(), "the insider's command never flew");
    assert!(ch1.iter().all(|&v| v == 1100), "{ch1:?}");
    // Not one log line per datagram: at most one per second for the reason.
    let lines = ingress
        .log_text()
        .lines()
        .filter(|l| l.contains("not_allowed:"))
        .count();
    assert!(
        (1..=3).contains(&lines),
        "{lines} lines:\n{}",
        ingress.log_text()
    );
}

/// The report: a plane (AETR, 8 channels) and a rover (TAER, 6) from one
/// configuration, both inheriting one `ingress.auth_key`; a ppm-send
/// groundstation for each. A passive listener between the plane's
/// groundstation and its ingress copies every plane datagram (throttle
/// 1800, `seq` ahead of the rover's) to the rover's port. The rover refuses
/// the copies as `wrong_output`, flies only its own throttle (1000), and
/// keeps accepting its own commands: no `replay`.
#[test]
fn a_signed_command_copied_to_another_output_with_the_same_key_is_refused() {
    let sb = Sandbox::new("authcopy");
    let key_path = sb.write_file("auth.key", &format!("{KEY_HEX}\n"), 0o600);
    let (plane, rover) = (format!("{}plane", sb.name), format!("{}rover", sb.name));
    let (plane_port, rover_port) = (sb.port, free_udp_port());
    let cfg = sb.dir.join("ppm.toml");
    std::fs::write(
        &cfg,
        format!(
            "[ingress]\nauth_key = {key_path:?}\n[ipc]\nroot = {:?}\n{GENTLE_RT}\n\
             [[outputs]]\nname = \"{plane}\"\noutput = \"sim:plane.trace\"\n\
             ingress.listen = \"127.0.0.1:{plane_port}\"\n\n\
             [[outputs]]\nname = \"{rover}\"\noutput = \"sim:rover.trace\"\n\
             [outputs.ingress]\nlisten = \"127.0.0.1:{rover_port}\"\n\
             [outputs.ppm]\nchannels = 6\norder = \"TAER\"\n",
            sb.dir.join("ipc"),
        ),
    )
    .unwrap();
    let (mut ppmd, mut ings) = start_outputs(&sb, &cfg, &[&plane, &rover]);
    for ing in &ings {
        ing.wait_for_log("commands must be signed", 10 * SECOND);
    }
    let plane_addr = SocketAddr::from(([127, 0, 0, 1], plane_port));
    let rover_addr = SocketAddr::from(([127, 0, 0, 1], rover_port));

    // The listener: passes every datagram on to the plane, and a copy to the rover.
    let tap = UdpSocket::bind("127.0.0.1:0").unwrap();
    tap.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let tap_addr = tap.local_addr().unwrap().to_string();
    let copier = std::thread::spawn(move || {
        let (mut copied, mut buf) = (vec![], [0u8; 65_536]);
        let end = Instant::now() + 30 * SECOND;
        while copied.len() < 100 && Instant::now() < end {
            if let Ok((n, _)) = tap.recv_from(&mut buf) {
                tap.send_to(&buf[..n], plane_addr).unwrap();
                tap.send_to(&buf[..n], rover_addr).unwrap();
                copied.push(buf[..n].to_vec());
            }
        }
        copied
    });
    let ppm_send = |to: &str, name: &str, command: &str| {
        std::process::Command::new(ppm_tests::bin("ppm-send"))
            .args(["--to", to, "--name", name])
            .args(["--auth-key", key_path.to_str().unwrap()])
            .args(["--count", "100", "--rate", "50", command])
            .spawn()
            .unwrap()
    };
    let mut rover_gs = ppm_send(&rover_addr.to_string(), &rover, r#"{"thr": 1000}"#);
    // Started later, the plane's seq (from the time in us) is ahead of the rover's.
    std::thread::sleep(Duration::from_millis(300));
    let mut plane_gs = ppm_send(&tap_addr, &plane, r#"{"thr": 1800}"#);
    assert!(rover_gs.wait().unwrap().success());
    assert!(plane_gs.wait().unwrap().success());
    let copied = copier.join().unwrap();
    assert_eq!(copied.len(), 100);
    // The copies are the plane's signed commands, valid under the shared key.
    let first = ppm_shared::auth::envelope(&copied[0]).unwrap().unwrap();
    assert!(first.verify(&key()));
    let msg: Value = serde_json::from_str(&first.msg).unwrap();
    assert_eq!((&msg["to"], &msg["thr"]), (&json!(plane), &json!(1800)));

    let (p, r) = (
        Client::new("127.0.0.1", plane_addr).status(),
        Client::new("127.0.0.1", rover_addr).status(),
    );
    assert_eq!(handed_over(&p), 100, "{p}");
    assert_eq!(rejected_total(&p), 0, "{p}");
    assert_eq!(r.name, rover, "{r}");
    assert_eq!(rejected(&r, WrongOutput), 100, "{r}");
    assert_eq!(rejected(&r, Replay), 0, "the copies moved no seq: {r}");
    assert_eq!(rejected_total(&r), 100, "{r}");
    assert_eq!(handed_over(&r), 100, "every own command taken: {r}");
    assert_eq!(r.datagrams.received, 200, "{r}");
    let (plane_seq, rover_seq) = (p.newest_seq.unwrap(), r.newest_seq.unwrap());
    assert!(
        rover_seq < plane_seq - 99,
        "the rover's newest command is its own, behind every copy: {rover_seq} {plane_seq}"
    );

    std::thread::sleep(Duration::from_millis(100));
    let [a, b] = &mut ings[..] else {
        unreachable!()
    };
    stop_all(&mut ppmd, &mut [a, b]);
    // The lines: the rover's throttle (channel 1, TAER) is its own, never
    // the plane's; the plane's (channel 3, AETR) is its own. Every frame
    // that carried the throttle counts, whole or cut short after it (exact).
    // One such frame on each line shows its command flew (about 90 frames
    // each on an idle machine; ppmd runs here without real-time priority,
    // so on a loaded one many are cut short, some before their first
    // channel: what is checked is what they carry).
    let thr =
        |trace: &str, i: usize| ppm_tests::channel_of_frames(&read_trace(&sb.dir.join(trace)), i);
    let rover_thr = thr("rover.trace", 0);
    assert!(!rover_thr.is_empty(), "the rover's command never flew");
    assert!(rover_thr.iter().all(|&v| v == 1000), "{rover_thr:?}");
    let plane_thr = thr("plane.trace", 2);
    assert!(!plane_thr.is_empty(), "the plane's command never flew");
    assert!(plane_thr.iter().all(|&v| v == 1800), "{plane_thr:?}");
}

/// Signed commands are bound to the output's name: an ingress with a key
/// whose output is left at the default name (as every board's would be)
/// says so at start; one with a name of its own does not.
#[test]
fn a_signed_output_left_at_the_default_name_is_warned_about() {
    const WARNING: &str = "another board with the same key and name accepts";
    let sb = Sandbox::new("authname");
    let key_path = sb.write_file("auth.key", &format!("{KEY_HEX}\n"), 0o600);
    let cfg = sb.config_with_ingress(&format!("auth_key = {key_path:?}"), GENTLE_RT);
    let mut named = start_ingress(&sb, cfg.to_str().unwrap(), "named");
    named.wait_for_log("commands must be signed", 10 * SECOND);
    assert!(!named.log_text().contains(WARNING), "{}", named.log_text());
    named.kill();
    let text = std::fs::read_to_string(&cfg).unwrap();
    let unnamed = text.replace(&format!("name = \"{}\"\n", sb.name), "");
    assert_ne!(text, unnamed);
    std::fs::write(&cfg, unnamed).unwrap();
    let mut default = start_ingress(&sb, cfg.to_str().unwrap(), "default");
    default.wait_for_log(WARNING, 10 * SECOND);
    default.kill();
}

/// Where the documentation shows signed commands.
fn readme() -> String {
    std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/security.md")).unwrap()
}

/// The block right after an HTML comment marker in docs/security.md.
fn block_after(readme: &str, marker: &str) -> String {
    readme
        .split(marker)
        .nth(1)
        .and_then(|s| s.split("```").nth(1))
        .and_then(|s| s.split_once('\n'))
        .map(|(_, body)| body.to_owned())
        .unwrap_or_else(|| panic!("docs/security.md has no code block after {marker}"))
}

#[test]
fn readme_test_vector_is_what_the_code_computes() {
    let block = block_after(&readme(), "<!-- auth-vector -->");
    let field = |name: &str| {
        block
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .map(str::trim)
            .unwrap_or_else(|| panic!("no `{name}` line in {block}"))
    };
    let k = AuthKey::from_hex(field("key ")).unwrap();
    let msg = field("msg ");
    assert_eq!(k.sign(msg.as_bytes()), field("mac "), "README's mac");
    let datagram = field("datagram ");
    let env = ppm_shared::auth::envelope(datagram.as_bytes())
        .expect("README's datagram is an envelope")
        .unwrap();
    assert_eq!(env.msg, msg);
    assert!(env.verify(&k));
    // It is a command for the output its `to` names, and for no other.
    let to = serde_json::from_str::<Value>(msg).unwrap()["to"]
        .as_str()
        .expect("the vector's msg names its output")
        .to_owned();
    let model = ppm_shared::config::Config::default().validate().unwrap();
    assert_eq!(env.open(&k, &to, &model).unwrap().seq, Some(1));
    assert_eq!(
        env.open(&k, "other", &model).unwrap_err().reason,
        ppm_shared::protocol::RejectReason::WrongOutput
    );
}

/// docs/security.md's Python signed sender, run as written (aimed at this test's
/// port and key file) against a real udp-ingress with that key.
#[test]
fn readme_python_signed_sender_is_accepted() {
    let sb = Sandbox::new("authpy");
    let key_path = sb.write_file("auth.key", &format!("{KEY_HEX}\n"), 0o600);
    let cfg = sb.config(GENTLE_RT);
    let cfg = cfg.to_str().unwrap();
    let ingress = sb.spawn(
        "udp-ingress",
        &["--config", cfg, "--auth-key", key_path.to_str().unwrap()],
        "ingress",
    );
    ingress.wait_for_log("listening on", 30 * SECOND);
    let code = block_after(&readme(), "<!-- signed-sender -->");
    assert!(
        code.contains("/etc/ppm/auth.key")
            && code.contains("5005")
            && code.contains(r#"name="rover""#),
        "{code}"
    );
    let code = code
        .replace("/etc/ppm/auth.key", key_path.to_str().unwrap())
        .replace("5005", &sb.port.to_string())
        .replace(r#"name="rover""#, &format!("name={:?}", sb.name));
    // The snippet imports the package from the source tree (`import ppm`).
    python3(&sb.dir, PYTHON_PACKAGE, &["-c", &code]);
    let s = Client::new("127.0.0.1", sb.addr()).status();
    let d = &s.datagrams;
    assert_eq!(d.received, 100, "{s}");
    assert_eq!(handed_over(&s), 100, "{s}");
    assert_eq!(rejected_total(&s), 0, "{s}");
    assert!(s.newest_seq.is_some());
}
