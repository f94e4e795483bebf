//! udp-ingress's real-time settings with the real binaries: a busy-polling
//! ingress delivers commands to the line and answers status queries, the new
//! keys are refused at start naming the key, and a CPU that cannot be had
//! stops the ingress unless a degraded run is allowed. Correctness only: no
//! latency figures are asserted (that is `ppm-bench`'s job).

use nix::sys::signal::Signal;
use ppm_shared::status::ReceiverStatus;
use ppm_tests::{read_trace, Sandbox, StatusReply};
use std::net::UdpSocket;
use std::time::Duration;

const SECOND: Duration = Duration::from_secs(1);

/// A CPU for the busy-polling ingress that is not ppmd's (`rt.cpu =
/// "last"`), when there is one.
fn spare_cpu() -> Option<usize> {
    let online = ppm_shared::sched::online_cpus();
    (online.len() >= 2).then(|| online[0])
}

#[test]
fn busy_poll_ingress_delivers_commands_and_answers_status() {
    let sb = Sandbox::new("busypoll");
    let cfg = sb.config("");
    let cfg = cfg.to_str().unwrap();
    let trace = sb.dir.join("line.trace");
    let output = format!("sim:{}", trace.display());
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg, "--output", &output], "ppmd");
    // From the command line: --busy-poll and --cpu override the file.
    let cpu = spare_cpu().map_or("none".to_string(), |c| c.to_string());
    let mut ingress = sb.spawn(
        "udp-ingress",
        &["--config", cfg, "--busy-poll", "--cpu", &cpu],
        "ingress",
    );
    ppmd.wait_for_log("commands from", 30 * SECOND);
    ingress.wait_for_log("listening on", 30 * SECOND);
    let log = ingress.log_text();
    assert!(log.contains("busy_poll: spins on the socket"), "{log}");
    if let Some(c) = spare_cpu() {
        assert!(log.contains(&format!("CPU {c};")), "{log}");
    }

    // Commands and status queries from one socket, so they arrive in order.
    let client = UdpSocket::bind("127.0.0.1:0").unwrap();
    client.set_read_timeout(Some(5 * SECOND)).unwrap();
    let status = |client: &UdpSocket| -> StatusReply {
        client.send_to(br#"{"get":"status"}"#, sb.addr()).unwrap();
        let mut buf = [0u8; 65_536];
        let (n, from) = client.recv_from(&mut buf).expect("a status reply");
        assert_eq!(from, sb.addr());
        serde_json::from_slice(&buf[..n]).expect("the reply is a status reply")
    };
    let first = status(&client);
    let receiver = first.receiver.as_ref().expect("the receive thread");
    assert_eq!(first.datagrams.received, 0, "{first}");
    assert_eq!(receiver.wait, "busy_poll", "{first}");
    assert_eq!(receiver.cpu, spare_cpu().map(|c| c as u64), "{first}");
    assert_eq!(first.status_requests, 1, "{first}");

    let send_for = |value: u32, n: u32| {
        for _ in 0..n {
            client
                .send_to(format!("[{value}, 1600, 1100, 1900]").as_bytes(), sb.addr())
                .unwrap();
            std::thread::sleep(Duration::from_millis(20));
        }
    };
    send_for(1234, 30);
    let middle = status(&client);
    send_for(1777, 30);
    std::thread::sleep(Duration::from_millis(100));
    let last = status(&client);
    // Answered after the commands before them were handed over: the counters add up.
    assert_eq!(middle.datagrams.received, 30, "{middle}");
    assert_eq!(last.datagrams.received, 60, "{last}");
    let applied = last.datagrams.applied;
    let superseded = last.datagrams.superseded;
    assert_eq!(applied + superseded, 60, "{last}");
    assert_eq!(last.status_requests, 3, "{last}");
    assert_eq!(last.publish_latency_us.count, applied, "{last}");

    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    // The spinning loop still sees the stop flag.
    assert!(ingress
        .signal_and_wait(Signal::SIGTERM, 10 * SECOND)
        .success());
    assert!(
        ingress.log_text().contains("stopped: received 60 "),
        "{}",
        ingress.log_text()
    );

    // Decoded from the line: the commands sent, in order, the newest last.
    // Every frame, whole or cut short at a late edge (then with the
    // channels before it, exact).
    let frames = read_trace(&trace).decode(false);
    let a = [1234, 1600, 1100, 1900, 1500, 1500, 1500, 1500];
    let b = [1777, 1600, 1100, 1900, 1500, 1500, 1500, 1500];
    assert!(
        frames
            .iter()
            .all(|f| ppm_tests::carries(f, &a) || ppm_tests::carries(f, &b)),
        "{:?}",
        frames.iter().map(|f| f.channels_us()).collect::<Vec<_>>()
    );
    let ch: Vec<Vec<u64>> = frames
        .iter()
        .map(|f| f.channels_us())
        .filter(|c| !c.is_empty())
        .collect();
    // 1234, then only 1777: one frame of each is all the order needs
    // (about 25 each on an idle machine; how many a loaded one cuts short
    // at a late edge is its business).
    let switch = ch
        .iter()
        .position(|c| c[0] == 1777)
        .expect("1777 on the line");
    assert!(switch >= 1, "1234 never flew: {ch:?}");
    assert!(ch[switch..].iter().all(|c| c[0] == 1777), "{ch:?}");
}

