//! CRSF through the whole pipeline, with the real binaries: commands in
//! over UDP, RC_CHANNELS_PACKED and LINK_STATISTICS frames out on the
//! simulated line (read back as a 420 000 baud 8N1 UART and each
//! firmware's framing read them) and on a pseudo-terminal (the exact bytes,
//! and the terminal settings ppmd set, read through termios2).

use ppm_shared::crsf::{self, CrsfReceiver, Framer, LinkStatistics, Verdict};
use ppm_shared::frame::Level;
use ppm_shared::wire::uart::{self, Parity, UartFormat};
use ppm_tests::{at_50hz, read_trace, stop_all, Pty, Sandbox, Sender};
use std::time::Duration;

/// CRSF's UART format at the default rate.
const FORMAT: UartFormat = UartFormat {
    baud: 420_000,
    parity: Parity::None,
    stop_bits: 1,
};

/// `[ppm]` for CRSF to `receiver`, following the commands.
fn crsf_config(receiver: &str) -> String {
    format!("[ppm]\nprotocol = \"crsf\"\nreceiver = \"{receiver}\"\ntiming = \"follow\"\n")
}

/// Sends 60 commands at 50 Hz, the k-th with aileron at 1100 + 5 k us,
/// rudder at 1700 and aux12 (the 16th channel) at 1900; returns their
/// aileron values, us.
fn send_60(sb: &Sandbox) -> Vec<u64> {
    let sender = Sender::new(sb.addr());
    let mut sent = Vec::new();
    at_50hz(60, |k| {
        let ail = 1_100 + 5 * k;
        sender.send(format!("{{\"ail\": {ail}, \"rud\": 1700, \"aux12\": 1900}}").as_bytes());
        sent.push(ail);
    });
    std::thread::sleep(Duration::from_millis(100));
    sent
}

/// What `r`'s framing takes from `bytes` (each with the time its stop bit
/// ends): the RC channels it uses, ns, and how many link statistics frames
/// it read.
fn taken(r: CrsfReceiver, bytes: &[(u8, u64)]) -> (Vec<[u64; 16]>, usize) {
    let mut framer = Framer::new(r);
    let (mut rc, mut links) = (Vec::new(), 0);
    for &(b, end) in bytes {
        if let Some(t) = framer.push(b, end) {
            match r.verdict(&t) {
                Verdict::Used { channels_ns } => rc.push(channels_ns),
                Verdict::LinkStatistics(l) => {
                    assert_eq!(l, LinkStatistics::WIRED);
                    links += 1;
                }
                Verdict::Ignored => panic!("{r:?} ignored {:02x?}", t.frame()),
            }
        }
    }
    (rc, links)
}

/// The simulated line's trace, read as a 420 000 baud 8N1 UART from the
/// real edge times, is every frame: each firmware takes every RC frame
/// and a LINK_STATISTICS after each, and reads the values as sent, in
/// channel order (AETR: ail, ele, thr, rud), to 1 us.
#[test]
fn crsf_on_the_simulated_line_reads_back_as_8n1_at_420000() {
    let sb = Sandbox::new("crsf-sim");
    let cfg = sb.config(&crsf_config("any"));
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let sent = send_60(&sb);
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let trace = read_trace(&sb.dir.join("line.trace"));
    assert_eq!(trace.protocol, ppm_shared::frame::Protocol::Crsf);
    let edges: Vec<(u64, Level)> = trace.edges.iter().map(|e| (e.actual_ns, e.level)).collect();
    let chars = uart::decode(FORMAT, &edges, Level::High);
    assert!(
        chars.iter().all(|c| c.parity_ok && c.stop_ok),
        "8N1 throughout"
    );
    let frame_len = crsf::RC_FRAME_LEN + LinkStatistics::FRAME_LEN;
    assert_eq!(chars.len() % frame_len, 0, "whole frames");
    let frames = chars.len() / frame_len;
    assert!(frames >= 60, "{frames} frames");
    let bytes: Vec<(u8, u64)> = chars.iter().map(|c| (c.byte, c.end_ns)).collect();
    for r in CrsfReceiver::ALL {
        let (rc, links) = taken(r, &bytes);
        assert_eq!(
            (rc.len(), links),
            (frames, frames),
            "{r:?} takes every frame"
        );
        let mut ail: Vec<u64> = Vec::new();
        for ch in &rc {
            let near = |ns: u64, us: u64| ns.abs_diff(us * 1_000) <= 1_000;
            assert!(near(ch[1], 1_500) && near(ch[2], 1_000), "{r:?} {ch:?}");
            ail.push((ch[0] + 500) / 1_000);
            if near(ch[3], 1_700) {
                assert!(near(ch[15], 1_900), "{r:?} {ch:?}");
            }
        }
        ail.dedup();
        let close =
            ail.len() == sent.len() && ail.iter().zip(&sent).all(|(a, s)| a.abs_diff(*s) <= 1);
        assert!(close, "{r:?}: every command in order: {ail:?} vs {sent:?}");
    }
}

