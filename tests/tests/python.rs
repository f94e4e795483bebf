//! The Python groundstation package (`tools/python`, `import ppm`) against
//! the real udp-ingress and ppmd: every command form lands exactly on the
//! simulated line, signed commands are accepted (also from a restarted
//! groundstation) and those under another key refused as `bad_mac`, status
//! queries get the reply also where padding matters (`status_allow = []`),
//! the package's own unit tests and doctests pass, and `pip install` works.
//!
//! The scripts import the package from the source tree (`PYTHONPATH`), so
//! nothing has to be installed for these tests but python3.

use nix::sys::signal::Signal;
use ppm_shared::protocol::RejectReason;
use ppm_tests::{
    handed_over, python3, read_trace, rejected_total, reply_of, stop_all, Sandbox, GENTLE_RT,
    PYTHON_PACKAGE,
};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

const SECOND: Duration = Duration::from_secs(1);
const KEY_HEX: &str = "8f2a55e0c1d94b7e3a6f0b1c2d3e4f5061728394a5b6c7d8e9f0a1b2c3d4e5f6";
const OTHER_KEY_HEX: &str = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";

/// Runs `code` (with `args` in `sys.argv[1:]`) and parses the last line it
/// prints as JSON.
fn python(sb: &Sandbox, code: &str, args: &[&str]) -> Value {
    let mut all = vec!["-c", code];
    all.extend_from_slice(args);
    let out = python3(&sb.dir, PYTHON_PACKAGE, &all);
    let last = out.lines().last().unwrap_or_default();
    serde_json::from_str(last).unwrap_or_else(|e| panic!("{e}: the script printed:\n{out}"))
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_micros() as u64
}

/// Which of `patterns` (channel values in us) each frame of the trace
/// carries, as runs: `(pattern index, frames)`; a frame matching none fails.
fn runs(trace: &Path, patterns: &[[f64; 8]]) -> Vec<(usize, usize)> {
    let ns: Vec<Vec<u64>> = patterns
        .iter()
        .map(|p| p.iter().map(|us| (us * 1e3).round() as u64).collect())
        .collect();
    let mut runs: Vec<(usize, usize)> = vec![];
    // Every frame, whole or cut short at a late edge (then with the channels
    // before it, exact); one too short to tell the patterns apart is left
    // out.
    for f in read_trace(trace).decode(false) {
        let v = &f.channels_ns;
        let fits: Vec<usize> = (0..ns.len())
            .filter(|&k| *v == ns[k][..v.len().min(ns[k].len())])
            .collect();
        let k = match fits[..] {
            [k] => k,
            [] => panic!(
                "frame at {} ns carries {v:?}, none of {patterns:?}",
                f.start_ns
            ),
            _ => continue,
        };
        match runs.last_mut() {
            Some((last, n)) if *last == k => *n += 1,
            _ => runs.push((k, 1)),
        }
    }
    runs
}

/// Four phases of 25 commands at 50 Hz, one per form, all numbered; then
/// the status reply and the last seq.
const FORMS: &str = r#"
import json, sys, time
import ppm

s = ppm.Sender(sys.argv[1])
phases = [
    lambda: s.send([1100, 1200.5, 1300, 1400]),
    lambda: s.send(ail=1600, ele=1700.25, thr=1250, rud=1450, aux1=1800),
    lambda: s.send_norm(ail=0.2, ele=-0.5, thr=-1, aux2=1),
    lambda: s.send_units(ail=-7.5, ele=5),
]
first = None
start, n = time.monotonic(), 0
for phase in phases:
    for _ in range(25):
        phase()
        first = first or s.last_seq
        n += 1
        time.sleep(max(0.0, start + 0.02 * n - time.monotonic()))
# Refused before sending: nothing of these reaches udp-ingress.
for bad in [
    lambda: s.send([1500], ail=1500),
    lambda: s.send([float("nan")]),
    lambda: s.send(["1500"]),
    lambda: s.send_norm(thr=float("inf")),
    lambda: s.send(yaw=1500),
]:
    try:
        bad()
        raise SystemExit(f"accepted: {bad}")
    except ValueError as e:
        print(e)
print(json.dumps({"first_seq": first, "last_seq": s.last_seq, "status": s.status()}))
"#;

