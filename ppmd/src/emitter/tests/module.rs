//! A grid output that drives an ExpressLRS transmitter module: RC frames
//! to 0xEE that the module's own framing (a port of ExpressLRS's
//! `CRSFHandset::handleInput`) takes, every one; periods that follow the
//! module's timing corrections as EdgeTX does (the rate, the offset added
//! once, bounded steps carrying the rest), back to `ppm.frame_us` when
//! corrections stop for 2 s.

use super::*;
use crate::emitter::module::ModuleTiming;
use ppm_shared::crsf::module::{Correction, HandsetParser};
use ppm_shared::crsf::{self, ADDRESS_TRANSMITTER, RC_FRAME_LEN};

/// A module output: 400000 baud, 4 ms before any correction.
fn module_model() -> FrameModel {
    Config::parse(
        "[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\nreceiver = 'betaflight'\n[ppmd]\npilot = 'sim:pilot.trace'\n[pilot]\nswitch_channel = 5",
    )
    .unwrap()
    .validate()
    .unwrap()
}

/// A module's end of the line: the frames written, each with when it
/// left; after the `at`th frame leaves, correction `c` is set (as the
/// telemetry thread sets one when the module's answer comes).
struct ModuleLine {
    sim: Sim,
    frames: Vec<(Vec<u8>, u64)>,
    timing: Arc<ModuleTiming>,
    corrections: Vec<(usize, Correction)>,
    /// After which frames the module is heard anew (the model ID is asked
    /// for).
    heard: Vec<usize>,
}

impl FrameLine for ModuleLine {
    fn park(&mut self, _: Level) -> Result<(), LineError> {
        Ok(())
    }
    fn write_frame(&mut self, frame: WholeFrame<'_>) -> Result<(), LineError> {
        let WholeFrame::Bytes { bytes, .. } = frame else {
            panic!("a PPM frame on a CRSF line");
        };
        self.frames.push((bytes.to_vec(), self.sim.at()));
        let k = self.frames.len() - 1;
        for (_, c) in self.corrections.iter().filter(|(at, _)| *at == k) {
            self.timing.set(*c, self.sim.at());
        }
        if self.heard.contains(&k) {
            self.timing.request_model_id();
        }
        Ok(())
    }
}

/// Runs a module output for `until_ms` with `corrections` (after which
/// frame, which correction); the frames and the steps between their
/// starts, us.
fn run_module(
    corrections: Vec<(usize, Correction)>,
    until_ms: u64,
) -> (Vec<(Vec<u8>, u64)>, Vec<u64>) {
    run_heard(corrections, vec![], until_ms).0
}

/// [`run_module`], the module heard anew after the frames `heard`: also
/// how many model ID commands the loop sent.
#[allow(clippy::type_complexity)]
fn run_heard(
    corrections: Vec<(usize, Correction)>,
    heard: Vec<usize>,
    until_ms: u64,
) -> ((Vec<(Vec<u8>, u64)>, Vec<u64>), u64) {
    let sim = Sim::new();
    let model = module_model();
    let timing = Arc::new(ModuleTiming::default());
    let mut line = ModuleLine {
        sim: sim.clone(),
        frames: Vec::new(),
        timing: timing.clone(),
        corrections,
        heard,
    };
    let mut src = Fresh::new(&sim, &model, "[1100, 1900, 1500, 1200]");
    let mut kit = Kit::default();
    let mut out = output(
        &model,
        cfg(100, FailsafeAction::Default),
        &mut src,
        LineRef::Whole(&mut line),
        &mut kit,
    );
    out.sync = Some(&timing);
    run_until(&sim, Margin::Fixed(100_000), &mut [out], &mut [], until_ms);
    let steps = line
        .frames
        .windows(2)
        .map(|w| (w[1].1 - w[0].1) / 1_000)
        .collect();
    ((line.frames, steps), timing.model_ids())
}

#[test]
fn a_module_heard_anew_gets_the_model_id_before_the_next_frame_once() {
    use ppm_shared::crsf::module::{model_id_frame, MODEL_ID_FRAME_LEN};
    let ((frames, steps), sent) = run_heard(vec![], vec![3, 20], 200);
    assert_eq!(sent, 2);
    let mut parser = HandsetParser::default();
    let mut kinds = Vec::new();
    for (k, (bytes, _)) in frames.iter().enumerate() {
        let want = if k == 4 || k == 21 {
            RC_FRAME_LEN + MODEL_ID_FRAME_LEN
        } else {
            RC_FRAME_LEN
        };
        assert_eq!(bytes.len(), want, "frame {k}");
        if want > RC_FRAME_LEN {
            assert_eq!(bytes[..MODEL_ID_FRAME_LEN], model_id_frame(0));
        }
        parser.feed(bytes, |f| kinds.push(f[2]));
    }
    assert_eq!(parser.bad, 0);
    assert_eq!(kinds.iter().filter(|&&k| k == 0x32).count(), 2);
    assert_eq!(kinds.iter().filter(|&&k| k == 0x16).count(), frames.len());
    // The pace is the grid's, model ID or not.
    assert!(steps.iter().all(|&s| s == 4_000), "{steps:?}");
}

