//! `ppm-web` in a real browser: the pipeline (udp-ingress, ppmd on the
//! simulated line) and ppm-web run as separate processes, a headless
//! Chromium (`chromium-headless-shell`) opens the page, and the test reads
//! what the page shows through the DevTools protocol while it sends
//! commands over UDP. Bounds (stated in docs/web.md):
//!
//! - the channels shown equal the commanded ones (within 1 us);
//! - a new command shows in the command column within 200 ms of its first
//!   datagram, and on the line column within 400 ms (ppmd publishes what
//!   the line carried at most 10 times a second);
//! - `failsafe` shows within 500 ms of the last command
//!   (`failsafe.after_ms = 100`);
//! - a simulated radio on ppmd's read-back input relays the commands,
//!   then the instructor takes over: the radio column and the takeover
//!   state show it;
//! - the page goes on across a restart of ppmd and of udp-ingress, saying
//!   "not running" meanwhile;
//! - the browser's console has no error.
//!
//! With `PPM_WEB_SCREENSHOT=FILE` the browser's screenshot is written to
//! FILE (docs/img/ppm-web.png is made so). Without chromium-headless-shell
//! the test fails and says what to install. A second test checks the
//! server without a browser: read-only (405), the allowlist, the exit
//! statuses of a busy port, a bad address and a bad flag, and that the
//! docs list every option.

use nix::sys::signal::Signal;
use ppm_tests::{bin, Proc, Pty, Sandbox, GENTLE_RT};
use serde_json::{json, Value};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, UdpSocket};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::SeqCst};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const SECOND: Duration = Duration::from_secs(1);
/// A command shows in the command column within this long.
const COMMAND_SHOWN: Duration = Duration::from_millis(200);
/// ... and in the line column within this long.
const LINE_SHOWN: Duration = Duration::from_millis(400);
/// `failsafe` shows within this long of the last command.
const FAILSAFE_SHOWN: Duration = Duration::from_millis(500);
/// What may take a while on a loaded machine: a program or the page
/// starting, a restart noticed.
const SLOW: Duration = Duration::from_secs(20);

fn now_ns() -> u64 {
    ppm_shared::time::now_ns()
}

/// The browser: `chromium-headless-shell` on PATH or in /usr/lib/chromium
/// (Debian's package), or `PPM_CHROMIUM`.
fn chromium() -> PathBuf {
    if let Some(p) = std::env::var_os("PPM_CHROMIUM") {
        return PathBuf::from(p);
    }
    let on_path = std::env::var_os("PATH")
        .iter()
        .flat_map(std::env::split_paths)
        .map(|d| d.join("chromium-headless-shell"))
        .chain(std::iter::once(PathBuf::from(
            "/usr/lib/chromium/chromium-headless-shell",
        )))
        .find(|p| p.is_file());
    on_path.unwrap_or_else(|| {
        panic!(
            "chromium-headless-shell is needed for this test (apt-get install chromium-headless-shell; or set PPM_CHROMIUM to a headless Chromium)"
        )
    })
}

/// A headless Chromium with its own profile, killed (with its helper
/// processes) when dropped.
struct Browser {
    proc: Proc,
    cdp: Cdp,
    session: String,
}

