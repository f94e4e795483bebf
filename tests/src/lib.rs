//! Helpers for the whole-system tests: build and locate the real binaries,
//! run them as separate processes in an isolated temporary directory (own
//! shared-memory root, own output name, own UDP port), and stop them.
//!
//! - [`Sandbox`]: one test's directory, configuration, port and processes.
//! - [`Scratch`], [`Proc`], [`free_udp_port`]: the process harness,
//!   `ppm_tools::harness` (the one `ppm-bench` runs its programs with),
//!   re-exported.
//! - [`status`], [`StatusReply`], [`reply_of`]: a status query and its typed reply.
//! - Traces, frames, pacing, Python and systemd helpers.

use std::fs::File;
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::OnceLock;
use std::time::Duration;

pub use ppm_shared::status::StatusReply;
pub use ppm_tools::harness::{free_udp_port, Proc, Pty, Scratch};

/// The directory holding the workspace's binaries, built once per test run
/// with the same profile as the tests.
pub fn bin_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        // target/<profile>/deps/<test binary>
        let exe = std::env::current_exe().expect("current_exe");
        let dir = exe
            .parent()
            .and_then(Path::parent)
            .expect("target/<profile>");
        let release = dir.file_name().is_some_and(|n| n == "release");
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut cmd = Command::new(cargo);
        cmd.args([
            "build",
            "--bins",
            "-p",
            "ppmd",
            "-p",
            "udp-ingress",
            "-p",
            "ppm-tools",
        ]);
        if release {
            cmd.arg("--release");
        }
        let status = cmd
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .status()
            .expect("running cargo build for the binaries");
        assert!(status.success(), "building the binaries failed");
        dir.to_owned()
    })
}

/// Path of one of the workspace's binaries.
pub fn bin(name: &str) -> PathBuf {
    bin_dir().join(name)
}

/// An `[rt]` section for tests that run several ppmd at once: the normal
/// scheduler, any CPU, the CPU's idle states left alone, and a run without
/// the privileges for more allowed.
pub const GENTLE_RT: &str =
    "[rt]\npriority = 0\ncpu = \"none\"\ncpu_dma_latency = false\nallow_degraded = true\n";

/// How long a program may take to start (debug builds on a busy machine).
const STARTUP: Duration = Duration::from_secs(30);

/// A fresh directory for one test, removed when the test passes: a
/// [`Scratch`] (its `dir` and `port`, through `Deref`) with a unique
/// output name, and the test's turn.
pub struct Sandbox {
    scratch: Scratch,
    /// A unique output name for this test.
    pub name: String,
    _turn: Turn,
}

impl std::ops::Deref for Sandbox {
    type Target = Scratch;

    fn deref(&self) -> &Scratch {
        &self.scratch
    }
}

