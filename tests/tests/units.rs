//! Engineering units and normalised values through the whole pipeline:
//! `units` and `norm` commands over UDP to the real udp-ingress and ppmd,
//! the simulated line's trace decoded with transmitter semantics. Every
//! channel lands to the nanosecond (in scheduled time) on what the
//! configured mapping defines, reverse and trim included.

use ppm_shared::config::Config;
use ppm_tests::{at_50hz, read_trace, stop_all, Sandbox, Sender};

/// ail: degrees on 1000..2000 us; ele: -20..20 on 1100..1900 us, reversed,
/// trimmed -12.5 us; rud: no unit range, reversed, trimmed +5 us (for `norm`).
const CHANNELS: &str = r#"
[ppm.channel.ail]
unit_min = -15.0
unit_max = 15.0
unit = "deg"
[ppm.channel.ele]
unit_min = -20.0
unit_max = 20.0
unit_us_min = 1100.0
unit_us_max = 1900.0
reverse = true
trim_us = -12.5
[ppm.channel.rud]
reverse = true
trim_us = 5.0
"#;

const UNITS: &str = r#"{"units": {"ail": 3.0333, "ele": -5}, "seq": SEQ}"#;
const NORM: &str = r#"{"norm": {"ail": 0.2, "ele": 1, "thr": -0.9, "rud": 0.25, "aux1": -0.5, "aux2": 7}, "seq": SEQ}"#;

/// Sends `n` datagrams at 50 Hz, `seq` numbered from `first`.
fn send_50hz(sender: &Sender, template: &str, first: u64, n: u64) {
    at_50hz(n, |i| {
        let text = template.replace("SEQ", &(first + i).to_string());
        sender.send(text.as_bytes());
    });
}

#[test]
fn units_and_norm_land_exactly_on_the_mapping() {
    let sb = Sandbox::new("units");
    let cfg_path = sb.config(CHANNELS);
    let model = Config::load(&cfg_path).unwrap().validate().unwrap();

    // What the mapping defines, worked out by hand (us), and the model agrees.
    let units_us = [
        1601.11, 1587.5, 1000.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0,
    ];
    let norm_us = [
        1600.0, 1087.5, 1050.0, 1380.0, 1250.0, 2000.0, 1500.0, 1500.0,
    ];
    let ns = |us: &[f64]| -> Vec<u64> { us.iter().map(|u| (u * 1e3).round() as u64).collect() };
    let (want_units, want_norm) = (ns(&units_us), ns(&norm_us));
    assert_eq!(model.units_to_ns(0, 3.0333), Some((1_601_110, false)));
    assert_eq!(model.units_to_ns(1, -5.0), Some((1_587_500, false)));
    assert_eq!(model.norm_to_ns(0, 0.2), (1_600_000, false));
    assert_eq!(model.norm_to_ns(1, 1.0), (1_087_500, false));
    assert_eq!(model.norm_to_ns(2, -0.9), (1_050_000, false));
    assert_eq!(model.norm_to_ns(3, 0.25), (1_380_000, false));
    assert_eq!(model.norm_to_ns(4, -0.5), (1_250_000, false));
    assert_eq!(model.norm_to_ns(5, 7.0), (2_000_000, true));

    let mut ppmd = sb.start_ppmd(&cfg_path, "line.trace");
    let mut ingress = sb.start_ingress(&cfg_path, &[]);

    let sender = Sender::new(sb.addr());
    send_50hz(&sender, UNITS, 1, 40);
    send_50hz(&sender, NORM, 100, 40);
    stop_all(&mut ppmd, &mut [&mut ingress]);

    // Every frame, whole or cut short at a late edge (then with the
    // channels before it, exact; one too short to tell the two apart is
    // left out).
    let frames = read_trace(&sb.dir.join("line.trace")).decode(false);
    let prefix = |v: &[u64], want: &[u64]| v == &want[..v.len().min(want.len())];
    let kinds: Vec<char> = frames
        .iter()
        .filter_map(|f| {
            let v = &f.channels_ns;
            match (prefix(v, &want_units), prefix(v, &want_norm)) {
                (true, true) => None,
                (true, false) => Some('u'),
                (false, true) => Some('n'),
                _ => panic!("frame at {} carries neither mapping: {v:?}", f.start_ns),
            }
        })
        .collect();
    let text: String = kinds.iter().collect();
    let units = text.chars().take_while(|&c| c == 'u').count();
    let norm = text[units..].chars().take_while(|&c| c == 'n').count();
    assert_eq!(
        units + norm,
        text.len(),
        "units frames, then norm frames: {text}"
    );
    // One frame of each is all the order needs (about 35 each on an idle
    // machine; how many a loaded one cuts short is its business).
    assert!(units >= 1 && norm >= 1, "{text}");

    // aux2 = 7 was clamped in every norm command, and counted.
    let log = ingress.log_text();
    let summary = log
        .lines()
        .find(|l| l.contains("stopped:"))
        .expect("ingress summary");
    assert!(summary.contains("clamped 40 (values 40)"), "{summary}");
    assert!(summary.contains("rejected 0 "), "{summary}");
}
