//! ppmd under `Type=notify` with a watchdog, against a stand-in for
//! systemd's notify socket: READY=1 once it runs, WATCHDOG=1 while its timing
//! loop makes progress, none while the timing thread alone is stopped (the
//! rest of the process lives on, as with a hung loop), again once it moves,
//! and STOPPING=1 at SIGTERM.

use nix::sys::ptrace;
use nix::sys::signal::Signal;
use nix::sys::wait::{waitpid, WaitPidFlag};
use nix::unistd::Pid;
use ppm_tests::{Proc, Sandbox};
use std::os::unix::net::UnixDatagram;
use std::time::{Duration, Instant};

const SECOND: Duration = Duration::from_secs(1);

/// The messages that reach `sock` within `d`, each with when it came
/// (from the start of the collection).
fn collect(sock: &UnixDatagram, d: Duration) -> Vec<(Duration, String)> {
    let start = Instant::now();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    while start.elapsed() < d {
        sock.set_read_timeout(Some((d - start.elapsed()).max(Duration::from_millis(1))))
            .unwrap();
        if let Ok(n) = sock.recv(&mut buf) {
            got.push((
                start.elapsed(),
                String::from_utf8_lossy(&buf[..n]).into_owned(),
            ));
        }
    }
    got
}

fn pets(msgs: &[(Duration, String)]) -> Vec<Duration> {
    msgs.iter()
        .filter(|(_, m)| m.lines().any(|l| l == "WATCHDOG=1"))
        .map(|(t, _)| *t)
        .collect()
}

/// The thread of `pid` named `name`.
fn thread_named(pid: u32, name: &str) -> Pid {
    for task in std::fs::read_dir(format!("/proc/{pid}/task")).unwrap() {
        let task = task.unwrap();
        let comm = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        if comm.trim() == name {
            return Pid::from_raw(task.file_name().to_str().unwrap().parse().unwrap());
        }
    }
    panic!("ppmd {pid} has no thread `{name}`");
}

/// Starts ppmd on a simulated line, as systemd does a `Type=notify` service:
/// its notify socket (`NOTIFY_SOCKET`) is one of the test's, returned with
/// ppmd; `env` adds to its environment.
fn start_notifying(sb: &Sandbox, env: &[(&str, &str)]) -> (UnixDatagram, Proc) {
    let notify = sb.dir.join("notify.sock");
    let sock = UnixDatagram::bind(&notify).unwrap();
    let cfg = sb.config("");
    let output = format!("sim:{}", sb.dir.join("line.trace").display());
    let mut all = vec![("NOTIFY_SOCKET", notify.to_str().unwrap())];
    all.extend_from_slice(env);
    let args = ["--config", cfg.to_str().unwrap(), "--output", &output];
    let ppmd = sb.spawn_with_env("ppmd", &args, &all, "ppmd");
    (sock, ppmd)
}

#[test]
fn a_stalled_timing_loop_stops_the_watchdog_petting() {
    let sb = Sandbox::new("watchdog");
    let (sock, mut ppmd) = start_notifying(&sb, &[("WATCHDOG_USEC", "1000000")]);

    // READY=1 once the loop runs, then a pet every 250 ms (a quarter of 1 s).
    let start = Instant::now();
    loop {
        assert!(
            start.elapsed() < 30 * SECOND,
            "no READY=1\n{}",
            ppmd.log_text()
        );
        let msgs = collect(&sock, Duration::from_millis(200));
        if msgs.iter().any(|(_, m)| m.lines().any(|l| l == "READY=1")) {
            break;
        }
    }
    let running = pets(&collect(&sock, 2 * SECOND));
    // How many is the function: a pet every quarter of the watchdog's
    // interval (8 in 2 s), neither missing nor one per loop turn.
    assert!(
        (5..=10).contains(&running.len()),
        "pets in 2 s while running: {running:?}\n{}",
        ppmd.log_text()
    );
    assert!(ppmd.log_text().contains("systemd watchdog: 1s"));

    // Stop the timing thread alone: the process and its main thread live on.
    let tid = thread_named(ppmd.pid(), "ppmd-timing");
    ptrace::seize(tid, ptrace::Options::empty()).expect("ptrace seize (needs root)");
    ptrace::interrupt(tid).unwrap();
    waitpid(tid, Some(WaitPidFlag::__WALL)).unwrap();
    let stalled = pets(&collect(&sock, 2 * SECOND));
    // At most the pet already earned when the thread stopped.
    assert!(
        stalled.len() <= 1 && stalled.iter().all(|t| *t < Duration::from_millis(400)),
        "pets while the loop was stopped: {stalled:?}"
    );
    assert!(
        ppmd.log_text()
            .contains("the timing loop has made no progress"),
        "{}",
        ppmd.log_text()
    );

    // Let it go: the petting resumes.
    ptrace::detach(tid, None).unwrap();
    // One pet shows the petting resumed (none came while it was stopped but
    // the one already earned).
    let resumed = pets(&collect(&sock, 2 * SECOND));
    assert!(
        !resumed.is_empty(),
        "pets after the loop resumed: {resumed:?}\n{}",
        ppmd.log_text()
    );
    assert!(ppmd.log_text().contains("makes progress again"));

    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let last = collect(&sock, Duration::from_millis(100));
    assert!(
        last.iter()
            .any(|(_, m)| m.lines().any(|l| l == "STOPPING=1")),
        "{last:?}"
    );
}

/// Without WATCHDOG_USEC (no `WatchdogSec=`): READY=1 and no pets.
#[test]
fn without_a_watchdog_ppmd_only_says_ready() {
    let sb = Sandbox::new("nowatchdog");
    let (sock, mut ppmd) = start_notifying(&sb, &[]);
    ppmd.wait_for_log("commands from", 30 * SECOND);
    let msgs = collect(&sock, SECOND);
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let texts: Vec<&str> = msgs.iter().map(|(_, m)| m.trim_end()).collect();
    assert_eq!(texts, ["READY=1"], "{msgs:?}");
}