/// The tests of one test binary take turns, one whole-system test at a
/// time: each test's ppmd pins its SCHED_FIFO timing thread to the same CPU
/// (`rt.cpu = "last"`), and two spinning there at one priority hold each
/// other up for milliseconds, which now cuts their frames short at late
/// edges. A test that makes several sandboxes (on one thread) takes one
/// turn.
struct Turn(#[allow(dead_code)] Option<std::sync::MutexGuard<'static, ()>>);

static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

thread_local! {
    static TURNS_HELD: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

impl Turn {
    fn take() -> Turn {
        let held = TURNS_HELD.with(|h| h.replace(h.get() + 1));
        Turn((held == 0).then(|| ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())))
    }
}

impl Drop for Turn {
    fn drop(&mut self) {
        TURNS_HELD.with(|h| h.set(h.get() - 1));
    }
}

impl Sandbox {
    /// A new sandbox for the test `label`.
    pub fn new(label: &str) -> Sandbox {
        let turn = Turn::take();
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let name = format!(
            "t{}x{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        );
        let scratch =
            Scratch::new(&format!("ppm-test-{label}-{name}")).expect("creating the test directory");
        Sandbox {
            scratch,
            name,
            _turn: turn,
        }
    }

    /// Writes `ppm.toml` with this sandbox's name, port and shared-memory
    /// root, plus `extra` TOML (sections after the top-level keys). Unless
    /// `extra` has an `[rt]` section, a degraded run is allowed, so the tests
    /// also pass without the privileges for real-time scheduling.
    pub fn config(&self, extra: &str) -> PathBuf {
        self.config_with_ingress("", extra)
    }

    /// Like [`Sandbox::config`], with the lines `ingress` added to the
    /// `[ingress]` section.
    pub fn config_with_ingress(&self, ingress: &str, extra: &str) -> PathBuf {
        let path = self.dir.join("ppm.toml");
        let rt = if extra.contains("[rt]") {
            ""
        } else {
            "[rt]\nallow_degraded = true\n"
        };
        // The late-edge guard at its widest (20 us) unless the test sets it:
        // on a loaded test machine a few-us guard cuts frames short often,
        // which the tests of the guard cover; elsewhere it would only make
        // frame counts vary with the load.
        // Grid timing unless the test sets the timing: the tests that set
        // none count frames on the grid (follow, the default, is tested
        // where it is set).
        let mut ppm_keys = String::new();
        if !extra.contains("late_edge_guard_us") {
            ppm_keys += "late_edge_guard_us = 20\n";
        }
        if !extra.contains("timing") {
            ppm_keys += "timing = \"grid\"\n";
        }
        let extra = if let Some(at) = extra.find("[ppm]\n") {
            let (head, tail) = extra.split_at(at + "[ppm]\n".len());
            format!("{head}{ppm_keys}{tail}")
        } else {
            format!("{extra}\n[ppm]\n{ppm_keys}")
        };
        let text = format!(
            "name = \"{}\"\n[ingress]\nlisten = \"127.0.0.1:{}\"\n{ingress}\n[ipc]\nroot = \"{}\"\n{rt}{extra}\n",
            self.name,
            self.port,
            self.dir.join("ipc").display()
        );
        std::fs::write(&path, text).expect("writing the config");
        path
    }

    /// Writes `text` to the file `name` in the sandbox with permissions
    /// `mode` (e.g. a key file, 0o600); returns its path.
    pub fn write_file(&self, name: &str, text: &str, mode: u32) -> PathBuf {
        use std::os::unix::fs::PermissionsExt;
        let path = self.dir.join(name);
        std::fs::write(&path, text).expect("writing a file in the sandbox");
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(mode))
            .expect("setting a file's mode");
        path
    }

    /// The ingress's address.
    pub fn addr(&self) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], self.port))
    }

    /// Starts ppmd with the configuration `cfg` on the simulated line
    /// `<dir>/<trace>` (log `ppmd`) and waits until it takes commands.
    pub fn start_ppmd(&self, cfg: &Path, trace: &str) -> Proc {
        let output = format!("sim:{}", self.dir.join(trace).display());
        let cfg = cfg.to_str().expect("a UTF-8 path");
        let p = self.spawn("ppmd", &["--config", cfg, "--output", &output], "ppmd");
        p.wait_for_log("commands from", STARTUP);
        p
    }

    /// Starts udp-ingress with the configuration `cfg` and `args` (log
    /// `ingress`) and waits until it listens.
    pub fn start_ingress(&self, cfg: &Path, args: &[&str]) -> Proc {
        let mut all = vec!["--config", cfg.to_str().expect("a UTF-8 path")];
        all.extend_from_slice(args);
        let p = self.spawn("udp-ingress", &all, "ingress");
        p.wait_for_log("listening on", STARTUP);
        p
    }

    /// Starts a binary with arguments; its stderr goes to `<dir>/<log>.log`.
    pub fn spawn(&self, binary: &str, args: &[&str], log: &str) -> Proc {
        self.spawn_with_env(binary, args, &[], log)
    }

    /// [`Sandbox::spawn`] with environment variables added.
    pub fn spawn_with_env(
        &self,
        binary: &str,
        args: &[&str],
        env: &[(&str, &str)],
        log: &str,
    ) -> Proc {
        let mut cmd = Command::new(bin(binary));
        cmd.args(args)
            .envs(env.iter().copied())
            .current_dir(&self.dir)
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(File::create(self.dir.join(format!("{log}.out"))).unwrap());
        Proc::start(cmd, self.dir.join(format!("{log}.log")))
            .unwrap_or_else(|e| panic!("starting {binary}: {e}"))
    }
}

/// Sends datagrams from one socket.
pub struct Sender {
    socket: UdpSocket,
    to: SocketAddr,
}

impl Sender {
    /// A sender to `to`.
    pub fn new(to: SocketAddr) -> Sender {
        Sender {
            socket: UdpSocket::bind("127.0.0.1:0").expect("binding a sender socket"),
            to,
        }
    }

    /// Sends one datagram.
    pub fn send(&self, bytes: &[u8]) {
        self.socket.send_to(bytes, self.to).expect("sending");
    }
}

/// One status query to an ingress at `to`, and its reply.
pub fn status(to: SocketAddr) -> StatusReply {
    let socket = UdpSocket::bind("127.0.0.1:0").expect("binding a socket");
    socket
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    socket
        .send_to(&ppm_shared::protocol::padded_status_query(), to)
        .unwrap();
    let mut buf = [0u8; 65_536];
    let (n, _) = socket.recv_from(&mut buf).expect("a status reply");
    serde_json::from_slice(&buf[..n]).unwrap_or_else(|e| {
        panic!(
            "not a status reply ({e}): {}",
            String::from_utf8_lossy(&buf[..n])
        )
    })
}

