//! Shared pieces of the fuzz targets: the frame models the wire targets parse
//! against, and the invariants every accepted command and every rejection must
//! satisfy.

use ppm_shared::auth::{self, AuthKey, MAC_HEX_LEN};
use ppm_shared::config::{Config, Timing, FOLLOW_SYNC_CEILING_US};
use ppm_shared::decode::{decode, DecoderLimits};
use ppm_shared::frame::{us_to_ns, Channels, FrameModel, Level, Protocol};
use ppm_shared::ipc::CommandSample;
use ppm_shared::protocol::{self, Command, Reject, RejectReason, To};
use ppm_shared::receiver::{decode_as, Receiver, SYNC_MARGIN_US};
use ppm_shared::sbus;
use std::sync::OnceLock;

/// Configurations the wire targets parse against.
pub const MODEL_CONFIGS: &[(&str, &str)] = &[
    ("default", ""),
    (
        // Follow timing: 12 channels, whose frame_us would not fit grid.
        "follow12",
        r#"
[ppm]
channels = 12
timing = "follow"
follow_sync_min_us = 4500
follow_sync_max_us = 18500
"#,
    ),
    (
        "taer4",
        r#"
[ppm]
channels = 4
order = "TAER"
receiver = "edgetx"
[ppm.channel.ail]
unit = "deg"
unit_min = -15.0
unit_max = 15.0
[ppm.channel.thr]
unit = "%"
unit_min = 0
unit_max = 100
"#,
    ),
    (
        // 16 channels, per-channel limits (one pinned, fractional ones),
        // unit ranges (reversed, trimmed, tiny, huge), idle high, an odd
        // order and pulse width.
        "limits16",
        r#"
[ppm]
channels = 16
order = "ETRA"
receiver = "ardupilot"
frame_us = 35000
pulse_us = 400.25
idle_level = "high"
min_us = 1100
max_us = 1900
[ppm.channel.thr]
min_us = 1000
max_us = 1900
reverse = true
trim_us = 5.0
[ppm.channel.ail]
min_us = 900
max_us = 2100
default_us = 1550.5
unit_min = -15.0
unit_max = 15.0
reverse = true
trim_us = -12.5
[ppm.channel.ele]
min_us = 800
max_us = 2200
unit_min = -20.0
unit_max = 20.0
unit_us_min = 1100.0
unit_us_max = 1900.0
[ppm.channel.rud]
min_us = 1100
max_us = 1800
default_us = 1400.001
unit_min = -1e300
unit_max = 1e300
[ppm.channel.aux1]
min_us = 1234.5678
max_us = 1234.5678
default_us = 1234.5678
reverse = true
[ppm.channel.aux3]
unit_min = 0
unit_max = 1
unit_us_min = 800
unit_us_max = 2200
[ppm.channel.aux2]
unit_min = 0
unit_max = 1e-9
trim_us = 500
[ppm.channel.aux5]
min_us = 950.25
max_us = 1999.75
default_us = 1000.0005
unit_min = 3
unit_max = 4
unit_us_min = 800
unit_us_max = 2200
trim_us = -500
[ppm.channel.aux12]
min_us = 800
max_us = 2200
default_us = 2200
"#,
    ),
    (
        // SBUS for every receiver: 16 channels at per-channel limits from
        // the lowest value all of them read to the highest, unit ranges.
        "sbus16",
        r#"
[ppm]
protocol = "sbus"
order = "TAER"
min_us = 882
max_us = 2159
timing = "follow"
[ppm.channel.thr]
min_us = 1000
max_us = 2000
unit_min = 0
unit_max = 100
[ppm.channel.aux12]
default_us = 2159
unit_min = -1
unit_max = 1
reverse = true
"#,
    ),
    (
        "one",
        "[ppm]\nreceiver = \"edgetx\"\nchannels = 1\nframe_us = 19300\npulse_us = 50\nmin_us = 820\nmax_us = 2180\n",
    ),
];

