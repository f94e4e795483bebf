//! CRSF through the seam: the configuration's checks (each refusal names
//! its key) and, for any accepted configuration, every frame the encoder
//! path writes ([`FrameModel::encode_bytes`], what ppmd's loop calls)
//! read back exactly through each firmware's framing.

use super::*;
use crate::config::Config;
use crate::crsf::{Framer, Verdict};
use crate::frame::{Channels, FrameModel};
use crate::wire::{Protocol, WireModel, MAX_FRAME_BYTES};
use proptest::prelude::*;

fn model(extra: &str) -> Result<FrameModel, crate::config::ConfigError> {
    Config::parse(&format!("[ppm]\nprotocol = \"crsf\"\n{extra}"))?.validate()
}

fn refused_key(text: &str) -> String {
    let e = Config::parse(text)
        .and_then(|c| c.validate())
        .expect_err(text);
    let key = e.key().unwrap_or("").to_string();
    eprintln!("{text}: {e}");
    key
}

#[test]
fn the_defaults_are_16_channels_at_420000_8n1_on_serial_and_sim() {
    for out in ["serial:/dev/ttyAMA0", "sim"] {
        let m = model(&format!("[ppmd]\noutput = \"{out}\"")).unwrap();
        let WireModel::Crsf(w) = *m.wire() else {
            panic!("{:?}", m.wire());
        };
        assert_eq!(w.encode_for(), CrsfFor::Any);
        assert_eq!(m.channels(), 16);
        assert_eq!(m.wire().uart().unwrap().describe(), "420000 baud 8N1");
        assert_eq!(m.wire().frame_wire_ns(), 952_380);
        assert_eq!(m.wire().protocol(), Protocol::Crsf);
    }
    let m = model("crsf_baud = 416666\nreceiver = \"ardupilot\"").unwrap();
    assert_eq!(m.wire().uart().unwrap().baud, 416_666);
}

#[test]
fn refusals_name_their_key() {
    let crsf = "[ppm]\nprotocol = \"crsf\"\n";
    for (extra, key) in [
        ("receiver = \"edgetx\"", "ppm.receiver"),
        ("receiver = \"opentx\"", "ppm.receiver"),
        ("[failsafe]\naction = \"flag\"", "failsafe.action"),
        ("[failsafe]\nstartup = \"flag\"", "failsafe.startup"),
        ("[ppmd]\noutput = \"gpio:/dev/gpiochip0:18\"", "ppmd.output"),
        ("[ppmd]\noutput = \"spi:/dev/spidev0.0\"", "ppmd.output"),
        ("[ppmd]\noutput = \"sim-spi\"", "ppmd.output"),
        (
            "idle_level = \"low\"\n[ppmd]\noutput = \"serial:/dev/ttyAMA0\"",
            "ppm.idle_level",
        ),
        ("crsf_baud = 9600", "ppm.crsf_baud"),
        ("channels = 8", "ppm.channels"),
        ("follow_sync_min_us = 1000.0", "ppm.follow_sync_min_us"),
        ("timing = \"grid\"\nframe_us = 2000.0", "ppm.frame_us"),
    ] {
        assert_eq!(refused_key(&format!("{crsf}{extra}")), key, "{extra}");
    }
    let e = Config::parse(&format!("{crsf}receiver = \"edgetx\""))
        .unwrap()
        .validate()
        .unwrap_err()
        .to_string();
    assert!(e.contains("trainer port"), "{e}");
    // hold, default and silence are taken.
    for action in ["silence", "hold", "default"] {
        model(&format!("[failsafe]\naction = \"{action}\"")).unwrap();
    }
}

/// Frames every `period_ns` from 1 ms, each `bytes` back to back at `baud`
/// (8N1), as `r`'s framing takes them.
fn take(r: CrsfReceiver, frames: &[Vec<u8>], period_ns: u64, baud: u64) -> Vec<Verdict> {
    let mut framer = Framer::new(r);
    let mut out = Vec::new();
    for (k, f) in frames.iter().enumerate() {
        let start = 1_000_000 + k as u64 * period_ns;
        for (i, &b) in f.iter().enumerate() {
            let end = start + (i as u64 + 1) * 10 * 1_000_000_000 / baud;
            if let Some(t) = framer.push(b, end) {
                out.push(r.verdict(&t));
            }
        }
    }
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any accepted configuration (receiver, baud, channel limits), any
    /// commands: every frame is taken by each firmware covered, its RC
    /// frame read as the encoder meant (exactly, or within Betaflight's
    /// half step, for the firmware encoded for; within 1 us for the others
    /// under `any`), in channel order, and link statistics after each.
    #[test]
    fn every_frame_reads_back_in_each_firmware(
        receiver in prop::sample::select(vec!["any", "betaflight", "ardupilot"]),
        baud in prop::sample::select(vec![416_666u32, 420_000, 921_600]),
        commands in prop::collection::vec(prop::collection::vec(1_000u32..=2_000, 1..=16), 1..8),
    ) {
        let m = model(&format!("receiver = \"{receiver}\"\ncrsf_baud = {baud}")).unwrap();
        let WireModel::Crsf(w) = *m.wire() else { unreachable!() };
        let mut frames = Vec::new();
        let mut wanted = Vec::new();
        for c in &commands {
            let ns: Vec<u32> = c.iter().map(|us| us * 1_000).collect();
            let values = Channels::from_ns(&ns);
            let mut out = [0u8; MAX_FRAME_BYTES];
            let n = m.encode_bytes(&values, false, &mut out);
            prop_assert_eq!(n, FRAME_LEN);
            frames.push(out[..n].to_vec());
            let want: Vec<u64> = (0..16)
                .map(|i| c.get(i).map_or(m.default_ns(i) as u64, |&us| u64::from(us) * 1_000))
                .collect();
            wanted.push(want);
        }
        let period = m.wire().frame_wire_ns() + GAP_LEAST_US * 1_000;
        for &r in w.encode_for().receivers() {
            let got = take(r, &frames, period, u64::from(baud));
            prop_assert_eq!(got.len(), 2 * frames.len(), "{:?}", r);
            for (pair, want) in got.chunks(2).zip(&wanted) {
                let Verdict::Used { channels_ns } = pair[0] else {
                    return Err(TestCaseError::fail(format!("{r:?}: {:?}", pair[0])));
                };
                prop_assert_eq!(pair[1], Verdict::LinkStatistics(LinkStatistics::WIRED));
                let tolerance = match w.encode_for() {
                    CrsfFor::Any => 1_000,
                    CrsfFor::One(_) => r.whole_us_error_ns(),
                };
                for (i, (&got, &want)) in channels_ns.iter().zip(want).enumerate() {
                    prop_assert!(got.abs_diff(want) <= tolerance, "{:?} ch{} {} vs {}", r, i, got, want);
                }
            }
            // What the seam reports as read: the firmware encoded for.
            let mut read = [0u64; MAX_CHANNELS];
            prop_assert_eq!(m.wire().reads(&frames[0], &mut read), 16);
        }
    }
}
