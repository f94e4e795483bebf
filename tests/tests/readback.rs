//! The read-back, end to end with the real binaries and a simulated radio:
//! ppmd writes its simulated line; a "radio" (this test) reads that line as
//! it grows, decodes it as EdgeTX's trainer input does, and transmits its
//! own PPM frames every 22.5 ms into a second trace, which ppmd reads back
//! (`ppmd.readback = "sim:PATH"`). While the radio relays ppm's values the
//! read-back must say `following`, never `overridden`; when the radio's
//! trainer switch flips to the instructor, `overridden` must reach the
//! command's sender as a JSON event, decided on the second frame that
//! differs (`readback.frames = 2`), and back to `following` after the
//! switch flips back, and `no_input` a second after the radio goes quiet.

use ppm_shared::capture::ReadbackState;
use ppm_shared::receiver::{Receiver, ReceiverDecoder};
use ppm_shared::signal::Level;
use ppm_shared::time::now_ns;
use ppm_tests::{status, Sandbox};
use std::io::Write;
use std::net::UdpSocket;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::SeqCst};
use std::sync::Arc;
use std::time::Duration;

/// The radio's frame period, ns.
const RADIO_FRAME_NS: u64 = 22_500_000;
/// The radio's channel count (ppm sends 4; the radio sends 8).
const RADIO_CHANNELS: usize = 8;
/// What the instructor's sticks send on the first four channels.
const INSTRUCTOR_US: [u64; 4] = [1_600, 1_450, 1_100, 1_550];
/// What the groundstation commands.
const COMMAND: &[u8] = b"[1300, 1700, 1000, 1200]";

/// The radio: relays the trainer channels it reads from ppm's line (what
/// EdgeTX hands on) until `instructor` is set, then sends the
/// instructor's sticks; returns when `stop` is set. Each edge is written
/// once its time has passed, as the kernel reports edges.
fn radio(
    line: &Path,
    out: &Path,
    instructor: &AtomicBool,
    flipped_at: &AtomicU64,
    stop: &AtomicBool,
) {
    let mut follow = ppm_tools::radio::Follow::new(line);
    let mut trainer = ReceiverDecoder::new(Receiver::EdgeTx, Level::High);
    let mut values: Option<Vec<u64>> = None;
    let mut file = std::fs::File::create(out).expect("creating the radio's trace");
    file.write_all(b"# idle_level 0\n").unwrap();
    let mut next = now_ns();
    let mut pending: std::collections::VecDeque<(u64, u8)> = Default::default();
    let mut was_instructor = false;
    while !stop.load(SeqCst) {
        for (t, level) in follow.edges().expect("reading the line's trace") {
            if let Some(f) = trainer.push(t, level) {
                if f.complete && f.channels_us().len() == 4 {
                    values = Some(f.channels_us());
                }
            }
        }
        let now = now_ns();
        let mut text = String::new();
        while pending.front().is_some_and(|(t, _)| *t <= now) {
            let (t, level) = pending.pop_front().unwrap();
            text.push_str(&format!("{t} {t} {level}\n"));
        }
        if !text.is_empty() {
            file.write_all(text.as_bytes()).unwrap();
            file.flush().unwrap();
        }
        if now < next {
            std::thread::sleep(Duration::from_nanos((next - now).min(500_000)));
            continue;
        }
        // A frame starts now. The radio is switched on once ppm's line
        // carries commands.
        let start = next;
        next += RADIO_FRAME_NS;
        let Some(v) = &values else { continue };
        let inst = instructor.load(SeqCst);
        if inst != was_instructor {
            // The switch flipped during the frame before: this frame is
            // the first to carry the new source.
            was_instructor = inst;
            flipped_at.store(start, SeqCst);
        }
        let mut us = vec![1_500; RADIO_CHANNELS];
        us[..4].copy_from_slice(if inst { &INSTRUCTOR_US[..] } else { &v[..] });
        pending.extend(ppm_tools::radio::frame_edges(start, &us));
    }
}