#[test]
fn bad_scheduling_keys_stop_the_ingress_naming_the_key() {
    let sb = Sandbox::new("rtkeys");
    let last_cpu = *ppm_shared::sched::online_cpus().last().unwrap();
    let busy_on_ppmd_cpu = format!("busy_poll = true\ncpu = {last_cpu}");
    let last = last_cpu.to_string();
    let cases: [(&str, &[&str], &str); 8] = [
        ("priority = 100", &[], "ingress.priority"),
        ("priority = 80", &[], "ingress.priority"),
        ("cpu = 'last'", &[], "ingress.cpu"),
        ("cpu = -2", &[], "ingress.cpu"),
        ("busy_poll = 'yes'", &[], "busy_poll"),
        // rt.cpu = "last" is that CPU on this machine.
        (&busy_on_ppmd_cpu, &[], "ingress.cpu"),
        // The command-line values are checked the same way.
        ("", &["--priority", "99"], "ingress.priority"),
        ("", &["--busy-poll", "--cpu", &last], "ingress.cpu"),
    ];
    for (ingress, args, key) in cases {
        let cfg = sb.config_with_ingress(ingress, "");
        let mut all = vec!["--config", cfg.to_str().unwrap()];
        all.extend_from_slice(args);
        let mut p = sb.spawn("udp-ingress", &all, "ingress");
        let status = p.wait(10 * SECOND);
        let log = p.log_text();
        assert!(!status.success(), "accepted {ingress:?} {args:?}: {log}");
        assert!(
            log.contains(key),
            "{ingress:?} {args:?}: {key} not named: {log}"
        );
    }
}

#[test]
fn a_cpu_that_cannot_be_had_stops_the_ingress_unless_degraded_allowed() {
    let sb = Sandbox::new("rtcpu");
    // No such CPU. Refused at start, naming the key and the fix.
    let cfg = sb.config_with_ingress("cpu = 4095", "[rt]\nallow_degraded = false\n");
    let cfg = cfg.to_str().unwrap();
    let mut p = sb.spawn("udp-ingress", &["--config", cfg], "refused");
    assert!(!p.wait(10 * SECOND).success());
    let log = p.log_text();
    assert!(
        log.contains("ingress.cpu") && log.contains("CPU 4095") && log.contains("allow_degraded"),
        "{log}"
    );
    assert!(!log.contains("listening on"), "{log}");

    // Allowed to run degraded: it runs, says so, and answers.
    let mut p = sb.spawn(
        "udp-ingress",
        &["--config", cfg, "--allow-degraded"],
        "degraded",
    );
    p.wait_for_log("listening on", 30 * SECOND);
    let log = p.log_text();
    assert!(
        log.contains("DEGRADED RUN: receive thread: CPU pinning"),
        "{log}"
    );
    let client = UdpSocket::bind("127.0.0.1:0").unwrap();
    client.set_read_timeout(Some(5 * SECOND)).unwrap();
    client.send_to(br#"{"get":"status"}"#, sb.addr()).unwrap();
    let mut buf = [0u8; 65_536];
    let (n, _) = client.recv_from(&mut buf).expect("a status reply");
    let reply: StatusReply = serde_json::from_slice(&buf[..n]).unwrap();
    // The status says what the receive thread did not get.
    assert_eq!(
        reply.receiver,
        Some(ReceiverStatus {
            wait: "epoll".into(),
            policy: "other".into(),
            priority: 0,
            cpu: None,
            degraded: true
        }),
        "{reply}"
    );
    assert!(p.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
}