impl Browser {
    /// Starts the browser and opens `url` in a page of 1280x1000.
    fn open(dir: &Path, url: &str) -> Browser {
        use std::os::unix::process::CommandExt;
        let profile = dir.join("chromium-profile");
        std::fs::create_dir_all(&profile).unwrap();
        let mut cmd = std::process::Command::new(chromium());
        cmd.args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--hide-scrollbars",
            "--remote-debugging-port=0",
            "--window-size=1280,1000",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("about:blank")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .process_group(0);
        let proc = Proc::start(cmd, dir.join("chromium.log")).expect("starting chromium");
        // Chromium writes its port and the browser's path once it listens.
        let file = profile.join("DevToolsActivePort");
        let end = Instant::now() + SLOW;
        let (port, path) = loop {
            let text = std::fs::read_to_string(&file).unwrap_or_default();
            let mut lines = text.lines();
            if let (Some(port), Some(path)) = (lines.next(), lines.next()) {
                break (port.to_string(), path.to_string());
            }
            assert!(
                Instant::now() < end,
                "chromium did not open its DevTools port: {}",
                proc.log_text()
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        let mut cdp = Cdp::connect(&format!("127.0.0.1:{port}"), &path);
        let target = cdp.call(None, "Target.createTarget", json!({"url": "about:blank"}));
        let target = target["targetId"]
            .as_str()
            .expect("a target id")
            .to_string();
        let attached = cdp.call(
            None,
            "Target.attachToTarget",
            json!({"targetId": target, "flatten": true}),
        );
        let session = attached["sessionId"]
            .as_str()
            .expect("a session")
            .to_string();
        for method in ["Runtime.enable", "Log.enable", "Page.enable"] {
            cdp.call(Some(&session), method, json!({}));
        }
        cdp.call(
            Some(&session),
            "Emulation.setDeviceMetricsOverride",
            json!({"width": 1280, "height": 1000, "deviceScaleFactor": 1, "mobile": false}),
        );
        cdp.call(Some(&session), "Page.navigate", json!({ "url": url }));
        Browser { proc, cdp, session }
    }

    /// What the page shows for output `name` (`None` before it is drawn).
    fn shown(&mut self, name: &str) -> Option<Shown> {
        let expression = format!(
            r#"(() => {{
              const s = document.querySelector('section[data-output="{name}"]');
              if (!s) return null;
              const col = (src) => [...s.querySelectorAll('td[data-src="' + src + '"]')].map((td) => td.textContent);
              const f = (k) => s.querySelector('[data-field="' + k + '"]').textContent;
              return JSON.stringify({{
                command: col("command"), line: col("line"), radio: col("readback"),
                takeover: s.querySelector('[data-field="takeover"]').dataset.state || "",
                state: s.querySelector('[data-field="line-state"]').dataset.state,
                ppmd: f("ppmd"), ingress: f("ingress"), datagrams: f("datagrams"),
                conn: document.getElementById("conn").dataset.state,
              }});
            }})()"#
        );
        let r = self.cdp.call(
            Some(&self.session.clone()),
            "Runtime.evaluate",
            json!({"expression": expression, "returnByValue": true}),
        );
        let text = r["result"]["value"].as_str()?;
        let v: Value = serde_json::from_str(text).expect("the page's JSON");
        let numbers = |k: &str| -> Vec<Option<f64>> {
            v[k].as_array()
                .unwrap()
                .iter()
                .map(|t| t.as_str().unwrap().parse().ok())
                .collect()
        };
        let text = |k: &str| v[k].as_str().unwrap_or_default().to_string();
        Some(Shown {
            command: numbers("command"),
            line: numbers("line"),
            radio: numbers("radio"),
            takeover: text("takeover"),
            state: text("state"),
            ppmd: text("ppmd"),
            ingress: text("ingress"),
            datagrams: text("datagrams"),
            conn: text("conn"),
        })
    }

    /// Polls the page until `ok` holds of what it shows for `name`; returns
    /// when it held (after the answer came), or panics with `what` and the
    /// last thing shown after `limit`.
    fn wait_until(
        &mut self,
        name: &str,
        what: &str,
        limit: Duration,
        ok: impl Fn(&Shown) -> bool,
    ) -> Instant {
        let end = Instant::now() + limit;
        let mut last = None;
        loop {
            let shown = self.shown(name);
            if shown.as_ref().is_some_and(&ok) {
                return Instant::now();
            }
            last = shown.or(last);
            assert!(
                Instant::now() < end,
                "the page did not show {what} within {limit:?}; it shows {last:?}"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// The text of field `key` of output `name`, and whether its row
    /// shows (`None` before the output is drawn).
    fn field(&mut self, name: &str, key: &str) -> Option<(String, bool)> {
        let expression = format!(
            r#"(() => {{
              const s = document.querySelector('section[data-output="{name}"]');
              const f = s && s.querySelector('[data-field="{key}"]');
              if (!f) return null;
              return JSON.stringify([f.textContent, !f.parentElement.classList.contains("hidden")]);
            }})()"#
        );
        let r = self.cdp.call(
            Some(&self.session.clone()),
            "Runtime.evaluate",
            json!({"expression": expression, "returnByValue": true}),
        );
        let v: (String, bool) = serde_json::from_str(r["result"]["value"].as_str()?).ok()?;
        Some(v)
    }

    /// The page as a PNG.
    fn screenshot(&mut self) -> Vec<u8> {
        let r = self.cdp.call(
            Some(&self.session.clone()),
            "Page.captureScreenshot",
            json!({"format": "png"}),
        );
        base64(r["data"].as_str().expect("screenshot data"))
    }

    /// Errors the page's console and log reported so far.
    fn console_errors(&mut self) -> Vec<String> {
        // One more call, so that every event sent before it is read.
        self.cdp.call(
            Some(&self.session.clone()),
            "Runtime.evaluate",
            json!({"expression": "1"}),
        );
        self.cdp
            .events
            .iter()
            .filter_map(|e| {
                let p = &e["params"];
                match e["method"].as_str()? {
                    "Runtime.consoleAPICalled"
                        if matches!(p["type"].as_str(), Some("error" | "assert")) =>
                    {
                        Some(format!("console.{}: {}", p["type"], p["args"]))
                    }
                    "Runtime.exceptionThrown" => {
                        Some(format!("exception: {}", p["exceptionDetails"]))
                    }
                    "Log.entryAdded" if p["entry"]["level"] == "error" => {
                        Some(format!("log: {}", p["entry"]))
                    }
                    _ => None,
                }
            })
            .collect()
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let pid = nix::unistd::Pid::from_raw(self.proc.pid() as i32);
        let _ = nix::sys::signal::killpg(pid, Signal::SIGKILL);
        self.proc.kill();
    }
}

