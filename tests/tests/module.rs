//! CRSF to an ExpressLRS transmitter module, end to end with the real
//! binaries: a simulated module on a pseudo-terminal
//! ([`ppm_tools::module::SimModule`]: frames ppmd's bytes as ExpressLRS does,
//! keeps its own radio packet timer and answers as the module does, a
//! timing correction every 200 ms and link statistics); a simulated pilot's
//! radio (a PPM trace read through `ppmd.pilot = "sim:PATH"`) whose
//! takeover switch gives the pilot the controls; the groundstation's
//! commands over UDP.

use ppm_shared::crsf::{self, CrsfReceiver, LinkStatistics, ADDRESS_TRANSMITTER, RC_FRAME_LEN};
use ppm_shared::time::now_ns;
use ppm_tests::{at_50hz, status, stop_all, Pty, Sandbox, Sender};
use ppm_tools::module::{pilot_radio, SimModule, PILOT_STICKS_US};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::SeqCst};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The module's packet interval, us: 200 Hz, not ppm's 4000 us default,
/// so following it shows.
const MODULE_INTERVAL_US: i64 = 5_000;
/// The module's link statistics: -67 dBm, 98 %, 9 dB SNR, RF mode 5.
const LINK: LinkStatistics = LinkStatistics {
    uplink_rssi_ant1: 67,
    uplink_rssi_ant2: 70,
    uplink_link_quality: 98,
    uplink_snr: 9,
    active_antenna: 0,
    rf_mode: 5,
    uplink_tx_power: 3,
    downlink_rssi: 60,
    downlink_link_quality: 97,
    downlink_snr: 7,
};

/// `[ppm]` and the rest for a module on `pty`, with a pilot's radio in
/// `pilot` (none: `None`).
fn module_config(pty: &Path, pilot: Option<&Path>) -> String {
    let pilot = pilot.map_or(String::new(), |p| {
        format!("pilot = \"sim:{}\"\n", p.display())
    });
    format!(
        "[ppm]\nprotocol = \"crsf\"\ncrsf_target = \"module\"\nreceiver = \"betaflight\"\n[ppmd]\noutput = \"serial:{}\"\n{pilot}[pilot]\nswitch_channel = 5\n[failsafe]\nstartup = \"silence\"\n",
        pty.display()
    )
}

/// ppmd refuses to drive a module without a pilot's radio: exit 78, the
/// message naming `ppmd.pilot`, nothing written to the module.
#[test]
fn a_module_without_a_pilots_radio_does_not_start() {
    let sb = Sandbox::new("module-refused");
    let pty = Pty::open().expect("a pseudo-terminal");
    let cfg = sb.config(&module_config(&pty.slave, None));
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg.to_str().unwrap()], "ppmd");
    let status = ppmd.wait(Duration::from_secs(20));
    let log = ppmd.log_text();
    assert_eq!(status.code(), Some(78), "{log}");
    assert!(
        log.contains("`ppmd.pilot`") && log.contains("take over"),
        "{log}"
    );
    assert!(pty.finish().is_empty(), "bytes reached the module");
}

