//! The pilot thread with a simulated pilot's radio: a trace in the
//! simulated line's format (`ppm_shared::trace`) that this test writes as
//! the radio would, read through `sim:PATH`. The switch channel low, then
//! high, then silence must put the slot in `groundstation`, `pilot`, then
//! `no_input`, with the frames' exact values, and publish the same on the
//! output's read-back service.

use ppm_shared::capture::{CaptureSettings, InputSpec, ReadbackState};
use ppm_shared::config::PilotPlan;
use ppm_shared::ipc::{self, ReadbackSample};
use ppm_shared::time::now_ns;
use ppmd::pilot::{Opened, PilotFrame, PilotSlot, PilotState};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The radio's frame period, ns.
const FRAME_NS: u64 = 22_500_000;
/// Its pulse width, ns.
const PULSE_NS: u64 = 300_000;
/// Its channels but the switch (channel 5), us.
const STICKS_US: [u64; 4] = [1_100, 1_200, 1_300, 1_400];
/// How long a test waits for what must happen before it fails (never a
/// limit on how fast it happens).
const PATIENCE: Duration = Duration::from_secs(20);

/// A fresh directory for one test.
fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("ppmd-pilot-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn append(path: &Path, text: &str) {
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .unwrap();
    f.write_all(text.as_bytes()).unwrap();
}

/// The leading edges of the radio's pulses: two lead-in pulses 10 ms
/// apart (the decoder finds the idle level in the gap between them, and a
/// sync before the first frame after them), then `switch_us.len()` frames
/// from `start`, every 22.5 ms, the sticks then the switch; and the pulse
/// that ends the last frame's sync. Frame `k` (0-based) begins at
/// `start + k * FRAME_NS`.
fn leads(start: u64, switch_us: &[u64]) -> Vec<u64> {
    let mut out = vec![start - 20_000_000, start - 10_000_000];
    for (k, sw) in switch_us.iter().enumerate() {
        let mut t = start + k as u64 * FRAME_NS;
        out.push(t);
        for us in STICKS_US.iter().chain([sw]) {
            t += us * 1_000;
            out.push(t);
        }
    }
    out.push(start + switch_us.len() as u64 * FRAME_NS);
    out
}

/// The trace lines of pulses at `leads` (idle low), as written at once.
fn lines(leads: &[u64]) -> String {
    leads
        .iter()
        .map(|t| format!("{t} {t} 1\n{} {} 0\n", t + PULSE_NS, t + PULSE_NS))
        .collect()
}

fn plan(trace: &Path) -> PilotPlan {
    PilotPlan {
        input: InputSpec::Sim {
            path: trace.to_owned(),
        },
        // Both found from the signal, as by default.
        capture: CaptureSettings::default(),
        switch_channel: 4,
        switch_above_ns: 1_500_000,
    }
}

