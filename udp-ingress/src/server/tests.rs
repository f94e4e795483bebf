//! Tests of the server: the exit status of a socket that cannot be bound,
//! a key file's fault named by its key, and a running ingress that tells
//! each read-back change while no datagram comes.

use super::open::{bind_error, load_key};
use super::*;
use ppm_shared::config::{Config, KeyName, OutputPlan, Plan};
use ppm_shared::daemon::{exit_status, EXIT_CONFIG, EXIT_FAILURE};

fn plan(text: &str) -> OutputPlan {
    Plan::resolve_one(&Config::parse(text).unwrap()).unwrap().1
}

/// A port this user may not take is the configuration's fault (78);
/// one still held by another process may pass (1).
#[test]
fn a_privileged_port_is_a_configuration_error_a_busy_one_is_not() {
    let cfg = plan("[ingress]\nlisten = \"0.0.0.0:80\"");
    let e = bind_error(&cfg, std::io::Error::from(nix::errno::Errno::EACCES));
    assert_eq!(exit_status(&e, |_| false), EXIT_CONFIG);
    let text = e.to_string();
    assert!(
        text.starts_with("config key `ingress.listen`: cannot listen on 0.0.0.0:80")
            && text.contains("use a port of 1024 or more"),
        "{text}"
    );
    let e = bind_error(&cfg, std::io::Error::from(nix::errno::Errno::EADDRINUSE));
    assert_eq!(exit_status(&e, |_| false), EXIT_FAILURE);
    let mut cfg = cfg;
    cfg.keys.note_option("ingress.listen", "--listen");
    let e = bind_error(&cfg, std::io::Error::from(nix::errno::Errno::EACCES));
    assert!(e.to_string().starts_with("--listen 0.0.0.0:80: "), "{e}");
}