/// The whole set-up: no frame before the pilot's radio is read; then the
/// groundstation's commands, at the module's rate and phase; the pilot's
/// sticks once the takeover switch is on, which the groundstation hears;
/// the module's link statistics in the status reply.
#[test]
fn a_module_gets_the_groundstation_then_the_pilot_at_its_own_pace() {
    let sb = Sandbox::new("module");
    let module = Arc::new(Mutex::new(SimModule::new(MODULE_INTERVAL_US, LINK)));
    let pty = {
        let m = module.clone();
        Pty::open_answering(move |now, bytes| m.lock().unwrap().bytes(now, bytes))
            .expect("a pseudo-terminal")
    };
    let pilot_trace = sb.dir.join("pilot.trace");
    let cfg = sb.config(&module_config(&pty.slave, Some(&pilot_trace)));
    let cfg_s = cfg.to_str().unwrap();
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg_s], "ppmd");
    ppmd.wait_for_log("telemetry: reading", Duration::from_secs(20));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let sender = Sender::new(sb.addr());
    let command = b"[1300, 1700, 1000, 1200]";

    // No pilot's radio yet: commands come, and none goes out.
    at_50hz(50, |_| sender.send(command));
    assert!(
        module.lock().unwrap().frames.is_empty(),
        "frames went out before a pilot could take over"
    );

    // The pilot's radio, switch off: the groundstation flies.
    let (takeover, flipped, stop) = (
        Arc::new(AtomicBool::new(false)),
        Arc::new(AtomicU64::new(0)),
        Arc::new(AtomicBool::new(false)),
    );
    let radio = {
        let (t, f, s, p) = (
            takeover.clone(),
            flipped.clone(),
            stop.clone(),
            pilot_trace.clone(),
        );
        std::thread::spawn(move || pilot_radio(&p, &t, &f, &s))
    };
    at_50hz(200, |_| sender.send(command));
    let settled = now_ns() - 1_500_000_000;
    let st = status(sb.addr());

    // The switch on: the pilot flies.
    takeover.store(true, SeqCst);
    at_50hz(50, |_| sender.send(command));
    let st_pilot = status(sb.addr());

    // The switch off again, then the pilot's radio lost while the
    // groundstation keeps sending: the line goes silent a second later.
    takeover.store(false, SeqCst);
    at_50hz(25, |_| sender.send(command));
    stop.store(true, SeqCst);
    radio.join().unwrap();
    let lost = now_ns();
    at_50hz(100, |_| sender.send(command));
    let st_lost = status(sb.addr());
    stop_all(&mut ppmd, &mut [&mut ingress]);
    drop(pty);
    let m = module.lock().unwrap();

    // The module's first answer made ppmd send it the model ID (0 by
    // default), before a frame of the next ones.
    assert!(!m.model_ids.is_empty(), "no model ID command");
    assert_eq!(m.model_ids[0].1, 0);
    assert!(
        m.model_ids[0].0 > m.frames[0].0,
        "the model ID came after the module answered"
    );
    assert!(m.model_ids[0].0 < m.frames[0].0 + 100_000_000);
    assert_eq!(m.other, 0);
    // Every other frame is an RC frame to the module; Betaflight behind
    // the link reads the groundstation's values, then the pilot's.
    assert_eq!(m.parser.bad, 0);
    let r = CrsfReceiver::Betaflight;
    let mut seen: Vec<[u64; 4]> = m
        .frames
        .iter()
        .map(|(_, f)| {
            assert_eq!((f[0], f.len()), (ADDRESS_TRANSMITTER, RC_FRAME_LEN));
            let raw = crsf::decode_rc_to(ADDRESS_TRANSMITTER, f[..].try_into().unwrap())
                .expect("an RC frame to 0xEE");
            std::array::from_fn(|i| (r.read_ns(raw[i]) + 500) / 1_000)
        })
        .collect();
    seen.dedup();
    assert_eq!(
        seen,
        [
            [1_300, 1_700, 1_000, 1_200],
            PILOT_STICKS_US,
            [1_300, 1_700, 1_000, 1_200]
        ],
        "the groundstation's command, the pilot's sticks, the groundstation's, nothing else"
    );
    // The pilot's thread finds its radio lost after a second without a
    // whole frame; the loop is silent at its next decision.
    let after: Vec<u64> = m.frames.iter().map(|f| f.0).filter(|&t| t > lost).collect();
    let last = after.last().map_or(0, |t| t - lost);
    eprintln!(
        "the pilot's radio lost: the last frame {} ms later",
        last / 1_000_000
    );
    assert!(
        last < 1_300_000_000,
        "a frame {last} ns after the pilot's radio was lost"
    );
    let rb = st_lost.readback.expect("the pilot's state");
    assert_eq!(rb.state, "no_input", "{rb:?}");

    // The module's pace: over the last 1.5 s before the switch, frames
    // at its 5 ms (not ppm's 4 ms), and whole a little before its packet
    // timer, as its corrections ask (the median lead; a module that is not
    // followed sees leads spread over its whole interval).
    let steady: Vec<u64> = m
        .frames
        .iter()
        .map(|f| f.0)
        .filter(|&t| t >= settled && t < settled + 1_500_000_000)
        .collect();
    assert!(
        (270..=330).contains(&steady.len()),
        "{} frames in 1.5 s at the module's 200 Hz",
        steady.len()
    );
    let mut leads: Vec<u64> = m
        .ticks
        .iter()
        .filter(|t| t.0 >= settled && t.0 < settled + 1_500_000_000)
        .map(|t| t.1)
        .collect();
    leads.sort_unstable();
    let median = leads[leads.len() / 2];
    eprintln!(
        "module: {} frames in 1.5 s; lead before its packet timer: p10 {} us, median {} us, p90 {} us",
        steady.len(),
        leads[leads.len() / 10] / 1_000,
        median / 1_000,
        leads[leads.len() * 9 / 10] / 1_000
    );
    assert!(
        median < 1_500_000,
        "median lead {median} ns of a 5 ms interval"
    );

    // Who flies reaches the groundstation, and the module's link.
    let rb = st.readback.expect("the pilot's state");
    assert_eq!(rb.state, "following", "{rb:?}");
    assert_eq!(rb.input, format!("sim:{}", pilot_trace.display()));
    let rb = st_pilot.readback.expect("the pilot's state");
    assert_eq!(rb.state, "overridden", "{rb:?}");
    assert_eq!(
        &rb.ch_us[..5],
        &[1_600.0, 1_450.0, 1_100.0, 1_550.0, 2_000.0]
    );
    let link = st
        .telemetry
        .expect("telemetry")
        .link_statistics
        .expect("link statistics");
    assert_eq!(
        (
            link.rssi_dbm,
            link.link_quality,
            link.snr_db,
            link.rf_mode,
            link.downlink_link_quality
        ),
        (-67, 98, 9, 5, 97)
    );
}