/// What the page shows for one output.
#[derive(Debug, Clone)]
#[allow(dead_code)] // every field is printed when a wait fails
struct Shown {
    command: Vec<Option<f64>>,
    line: Vec<Option<f64>>,
    radio: Vec<Option<f64>>,
    takeover: String,
    state: String,
    ppmd: String,
    ingress: String,
    datagrams: String,
    conn: String,
}

/// Whether `shown` is `want`, value by value, within 1 us.
fn equal(shown: &[Option<f64>], want: &[f64]) -> bool {
    shown.len() == want.len()
        && shown
            .iter()
            .zip(want)
            .all(|(s, w)| s.is_some_and(|s| (s - w).abs() <= 1.0))
}

/// A DevTools protocol client on one websocket: calls wait for their
/// answer; the events that come meanwhile are kept.
struct Cdp {
    ws: tungstenite::WebSocket<TcpStream>,
    next: u64,
    events: Vec<Value>,
}

impl Cdp {
    fn connect(addr: &str, path: &str) -> Cdp {
        let stream = TcpStream::connect(addr).expect("connecting to chromium");
        // A browser that stops answering fails the test instead of hanging it.
        stream.set_read_timeout(Some(30 * SECOND)).unwrap();
        let (ws, _) = tungstenite::client(format!("ws://{addr}{path}"), stream)
            .expect("the DevTools websocket");
        Cdp {
            ws,
            next: 1,
            events: vec![],
        }
    }

    fn call(&mut self, session: Option<&str>, method: &str, params: Value) -> Value {
        let id = self.next;
        self.next += 1;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = session {
            msg["sessionId"] = json!(s);
        }
        self.ws
            .send(tungstenite::Message::text(msg.to_string()))
            .unwrap_or_else(|e| panic!("{method}: {e}"));
        loop {
            let m = self
                .ws
                .read()
                .unwrap_or_else(|e| panic!("{method}: no answer from chromium: {e}"));
            let tungstenite::Message::Text(text) = m else {
                continue;
            };
            let v: Value = serde_json::from_str(text.as_str()).expect("CDP JSON");
            if v["id"] == json!(id) {
                assert!(v["error"].is_null(), "{method}: {}", v["error"]);
                return v["result"].clone();
            }
            if v["method"].is_string() {
                self.events.push(v);
            }
        }
    }
}

