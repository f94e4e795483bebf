//! Property tests: for random valid configurations and commands the decoder
//! reads back exactly what the encoder was given, and every invalid
//! configuration is refused with a message naming its key.

use ppm_shared::config::{ChannelOverride, Config, PpmSection, Timing};
use ppm_shared::decode::{decode, DecoderLimits};
use ppm_shared::frame::{Channels, FrameModel, Level};
use ppm_shared::protocol;
use ppm_shared::receiver::{decode_as, Receiver, ReceiverChoice};
use proptest::prelude::*;

/// The receivers a configuration may be for.
fn receiver() -> impl Strategy<Value = ReceiverChoice> {
    prop_oneof![
        Just(ReceiverChoice::Any),
        Just(ReceiverChoice::One(Receiver::EdgeTx)),
        Just(ReceiverChoice::One(Receiver::OpenTx)),
        Just(ReceiverChoice::One(Receiver::Betaflight)),
        Just(ReceiverChoice::One(Receiver::ArduPilot)),
    ]
}

/// Per-channel limits in tenths of a microsecond within `lo..=hi` (us):
/// (min, default, max).
fn limits(lo: f64, hi: f64) -> impl Strategy<Value = (u32, u32, u32)> {
    let (lo, hi) = ((lo * 10.0).ceil() as u32, (hi * 10.0).floor() as u32);
    (lo..=hi)
        .prop_flat_map(move |min| (Just(min), min..=hi))
        .prop_flat_map(|(min, max)| (Just(min), min..=max, Just(max)))
}

fn order() -> impl Strategy<Value = String> {
    Just(vec!['A', 'E', 'T', 'R'])
        .prop_shuffle()
        .prop_map(|v| v.into_iter().collect())
}

/// A valid `[ppm]` section, built from its receiver's rules.
fn ppm_section() -> impl Strategy<Value = PpmSection> {
    receiver()
        .prop_flat_map(|r| {
            let rules = r.rules();
            let counts = rules.min_channels.0..=rules.max_channels.0;
            (
                Just(r),
                prop::collection::vec(
                    limits(rules.channel_min_us.0, rules.channel_max_us.0),
                    counts,
                ),
                order(),
                any::<bool>(),
                0.0f64..1.0,
                0.0f64..1.0,
            )
        })
        .prop_filter_map(
            "no frame length fits both sync limits",
            |(receiver, lims, order, high, frame_pick, pulse_pick)| {
                let rules = receiver.rules();
                let us = |t: u32| t as f64 / 10.0;
                let sum_max: f64 = lims.iter().map(|l| us(l.2)).sum();
                let sum_min: f64 = lims.iter().map(|l| us(l.0)).sum();
                let (lo, hi) = (
                    sum_max + rules.sync_min_us.0,
                    sum_min + rules.sync_max_us.0.min(30_000.0),
                );
                if lo > hi {
                    return None;
                }
                let frame_us = (lo + (hi - lo) * frame_pick).round();
                let smallest_min = lims.iter().map(|l| us(l.0)).fold(f64::MAX, f64::min);
                let pulse_us = (50.0 + (smallest_min - 51.0) * pulse_pick).floor();
                let names =
                    ppm_shared::config::channel_names(&order, lims.len()).expect("valid order");
                let channel = names
                    .iter()
                    .zip(&lims)
                    .map(|(n, l)| {
                        let o = ChannelOverride {
                            min_us: Some(us(l.0)),
                            default_us: Some(us(l.1)),
                            max_us: Some(us(l.2)),
                            ..ChannelOverride::default()
                        };
                        (n.clone(), o)
                    })
                    .collect();
                Some(PpmSection {
                    channels: Some(lims.len() as u32),
                    frame_us: Some(if frame_us < lo {
                        lo.ceil()
                    } else {
                        frame_us.min(hi)
                    }),
                    pulse_us,
                    idle_level: Some(if high { Level::High } else { Level::Low }),
                    order,
                    channel,
                    receiver,
                    // On a grid: the frame length is part of what is
                    // checked.
                    timing: Timing::Grid,
                    ..PpmSection::default()
                })
            },
        )
}

/// A model and values for every channel within its limits (ns).
fn model_and_values() -> impl Strategy<Value = (FrameModel, Vec<u32>)> {
    ppm_section()
        .prop_map(|s| ppm_shared::frame::FrameModel::build(&s).expect("generated config is valid"))
        .prop_flat_map(|m| {
            let ranges: Vec<_> = (0..m.channels())
                .map(|i| m.min_ns(i)..=m.max_ns(i))
                .collect();
            (Just(m), ranges)
        })
}

/// A decoder that takes any gap longer than a channel as a sync (as
/// Betaflight and ArduPilot do; the receiver models check the rest).
fn any_sync() -> DecoderLimits {
    DecoderLimits {
        sync_min_ns: 2_700_000,
        sync_max_ns: u64::MAX,
        ..DecoderLimits::default()
    }
}