/// Every form, numbered, lands exactly on the line, and the counters say
/// every command was applied and none rejected.
#[test]
fn every_form_lands_exactly_on_the_line() {
    let sb = Sandbox::new("pyforms");
    // Unit ranges for `send_units`: ail -15..15, ele -20..20 (on 1000..2000 us).
    let units = "[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\n\
                 [ppm.channel.ele]\nunit_min = -20.0\nunit_max = 20.0\n";
    let cfg = sb.config(&format!("{GENTLE_RT}{units}"));
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let before = now_us();
    let out = python(&sb, FORMS, &[&sb.addr().to_string()]);
    std::thread::sleep(Duration::from_millis(100));
    stop_all(&mut ppmd, &mut [&mut ingress]);

    // seq: from the time in microseconds, one more per command.
    let (first, last) = (
        out["first_seq"].as_u64().unwrap(),
        out["last_seq"].as_u64().unwrap(),
    );
    assert!(before <= first && first <= now_us(), "{out}");
    assert!(last >= first + 99, "{out}");
    let s = &reply_of(&out["status"]);
    let d = &s.datagrams;
    assert_eq!(d.received, 100, "{s}");
    assert_eq!(handed_over(s), 100, "{s}");
    assert_eq!(d.stale, 0, "{s}");
    assert_eq!(d.clamped, 0, "{s}");
    assert_eq!(rejected_total(s), 0, "{s}");
    assert_eq!(s.newest_seq, Some(last), "{s}");

    // What each form defines (us, 8 channels AETR, throttle default 1000):
    // norm -1..1 on 1000..2000, units -15..15 and -20..20 on 1000..2000.
    let patterns = [
        [
            1100.0, 1200.5, 1300.0, 1400.0, 1500.0, 1500.0, 1500.0, 1500.0,
        ],
        [
            1600.0, 1700.25, 1250.0, 1450.0, 1800.0, 1500.0, 1500.0, 1500.0,
        ],
        [
            1600.0, 1250.0, 1000.0, 1500.0, 1500.0, 2000.0, 1500.0, 1500.0,
        ],
        [
            1250.0, 1625.0, 1000.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0,
        ],
    ];
    let runs = runs(&sb.dir.join("line.trace"), &patterns);
    // Each form's frames in one run, in the order sent, and no frame of
    // anything else. How many frames a run has is the machine's: ppmd
    // aborts a frame at an edge found late (a loaded CI machine cut two
    // runs of about 22 frames to 6), which the late-edge tests cover.
    let order: Vec<usize> = runs.iter().map(|r| r.0).collect();
    assert_eq!(order, [0, 1, 2, 3], "{runs:?}");
}

/// A key file `name` holding `hex` and a newline, with permissions `mode`.
fn write_key(sb: &Sandbox, name: &str, hex: &str, mode: u32) -> PathBuf {
    sb.write_file(name, &format!("{hex}\n"), mode)
}

/// One groundstation run: 25 signed commands (`ch` 1 at VALUE) for output
/// NAME at 50 Hz and, every fifth, one signed with another key; then the
/// status reply.
const SIGNED: &str = r#"
import json, sys, time
import ppm

target, key, other, value, name = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), sys.argv[5]
good = ppm.Sender(target, key_file=key, name=name)
forger = ppm.Sender(target, key_file=other, name=name)
start = time.monotonic()
for i in range(25):
    good.send([value, 1500])
    if i % 5 == 0:
        forger.send([1900, 1500])
    time.sleep(max(0.0, start + 0.02 * (i + 1) - time.monotonic()))
print(json.dumps({"last_seq": good.last_seq, "status": good.status()}))
"#;