/// A pilot's frames wake a follow output as commands do: with the switch
/// on, each frame of the pilot's radio goes out as soon as the line's
/// shortest sync allows, not when the output next looks for a command (its
/// longest sync, 18 ms). The frame log names each frame's command: the
/// pilot's frame, stamped with the time it ended.
#[test]
fn a_pilots_frames_wake_a_follow_output() {
    let sb = Sandbox::new("pilot-follow");
    let pilot_trace = sb.dir.join("pilot.trace");
    let log = sb.dir.join("frames.jsonl");
    let cfg = sb.config(&format!(
        "[ppm]\ntiming = \"follow\"\n[ppmd]\npilot = \"sim:{}\"\nframe_log = \"{}\"\n[pilot]\nswitch_channel = 5\n",
        pilot_trace.display(),
        log.display()
    ));
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let (takeover, flipped, stop) = (
        Arc::new(AtomicBool::new(true)),
        Arc::new(AtomicU64::new(0)),
        Arc::new(AtomicBool::new(false)),
    );
    let radio = {
        let (t, f, s, p) = (
            takeover.clone(),
            flipped.clone(),
            stop.clone(),
            pilot_trace.clone(),
        );
        std::thread::spawn(move || pilot_radio(&p, &t, &f, &s))
    };
    std::thread::sleep(Duration::from_secs(3));
    stop.store(true, SeqCst);
    radio.join().unwrap();
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let rows = ppm_shared::framelog::read_frames(&log).expect("the frame log");
    let mut waits: Vec<u64> = rows
        .iter()
        .filter(|r| r.ch_us.first().is_some_and(|&v| (v - 1_600.0).abs() < 2.0))
        .filter_map(|r| Some(r.mono_ns - r.recv_mono_ns?))
        .collect();
    assert!(waits.len() >= 60, "{} frames of the pilot's", waits.len());
    waits.sort_unstable();
    let median = waits[waits.len() / 2];
    eprintln!(
        "pilot's frame end to the line's frame start: median {} us, p90 {} us",
        median / 1_000,
        waits[waits.len() * 9 / 10] / 1_000
    );
    // Woken, a frame starts once the pilot's thread has read the frame
    // (it looks every 2 ms) and the shortest sync after the line's last
    // frame allows: measured here a median of 1.5 ms. Not woken, it waits
    // for the output's next look, the 18 ms longest sync: a median of
    // 7.9 ms here.
    assert!(median < 4_000_000, "median wait {median} ns");
}