/// The key signed datagrams are checked with: the README's test vector key,
/// the bytes 0, 1, ..., 31.
pub fn key() -> &'static AuthKey {
    static KEY: OnceLock<AuthKey> = OnceLock::new();
    KEY.get_or_init(|| AuthKey::new(std::array::from_fn(|i| i as u8)))
}

/// The models of [`MODEL_CONFIGS`], built once.
pub fn models() -> &'static [FrameModel] {
    static MODELS: OnceLock<Vec<FrameModel>> = OnceLock::new();
    MODELS.get_or_init(|| {
        MODEL_CONFIGS
            .iter()
            .map(|(name, text)| {
                let c = Config::parse(text).unwrap_or_else(|e| panic!("{name}: {e}"));
                let m = c.validate().unwrap_or_else(|e| panic!("{name}: {e}"));
                check_model(&m);
                m
            })
            .collect()
    })
}

/// What a validated model must satisfy, whatever configuration built it.
pub fn check_model(m: &FrameModel) {
    if m.protocol() == Protocol::Sbus {
        return check_sbus_model(m);
    }
    let n = m.channels();
    assert!((1..=16).contains(&n), "{n} channels");
    assert_eq!(m.names().len(), n);
    let sum_max: u64 = (0..n).map(|i| m.max_ns(i) as u64).sum();
    let sum_min: u64 = (0..n).map(|i| m.min_ns(i) as u64).sum();
    // Follow timing's syncs are its limits, whatever the frame; grid's are
    // what the frame leaves. Either way within the receiver's window, less
    // the margins.
    let rules = m.receiver().rules();
    let (rule_min, rule_max) = (
        us_to_ns(rules.sync_min_us.0),
        if rules.sync_max_us.0.is_finite() {
            us_to_ns(rules.sync_max_us.0)
        } else {
            u64::MAX
        },
    );
    assert!(rule_min >= us_to_ns(2_700.0 + SYNC_MARGIN_US));
    let (sync_min, sync_max) = m.follow_sync_ns();
    assert!(
        sync_min >= rule_min
            && sync_max <= us_to_ns(FOLLOW_SYNC_CEILING_US)
            && sync_min <= sync_max,
        "follow syncs {sync_min}..{sync_max}"
    );
    if m.timing() == Timing::Grid {
        assert!(
            m.frame_ns() >= sum_max + rule_min,
            "worst-case sync below {rule_min}: frame {} sum_max {sum_max}",
            m.frame_ns()
        );
        assert!(
            m.frame_ns() - sum_min <= rule_max,
            "best-case sync above {rule_max}: frame {} sum_min {sum_min}",
            m.frame_ns()
        );
    }
    let n_ok = rules.min_channels.0..=rules.max_channels.0;
    assert!(n_ok.contains(&n), "{n} channels for {:?}", m.receiver());
    assert!(m.pulse_ns() >= 50_000, "pulse {}", m.pulse_ns());
    for i in 0..n {
        let (lo, d, hi) = (m.min_ns(i), m.default_ns(i), m.max_ns(i));
        let window = us_to_ns(rules.channel_min_us.0)..=us_to_ns(rules.channel_max_us.0);
        assert!(
            window.contains(&(lo as u64)) && window.contains(&(hi as u64)),
            "channel {i}: {lo}..={hi} outside {window:?} ns for {:?}",
            m.receiver()
        );
        assert!(
            lo <= d && d <= hi,
            "channel {i}: default {d} outside {lo}..={hi}"
        );
        assert!(
            m.pulse_ns() < lo as u64,
            "pulse {} >= min {lo}",
            m.pulse_ns()
        );
        assert_eq!(m.index_of(&m.names()[i]), Some(i), "duplicate name");
    }
    let names: Vec<&str> = m.names().iter().map(String::as_str).collect();
    for name in names.iter().take(4) {
        assert!(["ail", "ele", "thr", "rud"].contains(name), "{name}");
    }
    for (i, name) in names.iter().enumerate().skip(4) {
        assert_eq!(*name, format!("aux{}", i - 3));
    }
    for i in 0..n {
        check_mapping(m, i);
    }
    // Every channel at its extremes and at its defaults encodes to a frame a
    // transmitter decodes back exactly.
    let mins: Vec<u32> = (0..n).map(|i| m.min_ns(i)).collect();
    let maxs: Vec<u32> = (0..n).map(|i| m.max_ns(i)).collect();
    for c in [
        Channels::from_ns(&mins),
        Channels::from_ns(&maxs),
        m.defaults(),
    ] {
        check_frame(m, &c);
    }
}