/// Signed commands from the key file apply, also from a restarted
/// groundstation (its seq keeps growing); those signed with another key are
/// refused as `bad_mac`; a key file others can read is refused by the
/// package as by udp-ingress.
#[test]
fn signed_commands_apply_and_another_key_is_bad_mac() {
    let sb = Sandbox::new("pysigned");
    let key = write_key(&sb, "auth.key", KEY_HEX, 0o600);
    let other = write_key(&sb, "other.key", OTHER_KEY_HEX, 0o600);
    let open = write_key(&sb, "open.key", KEY_HEX, 0o644);
    let cfg = sb.config_with_ingress(&format!("auth_key = {key:?}"), GENTLE_RT);
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let ingress = sb.start_ingress(&cfg, &[]);
    // Logged just after "listening on", which start_ingress waited for.
    ingress.wait_for_log("commands must be signed", 10 * SECOND);
    let target = sb.addr().to_string();
    let (key, other) = (key.to_str().unwrap(), other.to_str().unwrap());

    let first = python(&sb, SIGNED, &[&target, key, other, "1100", &sb.name]);
    let s = &reply_of(&first["status"]);
    assert_eq!(
        s.datagrams.rejected.count(RejectReason::BadMac),
        5,
        "another key: {s}"
    );
    assert_eq!(rejected_total(s), 5, "{s}");
    assert_eq!(s.newest_seq, first["last_seq"].as_u64(), "{s}");

    // The groundstation restarts: a new process, a new Sender; not a replay.
    let second = python(&sb, SIGNED, &[&target, key, other, "1300", &sb.name]);
    let s = &reply_of(&second["status"]);
    let d = &s.datagrams;
    assert_eq!(d.received, 60, "{s}");
    assert_eq!(handed_over(s), 50, "{s}");
    assert_eq!(d.rejected.count(RejectReason::BadMac), 10, "{s}");
    assert_eq!(rejected_total(s), 10, "no replay, unsigned, no_seq: {s}");
    assert!(
        second["last_seq"].as_u64() > first["last_seq"].as_u64(),
        "{first} {second}"
    );
    assert_eq!(s.newest_seq, second["last_seq"].as_u64(), "{s}");

    // The package refuses what udp-ingress refuses, before sending anything.
    let refused = python(
        &sb,
        r#"
import json, sys
import ppm
errors = []
for call in [
    lambda: ppm.Sender(sys.argv[1], key_file=sys.argv[2], name="x"),
    lambda: ppm.Sender(sys.argv[1], key_file=sys.argv[3], seq=False, name="x"),
    lambda: ppm.Sender(sys.argv[1], key_file=sys.argv[3]),
]:
    try:
        call()
        errors.append(None)
    except (ppm.KeyFileError, ValueError) as e:
        errors.append(str(e))
print(json.dumps(errors))
"#,
        &[&target, open.to_str().unwrap(), key],
    );
    let open_err = refused[0].as_str().unwrap_or_default();
    assert!(
        open_err.contains("chmod 600") && open_err.contains("open.key"),
        "{refused}"
    );
    assert!(
        refused[1].as_str().unwrap_or_default().contains("seq=True"),
        "{refused}"
    );
    assert!(
        refused[2]
            .as_str()
            .unwrap_or_default()
            .contains("a key needs name="),
        "{refused}"
    );

    std::thread::sleep(Duration::from_millis(100));
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let patterns = [
        [
            1100.0, 1500.0, 1000.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0,
        ],
        [
            1300.0, 1500.0, 1000.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0,
        ],
    ];
    // 1100, then 1300, and nothing else: a run has one frame at the least,
    // and one of each is all the order needs (how many a loaded machine
    // cuts short is its business).
    let runs = runs(&sb.dir.join("line.trace"), &patterns);
    assert_eq!(
        runs.iter().map(|r| r.0).collect::<Vec<_>>(),
        [0, 1],
        "{runs:?}"
    );
}