/// Consecutive frames on one timeline, plus the next frame's first edge.
fn waveform(m: &FrameModel, frames: &[Channels]) -> Vec<(u64, Level)> {
    let mut out = vec![];
    for (k, c) in frames.iter().enumerate() {
        let start = k as u64 * m.frame_ns();
        out.extend(
            m.encode(c)
                .edges()
                .iter()
                .map(|e| (start + e.at_ns, e.level)),
        );
    }
    out.push((
        frames.len() as u64 * m.frame_ns(),
        m.idle_level().opposite(),
    ));
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn decode_encode_is_identity((m, values) in model_and_values()) {
        let c = Channels::from_ns(&values);
        let edges = waveform(&m, &[c, c, c]);
        let frames = decode(edges, m.idle_level().opposite(), any_sync());
        // The first frame has no sync before it; a transmitter reads the next two.
        prop_assert_eq!(frames.len(), 2);
        for (k, f) in frames.iter().enumerate() {
            let want: Vec<u64> = values.iter().map(|&v| v as u64).collect();
            prop_assert_eq!(&f.channels_ns, &want);
            prop_assert!(f.complete);
            prop_assert_eq!(f.start_ns, (k as u64 + 1) * m.frame_ns());
        }
    }

    /// Every receiver a configuration is for reads every frame it makes,
    /// whatever the values within their limits, to the microsecond (their
    /// capture clocks truncate).
    #[test]
    fn every_receiver_reads_what_its_configuration_makes((m, values) in model_and_values()) {
        let c = Channels::from_ns(&values);
        // Enough frames for Betaflight to lock on.
        let edges = waveform(&m, &[c; 32]);
        for r in m.receiver().receivers() {
            let (frames, stats) = decode_as(r, edges.iter().copied(), m.idle_level().opposite());
            let complete: Vec<_> = frames.iter().filter(|f| f.complete).collect();
            // The first frame has no sync before it.
            prop_assert_eq!(complete.len(), 31 - r.warmup_frames(), "{:?} {:?}", r, stats);
            prop_assert_eq!(stats.invalid_periods, 0);
            for f in complete {
                prop_assert_eq!(f.channels_ns.len(), values.len());
                for (got, want) in f.channels_ns.iter().zip(&values) {
                    prop_assert!(got.abs_diff(*want as u64) < 1_000, "{:?}: {} for {}", r, got, want);
                }
            }
        }
    }

    #[test]
    fn wire_to_line_keeps_a_tenth_of_a_microsecond(
        (m, values) in model_and_values(),
        give in 1usize..=16,
    ) {
        // Values with one decimal, as a sender would write them.
        let give = give.min(m.channels());
        let tenths: Vec<u64> = values[..give].iter().map(|&v| (v as u64 + 50) / 100).collect();
        let text = format!(
            "[{}]",
            tenths.iter().map(|t| format!("{}.{}", t / 10, t % 10)).collect::<Vec<_>>().join(",")
        );
        let cmd = protocol::parse(text.as_bytes(), &m).expect("valid command");
        let frames = decode(
            waveform(&m, &[cmd.channels, cmd.channels]),
            m.idle_level().opposite(),
            any_sync(),
        );
        prop_assert_eq!(frames.len(), 1);
        for i in 0..m.channels() {
            let want = match tenths.get(i) {
                Some(t) => m.clamp(i, (*t * 100) as u32).0 as u64,
                None => m.default_ns(i) as u64,
            };
            prop_assert_eq!(frames[0].channels_ns[i], want, "channel {}", i + 1);
        }
    }

    #[test]
    fn invalid_configs_name_their_key(s in ppm_section(), which in 0usize..10, pick in 0usize..16) {
        let names = ppm_shared::config::channel_names(&s.order, s.channels() as usize).unwrap();
        let name = names[pick % names.len()].clone();
        let mut bad = s.clone();
        let o = bad.channel.get_mut(&name).unwrap();
        let (min, max) = (o.min_us.unwrap(), o.max_us.unwrap());
        let smallest_min = s.channel.values().map(|o| o.min_us.unwrap()).fold(f64::MAX, f64::min);
        let sum = |f: fn(&ChannelOverride) -> f64| -> f64 { s.channel.values().map(f).sum() };
        let rules = s.receiver.rules();
        // Betaflight and ArduPilot have no longest sync: push the frame to
        // the shortest one instead.
        let which = if which == 3 && !rules.sync_max_us.0.is_finite() { 2 } else { which };
        let key = match which {
            0 => { bad.channels = Some(if pick % 2 == 0 { 0 } else { 17 + pick as u32 }); "ppm.channels".to_string() }
            1 => { bad.pulse_us = smallest_min + pick as f64; "ppm.pulse_us".into() }
            2 => { bad.frame_us = Some(sum(|o| o.max_us.unwrap()) + rules.sync_min_us.0 - 1.0 - pick as f64); "ppm.frame_us".into() }
            3 => { bad.frame_us = Some(sum(|o| o.min_us.unwrap()) + rules.sync_max_us.0 + 1.0 + pick as f64); "ppm.frame_us".into() }
            4 => { o.min_us = Some(rules.channel_min_us.0 - 0.1 - pick as f64); format!("ppm.channel.{name}.min_us") }
            5 => { o.max_us = Some(rules.channel_max_us.0 + 0.1 + pick as f64); format!("ppm.channel.{name}.max_us") }
            6 => { o.default_us = Some(if pick % 2 == 0 { min - 0.1 } else { max + 0.1 }); format!("ppm.channel.{name}.default_us") }
            7 => { o.min_us = Some(max + 0.1); format!("ppm.channel.{name}.min_us") }
            8 => { bad.order = ["AETRA", "AER", "XETR", "aetr x"][pick % 4].into(); "ppm.order".into() }
            _ => { bad.channel.insert(format!("aux{}", 13 + pick), ChannelOverride::default()); format!("ppm.channel.aux{}", 13 + pick) }
        };
        let cfg = Config { ppm: bad, ..Config::default() };
        let err = cfg.validate().expect_err("mutated config must be refused");
        prop_assert_eq!(err.key(), Some(key.as_str()), "{}", err);
        prop_assert!(err.to_string().contains(&key), "{}", err);
    }
}