/// Invariants of an SBUS model: 16 channels, named as PPM's; limits inside
/// the values every receiver of `ppm.receiver` reads; idle lines and the
/// grid period each receiver takes; and every channel at its extremes and
/// defaults encoded into a frame that every receiver reads as sent (the one
/// encoded for to within its step, the others within their offset), and
/// flagged, into one each takes as failsafe.
pub fn check_sbus_model(m: &FrameModel) {
    let c = m.sbus().expect("an SBUS model has its receivers");
    assert_eq!(m.channels(), sbus::CHANNELS);
    let least = c.least_gap_us() * 1_000;
    let (gap_min, gap_max) = m.follow_sync_ns();
    assert!(
        least <= gap_min && gap_min <= gap_max && gap_max <= us_to_ns(sbus::timing::GAP_MAX_US),
        "idle lines {gap_min}..{gap_max}, least {least}"
    );
    assert!(
        m.frame_ns() >= sbus::FRAME_WIRE_NS + least,
        "period {}",
        m.frame_ns()
    );
    let (lo, hi) = c.value_range_us();
    for i in 0..m.channels() {
        let (min, d, max) = (m.min_ns(i), m.default_ns(i), m.max_ns(i));
        assert!(
            lo * 1_000 <= min as u64 && min <= d && d <= max && max as u64 <= hi * 1_000,
            "channel {i}: {min}..={max} (default {d}) outside {lo}..={hi} us"
        );
        assert_eq!(m.index_of(&m.names()[i]), Some(i), "duplicate name");
        check_mapping(m, i);
    }
    let mins: Vec<u32> = (0..m.channels()).map(|i| m.min_ns(i)).collect();
    let maxs: Vec<u32> = (0..m.channels()).map(|i| m.max_ns(i)).collect();
    for ch in [
        Channels::from_ns(&mins),
        Channels::from_ns(&maxs),
        m.defaults(),
    ] {
        check_sbus_frame(m, &ch);
    }
}

/// An SBUS frame carrying `ch` (values within limits; missing ones at
/// their defaults), as every receiver of the model reads it: the one
/// encoded for within its step, the others within their offset; flagged,
/// used by none.
pub fn check_sbus_frame(m: &FrameModel, ch: &Channels) {
    let c = m.sbus().expect("an SBUS model has its receivers");
    let frame = m.encode_sbus(ch, false);
    let exact = m.sbus_reads(&frame);
    for (i, &got) in exact.iter().enumerate() {
        let want = ch.as_ns().get(i).copied().unwrap_or(m.default_ns(i));
        // Whole microseconds (EdgeTX, ArduPilot) or 0.625 us steps.
        assert!(
            got.abs_diff(want as u64) <= 625,
            "channel {i}: {got} for {want}"
        );
    }
    for r in c.receivers() {
        match r.verdict(&frame) {
            sbus::Verdict::Used(reading) => {
                for (i, (&got, &want)) in reading.channels_ns.iter().zip(&exact).enumerate() {
                    assert!(
                        got.abs_diff(want) <= 7_000,
                        "{r:?} channel {i}: {got} for {want}"
                    );
                }
            }
            v => panic!("{r:?}: {v:?} for {ch:?}"),
        }
        let flagged = m.encode_sbus(ch, true);
        assert!(
            !matches!(r.verdict(&flagged), sbus::Verdict::Used(_)),
            "{r:?} used a flagged frame"
        );
    }
}