/// Decodes standard base64.
fn base64(text: &str) -> Vec<u8> {
    let value = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => (c - b'A') as u32,
            b'a'..=b'z' => (c - b'a' + 26) as u32,
            b'0'..=b'9' => (c - b'0' + 52) as u32,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {c}"),
        }
    };
    let bytes: Vec<u8> = text.bytes().filter(|&c| c != b'=').collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= value(c) << (18 - 6 * i);
        }
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

/// Sends the current command 50 times a second from a thread, nothing
/// while there is none; says when the first datagram of each new command
/// left.
struct Commands {
    current: Arc<Mutex<Option<String>>>,
    first_sent: Arc<AtomicU64>,
    last_sent: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
}

impl Commands {
    fn start(to: SocketAddr) -> Commands {
        let c = Commands {
            current: Arc::new(Mutex::new(None)),
            first_sent: Arc::new(AtomicU64::new(0)),
            last_sent: Arc::new(AtomicU64::new(0)),
            stop: Arc::new(AtomicBool::new(false)),
        };
        let (current, first, last, stop) = (
            c.current.clone(),
            c.first_sent.clone(),
            c.last_sent.clone(),
            c.stop.clone(),
        );
        std::thread::spawn(move || {
            let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
            let mut sent: Option<String> = None;
            while !stop.load(SeqCst) {
                let cmd = current.lock().unwrap().clone();
                if let Some(cmd) = &cmd {
                    socket.send_to(cmd.as_bytes(), to).unwrap();
                    let t = now_ns();
                    if sent.as_ref() != Some(cmd) {
                        first.store(t, SeqCst);
                    }
                    last.store(t, SeqCst);
                }
                sent = cmd;
                std::thread::sleep(Duration::from_millis(20));
            }
        });
        c
    }