/// A status reply read as its type from JSON that carried it (the reply
/// parsed for its wire form, or as the Python package hands it on).
pub fn reply_of(raw: &serde_json::Value) -> StatusReply {
    serde_json::from_value(raw.clone())
        .unwrap_or_else(|e| panic!("not a status reply ({e}): {raw}"))
}

/// How many commands a status reply counts as taken in: applied, or
/// superseded by a newer one before it was published.
pub fn handed_over(status: &StatusReply) -> u64 {
    status.datagrams.applied + status.datagrams.superseded
}

/// How many datagrams a status reply counts as rejected, for any reason.
pub fn rejected_total(status: &StatusReply) -> u64 {
    status.datagrams.rejected.total()
}

/// Writes `ppm.toml` with two outputs in grid timing, `<name>a` (the
/// defaults otherwise, on the sandbox's port, line `sim:a.trace`, frame
/// log `a.jsonl`) and `<name>b` (line `sim:b.trace`, on `port_b`), with
/// `b_keys` added to b's entry (keys, then its `[outputs.*]` sections);
/// returns the path and the names. Like [`Sandbox::config`], it sets the
/// late-edge guard to 20 us: these debug builds, two outputs in one
/// thread, write each simulated edge as a line of text.
pub fn two_outputs(sb: &Sandbox, port_b: u16, b_keys: &str) -> (PathBuf, [String; 2]) {
    let (a, b) = (format!("{}a", sb.name), format!("{}b", sb.name));
    let path = sb.dir.join("ppm.toml");
    let text = format!(
        "[ppm]\ntiming = \"grid\"\nlate_edge_guard_us = 20\n\
         [ingress]\nlisten = \"127.0.0.1:{}\"\n[ipc]\nroot = \"{}\"\n[rt]\nallow_degraded = true\n\n\
         [[outputs]]\nname = \"{a}\"\noutput = \"sim:a.trace\"\nframe_log = \"a.jsonl\"\n\n\
         [[outputs]]\nname = \"{b}\"\noutput = \"sim:b.trace\"\ningress.listen = \"127.0.0.1:{port_b}\"\n{b_keys}\n",
        sb.port,
        sb.dir.join("ipc").display(),
    );
    std::fs::write(&path, text).expect("writing the config");
    (path, [a, b])
}

/// Starts one ppmd with the configuration at `cfg` (several outputs) and one
/// `udp-ingress --name NAME` per name (logs `ing-0`, `ing-1`, ...), and waits
/// until ppmd has set up its last output and every ingress listens.
pub fn start_outputs(sb: &Sandbox, cfg: &Path, names: &[&str]) -> (Proc, Vec<Proc>) {
    let cfg = cfg.to_str().expect("a UTF-8 path");
    let ppmd = sb.spawn("ppmd", &["--config", cfg], "ppmd");
    let ingresses: Vec<Proc> = names
        .iter()
        .enumerate()
        .map(|(i, name)| {
            sb.spawn(
                "udp-ingress",
                &["--config", cfg, "--name", name],
                &format!("ing-{i}"),
            )
        })
        .collect();
    let last = names.last().expect("an output");
    let from = ppm_shared::ipc::command_service_name(last);
    ppmd.wait_for_log(&format!("commands from `{from}`"), STARTUP);
    for ing in &ingresses {
        ing.wait_for_log("listening on", STARTUP);
    }
    (ppmd, ingresses)
}

/// Stops ppmd (SIGTERM) and the ingresses (SIGINT), each of which must
/// exit with status 0.
pub fn stop_all(ppmd: &mut Proc, ingresses: &mut [&mut Proc]) {
    let wait = Duration::from_secs(10);
    assert!(
        ppmd.signal_and_wait(nix::sys::signal::Signal::SIGTERM, wait)
            .success(),
        "{}",
        ppmd.log_text()
    );
    for ing in ingresses {
        assert!(
            ing.signal_and_wait(nix::sys::signal::Signal::SIGINT, wait)
                .success(),
            "{}",
            ing.log_text()
        );
    }
}

/// Reads and decodes a sim trace by scheduled time.
pub fn read_trace(path: &Path) -> ppm_shared::trace::Trace {
    let f = File::open(path).unwrap_or_else(|e| panic!("opening {}: {e}", path.display()));
    ppm_shared::trace::Trace::read(std::io::BufReader::new(f)).expect("reading the trace")
}

/// Whether frame `f` carries `want`: its channels are `want`'s first ones
/// (all of them for a whole frame; a frame cut short at a late edge has only
/// the channels before that edge, exact) and, past `want`, anything.
pub fn carries(f: &ppm_shared::decode::DecodedFrame, want: &[u64]) -> bool {
    let got = f.channels_us();
    let n = got.len().min(want.len());
    got[..n] == want[..n]
}