/// Invariants of one encoded frame carrying `c` (values within limits).
pub fn check_frame(m: &FrameModel, c: &Channels) {
    if m.protocol() == Protocol::Sbus {
        return check_sbus_frame(m, c);
    }
    let n = m.channels();
    let s = m.encode(c);
    let e = s.edges();
    assert_eq!(e.len(), 2 * (n + 1), "edge count");
    assert!(
        e.windows(2).all(|w| w[0].at_ns <= w[1].at_ns),
        "edges out of order: {e:?}"
    );
    let active = m.idle_level().opposite();
    for (k, edge) in e.iter().enumerate() {
        let want = if k % 2 == 0 { active } else { m.idle_level() };
        assert_eq!(edge.level, want, "edge {k} level");
    }
    assert_eq!(e[0].at_ns, 0);
    for k in 0..=n {
        assert_eq!(
            e[2 * k + 1].at_ns - e[2 * k].at_ns,
            m.pulse_ns(),
            "pulse {k} width"
        );
    }
    for i in 0..n {
        assert_eq!(
            e[2 * (i + 1)].at_ns - e[2 * i].at_ns,
            c.as_ns()[i] as u64,
            "channel {i} period"
        );
    }
    let last_start = e[2 * n].at_ns;
    // Frame to frame: grid frames every frame_ns; follow frames as close as
    // they may come (the shortest sync) and as far (the longest).
    let (sync_min, sync_max) = m.follow_sync_ns();
    let periods = match m.timing() {
        Timing::Grid => vec![m.frame_ns()],
        Timing::Follow => vec![last_start + sync_min, last_start + sync_max],
    };
    let rules = m.receiver().rules();
    for period in periods {
        assert!(
            last_start + us_to_ns(rules.sync_min_us.0) <= period,
            "last pulse at {last_start} leaves too short a sync in a {period} ns frame"
        );
        assert!(
            !rules.sync_max_us.0.is_finite()
                || period - last_start <= us_to_ns(rules.sync_max_us.0),
            "sync over {} us",
            rules.sync_max_us.0
        );
        // Two frames plus the next frame's first edge: a transmitter reads
        // the second frame, and it must be exactly the values.
        let mut edges: Vec<(u64, Level)> = Vec::with_capacity(2 * e.len() + 1);
        for k in 0..2u64 {
            edges.extend(e.iter().map(|x| (k * period + x.at_ns, x.level)));
        }
        edges.push((2 * period, active));
        // The trainer inputs among the receivers read it to the microsecond.
        for r in m.receiver().receivers() {
            if matches!(r, Receiver::EdgeTx | Receiver::OpenTx) {
                let (read, stats) = decode_as(r, edges.iter().copied(), active);
                assert_eq!(stats.invalid_periods, 0, "{r:?}");
                assert_eq!(read.len(), 1, "{r:?} read {read:?}");
                let ch = &read[0].channels_ns;
                assert!(
                    ch.len() == n
                        && ch
                            .iter()
                            .zip(c.as_ns())
                            .all(|(g, w)| g.abs_diff(*w as u64) < 1_000),
                    "{r:?} read {read:?}"
                );
            }
        }
        let any_sync = DecoderLimits {
            sync_min_ns: 2_700_000,
            sync_max_ns: u64::MAX,
            ..DecoderLimits::default()
        };
        let frames = decode(edges, active, any_sync);
        assert_eq!(frames.len(), 1, "decoded {frames:?}");
        let got: Vec<u32> = frames[0].channels_ns.iter().map(|&v| v as u32).collect();
        assert_eq!(got, c.as_ns(), "decoded values");
        assert!(frames[0].complete);
        assert_eq!(frames[0].start_ns, period);
    }
}