/// Two targets, one sender each: `status()` returns each one's reply as a
/// dict, also from an ingress with `status_allow = []`, where an unpadded
/// query gets only `{"pad_to": N}`.
#[test]
fn status_returns_the_reply_also_where_padding_matters() {
    let strict = Sandbox::new("pystatus");
    let open = Sandbox::new("pystatus2");
    let strict_cfg = strict.config_with_ingress("status_allow = []", GENTLE_RT);
    let open_cfg = open.config(GENTLE_RT);
    let _a = strict.start_ingress(&strict_cfg, &[]);
    let _b = open.start_ingress(&open_cfg, &[]);
    let out = python(
        &strict,
        r#"
import json, socket, sys
import ppm

targets = sys.argv[1:]
host, port = ppm.parse_target(targets[0])
with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
    raw.settimeout(5)
    raw.sendto(b'{"get":"status"}', (host, port))
    short = json.loads(raw.recv(65536))
senders = [ppm.Sender(t) for t in targets]
for i, s in enumerate(senders):
    for _ in range(3 + 2 * i):
        s.send([1200])
print(json.dumps({"short": short, "replies": [s.status(timeout=5) for s in senders]}))
"#,
        &[&strict.addr().to_string(), &open.addr().to_string()],
    );
    let pad_to = out["short"]["pad_to"].as_u64();
    assert!(
        pad_to.is_some_and(
            |n| (100..=ppm_shared::protocol::STATUS_QUERY_PADDED_LEN as u64).contains(&n)
        ),
        "the unpadded query: {out}"
    );
    for (i, want) in [3, 5].into_iter().enumerate() {
        // The dict as the package returns it: the reply's own members.
        let raw = &out["replies"][i];
        assert!(raw.is_object() && raw["datagrams"].is_object(), "{raw}");
        assert!(
            raw["uptime_s"].as_f64().is_some() && raw.get("ppmd").is_some(),
            "{raw}"
        );
        let s = &reply_of(raw);
        assert_eq!(s.datagrams.received, want, "{s}");
        assert_eq!(handed_over(s), want, "{s}");
        assert_eq!(rejected_total(s), 0, "{s}");
    }
    let strict_reply = reply_of(&out["replies"][0]);
    assert_eq!(strict_reply.status_requests, 2, "{strict_reply}");
    assert_eq!(
        strict_reply.status_short, 1,
        "only the unpadded query was short: {strict_reply}"
    );
}

/// The package's own tests: its unit tests (stand-in servers, key files,
/// input checks) and its doctests (the README's test vector).
#[test]
fn the_packages_unit_tests_and_doctests_pass() {
    let dir = Path::new(PYTHON_PACKAGE);
    python3(
        dir,
        PYTHON_PACKAGE,
        &["-m", "unittest", "discover", "-s", "tests"],
    );
    python3(dir, PYTHON_PACKAGE, &["-m", "doctest", "ppm/__init__.py"]);
}

/// The package pads its status queries as the Rust tools do (the size
/// the largest reply needs: shared/src/protocol/status_query.rs).
#[test]
fn the_package_pads_status_queries_as_the_tools_do() {
    let out = python3(
        Path::new(PYTHON_PACKAGE),
        PYTHON_PACKAGE,
        &["-c", "import ppm; print(len(ppm.status_query()))"],
    );
    assert_eq!(
        out.trim(),
        ppm_shared::protocol::STATUS_QUERY_PADDED_LEN.to_string()
    );
}

/// `pip install tools/python` installs a package that imports. pip builds in
/// the source directory (it leaves `build/` and `*.egg-info` there), so it
/// installs from a copy, into a directory of its own.
#[test]
fn pip_installs_the_package() {
    let pip = Command::new("python3")
        .args(["-m", "pip", "--version"])
        .output();
    if !pip.as_ref().is_ok_and(|o| o.status.success()) {
        let why = "python3 -m pip is not available (apt-get install python3-pip)";
        assert!(std::env::var_os("CI").is_none(), "{why}: needed in CI");
        println!("skipped: {why}");
        return;
    }
    let sb = Sandbox::new("pypip");
    let src = sb.dir.join("src");
    std::fs::create_dir_all(src.join("ppm")).unwrap();
    std::fs::copy(
        format!("{PYTHON_PACKAGE}/pyproject.toml"),
        src.join("pyproject.toml"),
    )
    .unwrap();
    for entry in std::fs::read_dir(format!("{PYTHON_PACKAGE}/ppm")).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, src.join("ppm").join(path.file_name().unwrap())).unwrap();
        }
    }
    let site = sb.dir.join("site");
    let out = Command::new("python3")
        .args(["-m", "pip", "install", "--quiet", "--target"])
        .arg(&site)
        .arg(&src)
        .env("PIP_DISABLE_PIP_VERSION_CHECK", "1")
        .env("PIP_ROOT_USER_ACTION", "ignore")
        .env("PIP_NO_INPUT", "1")
        .current_dir(&sb.dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "pip install failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(site.join("ppm/py.typed").is_file(), "the type-hint marker");
    let site = site.to_str().unwrap();
    let printed = python3(
        &sb.dir,
        site,
        &[
            "-c",
            "import ppm; print(ppm.__file__); print(ppm.sign(bytes(range(32)), 'x'))",
        ],
    );
    assert!(
        printed.starts_with(site),
        "imported from elsewhere: {printed}"
    );
}
