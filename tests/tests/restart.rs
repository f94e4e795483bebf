//! Restarts never fly an old command: with the real binaries, a command is
//! sent and left to expire, then ppmd, udp-ingress or both are restarted
//! (in either order, with SIGTERM or SIGKILL). A ppmd started after the
//! command does exactly what `failsafe.startup` says until a fresh command
//! comes, whatever the command service's history still offers; a ppmd that
//! kept running keeps its failsafe action. Then a fresh command flies.
//! Each failsafe action and both startups are covered, in grid and follow.

use nix::sys::signal::Signal;
use ppm_shared::time::now_ns;
use ppm_tests::{carries, read_trace, Proc, Sandbox, Sender};
use std::time::Duration;

const SECOND: Duration = Duration::from_secs(1);
/// The old command, and the fresh one after the restart (AETR: aileron on
/// channel 1, throttle on channel 3).
const OLD: &[u8] = br#"{"thr": 1900, "ail": 1100}"#;
const OLD_US: [u64; 3] = [1100, 1500, 1900];
const NEW: &[u8] = br#"{"thr": 1200, "ail": 1700}"#;
const NEW_US: [u64; 3] = [1700, 1500, 1200];
const DEFAULTS_US: [u64; 8] = [1500, 1500, 1000, 1500, 1500, 1500, 1500, 1500];

/// Which process restarts, in which order.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Order {
    Ppmd,
    Ingress,
    IngressThenPpmd,
    PpmdThenIngress,
}

/// `count` datagrams of `cmd` at 50 Hz.
fn send(sb: &Sandbox, cmd: &[u8], count: u64) {
    let s = Sender::new(sb.addr());
    ppm_tests::at_50hz(count, |_| s.send(cmd));
}

fn stop(p: &mut Proc, signal: Signal) {
    match signal {
        Signal::SIGKILL => p.kill(),
        _ => assert!(
            p.signal_and_wait(signal, 10 * SECOND).success(),
            "{}",
            p.log_text()
        ),
    }
}