/// Invariants of an accepted command.
pub fn check_accepted(m: &FrameModel, cmd: &Command) {
    let n = m.channels();
    assert_eq!(cmd.channels.len(), n, "channel count");
    for (i, &v) in cmd.channels.as_ns().iter().enumerate() {
        assert!(
            (m.min_ns(i)..=m.max_ns(i)).contains(&v),
            "channel {i} = {v} ns outside {}..={}",
            m.min_ns(i),
            m.max_ns(i)
        );
    }
    assert!(cmd.clamped as usize <= n, "clamped {} > {n}", cmd.clamped);
    check_frame(m, &cmd.channels);
    // The values written back exactly (to the nanosecond) parse to the same
    // command, with nothing clamped.
    let values: Vec<String> = cmd
        .channels
        .as_ns()
        .iter()
        .map(|&v| format!("{}.{:03}", v / 1000, v % 1000))
        .collect();
    let text = match cmd.seq {
        Some(s) => format!("{{\"seq\": {s}, \"ch\": [{}]}}", values.join(", ")),
        None => format!("[{}]", values.join(",")),
    };
    let again = protocol::parse(text.as_bytes(), m)
        .unwrap_or_else(|e| panic!("re-encoded command {text} rejected: {e}"));
    assert_eq!(again.channels, cmd.channels, "{text}");
    assert_eq!(again.seq, cmd.seq, "{text}");
    assert_eq!(again.clamped, 0, "{text}");
}

/// An accepted command as udp-ingress hands it to ppmd: it comes back
/// whole under its own model, and ppmd's freshness rule holds whatever the
/// times (drawn from `seed`): a sample received before the daemon's loop
/// started (a service's history of an earlier run) never flies, nor one
/// older than the failsafe limit, and every other one does.
pub fn check_sample(m: &FrameModel, cmd: &Command, seed: u64) {
    let mut x = seed | 1;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    let recv = next() % 10_000_000_000;
    let s = CommandSample::new(cmd, m.fingerprint(), 1, recv, 0);
    assert_eq!(s.channels(m), Some(cmd.channels), "through shared memory");
    let after = next() % 2_000_000_000;
    let started = next() % 10_000_000_000;
    let now = recv.max(started) + next() % 4_000_000_000;
    let want = recv >= started && now - recv <= after;
    assert_eq!(
        s.fresh(started, now, after),
        want,
        "received {recv}, loop started {started}, now {now}, limit {after}"
    );
    // The last command of an earlier run, however young, never flies.
    assert!(!s.fresh(recv + 1, recv + 1, u64::MAX));
    // One past the limit never flies.
    assert!(!s.fresh(recv, recv + after + 1, after));
}

/// Invariants of a rejection.
pub fn check_rejected(e: &Reject) {
    let name = e.reason.as_str();
    assert!(
        RejectReason::ALL.iter().any(|r| r.as_str() == name),
        "reason {name} not in RejectReason::ALL"
    );
    assert_eq!(RejectReason::ALL[e.reason.index()], e.reason);
    let shown = e.to_string();
    assert!(shown.starts_with(name), "{shown}");
    assert!(!e.detail.is_empty(), "{name} without a detail");
}

/// Parses a datagram and checks whichever invariants apply.
pub fn parse_checked(data: &[u8], m: &FrameModel) -> Result<Command, Reject> {
    let r = protocol::parse(data, m);
    match &r {
        Ok(cmd) => {
            check_accepted(m, cmd);
            let seed = data.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
                (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
            });
            check_sample(m, cmd, seed);
        }
        Err(e) => check_rejected(e),
    }
    r
}

/// Probe values for `norm` and `units`.
const PROBES: &[f64] = &[
    -1.0,
    0.0,
    1.0,
    -0.0,
    -0.5,
    0.5,
    -1.000001,
    1.000001,
    -2.0,
    2.0,
    1e308,
    -1e308,
    f64::MAX,
    f64::MIN,
    f64::MIN_POSITIVE,
    -f64::MIN_POSITIVE,
];