/// ppmd sets the pseudo-terminal to raw 420 000 baud 8N1 (read through
/// termios2 from another descriptor) and writes whole frames: an RC frame
/// (address 0xC8, type 0x16, CRC holding, the values Betaflight reads as
/// sent, in channel order), then LINK_STATISTICS.
#[test]
fn crsf_on_a_serial_port_is_rc_frames_and_link_statistics() {
    let sb = Sandbox::new("crsf-pty");
    let pty = Pty::open().expect("a pseudo-terminal");
    let cfg = sb.config(&crsf_config("betaflight"));
    let output = format!("serial:{}", pty.slave.display());
    let cfg_s = cfg.to_str().unwrap();
    let mut ppmd = sb.spawn("ppmd", &["--config", cfg_s, "--output", &output], "ppmd");
    ppmd.wait_for_log("commands from", Duration::from_secs(20));
    let mut ingress = sb.start_ingress(&cfg, &[]);
    let settings = ppmd::line::serial::SerialLine::settings_of(&pty.slave).expect("TCGETS2");
    let sent = send_60(&sb);
    stop_all(&mut ppmd, &mut [&mut ingress]);
    let chunks = pty.finish();
    assert_eq!((settings.ispeed, settings.ospeed), (420_000, 420_000));
    assert_eq!(
        (settings.data_bits, settings.stop_bits, settings.parity),
        (8, 1, Parity::None)
    );
    assert!(settings.raw && !settings.flow_control, "{settings:?}");
    let bytes: Vec<u8> = chunks.iter().flat_map(|c| c.1.clone()).collect();
    let frame_len = crsf::RC_FRAME_LEN + LinkStatistics::FRAME_LEN;
    assert_eq!(bytes.len() % frame_len, 0, "whole frames only");
    let r = CrsfReceiver::Betaflight;
    let mut ail = Vec::new();
    for f in bytes.chunks(frame_len) {
        let (rc, link) = f.split_at(crsf::RC_FRAME_LEN);
        assert_eq!(link, LinkStatistics::WIRED.encode(), "link statistics");
        assert!(crsf::crc_holds(link));
        let raw = crsf::decode_rc(rc.try_into().unwrap()).expect("0xC8, 0x16, CRC");
        // Betaflight's scaling, to half its 0.625 us step.
        let read = |i: usize| r.read_ns(raw[i]);
        assert!(
            read(2).abs_diff(1_000_000) <= 313,
            "throttle at its default"
        );
        assert!(
            read(1).abs_diff(1_500_000) <= 313,
            "elevator at its default"
        );
        assert!(read(15).abs_diff(1_900_000) <= 313 || read(3).abs_diff(1_500_000) <= 313);
        ail.push((read(0) + 500) / 1_000);
    }
    ail.dedup();
    assert_eq!(ail, sent, "every command, in order");
}