/// Waits until `slot`'s newest frame is frame `n`, and returns it.
fn frame_number(slot: &PilotSlot, n: u64) -> PilotFrame {
    let since = Instant::now();
    loop {
        if let Some(f) = slot.frame().filter(|f| f.frame >= n) {
            return f;
        }
        assert!(
            since.elapsed() < PATIENCE,
            "no frame {n}: {:?}",
            slot.frame()
        );
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Waits for a published sample that `done` accepts, and returns it.
fn published(
    sub: &iceoryx2::port::subscriber::Subscriber<
        iceoryx2::service::ipc::Service,
        ReadbackSample,
        (),
    >,
    done: impl Fn(&ReadbackSample) -> bool,
) -> ReadbackSample {
    let since = Instant::now();
    let mut last = None;
    loop {
        while let Some(s) = sub.receive().unwrap() {
            last = Some(*s.payload());
        }
        if let Some(s) = last.filter(&done) {
            return s;
        }
        assert!(since.elapsed() < PATIENCE, "last published: {last:?}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn the_switch_gives_the_pilot_the_controls_and_silence_takes_them_from_everyone() {
    let d = dir("switch");
    let (trace, root) = (d.join("radio.trace"), d.join("ipc"));
    let name = format!("pilot{}", std::process::id());
    // Six frames with the switch low (the first two lock the count of 5),
    // then three high, the first of those split across the two writes.
    // The frames lie 5 s ahead, so the input stays valid however long
    // this test takes between its writes on a busy machine.
    let start = now_ns() + 5_000_000_000;
    let all = leads(
        start,
        &[
            1_000, 1_000, 1_000, 1_000, 1_000, 1_000, 2_000, 2_000, 2_000,
        ],
    );
    let split = 2 + 6 * 6 + 1;
    append(&trace, "# idle_level 0\n");
    append(&trace, &lines(&all[..split]));

    let node = ipc::create_node(&root, "pilot-test").unwrap();
    let service = ipc::open_readback_service(&node, &name).unwrap();
    let sub = service.subscriber_builder().create().unwrap();
    let slot = Arc::new(PilotSlot::default());
    let opened = Opened::open(&name, "", &plan(&trace)).unwrap();
    assert_eq!(slot.state(), PilotState::NoInput);
    let mut pilot = opened.start(&root, slot.clone(), None).unwrap();

    let f = frame_number(&slot, 4);
    assert_eq!(f.frame, 4, "frames 3 to 6 of the trace");
    assert_eq!(f.state, PilotState::Groundstation);
    assert_eq!(slot.state(), PilotState::Groundstation);
    assert_eq!(
        f.values(),
        [1_100_000, 1_200_000, 1_300_000, 1_400_000, 1_000_000]
    );
    assert_eq!(f.end_mono_ns, start + 6 * FRAME_NS);
    let s = published(&sub, |s| s.frames == 4);
    assert_eq!(s.state, ReadbackState::Following as u32);
    assert_eq!((s.matched, s.mismatched, s.changes), (4, 0, 1));
    assert_eq!(s.changed_mono_ns, start + 3 * FRAME_NS);

    append(&trace, &lines(&all[split..]));
    let f = frame_number(&slot, 7);
    assert_eq!(f.frame, 7);
    assert_eq!(f.state, PilotState::Pilot);
    assert_eq!(
        f.values(),
        [1_100_000, 1_200_000, 1_300_000, 1_400_000, 2_000_000]
    );
    assert_eq!(f.end_mono_ns, start + 9 * FRAME_NS);
    let s = published(&sub, |s| s.frames == 7);
    assert_eq!(s.state, ReadbackState::Overridden as u32);
    assert_eq!((s.matched, s.mismatched, s.changes), (4, 3, 2));
    assert_eq!(s.changed_mono_ns, start + 7 * FRAME_NS);

    // A second after the last frame ended, nobody flies.
    let s = published(&sub, |s| s.state == ReadbackState::NoInput as u32);
    assert_eq!(slot.state(), PilotState::NoInput);
    assert!(now_ns() >= start + 9 * FRAME_NS + 1_000_000_000);
    assert_eq!((s.frames, s.matched, s.mismatched, s.changes), (7, 4, 3, 3));
    assert!(s.changed_mono_ns >= start + 9 * FRAME_NS + 1_000_000_000);
    assert_eq!(s.edges, 2 * all.len() as u64);
    assert_eq!(s.refused, [0, 0, 0, 0, 0, 0, 2, 0], "the two that locked");
    assert_eq!(s.channels, 5);
    assert_eq!(s.start_mono_ns, start + 8 * FRAME_NS);
    assert_eq!(
        s.values_ns[..6],
        [1_100_000, 1_200_000, 1_300_000, 1_400_000, 2_000_000, 0]
    );
    pilot.finish();
    drop((sub, service, node));
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn a_stopped_pilot_thread_leaves_no_input() {
    let d = dir("stop");
    let (trace, root) = (d.join("radio.trace"), d.join("ipc"));
    let name = format!("pilotstop{}", std::process::id());
    let start = now_ns() + 2_000_000_000;
    append(&trace, &lines(&leads(start, &[1_000; 4])));
    let slot = Arc::new(PilotSlot::default());
    let mut pilot = Opened::open(&name, "", &plan(&trace))
        .unwrap()
        .start(&root, slot.clone(), None)
        .unwrap();
    assert_eq!(frame_number(&slot, 2).frame, 2);
    assert_eq!(slot.state(), PilotState::Groundstation);
    pilot.finish();
    assert_eq!(slot.state(), PilotState::NoInput);
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn an_input_that_cannot_be_had_names_ppmd_pilot_and_is_a_fault_of_the_configuration() {
    let mut p = plan(Path::new("unused"));
    p.input = "gpio:ppm-no-such-chip:17".parse().unwrap();
    let e = Opened::open("x", "x: ", &p).err().expect("no such chip");
    let msg = format!("{e:#}");
    assert!(
        msg.starts_with("x: ppmd.pilot: opening gpio:ppm-no-such-chip:17: input gpio:ppm-no-such-chip:17: no GPIO chip `ppm-no-such-chip`"),
        "{msg}"
    );
    assert_eq!(
        ppm_shared::daemon::exit_status(&e, ppmd::output_fault),
        ppm_shared::daemon::EXIT_CONFIG
    );
}