/// Channel `i` (from 0) of every frame of a sim trace that carried it,
/// decoded by scheduled time: whole frames and those cut short after it.
pub fn channel_of_frames(trace: &ppm_shared::trace::Trace, i: usize) -> Vec<u64> {
    trace
        .decode(false)
        .iter()
        .filter_map(|f| f.channels_us().get(i).copied())
        .collect()
}

/// The frames a sim trace carries whole (as many channels as its header
/// names), decoded by scheduled time. ppmd runs these tests without
/// real-time priority, so on a loaded machine a frame is now and then
/// aborted at a late edge: it shows as a short frame (the channels before
/// the abort, exact), left out here.
pub fn whole_frames(trace: &ppm_shared::trace::Trace) -> Vec<ppm_shared::decode::DecodedFrame> {
    let frames = trace.decode(false);
    let n = trace.channels.unwrap_or_else(|| {
        frames
            .iter()
            .map(|f| f.channels_ns.len())
            .max()
            .unwrap_or(0)
    });
    frames
        .into_iter()
        .filter(|f| f.channels_ns.len() == n)
        .collect()
}

/// Calls `send(i)` for i = 0..n, one call every 20 ms (50 Hz) from now, on
/// a fixed schedule (a slow call does not shift the later ones).
pub fn at_50hz(n: u64, mut send: impl FnMut(u64)) {
    let start = ppm_shared::time::now_ns();
    for i in 0..n {
        send(i);
        let next = start + (i + 1) * 20_000_000;
        let now = ppm_shared::time::now_ns();
        if next > now {
            std::thread::sleep(Duration::from_nanos(next - now));
        }
    }
}

/// The first ```python block of the section a heading line (`## Quick
/// start`, `### From a MAVLink groundstation`) opens in `file` (relative
/// to the repository), up to the next heading of its level or above.
pub fn python_block(file: &str, heading: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(file);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{file}: {e}"));
    let level = heading.chars().take_while(|&c| c == '#').count();
    let mut lines = text
        .lines()
        .skip_while(|l| *l != heading)
        .skip(1)
        .take_while(|l| {
            let h = l.chars().take_while(|&c| c == '#').count();
            !(h > 0 && h <= level && l[h..].starts_with(' '))
        });
    let mut code = String::new();
    if lines.any(|l| l == "```python") {
        for l in lines.take_while(|l| *l != "```") {
            code.push_str(l);
            code.push('\n');
        }
    }
    assert!(
        !code.is_empty(),
        "{file}: no python block under \"{heading}\""
    );
    code
}

/// The Python groundstation package in the source tree (`import ppm`).
pub const PYTHON_PACKAGE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../tools/python");

/// Runs python3 with `args` in `dir`, with the modules under `pythonpath`
/// importable (e.g. [`PYTHON_PACKAGE`]) and no bytecode written; returns
/// its standard output. The test fails, with both outputs, when python3
/// fails or is missing.
pub fn python3(dir: &Path, pythonpath: &str, args: &[&str]) -> String {
    let out = Command::new("python3")
        .args(args)
        .env("PYTHONPATH", pythonpath)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .current_dir(dir)
        .output()
        .expect("python3 is needed for this test (apt-get install python3)");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "python3 {args:?} failed ({}):\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// The `key=value` directives of a systemd unit in `deploy/`, in order
/// (comments and section headers dropped).
pub fn unit_directives(unit: &str) -> Vec<(String, String)> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deploy")
        .join(unit);
    std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#') && !l.starts_with('['))
        .map(|l| {
            let (k, v) = l
                .split_once('=')
                .unwrap_or_else(|| panic!("{unit}: `{l}` is not key=value"));
            (k.trim().to_string(), v.trim().to_string())
        })
        .collect()
}

/// Every program the workspace builds, in the order the docs list them
/// (and the package ships them).
pub const PROGRAMS: [&str; 11] = [
    "ppmd",
    "udp-ingress",
    "ppm-send",
    "ppm-status",
    "ppm-watch",
    "ppm-capture",
    "ppm-web",
    "jitter",
    "timing-bench",
    "ppm-bench",
    "ppm-interfere",
];

/// Runs `cmd` and returns its standard output; the test fails, with both
/// outputs, unless it succeeds.
pub fn run_ok(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    assert!(
        out.status.success(),
        "{cmd:?} failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Builds the arm64 Debian package with `tools/package arm64`; returns
/// the .deb (target/debian/ppm_VERSION-1_arm64.deb).
pub fn arm64_package() -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    run_ok(
        Command::new(root.join("tools/package"))
            .arg("arm64")
            .current_dir(&root),
    );
    let deb = root.join(format!(
        "target/debian/ppm_{}-1_arm64.deb",
        env!("CARGO_PKG_VERSION")
    ));
    assert!(deb.exists(), "{}", deb.display());
    deb
}
