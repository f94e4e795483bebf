//! Status queries against the real udp-ingress and ppmd: exact counters for
//! a known mix of datagrams, ppmd's timing summary, and `ppm-status`.

use nix::sys::signal::Signal;
use ppm_tests::{bin, reply_of, Proc, Sandbox, StatusReply};
use serde_json::{json, Value};
use std::net::{SocketAddr, UdpSocket};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

const SECOND: Duration = Duration::from_secs(1);

/// Sends commands and status queries from one socket, so they reach the
/// ingress in the order sent.
struct Client {
    socket: UdpSocket,
    to: SocketAddr,
    queries: u64,
}

impl Client {
    fn new(to: SocketAddr) -> Client {
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        socket.set_read_timeout(Some(5 * SECOND)).unwrap();
        Client {
            socket,
            to,
            queries: 0,
        }
    }

    fn send(&self, bytes: &[u8]) {
        self.socket.send_to(bytes, self.to).unwrap();
    }

    /// One status query and its reply as JSON, for what the wire carries.
    /// The ingress answers after publishing what it received before, so
    /// the reply counts everything sent so far.
    fn status_json(&mut self) -> Value {
        self.send(br#"{"get":"status"}"#);
        self.queries += 1;
        let mut buf = [0u8; 65_536];
        let (n, from) = self.socket.recv_from(&mut buf).expect("a status reply");
        assert_eq!(from, self.to);
        serde_json::from_slice(&buf[..n]).expect("the reply is JSON")
    }

    /// One status query and its reply ([`Client::status_json`], typed).
    fn status(&mut self) -> StatusReply {
        reply_of(&self.status_json())
    }
}

fn ppm_status(args: &[&str]) -> Output {
    Command::new(bin("ppm-status"))
        .args(args)
        .output()
        .expect("running ppm-status")
}

fn stdout_of(args: &[&str]) -> String {
    let out = ppm_status(args);
    assert!(
        out.status.success(),
        "ppm-status {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// The keys of a JSON value, recursively, with each leaf's type.
fn shape(v: &Value) -> Value {
    match v {
        Value::Object(m) => Value::Object(m.iter().map(|(k, v)| (k.clone(), shape(v))).collect()),
        Value::Null => json!("null"),
        Value::Bool(_) => json!("bool"),
        Value::Number(_) => json!("number"),
        Value::String(_) => json!("string"),
        Value::Array(_) => json!("array"),
    }
}

fn start(sb: &Sandbox, with_ppmd: bool) -> (Option<Proc>, Proc) {
    let cfg = sb.config("");
    let ppmd = with_ppmd.then(|| sb.start_ppmd(&cfg, "line.trace"));
    (ppmd, sb.start_ingress(&cfg, &[]))
}

/// Malformed datagrams, one of each reason and two malformed queries.
const MALFORMED: [&[u8]; 10] = [
    b"\xff\xfe[1500]",
    b"[1000, 1200",
    br#"[1000, "1200"]"#,
    b"[1000, 1200, 2600]",
    b"[1500,1500,1500,1500,1500,1500,1500,1500,1500]",
    br#"{"yaw": 1500}"#,
    b"{}",
    b"1500",
    br#"{"get":"config"}"#,
    br#"{"get":"status","seq":1}"#,
];

#[test]
fn status_counts_every_datagram_and_reports_ppmd() {
    let sb = Sandbox::new("status");
    let (ppmd, ingress) = start(&sb, true);
    let mut ppmd = ppmd.unwrap();
    let mut c = Client::new(sb.addr());

    let first = c.status();
    assert_eq!(first.name, sb.name);
    assert_eq!(first.datagrams.received, 0);
    assert_eq!(first.datagrams.applied, 0);
    assert_eq!(first.newest_command_age_ms, None);
    assert_eq!(first.newest_seq, None);
    assert_eq!(first.status_requests, 1);

    // 2 s of commands at 50 Hz, with malformed, stale and clamped ones; a
    // status round trip after each keeps every command in its own wake-up.
    let (mut malformed, mut stale) = (0, 0);
    let start = Instant::now();
    let mut last_sent = start;
    for i in 0..100u64 {
        let command = if i == 50 {
            json!({"ch": [900, 2100, 1200], "seq": i + 1})
        } else {
            json!({"ch": [1000 + i, 1500, 1200], "seq": i + 1})
        };
        last_sent = Instant::now();
        c.send(command.to_string().as_bytes());
        if i % 10 == 5 {
            c.send(MALFORMED[malformed]);
            malformed += 1;
        }
        if i % 25 == 10 {
            c.send(br#"{"ch": [1500], "seq": 1}"#);
            stale += 1;
        }
        c.status();
        let next = start + Duration::from_millis(20 * (i + 1));
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
    assert_eq!((malformed, stale), (10, 4));

    // ppmd publishes its timing once a second.
    let end = Instant::now() + 10 * SECOND;
    let (raw, reply) = loop {
        let raw = c.status_json();
        let r = reply_of(&raw);
        if r.ppmd.as_ref().is_some_and(|p| p.frames > 0) {
            break (raw, r);
        }
        assert!(
            Instant::now() < end,
            "no ppmd timing in the status: {r}\n{}",
            ppmd.log_text()
        );
        std::thread::sleep(Duration::from_millis(200));
    };

    // The counters as the wire carries them.
    assert_eq!(
        raw["datagrams"],
        json!({
            "received": 114,
            "applied": 100,
            "superseded": 0,
            "stale": 4,
            "seq_resets": 0,
            "clamped": 1,
            "clamped_values": 2,
            "rejected": {
                "invalid_utf8": 1,
                "invalid_json": 1,
                "not_a_number": 1,
                "out_of_range": 1,
                "too_many_values": 1,
                "unknown_channel": 1,
                "bad_shape": 4,
                "duplicate_key": 0,
                "unsigned": 0,
                "bad_mac": 0,
                "no_seq": 0,
                "replay": 0,
                "not_allowed": 0,
                "wrong_output": 0,
                "no_to": 0,
                "mavlink_junk": 0,
                "mavlink_truncated": 0,
                "mavlink_bad_length": 0,
                "mavlink_bad_crc": 0,
                "mavlink_unknown_message": 0,
            },
        }),
        "{reply}"
    );
    assert_eq!(reply.status_requests, c.queries);
    assert_eq!(reply.status_dropped, 0);
    assert_eq!(reply.newest_seq, Some(100));
    // The newest command's age: received after it was sent, reported before
    // the reply came back.
    let age_ms = reply.newest_command_age_ms.unwrap();
    let since_sent_ms = last_sent.elapsed().as_secs_f64() * 1e3;
    assert!(
        age_ms <= since_sent_ms,
        "age {age_ms} ms, but it was sent {since_sent_ms} ms ago"
    );
    assert!(reply.uptime_s >= 2.0, "{reply}");
    assert!(!reply.ppmd_stale);
    let typed_ppmd = reply.ppmd.as_ref().unwrap();
    let p = &raw["ppmd"];
    assert!(
        ["silent", "active", "failsafe"].contains(&typed_ppmd.state.as_str()),
        "{p}"
    );
    let e = typed_ppmd.edge_error_us;
    let (p50, p99, max) = (e.p50, e.p99, e.max);
    assert!(0.0 <= p50 && p50 <= p99 && p99 <= max, "{e:?}");
    for k in [
        "overruns",
        "late_frames",
        "aborted_frames",
        "glitched_frames",
        "failsafe_entries",
        "repeats",
        "mismatched_commands",
        "expired_commands",
        "log_errors",
    ] {
        assert!(p[k].is_u64(), "{k}: {p}");
    }
    assert_eq!(typed_ppmd.timing, "grid", "{p}");
    assert!(p["degraded"].is_boolean(), "{p}");
    let age = typed_ppmd.snapshot_age_ms;
    assert!((0.0..=3_000.0).contains(&age), "{p}");
    assert_eq!(
        p.as_object().unwrap().len(),
        15,
        "exactly the documented keys: {p}"
    );

    // The documentation's example reply has exactly these keys.
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/status.md")).unwrap();
    let example = readme
        .split("## Status queries")
        .nth(1)
        .and_then(|s| s.split("```json\n").nth(1))
        .and_then(|s| s.split("```").next())
        .expect("docs/status.md shows an example status reply");
    let example: Value = serde_json::from_str(example).expect("the README's reply is JSON");
    assert_eq!(shape(&example), shape(&raw), "README's example vs {raw}");

    // ppm-status prints the same, readably and as JSON; queries change nothing.
    let addr = sb.addr().to_string();
    let text = stdout_of(&["--to", &addr]);
    for line in [
        format!("udp-ingress `{}`, up ", sb.name),
        "datagrams: received 114, applied 100, superseded 0, stale 4, clamped 1 (2 values)\n"
            .into(),
        "rejected: 10 (invalid_utf8 1, invalid_json 1, not_a_number 1, out_of_range 1, too_many_values 1, unknown_channel 1, bad_shape 4)\n".into(),
        ", seq 100\n".into(),
        format!("status queries: {} (0 replies dropped)\n", c.queries + 1),
        " frames; edge error p50 ".into(),
    ] {
        assert!(text.contains(&line), "`{line}` not in:\n{text}");
    }
    let printed: Value = serde_json::from_str(&stdout_of(&["--to", &addr, "--json"])).unwrap();
    assert_eq!(printed["datagrams"], raw["datagrams"]);
    assert_eq!(reply_of(&printed).status_requests, c.queries + 2);
    c.queries += 2;

    // ppmd gone: its last snapshot ages out after 3 s.
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    std::thread::sleep(Duration::from_millis(3_500));
    let r = c.status();
    assert_eq!((&r.ppmd, r.ppmd_stale), (&None, true));
    assert!(stdout_of(&["--to", &addr]).contains("ppmd: no timing snapshot for more than 3 s"));
    drop(ingress);
}

#[test]
fn status_without_ppmd_and_ppm_status_errors() {
    let sb = Sandbox::new("status-alone");
    let (_, _ingress) = start(&sb, false);
    let mut c = Client::new(sb.addr());
    let r = c.status();
    assert_eq!((&r.ppmd, r.ppmd_stale), (&None, false));
    assert_eq!(
        r.datagrams.rejected.0.len(),
        ppm_shared::protocol::RejectReason::ALL.len(),
        "every reason, zeros included: {r}"
    );
    let text = stdout_of(&["--to", &sb.addr().to_string()]);
    assert!(text.contains("newest command: none yet"), "{text}");
    assert!(text.contains("ppmd: no timing snapshot yet"), "{text}");

    // Something that never answers: a timeout, with a clear message.
    let silent = UdpSocket::bind("127.0.0.1:0").unwrap();
    let to = silent.local_addr().unwrap().to_string();
    let started = Instant::now();
    let out = ppm_status(&["--to", &to, "--timeout", "300ms"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains(&format!("no reply from {to} within 300ms")),
        "{err}"
    );
    assert!(started.elapsed() >= Duration::from_millis(300));
    let mut buf = [0u8; 4096];
    let (n, _) = silent.recv_from(&mut buf).unwrap();
    assert_eq!(n, ppm_shared::protocol::STATUS_QUERY_PADDED_LEN, "padded");
    assert_eq!(buf[..n].trim_ascii_end(), br#"{"get":"status"}"#);
}

/// No reply is more than 3 times the datagram that asked for it, unless the
/// source is in `ingress.status_allow` (the loopback blocks by default): a
/// bare 16-byte query used to earn a reply of about 700 bytes, whatever its
/// (spoofable) source.
#[test]
fn status_replies_are_at_most_three_times_their_query_outside_status_allow() {
    let ask = |c: &Client, query: &[u8]| -> Vec<u8> {
        c.send(query);
        let mut buf = [0u8; 65_536];
        let (n, _) = c.socket.recv_from(&mut buf).expect("an answer");
        buf[..n].to_vec()
    };
    let bare = br#"{"get":"status"}"#;

    // Loopback outside status_allow: a bare query gets {"pad_to": N} only.
    let sb = Sandbox::new("amplify");
    let cfg = sb.config_with_ingress("status_allow = []", "");
    let ppmd = sb.start_ppmd(&cfg, "line.trace");
    let ingress = sb.start_ingress(&cfg, &[]);
    let c = Client::new(sb.addr());
    // Padded to what it asked (whitespace after the JSON): the whole reply.
    // The reply can grow between two queries (ppmd's first timing snapshot
    // arrives once a second): then the padded query gets a new pad_to.
    let mut query = bare.to_vec();
    let mut pad_tos = 0;
    let reply = loop {
        let answer = ask(&c, &query);
        assert!(
            answer.len() <= 3 * query.len(),
            "{} bytes for {}",
            answer.len(),
            query.len()
        );
        match serde_json::from_slice::<Value>(&answer).unwrap()["pad_to"].as_u64() {
            Some(need) => {
                assert!(need as usize > query.len(), "pad_to {need}");
                assert!(pad_tos < 5, "still pad_to after {pad_tos} padded queries");
                pad_tos += 1;
                query.resize(need as usize, b' ');
            }
            None => break answer,
        }
    };
    assert!(pad_tos >= 1, "a bare query got the whole reply");
    // pad_to asks for no more than the reply needs, give or take the few
    // characters by which its numbers (ages, counts) change in between.
    assert!(
        reply.len() + 24 > 3 * (query.len() - 1),
        "{} bytes for {}",
        reply.len(),
        query.len()
    );
    let reply: StatusReply = serde_json::from_slice(&reply).unwrap();
    assert_eq!(reply.status_short, pad_tos, "{reply}");
    assert_eq!(reply.status_requests, pad_tos + 1, "{reply}");
    // The escaped spelling is a query too, and short as well.
    let escaped = br#"{"\u0067et":"status"}"#;
    let short = ask(&c, escaped);
    assert!(short.len() <= 3 * escaped.len());
    assert!(String::from_utf8_lossy(&short).starts_with(r#"{"pad_to":"#));
    // ppm-status pads its query: the full reply from a non-allowed source.
    let out = stdout_of(&["--to", &sb.addr().to_string(), "--json"]);
    let reply: StatusReply = serde_json::from_str(&out).unwrap();
    assert_eq!(reply.status_short, pad_tos + 1, "{reply}");
    drop((ppmd, ingress));

    // The default status_allow (loopback): a bare query gets the reply.
    let sb = Sandbox::new("amplify2");
    let cfg = sb.config("");
    let ingress = sb.start_ingress(&cfg, &[]);
    let c = Client::new(sb.addr());
    let raw: Value = serde_json::from_slice(&ask(&c, bare)).unwrap();
    assert_eq!(reply_of(&raw).status_short, 0, "{raw}");
    assert!(raw["datagrams"].is_object(), "{raw}");
    drop(ingress);
}

/// udp-ingress killed (SIGKILL) and started again while ppmd flies: its
/// very first status reply has ppmd's timing, not `"ppmd": null` (ppmd
/// hands its last snapshot to the new subscriber, and the ingress takes it
/// before it answers).
#[test]
fn a_restarted_ingress_reports_ppmd_in_its_first_reply() {
    let sb = Sandbox::new("restart-status");
    let cfg = sb.config("");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let c = Client::new(sb.addr());
    // Flying, and ppmd's timing seen through the first ingress.
    let until = Instant::now() + 30 * SECOND;
    loop {
        c.send(b"[1500, 1500, 1200, 1500]");
        let s = ppm_tests::status(sb.addr());
        if s.ppmd.as_ref().is_some_and(|p| p.state == "active") {
            break;
        }
        assert!(Instant::now() < until, "ppmd never showed active: {s}");
        std::thread::sleep(Duration::from_millis(20));
    }
    for round in 0..3 {
        ingress.kill();
        ingress = sb.start_ingress(&cfg, &[]);
        let s = ppm_tests::status(sb.addr());
        assert!(s.ppmd.is_some(), "round {round}: {s}");
        assert!(!s.ppmd_stale, "round {round}: {s}");
        assert!(
            s.ppmd.as_ref().map(|p| p.frames) > Some(0),
            "round {round}: {s}"
        );
    }
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
}