/// Channel `i`'s period for a `units` (`units`) or `norm` value `x`, by the
/// README's formula, and whether it counts as clamped; `None` for `units` on
/// a channel without a unit range.
pub fn mapped_ns(m: &FrameModel, i: usize, units: bool, x: f64) -> Option<(u32, bool)> {
    let map = m.mapping(i);
    let (lo, hi) = if units { map.units? } else { (-1.0, 1.0) };
    let v = x.clamp(lo, hi);
    let f = match (units, map.reverse) {
        (true, false) => (v - lo) / (hi - lo),
        (true, true) => (hi - v) / (hi - lo),
        (false, false) => (v + 1.0) / 2.0,
        (false, true) => (1.0 - v) / 2.0,
    };
    assert!(
        (0.0..=1.0).contains(&f),
        "channel {i}: position {f} of {x} along {lo}..={hi} is not within 0..=1"
    );
    let us = map.us_lo + f * (map.us_hi - map.us_lo) + map.trim_us;
    let ns = (us * 1000.0).round();
    let c = ns.clamp(m.min_ns(i) as f64, m.max_ns(i) as f64);
    Some((c as u32, v != x || c != ns))
}

/// The `units` and `norm` mappings of channel `i`: within the channel's
/// limits for any value, as the README's formula says, monotonic, and
/// clamped when outside their range.
pub fn check_mapping(m: &FrameModel, i: usize) {
    let (lo_ns, hi_ns) = (m.min_ns(i), m.max_ns(i));
    let map = *m.mapping(i);
    assert!(map.us_lo < map.us_hi || map.units.is_none() && map.us_lo <= map.us_hi);
    assert!(map.trim_us.is_finite() && map.trim_us.abs() <= 500.0);
    let mut probes: Vec<(bool, f64)> = PROBES.iter().map(|&x| (false, x)).collect();
    if let Some((lo, hi)) = map.units {
        assert!(
            lo.is_finite() && hi.is_finite() && lo < hi,
            "unit range {lo}..{hi}"
        );
        let unit_probes = [
            lo,
            hi,
            lo / 2.0 + hi / 2.0,
            lo - 1.0,
            hi + 1.0,
            lo.next_down(),
            hi.next_up(),
        ];
        probes.extend(PROBES.iter().chain(&unit_probes).map(|&x| (true, x)));
    } else {
        assert_eq!(m.units_to_ns(i, 0.0), None);
        assert!(m.ns_to_units(i, lo_ns).is_none());
    }
    for (units, x) in probes {
        let got = if units {
            m.units_to_ns(i, x).expect("a unit range")
        } else {
            m.norm_to_ns(i, x)
        };
        let form = if units { "units" } else { "norm" };
        assert!(
            (lo_ns..=hi_ns).contains(&got.0),
            "{form} {x} on channel {i} gives {} ns, outside {lo_ns}..={hi_ns}",
            got.0
        );
        let want = mapped_ns(m, i, units, x).unwrap();
        assert_eq!(got, want, "{form} {x} on channel {i}");
        let (lo, hi) = if units {
            map.units.unwrap()
        } else {
            (-1.0, 1.0)
        };
        if !(lo..=hi).contains(&x) {
            assert!(
                got.1,
                "{form} {x} outside {lo}..={hi} not counted as clamped"
            );
        }
    }
    // Monotonic in the value, falling when reversed.
    let ends = |units: bool| {
        let (lo, hi) = if units {
            map.units.unwrap()
        } else {
            (-1.0, 1.0)
        };
        let at = |x: f64| mapped_ns(m, i, units, x).unwrap().0;
        (at(lo), at(lo / 2.0 + hi / 2.0), at(hi))
    };
    for units in [false, map.units.is_some()] {
        let (a, b, c) = ends(units);
        if map.reverse {
            assert!(a >= b && b >= c, "channel {i} not falling: {a} {b} {c}");
        } else {
            assert!(a <= b && b <= c, "channel {i} not rising: {a} {b} {c}");
        }
    }
}