fn rows(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .map(|l| serde_json::from_str(l).expect("a JSON row"))
        .collect()
}

/// Waits up to `limit` for a `{"event":"readback"}` datagram on `socket`,
/// sending the command every 20 ms meanwhile; returns it and when it came.
fn event(
    socket: &UdpSocket,
    to: std::net::SocketAddr,
    limit: Duration,
) -> Option<(serde_json::Value, u64)> {
    let end = now_ns() + limit.as_nanos() as u64;
    let mut buf = [0u8; 4096];
    while now_ns() < end {
        socket.send_to(COMMAND, to).unwrap();
        if let Ok((n, _)) = socket.recv_from(&mut buf) {
            let at = now_ns();
            let v: serde_json::Value = serde_json::from_slice(&buf[..n]).expect("JSON");
            if v["event"] == "readback" {
                return Some((v, at));
            }
        }
    }
    None
}

#[test]
fn the_sender_hears_overridden_when_the_instructor_takes_over_and_following_when_he_gives_back() {
    let sb = Sandbox::new("readback");
    let radio_trace = sb.dir.join("radio.trace");
    let log = sb.dir.join("readback.jsonl");
    let frames = sb.dir.join("frames.jsonl");
    let cfg = sb.config(&format!(
        "[ppmd]\nreadback = \"sim:{}\"\nreadback_log = {:?}\nframe_log = {:?}\n[readback]\nframes = 2\n[ppm]\nchannels = 4\nreceiver = \"edgetx\"\n[failsafe]\nafter_ms = 500\naction = \"hold\"",
        radio_trace.display(),
        log.to_str().unwrap(),
        frames.to_str().unwrap()
    ));
    let _ppmd = sb.start_ppmd(&cfg, "line.trace");
    let _ingress = sb.start_ingress(&cfg, &[]);

    let instructor = Arc::new(AtomicBool::new(false));
    let flipped_at = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let radio = {
        let (line, out) = (sb.dir.join("line.trace"), radio_trace.clone());
        let (i, f, s) = (instructor.clone(), flipped_at.clone(), stop.clone());
        std::thread::spawn(move || radio(&line, &out, &i, &f, &s))
    };
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    socket
        .set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();

    // The radio relays: following.
    let (first, _) = event(&socket, sb.addr(), Duration::from_secs(10)).expect("a first event");
    assert_eq!(first["state"], "following", "{first}");
    assert_eq!(first["from"], "no_input", "{first}");
    // Two seconds of relaying: no event at all.
    assert_eq!(
        event(&socket, sb.addr(), Duration::from_secs(2)).map(|e| e.0),
        None
    );

    // The instructor takes over.
    instructor.store(true, SeqCst);
    let (over, at) = event(&socket, sb.addr(), Duration::from_secs(5)).expect("overridden");
    assert_eq!(
        (over["state"].as_str(), over["from"].as_str()),
        (Some("overridden"), Some("following")),
        "{over}"
    );
    let flip = flipped_at.load(SeqCst);
    println!(
        "switch flip (the radio's first frame from the instructor began) to the sender hearing overridden: {:.1} ms",
        (at - flip) as f64 / 1e6
    );
    let st = status(sb.addr());
    let rb = st.readback.as_ref().expect("a readback member");
    assert_eq!(rb.state, "overridden");
    assert_eq!(rb.input, format!("sim:{}", radio_trace.display()));
    assert_eq!(&rb.ch_us[..4], &INSTRUCTOR_US.map(|u| u as f64));
    // A clean input: nothing refused but what came before the first sync
    // and the frames that locked the channel count.
    for (reason, n) in &rb.refused {
        if !["unsynced", "wrong_count"].contains(&reason.as_str()) {
            assert_eq!(*n, 0, "{reason}: {:?}", rb.refused);
        }
    }

    // The instructor gives control back.
    instructor.store(false, SeqCst);
    let (back, _) = event(&socket, sb.addr(), Duration::from_secs(5)).expect("following again");
    assert_eq!(
        (back["state"].as_str(), back["from"].as_str()),
        (Some("following"), Some("overridden")),
        "{back}"
    );
    // The radio goes quiet: no_input a second after its last frame.
    stop.store(true, SeqCst);
    radio.join().unwrap();
    let (lost, _) = event(&socket, sb.addr(), Duration::from_secs(5)).expect("no_input");
    assert_eq!(
        (lost["state"].as_str(), lost["from"].as_str()),
        (Some("no_input"), Some("following")),
        "{lost}"
    );
    std::thread::sleep(Duration::from_millis(300));

    // The log: every change, each decided on the second frame that agreed.
    let rows = rows(&log);
    let changes: Vec<(String, String)> = rows
        .iter()
        .filter(|r| r["type"] == "readback")
        .map(|r| {
            (
                r["from"].as_str().unwrap().into(),
                r["to"].as_str().unwrap().into(),
            )
        })
        .collect();
    let names = |a: ReadbackState, b: ReadbackState| (a.name().to_string(), b.name().to_string());
    assert_eq!(
        changes,
        [
            names(ReadbackState::NoInput, ReadbackState::Following),
            names(ReadbackState::Following, ReadbackState::Overridden),
            names(ReadbackState::Overridden, ReadbackState::Following),
            names(ReadbackState::Following, ReadbackState::NoInput),
        ]
    );
    // Frames read before the flip all matched ppm's values; the change to
    // overridden comes right after the second frame from the instructor.
    let reads: Vec<&serde_json::Value> = rows.iter().filter(|r| r["type"] == "read").collect();
    let first_inst = reads
        .iter()
        .position(|r| r["ch_us"][0] == 1600.0)
        .expect("a frame from the instructor");
    assert!(reads[..first_inst]
        .iter()
        .skip(2)
        .all(|r| r["match"] == true));
    assert_eq!(reads[first_inst]["state"], "following");
    assert_eq!(reads[first_inst + 1]["state"], "overridden");
    assert_eq!(reads[first_inst]["mono_ns"].as_u64(), Some(flip));
    // What the radio relayed is what EdgeTX read of ppm's line (to the
    // us, as late as the line's edges were), its own channels after.
    let relayed: Vec<f64> = reads[first_inst - 1]["ch_us"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    for (got, want) in relayed.iter().zip([1300.0, 1700.0, 1000.0, 1200.0]) {
        assert!((got - want).abs() <= 10.0, "{relayed:?}");
    }
    assert_eq!(&relayed[4..], [1500.0; 4]);
    let inst: Vec<f64> = INSTRUCTOR_US.iter().map(|&u| u as f64).collect();
    assert_eq!(
        reads[first_inst]["ch_us"].as_array().unwrap()[..4],
        inst.iter()
            .map(|&v| serde_json::json!(v))
            .collect::<Vec<_>>()[..]
    );

    // The Python package joins the three streams: every frame read, with
    // the line's frame before it and that frame's command.
    let joined = ppm_tests::python3(
        &sb.dir,
        ppm_tests::PYTHON_PACKAGE,
        &[
            "-c",
            "import json, sys, ppm\nfor j in ppm.joined(sys.argv[1], sys.argv[2]): print(json.dumps(j))",
            frames.to_str().unwrap(),
            log.to_str().unwrap(),
        ],
    );
    let joined: Vec<serde_json::Value> = joined
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(joined.len(), reads.len());
    for j in &joined {
        let (read, line) = (&j["read"], &j["line"]);
        assert!(line["mono_ns"].as_u64() <= read["mono_ns"].as_u64(), "{j}");
        assert!(j["lag_ms"].as_f64().unwrap() >= 0.0, "{j}");
        // The groundstation's command is in the line's frame.
        assert_eq!(j["command"]["ingress_seq"], line["ingress_seq"], "{j}");
        // A whole frame of the line carries the command's 4 channels (one
        // cut short at a late edge carries fewer).
        if line["status"] == "whole" {
            assert_eq!(line["ch_us"].as_array().unwrap().len(), 4, "{j}");
        }
    }
}