fn correction(rate_us: i32, offset_us: i32) -> Correction {
    Correction {
        rate_tenths: rate_us * 10,
        offset_tenths: offset_us * 10,
    }
}

#[test]
fn every_frame_is_an_rc_frame_to_the_module_that_its_framing_takes() {
    let (frames, _) = run_module(vec![], 200);
    assert!(frames.len() >= 40, "{} frames", frames.len());
    let mut parser = HandsetParser::default();
    let mut taken = Vec::new();
    for (bytes, _) in &frames {
        assert_eq!(bytes.len(), RC_FRAME_LEN, "an RC frame alone");
        parser.feed(bytes, |f| taken.push(f.to_vec()));
    }
    assert_eq!(parser.bad, 0);
    assert_eq!(taken.len(), frames.len());
    let model = module_model();
    for f in &taken {
        assert_eq!(f[0], ADDRESS_TRANSMITTER);
        let rc: [u8; RC_FRAME_LEN] = f.as_slice().try_into().unwrap();
        let raw = crsf::decode_rc_to(ADDRESS_TRANSMITTER, &rc).expect("an RC frame to 0xEE");
        // The flight controller behind the link (Betaflight) reads the
        // command to its 0.62 us step, the rest at their defaults.
        let want = [1_100_000, 1_900_000, 1_500_000, 1_200_000];
        for (i, &r) in raw.iter().enumerate() {
            let got = crsf::CrsfReceiver::Betaflight.read_ns(r);
            let want = want
                .get(i)
                .copied()
                .unwrap_or(u64::from(model.default_ns(i)));
            assert!(got.abs_diff(want) <= 320, "channel {i}: {got} for {want}");
        }
    }
}

#[test]
fn the_grid_takes_the_module_rate_and_adds_its_offset_once() {
    let (_, steps) = run_module(vec![(10, correction(5_000, 1_000))], 400);
    // Frames 0..=11 were placed before the correction came (frame 11's
    // start was set when frame 10 was decided): 4 ms apart.
    assert!(
        steps[..11].iter().all(|&s| s == 4_000),
        "{:?}",
        &steps[..12]
    );
    // Frame 12 comes 5 ms + 1 ms after frame 11, then every 5 ms.
    assert_eq!(steps[11], 6_000, "{:?}", &steps[..14]);
    assert!(
        steps[12..].iter().all(|&s| s == 5_000),
        "{:?}",
        &steps[12..]
    );
    assert!(steps.len() > 60, "{} steps", steps.len());
}

#[test]
fn a_large_offset_is_spread_over_bounded_steps() {
    // -10 ms at a 4 ms rate: steps are at least the RC frame's time on the
    // wire (650 us at 400000 baud) and the 100 us idle line; the rest of
    // the offset is carried to the next steps, as EdgeTX carries its lag.
    let (_, steps) = run_module(vec![(5, correction(4_000, -10_000))], 100);
    assert_eq!(
        &steps[5..11],
        &[4_000, 750, 750, 750, 3_750, 4_000],
        "{steps:?}"
    );
    // The module asked 10 ms less in all: that is what the steps took.
    let taken: i64 = steps[6..10].iter().map(|&s| s as i64 - 4_000).sum();
    assert_eq!(taken, -10_000);
}

#[test]
fn a_newer_correction_replaces_the_rate_and_its_offset_goes_once() {
    let (_, steps) = run_module(
        vec![(5, correction(5_000, 0)), (30, correction(2_000, 300))],
        200,
    );
    assert_eq!(steps[6], 5_000, "{steps:?}");
    assert_eq!(steps[31], 2_300, "{:?}", &steps[28..35]);
    assert!(
        steps[32..].iter().all(|&s| s == 2_000),
        "{:?}",
        &steps[32..]
    );
}

#[test]
fn without_corrections_for_2_s_the_grid_goes_back_to_frame_us() {
    let (frames, steps) = run_module(vec![(0, correction(5_000, 0))], 3_000);
    let start = frames[0].1;
    for (w, &s) in frames.windows(2).zip(&steps).skip(2) {
        // The correction was set when frame 0 left: 2 s later it is stale.
        let age = w[0].1 - start;
        if age + 100_000 < crate::emitter::module::STALE_NS - 10_000_000 {
            assert_eq!(s, 5_000, "at {age} ns");
        } else if age > crate::emitter::module::STALE_NS + 10_000_000 {
            assert_eq!(s, 4_000, "at {age} ns");
        }
    }
    assert_eq!(*steps.last().unwrap(), 4_000);
}