/// A running ingress with a read-back (its receive loop, socket and
/// shared memory under a temporary root): it waits at most
/// READBACK_POLL_TIMEOUT for datagrams, so the read-back samples
/// published here are seen while none comes. Each change reaches the
/// JSON sender as one event (none for a sample without a change) and a
/// MAVLink peer as a STATUSTEXT; the status reply carries the newest;
/// RC_CHANNELS carry the radio's frame, SERVO_OUTPUT_RAW the line's (no
/// ppmd here: none). No time limit is asserted: the latency of the
/// first event is printed.
#[test]
fn a_running_ingress_tells_each_readback_change_while_no_datagram_comes() {
    use crate::readback::tests::{decode, rc_channels, sample, servo_output_raw, statustext};
    use ppm_shared::capture::ReadbackState::{Following, NoInput, Overridden};
    use ppm_shared::mavlink::{self, HEARTBEAT, RC_CHANNELS, SERVO_OUTPUT_RAW, STATUSTEXT};
    use std::net::UdpSocket as StdSocket;
    use std::sync::{mpsc, Arc};

    let root = std::env::temp_dir().join(format!("ppm-readback-server-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let cfg = format!(
        "name = \"rb\"\n[ingress]\nlisten = \"127.0.0.1:0\"\n[ppmd]\nreadback = \"sim:{0}/radio.trace\"\n[ipc]\nroot = \"{0}\"\n",
        root.display()
    );
    let (shared, out) = Plan::resolve_one(&Config::parse(&cfg).unwrap()).unwrap();
    // Without a read-back, the loop waits as long as it always did.
    let plain = cfg.replace("name = \"rb\"", "name = \"plain\"");
    let plain =
        plain[..plain.find("[ppmd]").unwrap()].to_string() + &plain[plain.find("[ipc]").unwrap()..];
    let (plain_shared, plain) = Plan::resolve_one(&Config::parse(&plain).unwrap()).unwrap();
    assert!(plain.readback.is_none());
    let server = Server::open(&plain_shared, plain).unwrap();
    assert_eq!(server.idle_every, POLL_TIMEOUT);
    drop(server);
    let stop = Arc::new(AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let running = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let server = Server::open(&shared, out).unwrap();
            tx.send((server.local_addr().unwrap(), server.idle_every))
                .unwrap();
            server.run(&stop).unwrap();
        })
    };
    let (at, idle_every) = rx.recv_timeout(Duration::from_secs(30)).unwrap();
    assert_eq!(idle_every, READBACK_POLL_TIMEOUT);

    let node = ipc::create_node(&root, "readback-test").unwrap();
    let service = ipc::open_readback_service(&node, "rb").unwrap();
    let publisher = service.publisher_builder().create().unwrap();
    let socket = || {
        let s = StdSocket::bind("127.0.0.1:0").unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        s
    };
    let (json, gcs, query) = (socket(), socket(), socket());
    let mut buf = [0u8; 4_096];
    let mut recv = |s: &StdSocket| -> Vec<u8> {
        let n = s.recv(&mut buf).expect("a datagram within 10 s");
        buf[..n].to_vec()
    };
    // The newest readback member as a status reply has it.
    let status = |query: &StdSocket, recv: &mut dyn FnMut(&StdSocket) -> Vec<u8>| {
        query.send_to(br#"{"get":"status"}"#, at).unwrap();
        let reply: serde_json::Value = serde_json::from_slice(&recv(query)).unwrap();
        reply["readback"].clone()
    };
    // Waits until the ingress has taken a sample of `frames` frames.
    let taken = |frames: u64, recv: &mut dyn FnMut(&StdSocket) -> Vec<u8>| {
        for _ in 0..500 {
            if status(&query, recv)["frames"] == frames {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!("the ingress never took the sample of {frames} frames");
    };

    json.send_to(br#"{"ch":[1500,1500,1500,1500],"seq":1}"#, at)
        .unwrap();
    let hb = mavlink::frame(2, (0, 255, 190), &HEARTBEAT, &[0, 0, 0, 0, 6, 8, 0, 4, 3]);
    gcs.send_to(&hb, at).unwrap();
    let before = status(&query, &mut recv);
    assert_eq!(
        (&before["state"], &before["input"]),
        (
            &serde_json::json!("stale"),
            &serde_json::json!(format!("sim:{}/radio.trace", root.display()))
        )
    );

    let publish = |s: ppm_shared::ipc::ReadbackSample| {
        ipc::publish(&publisher, s).unwrap();
    };
    let t0 = now_ns();
    let mut first = sample(t0, NoInput, 0, 0);
    first.frames = 1;
    publish(first);
    taken(1, &mut recv);
    // The change, while nothing is sent to the ingress.
    let t1 = now_ns();
    publish(sample(t1, Following, 1, t1));
    let event = recv(&json);
    eprintln!(
        "first event {:.3} ms after its sample",
        (now_ns() - t1) as f64 / 1e6
    );
    assert_eq!(
        String::from_utf8(event).unwrap(),
        format!(
            r#"{{"changed_mono_ns":{t1},"changes":1,"event":"readback","from":"no_input","name":"rb","state":"following"}}"#
        )
    );
    // A sample without a change: no event (the next datagram is the
    // next change's).
    let mut same = sample(now_ns(), Following, 1, t1);
    same.frames = 260;
    publish(same);
    taken(260, &mut recv);
    let t2 = now_ns();
    publish(sample(t2, Overridden, 2, t2));
    assert_eq!(
        String::from_utf8(recv(&json)).unwrap(),
        format!(
            r#"{{"changed_mono_ns":{t2},"changes":2,"event":"readback","from":"following","name":"rb","state":"overridden"}}"#
        )
    );
    let r = status(&query, &mut recv);
    assert_eq!(
        (
            &r["state"],
            &r["changes"],
            &r["frames"],
            &r["ch_us"],
            &r["max_diff_us"]
        ),
        (
            &serde_json::json!("overridden"),
            &serde_json::json!(2),
            &serde_json::json!(250),
            &serde_json::json!([1100.4, 1499.6, 1900.0, 1500.0]),
            &serde_json::json!(12.345)
        )
    );
    assert_eq!(r["refused"]["unsynced"], 8);

    // The MAVLink peer: both STATUSTEXTs, in order; RC_CHANNELS carry
    // the radio's frame; SERVO_OUTPUT_RAW the line's (none).
    let (mut texts, mut rc, mut servo) = (vec![], None, None);
    while texts.len() < 2 || rc.is_none() || servo.is_none() {
        let (id, p) = decode(&recv(&gcs));
        match id {
            id if id == STATUSTEXT.id => texts.push(statustext(&p)),
            id if id == RC_CHANNELS.id && texts.len() == 2 => rc = Some(rc_channels(&p)),
            id if id == SERVO_OUTPUT_RAW.id => servo = Some(servo_output_raw(&p)),
            _ => {}
        }
    }
    assert_eq!(
        texts,
        [
            (5, "ppm rb: following".to_string(), 0, 0),
            (
                4,
                "ppm rb: overridden (instructor has control)".to_string(),
                0,
                0
            )
        ]
    );
    let (_, count, chan, rest_unused) = rc.unwrap();
    assert_eq!(
        (count, chan, rest_unused),
        (4, vec![1100, 1500, 1900, 1500], true)
    );
    assert_eq!(servo.unwrap().2, vec![0; 16]);

    stop.store(true, Relaxed);
    running.join().unwrap();
    drop((publisher, service, node));
    let _ = std::fs::remove_dir_all(&root);
}

/// A key file from the configuration is named by its key, with where
/// to point it; one given with --auth-key keeps the key file's message.
#[test]
fn a_key_file_from_the_configuration_names_its_key() {
    let missing = std::path::Path::new("/nonexistent-ppm-test/k.key");
    let e = load_key(&KeyName::File("mavlink.key_file".into()), missing).unwrap_err();
    assert_eq!(exit_status(&e, |_| false), EXIT_CONFIG);
    assert_eq!(
        e.to_string(),
        "config key `mavlink.key_file`: cannot read auth key file /nonexistent-ppm-test/k.key: No such file or directory (os error 2): point mavlink.key_file at the key file, a regular file this user may read holding 64 hex characters, mode 600 (`openssl rand -hex 32 > FILE; chmod 600 FILE`)"
    );
    let e = load_key(&KeyName::Option("--auth-key"), missing).unwrap_err();
    assert_eq!(exit_status(&e, |_| false), EXIT_CONFIG);
    assert_eq!(
        format!("{e:#}"),
        "cannot read auth key file /nonexistent-ppm-test/k.key: No such file or directory (os error 2)"
    );
}