    /// Sends `values` from now on; returns when its first datagram left
    /// (CLOCK_MONOTONIC ns).
    fn send(&self, values: &[f64]) -> u64 {
        let before = self.first_sent.load(SeqCst);
        *self.current.lock().unwrap() = Some(serde_json::to_string(values).unwrap());
        loop {
            let t = self.first_sent.load(SeqCst);
            if t != before {
                return t;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Stops sending; returns when the last datagram left.
    fn pause(&self) -> u64 {
        *self.current.lock().unwrap() = None;
        std::thread::sleep(Duration::from_millis(30));
        self.last_sent.load(SeqCst)
    }
}

impl Drop for Commands {
    fn drop(&mut self) {
        self.stop.store(true, SeqCst);
    }
}

/// What the instructor's sticks send, when he takes over.
const INSTRUCTOR_US: [u64; 8] = [1600, 1450, 1100, 1550, 1500, 1500, 1500, 1500];

/// A simulated radio on ppmd's read-back input (`ppmd.readback =
/// "sim:PATH"`): every 22.5 ms a PPM frame of what the test commands (the
/// trainer relayed, to the whole microsecond) or, while `instructor` is
/// set, the instructor's sticks; each edge written once its time has
/// passed, as the kernel reports edges. Returns when `stop` is set.
fn radio(out: &Path, commands: &Mutex<Option<String>>, instructor: &AtomicBool, stop: &AtomicBool) {
    let mut file = std::fs::File::create(out).expect("creating the radio's trace");
    file.write_all(b"# idle_level 0\n").unwrap();
    let mut relayed = vec![1500u64; 8];
    let mut pending = std::collections::VecDeque::new();
    let mut next = now_ns();
    while !stop.load(SeqCst) {
        let now = now_ns();
        let mut text = String::new();
        while pending.front().is_some_and(|(t, _)| *t <= now) {
            let (t, level) = pending.pop_front().unwrap();
            text.push_str(&format!("{t} {t} {level}\n"));
        }
        if !text.is_empty() {
            file.write_all(text.as_bytes()).unwrap();
        }
        if now >= next {
            if let Some(cmd) = commands.lock().unwrap().as_deref() {
                let v: Vec<f64> = serde_json::from_str(cmd).unwrap();
                relayed = v.iter().map(|u| u.round() as u64).collect();
            }
            let us = if instructor.load(SeqCst) {
                INSTRUCTOR_US.to_vec()
            } else {
                relayed.clone()
            };
            pending.extend(ppm_tools::radio::frame_edges(next, &us));
            next += 22_500_000;
        }
        std::thread::sleep(Duration::from_micros(500));
    }
}

/// Time from `from_ns` (CLOCK_MONOTONIC) to the instant `at`.
fn since(from_ns: u64, at: Instant) -> Duration {
    let now = now_ns();
    let back = Instant::now().saturating_duration_since(at);
    Duration::from_nanos(now.saturating_sub(from_ns)).saturating_sub(back)
}

/// Starts ppm-web on any free port; returns it and its address.
fn start_web(sb: &Sandbox, cfg: &Path) -> (Proc, String) {
    let web = sb.spawn(
        "ppm-web",
        &["--config", cfg.to_str().unwrap(), "--listen", "127.0.0.1:0"],
        "web",
    );
    web.wait_for_log("serving http://", SLOW);
    let log = web.log_text();
    let addr = log
        .split("serving http://")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .expect("ppm-web says its address")
        .to_string();
    (web, addr)
}

/// Starts ppmd on the sandbox's simulated SPI line (frames written whole:
/// none cut short on a loaded machine without real-time priority).
fn start_ppmd(sb: &Sandbox, cfg: &Path, trace: &str) -> Proc {
    let output = format!("sim-spi:{}", sb.dir.join(trace).display());
    let p = sb.spawn(
        "ppmd",
        &["--config", cfg.to_str().unwrap(), "--output", &output],
        "ppmd",
    );
    p.wait_for_log("commands from", SLOW);
    p
}

#[test]
fn the_page_shows_the_pipeline_live_in_a_browser() {
    let browser_binary = chromium();
    assert!(browser_binary.is_file());
    let sb = Sandbox::new("web");
    let name = sb.name.clone();
    let radio_trace = sb.dir.join("radio.trace");
    let cfg = sb.config(&format!(
        "{GENTLE_RT}[ppmd]\nreadback = \"sim:{}\"\n[failsafe]\nafter_ms = 100\naction = 'default'\n",
        radio_trace.display()
    ));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let mut ppmd = start_ppmd(&sb, &cfg, "line.trace");
    let (mut web, addr) = start_web(&sb, &cfg);
    let mut b = Browser::open(&sb.dir, &format!("http://{addr}/"));
    let commands = Commands::start(sb.addr());
    let instructor = Arc::new(AtomicBool::new(false));
    let radio_stop = Arc::new(AtomicBool::new(false));
    let radio = {
        let (c, i, s) = (
            commands.current.clone(),
            instructor.clone(),
            radio_stop.clone(),
        );
        std::thread::spawn(move || radio(&radio_trace, &c, &i, &s))
    };
    let defaults = [
        1500.0, 1500.0, 1000.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0,
    ];

    // The page comes up, ppmd silent before the first command.
    b.wait_until(&name, "ppmd running, the line silent", SLOW, |s| {
        s.state == "silent" && s.ppmd.starts_with("running") && s.ingress.starts_with("running")
    });

    // The first command: shown exactly, in both columns.
    let first = [
        1100.0, 1900.0, 1300.0, 1650.5, 1500.0, 1200.0, 1800.0, 1500.0,
    ];
    commands.send(&first);
    b.wait_until(&name, "the first command on both columns", SLOW, |s| {
        equal(&s.command, &first) && equal(&s.line, &first) && s.state == "flying"
    });
    // A PPM output has no flight controller telemetry: its row is hidden.
    assert_eq!(b.field(&name, "telemetry").map(|f| f.1), Some(false));
    // The radio relays it (to the whole microsecond): following.
    b.wait_until(&name, "the radio following", SLOW, |s| {
        s.takeover == "following" && equal(&s.radio, &first)
    });
    // The instructor takes over, and gives back.
    instructor.store(true, SeqCst);
    let sticks = INSTRUCTOR_US.map(|u| u as f64);
    b.wait_until(&name, "the instructor's takeover", SLOW, |s| {
        s.takeover == "overridden" && equal(&s.radio, &sticks) && equal(&s.line, &first)
    });
    instructor.store(false, SeqCst);
    b.wait_until(&name, "the radio following again", SLOW, |s| {
        s.takeover == "following"
    });

    // New commands show within the bounds.
    for (i, values) in [
        [
            1000.0, 2000.0, 1500.0, 1250.0, 1500.0, 1500.0, 1500.0, 1500.0,
        ],
        [
            1700.0, 1300.0, 1900.0, 1800.0, 1100.0, 1500.0, 1500.0, 1999.0,
        ],
        [
            1234.0, 1567.0, 1100.0, 1890.0, 1500.0, 1500.0, 1000.0, 1500.0,
        ],
    ]
    .iter()
    .enumerate()
    {
        let sent = commands.send(values);
        let on_command = b.wait_until(&name, "a new command", SLOW, |s| equal(&s.command, values));
        let on_line = b.wait_until(&name, "a new command on the line", SLOW, |s| {
            equal(&s.line, values)
        });
        let (c, l) = (since(sent, on_command), since(sent, on_line));
        eprintln!("command {i}: shown after {c:?}, on the line after {l:?}");
        assert!(c <= COMMAND_SHOWN, "command {i} shown after {c:?}");
        assert!(
            l <= LINE_SHOWN,
            "command {i} on the line column after {l:?}"
        );
    }

    // The commands stop: failsafe, the defaults on the line.
    let last = commands.pause();
    let at = b.wait_until(&name, "failsafe", SLOW, |s| s.state == "failsafe");
    let f = since(last, at);
    eprintln!("failsafe shown {f:?} after the last command");
    assert!(f <= FAILSAFE_SHOWN, "failsafe shown after {f:?}");
    b.wait_until(&name, "the defaults on the line", SLOW, |s| {
        equal(&s.line, &defaults)
    });

    // ppmd restarts: "not running" meanwhile, then live again.
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    b.wait_until(&name, "ppmd not running", SLOW, |s| {
        s.state == "not_running" && s.ppmd == "not running" && s.conn == "ok"
    });
    ppmd = start_ppmd(&sb, &cfg, "line2.trace");
    let after_ppmd = [
        1400.0, 1600.0, 1200.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0,
    ];
    commands.send(&after_ppmd);
    b.wait_until(&name, "commands flying after ppmd's restart", SLOW, |s| {
        s.state == "flying" && s.ppmd.starts_with("running") && equal(&s.line, &after_ppmd)
    });

    // udp-ingress restarts: "not running" meanwhile, then live again.
    assert!(ingress
        .signal_and_wait(Signal::SIGINT, 10 * SECOND)
        .success());
    b.wait_until(&name, "udp-ingress not running", SLOW, |s| {
        s.ingress.starts_with("not running")
    });
    ingress = sb.start_ingress(&cfg, &[]);
    let after_ingress = [
        1900.0, 1100.0, 1600.0, 1300.0, 1500.0, 1700.0, 1500.0, 1500.0,
    ];
    commands.send(&after_ingress);
    b.wait_until(
        &name,
        "commands flying after udp-ingress's restart",
        SLOW,
        |s| {
            s.ingress.starts_with("running")
                && equal(&s.command, &after_ingress)
                && equal(&s.line, &after_ingress)
        },
    );
    // Long enough for a few timing snapshots: the histogram has the
    // seconds since the restart.
    std::thread::sleep(3 * SECOND);

    let png = b.screenshot();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"), "a PNG");
    assert!(png.len() > 10_000, "a screenshot of {} bytes", png.len());
    if let Some(path) = std::env::var_os("PPM_WEB_SCREENSHOT") {
        std::fs::write(&path, &png).expect("writing PPM_WEB_SCREENSHOT");
        eprintln!("screenshot written to {}", Path::new(&path).display());
    }
    let errors = b.console_errors();
    assert!(errors.is_empty(), "the browser's console: {errors:#?}");

    drop(commands);
    radio_stop.store(true, SeqCst);
    radio.join().unwrap();
    for (p, signal) in [
        (&mut web, Signal::SIGTERM),
        (&mut ppmd, Signal::SIGTERM),
        (&mut ingress, Signal::SIGINT),
    ] {
        assert!(
            p.signal_and_wait(signal, 10 * SECOND).success(),
            "{}",
            p.log_text()
        );
    }
}

/// One HTTP/1.0 request to `addr`; the status code and the whole answer.
/// A CRSF output's telemetry on the page: a flight controller (a
/// pseudo-terminal at ppmd's serial output) sends its battery, attitude and
/// flight mode; the page's "flight controller" row shows them, and it is
/// hidden for an output without telemetry. No console error.
#[test]
fn the_page_shows_a_flight_controllers_telemetry() {
    let sb = Sandbox::new("web-crsf");
    let name = sb.name.clone();
    let pty = Pty::open().expect("a pseudo-terminal");
    let cfg = sb.config(&format!(
        "{GENTLE_RT}[ppmd]\noutput = \"serial:{}\"\n[ppm]\nprotocol = \"crsf\"\n",
        pty.slave.display()
    ));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg.to_str().unwrap()], "ppmd");
    ppmd.wait_for_log("telemetry: reading", SLOW);
    let (mut web, addr) = start_web(&sb, &cfg);
    let mut b = Browser::open(&sb.dir, &format!("http://{addr}/"));
    let frame = |kind: u8, payload: &[u8]| {
        ppm_shared::crsf::frame(ppm_shared::crsf::ADDRESS_FLIGHT_CONTROLLER, kind, payload)
    };
    // 16.8 V, 12.3 A, 75 %; roll -0.5 rad (-29 deg); "ANGL".
    let mut burst = frame(0x08, &[0x00, 0xA8, 0x00, 0x7B, 0x00, 0x04, 0xD2, 0x4B]);
    burst.extend(frame(0x1E, &[0x04, 0xD2, 0xEC, 0x78, 0x7A, 0xB7]));
    burst.extend(frame(0x21, b"ANGL\0"));
    let end = Instant::now() + SLOW;
    let shown = loop {
        pty.send(&burst).expect("writing to the pty");
        let f = b.field(&name, "telemetry");
        if let Some((text, true)) = &f {
            if text.contains("ANGL") {
                break text.clone();
            }
        }
        assert!(Instant::now() < end, "no telemetry on the page: {f:?}");
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(
        shown,
        "receiving; 16.8 V, 12.3 A, 75 %; ANGL; roll -29\u{b0} pitch 7\u{b0} yaw 180\u{b0}"
    );
    let errors = b.console_errors();
    assert!(errors.is_empty(), "console errors: {errors:?}");
    drop(b);
    assert!(web.signal_and_wait(Signal::SIGINT, 10 * SECOND).success());
    ppm_tests::stop_all(&mut ppmd, &mut [&mut ingress]);
    let _ = pty.finish();
}

fn http(addr: &str, method: &str, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).expect("connecting to ppm-web");
    s.set_read_timeout(Some(10 * SECOND)).unwrap();
    write!(s, "{method} {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let code = text
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP answer: {text}"));
    (code, text)
}

#[test]
fn the_server_is_read_only_and_says_what_is_wrong() {
    let sb = Sandbox::new("web-server");
    let cfg = sb.config(GENTLE_RT);
    // Nothing else runs: the page still answers, saying so.
    let (mut web, addr) = start_web(&sb, &cfg);
    let (code, page) = http(&addr, "GET", "/");
    assert_eq!(code, 200, "{page}");
    assert!(page.contains("src=\"/app.js\""), "{page}");
    assert!(page.contains("Content-Security-Policy"), "{page}");
    for path in ["/app.js", "/style.css"] {
        assert_eq!(http(&addr, "GET", path).0, 200, "{path}");
    }
    let end = Instant::now() + SLOW;
    let state: Value = loop {
        let (code, text) = http(&addr, "GET", "/api/state");
        assert_eq!(code, 200, "{text}");
        let body = text.split("\r\n\r\n").nth(1).unwrap_or_default();
        let v: Value = serde_json::from_str(body).expect("JSON");
        if v["outputs"].as_array().is_some_and(|o| !o.is_empty()) {
            break v;
        }
        assert!(Instant::now() < end, "no outputs in {v}");
        std::thread::sleep(Duration::from_millis(50));
    };
    let o = &state["outputs"][0];
    assert_eq!(o["name"], sb.name.as_str());
    assert_eq!(o["line_state"], "not_running");
    assert_eq!(o["ingress"]["running"], false);
    assert_eq!(http(&addr, "GET", "/nothing-here").0, 404);
    for method in ["POST", "PUT", "DELETE", "PATCH"] {
        let (code, text) = http(&addr, method, "/api/state");
        assert_eq!(code, 405, "{method}: {text}");
        assert!(text.contains("Allow: GET, HEAD"), "{text}");
    }
    // Asked by a name that is not this machine's address (DNS rebinding): 421.
    let mut c = TcpStream::connect(&addr).unwrap();
    c.set_read_timeout(Some(10 * SECOND)).unwrap();
    write!(
        c,
        "GET /api/state HTTP/1.1\r\nHost: evil.example:5080\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    c.read_to_string(&mut text).unwrap();
    assert!(text.starts_with("HTTP/1.1 421"), "{text}");
    assert!(!text.contains("outputs"), "{text}");

    // A port in use: 75, and the message says so.
    let run = |args: &[&str]| {
        let out = std::process::Command::new(bin("ppm-web"))
            .args(args)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let c = cfg.to_str().unwrap();
    let (code, err) = run(&["--config", c, "--listen", &addr]);
    assert_eq!(code, Some(75), "{err}");
    assert!(err.contains("in use"), "{err}");
    // An address this machine does not have (TEST-NET-1): 78.
    let (code, err) = run(&["--config", c, "--listen", "192.0.2.1:5080"]);
    assert_eq!(code, Some(78), "{err}");
    assert!(err.contains("no interface"), "{err}");
    // Flags that do not parse, an output the configuration lacks: 2.
    for bad in [
        &["--listen", "localhost"][..],
        &["--allow", "10.0.0.0/33"],
        &["--config", c, "--name", "nope"],
    ] {
        let (code, err) = run(bad);
        assert_eq!(code, Some(2), "{bad:?}: {err}");
    }
    // Only allowed clients: a ppm-web that allows another block refuses
    // this machine.
    let other = sb.spawn(
        "ppm-web",
        &[
            "--config",
            c,
            "--listen",
            "127.0.0.1:0",
            "--allow",
            "10.9.0.0/16",
        ],
        "web-other",
    );
    other.wait_for_log("serving http://", SLOW);
    let other_addr = other
        .log_text()
        .split("serving http://")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .unwrap()
        .to_string();
    assert_eq!(http(&other_addr, "GET", "/api/state").0, 403);
    assert!(web.signal_and_wait(Signal::SIGINT, 10 * SECOND).success());
}

/// docs/programs.md lists ppm-web with every option its --help shows, and
/// docs/web.md states a bound on the page's size that holds.
#[test]
fn the_docs_list_every_option_and_the_page_size() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let programs = std::fs::read_to_string(root.join("docs/programs.md")).unwrap();
    let line = programs
        .lines()
        .find(|l| l.starts_with("ppm-web "))
        .expect("docs/programs.md has a ppm-web synopsis");
    let help = std::process::Command::new(bin("ppm-web"))
        .arg("--help")
        .output()
        .unwrap();
    let help = String::from_utf8(help.stdout).unwrap();
    for word in help.split_whitespace() {
        let opt = word.trim_end_matches(',');
        if opt.starts_with("--") && !["--help", "--version"].contains(&opt) {
            assert!(
                line.contains(opt),
                "docs/programs.md's ppm-web line lacks {opt}"
            );
        }
    }
    let web = std::fs::read_to_string(root.join("docs/web.md")).unwrap();
    let bytes = ppm_tools::web::assets::page_bytes();
    let stated: usize = web
        .split(" KiB")
        .next()
        .and_then(|s| s.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .expect("docs/web.md states the page's size in KiB (`under N KiB`)");
    assert!(
        bytes <= stated * 1024,
        "the page is {bytes} bytes, docs/web.md says under {stated} KiB"
    );
}