/// A model whose aileron channel (index 0, limits 820..=2180 us, EdgeTX's
/// window less its margin) has a random
/// unit range, µs range, direction and trim: `(model, unit_min, unit_max)`.
fn units_model() -> impl Strategy<Value = (FrameModel, f64, f64)> {
    (
        -1_000.0f64..1_000.0,
        0.001f64..2_000.0,
        8_000u32..22_000,
        1u32..=14_000,
        any::<bool>(),
        -500.0f64..=500.0,
    )
        .prop_map(|(lo, span, us_lo, us_span, reverse, trim_us)| {
            let us_lo = us_lo as f64 / 10.0;
            let us_hi = (us_lo + us_span as f64 / 10.0).min(2_200.0);
            let o = ChannelOverride {
                min_us: Some(820.0),
                max_us: Some(2_180.0),
                unit_min: Some(lo),
                unit_max: Some(lo + span),
                unit_us_min: Some(us_lo),
                unit_us_max: Some(us_hi),
                reverse,
                trim_us,
                ..ChannelOverride::default()
            };
            let ppm = PpmSection {
                channel: [("ail".to_string(), o)].into(),
                receiver: ReceiverChoice::One(Receiver::EdgeTx),
                ..PpmSection::default()
            };
            let m = ppm_shared::frame::FrameModel::build(&ppm).expect("generated config is valid");
            (m, lo, lo + span)
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1024))]

    /// Unit value -> ns -> the inverse mapping lands within 1 ns of where it
    /// started, and the mapping is monotonic (falling when reversed),
    /// clamping included. Likewise for normalised values.
    #[test]
    fn units_and_norm_round_trip_and_are_monotonic(
        (m, lo, hi) in units_model(),
        p in -0.5f64..1.5,
        q in -0.5f64..1.5,
    ) {
        let span = hi - lo;
        let map = *m.mapping(0);
        let ns_per_unit = (map.us_hi - map.us_lo) * 1e3 / span;
        let (u, v) = (lo + p * span, lo + q * span);
        let (ns_u, clamped) = m.units_to_ns(0, u).expect("ail has a unit range");
        if !clamped {
            let back = m.ns_to_units(0, ns_u).unwrap();
            prop_assert!((back - u).abs() * ns_per_unit <= 1.0, "{} -> {} ns -> {}", u, ns_u, back);
        }
        let ns_v = m.units_to_ns(0, v).unwrap().0;
        let rising = (u <= v) != map.reverse;
        prop_assert!(if rising { ns_u <= ns_v } else { ns_u >= ns_v }, "{} -> {}, {} -> {}", u, ns_u, v, ns_v);

        let (a, b) = (2.0 * p - 1.0, 2.0 * q - 1.0);
        let (ns_a, clamped) = m.norm_to_ns(0, a);
        if !clamped {
            let back = m.ns_to_norm(0, ns_a);
            let ns_per_norm = (map.us_hi - map.us_lo) * 1e3 / 2.0;
            prop_assert!((back - a).abs() * ns_per_norm <= 1.0, "{} -> {} ns -> {}", a, ns_a, back);
            // norm is the unit range stretched to -1..1.
            let same = m.units_to_ns(0, lo + (a + 1.0) / 2.0 * span).unwrap().0;
            prop_assert!(same.abs_diff(ns_a) <= 1, "norm {} -> {} ns, units -> {} ns", a, ns_a, same);
        }
        let ns_b = m.norm_to_ns(0, b).0;
        let rising = (a <= b) != map.reverse;
        prop_assert!(if rising { ns_a <= ns_b } else { ns_a >= ns_b }, "{} -> {}, {} -> {}", a, ns_a, b, ns_b);
    }
}
