//! A flood from a sender on the same machine: the ingress stays up, its
//! memory stays flat, and within two frames after the flood ends the newest
//! command is on the line. (The figures, datagrams/s and ppmd's timing
//! during a flood, are `ppm-bench`'s; this checks the behaviour.)

use nix::sys::signal::Signal;
use ppm_shared::time::now_ns;
use ppm_tests::{at_50hz, read_trace, Sandbox, Sender, StatusReply};
use std::net::UdpSocket;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

const FRAME_NS: u64 = 22_500_000;

#[test]
fn a_flood_leaves_only_the_newest_command() {
    let sb = Sandbox::new("flood");
    let cfg = sb.config("");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let ingress = sb.start_ingress(&cfg, &[]);
    let calm = Sender::new(sb.addr());
    for _ in 0..50 {
        calm.send(b"[1100]");
        std::thread::sleep(Duration::from_millis(20));
    }
    let rss_before = ingress.rss_kib();

    let stop = Arc::new(AtomicBool::new(false));
    let sent = Arc::new(AtomicU64::new(0));
    let flood = {
        let (stop, sent, addr) = (stop.clone(), sent.clone(), sb.addr());
        std::thread::spawn(move || {
            let s = UdpSocket::bind("127.0.0.1:0").unwrap();
            let mut i = 0u64;
            while !stop.load(Relaxed) {
                let d = format!("[{}, {}]", 1000 + i % 1000, 1000 + (i / 1000) % 1000);
                if s.send_to(d.as_bytes(), addr).is_ok() {
                    i += 1;
                }
            }
            sent.store(i, Relaxed);
        })
    };
    std::thread::sleep(Duration::from_secs(2));
    stop.store(true, Relaxed);
    flood.join().unwrap();
    // A groundstation goes on at 50 Hz. (Its first datagram can meet a
    // receive buffer the flood still fills, and the kernel then drops it,
    // the newest: that is why udp-ingress drains on every wake-up.)
    let last = now_ns();
    at_50hz(8, |_| calm.send(b"[1777, 1333]"));
    let rss_after = ingress.rss_kib();
    assert!(ppmd
        .signal_and_wait(Signal::SIGTERM, Duration::from_secs(10))
        .success());

    // How many is the function: a flood, not a trickle (a sender on a
    // loaded machine still sends far more in 2 s).
    assert!(
        sent.load(Relaxed) > 10_000,
        "the flood sent only {}",
        sent.load(Relaxed)
    );
    // Still up and answering.
    let q = UdpSocket::bind("127.0.0.1:0").unwrap();
    q.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
    q.send_to(br#"{"get":"status"}"#, sb.addr()).unwrap();
    let mut buf = [0u8; 65536];
    let n = q
        .recv(&mut buf)
        .expect("udp-ingress answers after the flood");
    let status: StatusReply = serde_json::from_slice(&buf[..n]).unwrap();
    // It took the flood in (how many is the function, as above).
    assert!(status.datagrams.received > 10_000);
    // Memory stays flat: no queue of stale commands builds up.
    assert!(
        rss_after <= rss_before + 2048,
        "udp-ingress grew from {rss_before} KiB to {rss_after} KiB"
    );
    // From two frames after the last datagram on, the line carries it:
    // every frame, whole or cut short at a late edge (then with the
    // channels before it, exact), and one carrying both channels shows it
    // (how many a loaded machine cuts short is its business).
    let frames = read_trace(&trace).decode(false);
    let after: Vec<_> = frames
        .iter()
        .filter(|f| f.start_ns >= last + 2 * FRAME_NS && f.start_ns <= last + 150_000_000)
        .collect();
    assert!(
        after.iter().any(|f| f.channels_us().len() >= 2),
        "no frame after the flood with both channels: {:?}",
        after.iter().map(|f| f.channels_us()).collect::<Vec<_>>()
    );
    for f in after {
        assert!(
            ppm_tests::carries(f, &[1777, 1333]),
            "frame at +{} ms: {:?}",
            (f.start_ns - last) / 1_000_000,
            f.channels_us()
        );
    }
}