/// The signed form: a datagram taken apart by `auth::envelope` is either not
/// signed, rejected as `bad_shape`/`bad_mac`, or a `msg` and a well-formed
/// MAC. Returns the envelope's `msg` when its MAC verifies under [`key`].
pub fn check_envelope(data: &[u8]) -> Option<String> {
    match auth::envelope(data)? {
        Err(e) => {
            check_rejected(&e);
            assert!(
                matches!(e.reason, RejectReason::BadShape | RejectReason::BadMac),
                "{e}"
            );
            None
        }
        Ok(env) => {
            assert_eq!(env.mac.len(), MAC_HEX_LEN);
            assert!(env.mac.bytes().all(|b| b.is_ascii_hexdigit()));
            env.verify(key()).then_some(env.msg)
        }
    }
}

/// The output name signed commands are opened for: the one of the test
/// vector in ../docs/security.md.
pub const OUTPUT: &str = "rover";

/// Another output that shares [`OUTPUT`]'s key.
pub const OTHER_OUTPUT: &str = "plane";

/// A signed datagram whose MAC verifies under [`key`], opened for
/// [`OUTPUT`] with `m`: the same as parsing its `msg` for exactly that
/// output (so `no_to` and `wrong_output` come before the command's other
/// faults), plus `no_seq` for an accepted command without a `seq`; and
/// never accepted unless `msg` names [`OUTPUT`].
pub fn check_open(data: &[u8], m: &FrameModel) {
    let Some(Ok(env)) = auth::envelope(data) else {
        return;
    };
    let opened = env.open(key(), OUTPUT, m);
    if !env.verify(key()) {
        assert_eq!(opened.map_err(|e| e.reason), Err(RejectReason::BadMac));
        return;
    }
    let parsed = protocol::parse_for(env.msg.as_bytes(), m, To::Exactly(OUTPUT));
    match (&opened, parsed) {
        (Ok(cmd), Ok(p)) => {
            assert_eq!(*cmd, p);
            assert!(cmd.seq.is_some(), "{}", env.msg);
            let v: serde_json::Value = serde_json::from_str(&env.msg).unwrap();
            assert_eq!(v["to"], OUTPUT, "{}", env.msg);
        }
        (Err(e), Ok(p)) => {
            assert_eq!(e.reason, RejectReason::NoSeq, "{e}");
            assert_eq!(p.seq, None);
        }
        (Err(e), Err(p)) => assert_eq!(e.reason, p.reason, "{e}"),
        (Ok(cmd), Err(p)) => panic!("{}: opened as {cmd:?}, parsed as {p}", env.msg),
    }
    if let Err(e) = &opened {
        check_rejected(e);
    }
    // The same datagram copied to another output under the same key: what
    // opens for this output is refused there as `wrong_output`, so it never
    // reaches that output's seq gate.
    if opened.is_ok() {
        let copy = env.open(key(), OTHER_OUTPUT, m);
        assert_eq!(
            copy.map(|_| ()).map_err(|e| e.reason),
            Err(RejectReason::WrongOutput)
        );
    }
}

/// Signs `msg`, takes the envelope apart again and checks it verifies, and
/// that changing any part of it makes it fail.
pub fn check_signing(msg: &str) {
    let k = key();
    let datagram = k.envelope(msg);
    let env = match auth::envelope(datagram.as_bytes()) {
        Some(Ok(env)) => env,
        other => panic!("{datagram}: {other:?}"),
    };
    assert_eq!(env.msg, msg);
    assert!(env.verify(k));
    assert_eq!(check_envelope(datagram.as_bytes()).as_deref(), Some(msg));
    let mut mac = env.mac.clone().into_bytes();
    mac[0] = if mac[0] == b'0' { b'1' } else { b'0' };
    assert!(!k.verify(msg.as_bytes(), std::str::from_utf8(&mac).unwrap()));
    let other = format!("{msg} ");
    assert!(!k.verify(other.as_bytes(), &env.mac));
}
