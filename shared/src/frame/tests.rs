use super::*;

/// The model of the `[ppm]` section in configuration text (every default
/// without one), as the configuration builds it.
fn model(text: &str) -> FrameModel {
    let file: toml::Table = text.parse().unwrap();
    let ppm: PpmSection = file
        .get("ppm")
        .cloned()
        .map_or_else(PpmSection::default, |v| v.try_into().unwrap());
    FrameModel::build(&ppm).unwrap()
}

#[test]
fn default_frame_edges() {
    let m = model("");
    let s = m.encode(&Channels::from_ns(&[
        1_000_000, 1_200_000, 1_700_000, 2_000_000,
    ]));
    let e = s.edges();
    assert_eq!(e.len(), 18);
    assert_eq!(
        e[0],
        Edge {
            at_ns: 0,
            level: Level::High
        }
    );
    assert_eq!(
        e[1],
        Edge {
            at_ns: 300_000,
            level: Level::Low
        }
    );
    let starts: Vec<u64> = e.iter().step_by(2).map(|e| e.at_ns).collect();
    assert_eq!(
        starts,
        [
            0, 1_000_000, 2_200_000, 3_900_000, 5_900_000, 7_400_000, 8_900_000, 10_400_000,
            11_900_000
        ]
    );
}

#[test]
fn encode_clamps_and_fills_defaults() {
    let m = model("");
    let s = m.encode(&Channels::from_ns(&[3_000_000]));
    let starts: Vec<u64> = s.edges().iter().step_by(2).map(|e| e.at_ns).collect();
    assert_eq!(starts[1], 2_000_000, "clamped to max");
    assert_eq!(starts[2] - starts[1], 1_500_000, "ele default");
    assert_eq!(
        starts[3] - starts[2],
        1_000_000,
        "thr default is its minimum"
    );
}

#[test]
fn idle_high_inverts() {
    let m = model("[ppm]\nidle_level = 'high'");
    let s = m.encode(&m.defaults());
    assert_eq!(s.edges()[0].level, Level::Low);
    assert_eq!(s.edges().last().unwrap().level, Level::High);
}

/// The `units` and `norm` mappings.
mod units {
    use super::model;
    use crate::frame::FrameModel;

    /// The defaults plus `[ppm.channel.ail]` with a -15..15 degree range and `extra` keys.
    fn ail_deg(extra: &str) -> FrameModel {
        let text =
            format!("[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\nunit = 'deg'\n{extra}");
        model(&text)
    }

    #[test]
    fn aileron_degrees_map_linearly() {
        let m = ail_deg("");
        assert_eq!(
            m.units_to_ns(0, 3.0),
            Some((1_600_000, false)),
            "3 deg is 1600 us"
        );
        assert_eq!(m.units_to_ns(0, -15.0), Some((1_000_000, false)));
        assert_eq!(m.units_to_ns(0, 0.0), Some((1_500_000, false)));
        assert_eq!(m.units_to_ns(0, 15.0), Some((2_000_000, false)));
        // A tenth of a microsecond (and finer) survives the mapping.
        assert_eq!(m.units_to_ns(0, 3.0333), Some((1_601_110, false)));
        assert_eq!(m.ns_to_units(0, 1_600_000), Some(3.0));
        assert_eq!(m.units_to_ns(1, 3.0), None, "ele has no unit range");
    }

    #[test]
    fn reverse_and_trim() {
        assert_eq!(
            ail_deg("reverse = true").units_to_ns(0, 3.0),
            Some((1_400_000, false))
        );
        assert_eq!(
            ail_deg("trim_us = 10.0").units_to_ns(0, 3.0),
            Some((1_610_000, false))
        );
        assert_eq!(
            ail_deg("trim_us = -2.5\nreverse = true").units_to_ns(0, 3.0),
            Some((1_397_500, false))
        );
        let m = ail_deg("unit_us_min = 1100.0\nunit_us_max = 1900.0");
        assert_eq!(m.units_to_ns(0, 3.0), Some((1_580_000, false)));
        assert_eq!(m.norm_to_ns(0, -1.0), (1_100_000, false));
        assert_eq!(m.norm_to_ns(0, 1.0), (1_900_000, false));
    }

    #[test]
    fn range_ends_clamp_and_count() {
        let m = ail_deg("");
        assert_eq!(m.units_to_ns(0, 15.01), Some((2_000_000, true)));
        assert_eq!(m.units_to_ns(0, -90.0), Some((1_000_000, true)));
        assert_eq!(m.units_to_ns(0, f64::MAX), Some((2_000_000, true)));
        // Trim past the channel's max_us is clamped to it, and counted.
        let m = ail_deg("trim_us = 10.0");
        assert_eq!(m.units_to_ns(0, 15.0), Some((2_000_000, true)));
        assert_eq!(
            m.units_to_ns(0, 14.0),
            Some((1_976_667, false)),
            "rounded to the ns"
        );
        assert_eq!(m.norm_to_ns(1, 1.5), (2_000_000, true));
        assert_eq!(m.norm_to_ns(1, -1.000001), (1_000_000, true));
    }

    #[test]
    fn norm_on_a_plain_channel_and_on_throttle() {
        let m = model("");
        // ele: -1 is min_us, 0 the midpoint, +1 max_us.
        assert_eq!(m.norm_to_ns(1, -1.0), (1_000_000, false));
        assert_eq!(m.norm_to_ns(1, 0.0), (1_500_000, false));
        assert_eq!(m.norm_to_ns(1, 1.0), (2_000_000, false));
        assert_eq!(m.norm_to_ns(0, 0.2), (1_600_000, false));
        // thr: the same line; -1 is its minimum, zero actuation (its default).
        assert_eq!(m.norm_to_ns(2, -1.0), (m.default_ns(2), false));
        assert_eq!(m.norm_to_ns(2, 0.0), (1_500_000, false));
        assert_eq!(m.norm_to_ns(2, 1.0), (2_000_000, false));
        assert_eq!(m.ns_to_norm(2, 1_250_000), -0.5);
        let c = "[ppm.channel.thr]\nmax_us = 1900.0\nreverse = true\ntrim_us = 5.0";
        let m = model(c);
        assert_eq!(m.norm_to_ns(2, -1.0), (1_900_000, true), "1905 us clamped");
        assert_eq!(m.norm_to_ns(2, 0.5), (1_230_000, false));
    }
}