/// Runs one restart case: `after_ms = 200`, the given timing, action and
/// startup.
fn case(order: Order, signal: Signal, follow: bool, action: &str, startup: &str) {
    let label = format!("{order:?} {signal:?} follow={follow} {action}/{startup}");
    let sb = Sandbox::new("restart");
    let timing = if follow { "follow" } else { "grid" };
    let cfg = sb.config(&format!(
        "[ppm]\ntiming = '{timing}'\n[failsafe]\nafter_ms = 200\naction = '{action}'\nstartup = '{startup}'"
    ));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let mut ppmd = sb.start_ppmd(&cfg, "before.trace");
    send(&sb, OLD, 10);
    // The old command expires (200 ms) while the processes run.
    std::thread::sleep(Duration::from_millis(400));
    let restarted_ppmd = order != Order::Ingress;
    match order {
        Order::Ppmd => {
            stop(&mut ppmd, signal);
            std::thread::sleep(Duration::from_millis(300));
            ppmd = sb.start_ppmd(&cfg, "after.trace");
        }
        Order::Ingress => {
            stop(&mut ingress, signal);
            ingress = sb.start_ingress(&cfg, &[]);
        }
        Order::IngressThenPpmd => {
            stop(&mut ingress, signal);
            stop(&mut ppmd, signal);
            ingress = sb.start_ingress(&cfg, &[]);
            ppmd = sb.start_ppmd(&cfg, "after.trace");
        }
        Order::PpmdThenIngress => {
            stop(&mut ppmd, signal);
            stop(&mut ingress, signal);
            ppmd = sb.start_ppmd(&cfg, "after.trace");
            ingress = sb.start_ingress(&cfg, &[]);
        }
    }
    let restarted = now_ns();
    // What the line does until a fresh command comes.
    std::thread::sleep(Duration::from_millis(700));
    let fresh_from = now_ns();
    send(&sb, NEW, 15);
    stop(&mut ppmd, Signal::SIGTERM);
    stop(&mut ingress, Signal::SIGTERM);
    let trace = if restarted_ppmd {
        "after.trace"
    } else {
        "before.trace"
    };
    // Every frame, whole or cut short at a late edge (then with the
    // channels before it, exact).
    let frames = read_trace(&sb.dir.join(trace)).decode(false);
    let (waiting, fresh): (Vec<_>, Vec<_>) = frames
        .iter()
        .filter(|f| f.start_ns >= restarted)
        .partition(|f| f.start_ns < fresh_from);
    // What the line carries until the fresh command, and may carry after it
    // once that expires.
    let expected: Option<[u64; 3]> = match (restarted_ppmd, action, startup) {
        // A ppmd that saw the old command fresh holds it; a new one never
        // saw it.
        (false, "hold", _) => Some(OLD_US),
        (false, "default", _) | (true, _, "default") => Some([1500, 1500, 1000]),
        _ => None,
    };
    match expected {
        None => assert!(
            waiting.is_empty(),
            "{label}: {} frames before the fresh command: {:?}",
            waiting.len(),
            waiting.iter().map(|f| f.channels_us()).collect::<Vec<_>>()
        ),
        Some(want) => {
            // One frame carrying the three channels that tell the old
            // command from the defaults shows the action (how many a loaded
            // machine cuts short is its business).
            assert!(
                waiting.iter().any(|f| f.channels_us().len() >= 3),
                "{label}: {} frames, none with three channels",
                waiting.len()
            );
            for f in &waiting {
                let full = if want[0] == 1500 {
                    &DEFAULTS_US[..]
                } else {
                    &want[..]
                };
                assert!(carries(f, full), "{label}: {:?}", f.channels_us());
            }
        }
    }
    assert!(
        fresh
            .iter()
            .any(|f| f.channels_us().len() >= 3 && carries(f, &NEW_US)),
        "{label}: the fresh command flies: {:?}",
        fresh.iter().map(|f| f.channels_us()).collect::<Vec<_>>()
    );
    if restarted_ppmd {
        assert!(
            frames
                .iter()
                .all(|f| f.channels_us().len() < 3 || !carries(f, &OLD_US)),
            "{label}: the old command flew after the restart"
        );
    }
    if order == Order::Ppmd {
        // The running ingress's last command, offered to the new ppmd by
        // the service's history: refused, counted in the exit summary.
        let log = ppmd.log_text();
        assert!(log.contains(", 1 expired samples"), "{label}: {log}");
    }
}

/// One test per order and signal, each running every failsafe action (and
/// both startups, hold with each) in both timings: across a test's two
/// signals every action flies in grid and in follow.
macro_rules! restart_cases {
    ($($name:ident: $order:expr, $signal:expr;)*) => {$(
        #[test]
        fn $name() {
            let follow = $signal == Signal::SIGKILL;
            case($order, $signal, follow, "hold", "silence");
            case($order, $signal, !follow, "default", "silence");
            case($order, $signal, follow, "silence", "default");
            case($order, $signal, !follow, "hold", "default");
        }
    )*};
}

restart_cases! {
    ppmd_restarted_after_sigterm: Order::Ppmd, Signal::SIGTERM;
    ppmd_restarted_after_sigkill: Order::Ppmd, Signal::SIGKILL;
    ingress_restarted_after_sigterm: Order::Ingress, Signal::SIGTERM;
    ingress_restarted_after_sigkill: Order::Ingress, Signal::SIGKILL;
    both_restarted_ingress_first_after_sigterm: Order::IngressThenPpmd, Signal::SIGTERM;
    both_restarted_ingress_first_after_sigkill: Order::IngressThenPpmd, Signal::SIGKILL;
    both_restarted_ppmd_first_after_sigterm: Order::PpmdThenIngress, Signal::SIGTERM;
    both_restarted_ppmd_first_after_sigkill: Order::PpmdThenIngress, Signal::SIGKILL;
}
