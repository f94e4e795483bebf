//! Building the [`FrameModel`] from the `[ppm]` section: every check of
//! what the receivers of `ppm.receiver` read, then the model in one step.
//! Errors name the key and say how to fix it.

use super::section::{ppm_defaults, ChannelOverride, PpmSection};
use super::{us_to_ns, FrameModel, UnitMapping, MAX_CHANNELS, PULSE_MIN_US};
use crate::receiver::{ReceiverChoice, Rules, CHANNEL_MARGIN_US, SYNC_MARGIN_US};
use crate::signal::{Timing, CHANNEL_MAX_US, CHANNEL_MIN_US, SYNC_MAX_US};
use crate::wire::{PpmWire, Protocol, WireModel};

/// A `[ppm]` key whose value a transmitter would reject or misread: the
/// key and why (the configuration reports it as its own error).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("config key `{key}`: {message}")]
pub struct InvalidKey {
    /// The key, dotted (`ppm.channel.thr.min_us`).
    pub key: String,
    /// What is wrong, and the fix.
    pub message: String,
}

impl InvalidKey {
    pub(crate) fn new(key: impl Into<String>, message: impl Into<String>) -> Self {
        InvalidKey {
            key: key.into(),
            message: message.into(),
        }
    }
}

/// The longest sync `follow` timing leaves, for every receiver: EdgeTX's
/// 19 ms less [`crate::receiver::SYNC_MARGIN_US`]. A `follow` frame that
/// comes late is moved later only while its sync stays under this.
pub const FOLLOW_SYNC_CEILING_US: f64 = SYNC_MAX_US - SYNC_MARGIN_US;

impl FrameModel {
    /// Checks `[ppm]` against what transmitters accept (the receivers of
    /// `ppm.receiver`) and builds the model from it in one step: a model
    /// exists only once every check passed. Errors name the key. Each
    /// protocol builds its own.
    pub fn build(ppm: &PpmSection) -> Result<FrameModel, InvalidKey> {
        match ppm.protocol {
            Protocol::Ppm => build_ppm(ppm),
            Protocol::Sbus => super::build_sbus::build(ppm),
            Protocol::Crsf => super::build_crsf::build(ppm),
        }
    }
}

/// A PPM model: channel count, values, pulse, frame and syncs against the
/// PPM receivers of `ppm.receiver`.
fn build_ppm(ppm: &PpmSection) -> Result<FrameModel, InvalidKey> {
    let (names, limits) = resolve_channels(ppm)?;
    let late_edge_guard_ns = late_edge_guard(ppm)?;
    let rules = ppm.receiver.rules();
    check_channel_count(ppm, &rules, limits.len())?;
    check_channel_values(ppm, &rules, &limits)?;
    let pulse_ns = pulse_ns(ppm, &limits)?;
    let frame_us = ppm.frame_us();
    if !frame_us.is_finite() || frame_us <= 0.0 {
        return Err(InvalidKey::new(
            "ppm.frame_us",
            format!("{frame_us} us is not a frame length"),
        ));
    }
    let frame_ns = us_to_ns(frame_us);
    let follow_sync_ns = follow_sync(ppm, &rules)?;
    // Under follow timing the sync gaps are the follow limits, whatever
    // the channel values: frame_us is not used.
    if ppm.timing == Timing::Grid {
        check_grid_sync(ppm, &rules, &limits, frame_ns)?;
    }
    Ok(model(
        ppm,
        names,
        &limits,
        Wire {
            frame_ns,
            follow_sync_ns,
            sync_window_ns: (us_to_ns(rules.sync_min_us.0), us_to_ns(rules.sync_max_us.0)),
            late_edge_guard_ns,
            wire: WireModel::Ppm(PpmWire { pulse_ns }),
        },
    ))
}

/// A model's timing and wire settings, checked by its protocol's build.
pub(crate) struct Wire {
    pub(crate) frame_ns: u64,
    pub(crate) follow_sync_ns: (u64, u64),
    pub(crate) sync_window_ns: (u64, u64),
    pub(crate) late_edge_guard_ns: u64,
    pub(crate) wire: WireModel,
}

/// The model of checked channels and wire settings.
pub(crate) fn model(
    ppm: &PpmSection,
    names: Vec<String>,
    limits: &[ChannelLimits],
    w: Wire,
) -> FrameModel {
    // Channel i's value in ns; 0 past the last channel.
    let ns = |i: usize, us: fn(&ChannelLimits) -> f64| {
        limits.get(i).map_or(0, |l| us_to_ns(us(l)) as u32)
    };
    FrameModel {
        default_ns: std::array::from_fn(|i| ns(i, |l| l.default_us)),
        min_ns: std::array::from_fn(|i| ns(i, |l| l.min_us)),
        max_ns: std::array::from_fn(|i| ns(i, |l| l.max_us)),
        mapping: std::array::from_fn(|i| {
            limits.get(i).map_or_else(Default::default, |l| l.mapping)
        }),
        channels: limits.len(),
        names,
        frame_ns: w.frame_ns,
        idle: ppm.idle_level(),
        timing: ppm.timing,
        follow_sync_ns: w.follow_sync_ns,
        receiver: ppm.receiver,
        sync_window_ns: w.sync_window_ns,
        late_edge_guard_ns: w.late_edge_guard_ns,
        wire: w.wire,
    }
}

/// The channel count against the receivers' bounds.
fn check_channel_count(ppm: &PpmSection, rules: &Rules, n: usize) -> Result<(), InvalidKey> {
    let (fewest, most) = (rules.min_channels, rules.max_channels);
    if (fewest.0..=most.0).contains(&n) {
        return Ok(());
    }
    let rule = if n < fewest.0 { fewest.1 } else { most.1 };
    Err(InvalidKey::new(
        "ppm.channels",
        format!(
            "{} channels: {rule}; under {}: use {}..={} channels, or set ppm.receiver to the one receiver you use",
            n,
            receiver_key(ppm.receiver),
            fewest.0,
            most.0
        ),
    ))
}

/// Every channel's limits against the values the receivers read.
fn check_channel_values(
    ppm: &PpmSection,
    rules: &Rules,
    limits: &[ChannelLimits],
) -> Result<(), InvalidKey> {
    for l in limits {
        let (lo, hi) = (rules.channel_min_us, rules.channel_max_us);
        let (key, v, bound, rule, nearest) = if l.min_us < lo.0 {
            (&l.min_key, l.min_us, lo, "raise", lo.0)
        } else if l.max_us > hi.0 {
            (&l.max_key, l.max_us, hi, "lower", hi.0)
        } else {
            continue;
        };
        return Err(InvalidKey::new(
            key,
            format!(
                "{v} us: {}, less {} us for edge error, so {}..={} us under {}: {rule} {key} to {nearest} us",
                bound.1,
                CHANNEL_MARGIN_US,
                lo.0,
                hi.0,
                receiver_key(ppm.receiver),
            ),
        ));
    }
    Ok(())
}

/// `ppm.pulse_us` in ns, checked: at least [`PULSE_MIN_US`] and shorter
/// than every channel's minimum.
fn pulse_ns(ppm: &PpmSection, limits: &[ChannelLimits]) -> Result<u64, InvalidKey> {
    let smallest_min = limits
        .iter()
        .map(|l| us_to_ns(l.min_us) as u32)
        .min()
        .unwrap_or(0) as u64;
    if !ppm.pulse_us.is_finite()
        || ppm.pulse_us < PULSE_MIN_US
        || us_to_ns(ppm.pulse_us) >= smallest_min
    {
        return Err(InvalidKey::new(
            "ppm.pulse_us",
            format!(
                "{} us must be at least {PULSE_MIN_US} us and shorter than the smallest channel minimum, {} us",
                ppm.pulse_us,
                smallest_min as f64 / 1e3
            ),
        ));
    }
    Ok(us_to_ns(ppm.pulse_us))
}

/// Grid timing: the sync gap `frame_ns` leaves, with every channel at its
/// maximum and at its minimum, against the receivers' sync window.
fn check_grid_sync(
    ppm: &PpmSection,
    rules: &Rules,
    limits: &[ChannelLimits],
    frame_ns: u64,
) -> Result<(), InvalidKey> {
    let sum_max: u64 = limits
        .iter()
        .map(|l| us_to_ns(l.max_us) as u32 as u64)
        .sum();
    let sum_min: u64 = limits
        .iter()
        .map(|l| us_to_ns(l.min_us) as u32 as u64)
        .sum();
    let n = limits.len();
    let (sync_min, sync_max) = (rules.sync_min_us, rules.sync_max_us);
    let sync_min_ns = us_to_ns(sync_min.0);
    if frame_ns < sum_max + sync_min_ns {
        return Err(InvalidKey::new(
            "ppm.frame_us",
            format!(
                "{} us leaves a sync gap of {} us when all {} channels are at their maximum (sum {} us); {}, and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: the gap must be at least {} us under {}: raise ppm.frame_us to at least {} us or lower the channel maximums",
                ppm.frame_us(),
                (frame_ns as f64 - sum_max as f64) / 1e3,
                n,
                sum_max as f64 / 1e3,
                sync_min.1,
                sync_min.0,
                receiver_key(ppm.receiver),
                (sum_max + sync_min_ns) as f64 / 1e3
            ),
        ));
    }
    if frame_ns > sum_min + us_to_ns(sync_max.0) {
        let sync_max_ns = us_to_ns(sync_max.0);
        return Err(InvalidKey::new(
            "ppm.frame_us",
            format!(
                "{} us leaves a sync gap of {} us when all {} channels are at their minimum (sum {} us); {} (a longer gap is signal loss), and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: the gap must be at most {} us under {}: lower ppm.frame_us to at most {} us or add channels",
                ppm.frame_us(),
                (frame_ns - sum_min) as f64 / 1e3,
                n,
                sum_min as f64 / 1e3,
                sync_max.1,
                sync_max.0,
                receiver_key(ppm.receiver),
                (sum_min + sync_max_ns) as f64 / 1e3
            ),
        ));
    }
    Ok(())
}

/// `ppm.receiver = "NAME"`, for messages.
pub(crate) fn receiver_key(r: ReceiverChoice) -> String {
    match r {
        ReceiverChoice::Any => "ppm.receiver = \"any\" (every supported receiver)".into(),
        ReceiverChoice::One(r) => format!("ppm.receiver = \"{}\"", r.name()),
    }
}

/// `ppm.follow_sync_min_us` and `ppm.follow_sync_max_us` in ns, checked
/// against the sync window of the receiver (checked in either timing, so a
/// file stays valid when its timing is switched).
fn follow_sync(ppm: &PpmSection, rules: &Rules) -> Result<(u64, u64), InvalidKey> {
    let min = ppm
        .follow_sync_min_us
        .unwrap_or(ppm_defaults::FOLLOW_SYNC_MIN_US);
    let max = ppm
        .follow_sync_max_us
        .unwrap_or(ppm_defaults::FOLLOW_SYNC_MAX_US);
    let floor = rules.sync_min_us;
    let ceiling = rules.sync_max_us.0.min(FOLLOW_SYNC_CEILING_US);
    if !min.is_finite() || min < floor.0 {
        return Err(InvalidKey::new(
            "ppm.follow_sync_min_us",
            format!(
                "{min} us: {}, and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: at least {} us under {}",
                floor.1,
                floor.0,
                receiver_key(ppm.receiver)
            ),
        ));
    }
    if !max.is_finite() || max > ceiling {
        return Err(InvalidKey::new(
            "ppm.follow_sync_max_us",
            format!(
                "{max} us is above {ceiling} us: EdgeTX and OpenTX read a sync only below 19000 us, and a late frame must not take it there ({SYNC_MARGIN_US} us kept; the most for every receiver)"
            ),
        ));
    }
    if max < min {
        return Err(InvalidKey::new(
            "ppm.follow_sync_max_us",
            format!("{max} us is below ppm.follow_sync_min_us = {min} us"),
        ));
    }
    Ok((us_to_ns(min), us_to_ns(max)))
}

/// The largest `ppm.late_edge_guard_us`: a written edge may be this late,
/// which moves a channel value by as much, and ppm keeps values
/// [`CHANNEL_MARGIN_US`] inside every receiver's window for that.
pub const LATE_EDGE_GUARD_MAX_US: f64 = CHANNEL_MARGIN_US;

/// `ppm.late_edge_guard_us` in ns, checked: 1..=[`LATE_EDGE_GUARD_MAX_US`].
fn late_edge_guard(ppm: &PpmSection) -> Result<u64, InvalidKey> {
    let g = ppm.late_edge_guard_us;
    if !g.is_finite() || !(1.0..=LATE_EDGE_GUARD_MAX_US).contains(&g) {
        return Err(InvalidKey::new(
            "ppm.late_edge_guard_us",
            format!(
                "{g} us is outside 1..={LATE_EDGE_GUARD_MAX_US} us: an edge written later than the guard moves two channel values by as much, and ppm keeps values only {CHANNEL_MARGIN_US} us inside the receivers' windows (a larger guard lets a receiver misread a value at its limit); below 1 us, the edges' ordinary sub-microsecond error would abort frames a receiver reads exactly"
            ),
        ));
    }
    Ok(us_to_ns(g))
}

/// Validated per-channel limits, in microseconds.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ChannelLimits {
    default_us: f64,
    pub(crate) min_us: f64,
    pub(crate) max_us: f64,
    mapping: UnitMapping,
    /// The keys `min_us` and `max_us` come from, for messages.
    pub(crate) min_key: String,
    pub(crate) max_key: String,
}

/// Resolves names and limits of every channel and checks them.
pub(crate) fn resolve_channels(
    ppm: &PpmSection,
) -> Result<(Vec<String>, Vec<ChannelLimits>), InvalidKey> {
    let n = ppm.channels() as usize;
    if !(1..=MAX_CHANNELS).contains(&n) {
        return Err(InvalidKey::new(
            "ppm.channels",
            format!("{n} is outside 1..={MAX_CHANNELS}"),
        ));
    }
    let names = channel_names(&ppm.order, n)?;
    for key in ppm.channel.keys() {
        if !names.iter().any(|n| n == key) {
            return Err(InvalidKey::new(
                format!("ppm.channel.{key}"),
                format!(
                    "no channel is named `{key}`; channels are {}",
                    names.join(", ")
                ),
            ));
        }
    }
    let mut limits = Vec::with_capacity(n);
    for name in &names {
        let o = ppm.channel.get(name).cloned().unwrap_or_default();
        let key = |field: &str, overridden: bool| {
            if overridden {
                format!("ppm.channel.{name}.{field}")
            } else {
                format!("ppm.{field}")
            }
        };
        let min_us = o.min_us.unwrap_or(ppm.min_us);
        let max_us = o.max_us.unwrap_or(ppm.max_us);
        let min_key = key("min_us", o.min_us.is_some());
        let max_key = key("max_us", o.max_us.is_some());
        check_range(&min_key, min_us)?;
        check_range(&max_key, max_us)?;
        if min_us > max_us {
            return Err(InvalidKey::new(
                min_key,
                format!("{min_us} us is above {max_key} = {max_us} us"),
            ));
        }
        // Throttle's zero actuation is its minimum: a command that leaves
        // throttle out must not spin motors up.
        let default_us = match o.default_us {
            Some(v) => v,
            None if name == "thr" => min_us,
            None => ppm.default_us,
        };
        let default_key = key("default_us", o.default_us.is_some());
        if !default_us.is_finite() || default_us < min_us || default_us > max_us {
            return Err(InvalidKey::new(
                default_key,
                format!("{default_us} us is outside this channel's {min_us}..={max_us} us"),
            ));
        }
        limits.push(ChannelLimits {
            default_us,
            min_us,
            max_us,
            mapping: resolve_mapping(name, &o, min_us, max_us)?,
            min_key,
            max_key,
        });
    }
    Ok((names, limits))
}

/// Largest `trim_us` either way, in microseconds.
pub const TRIM_MAX_US: f64 = 500.0;

/// Checks and resolves the `units`/`norm` mapping keys of channel `name`,
/// whose limits are `min_us..=max_us`.
fn resolve_mapping(
    name: &str,
    o: &ChannelOverride,
    min_us: f64,
    max_us: f64,
) -> Result<UnitMapping, InvalidKey> {
    let key = |field: &str| format!("ppm.channel.{name}.{field}");
    let units = match (o.unit_min, o.unit_max) {
        (None, None) => None,
        (Some(_), None) | (None, Some(_)) => {
            let (given, missing) = if o.unit_min.is_some() {
                ("unit_min", "unit_max")
            } else {
                ("unit_max", "unit_min")
            };
            return Err(InvalidKey::new(
                key(missing),
                format!("{given} is set but {missing} is not: a unit range needs both ends"),
            ));
        }
        (Some(lo), Some(hi)) => {
            for (field, v) in [("unit_min", lo), ("unit_max", hi)] {
                if !v.is_finite() {
                    return Err(InvalidKey::new(
                        key(field),
                        format!("{v} is not a finite number"),
                    ));
                }
            }
            if lo >= hi {
                return Err(InvalidKey::new(
                    key("unit_min"),
                    format!("{lo} is not below unit_max = {hi} (use reverse = true to swap the direction)"),
                ));
            }
            // The mapping divides by the width: an infinite one gives NaN.
            if !(hi - lo).is_finite() {
                return Err(InvalidKey::new(
                    key("unit_max"),
                    format!("the range {lo}..{hi} is too wide: unit_max - unit_min must be a finite number"),
                ));
            }
            Some((lo, hi))
        }
    };
    if units.is_none() {
        let needs_range = [
            ("unit_us_min", o.unit_us_min.is_some()),
            ("unit_us_max", o.unit_us_max.is_some()),
            ("unit", o.unit.is_some()),
        ];
        if let Some((field, _)) = needs_range.iter().find(|(_, set)| *set) {
            return Err(InvalidKey::new(
                key(field),
                format!("needs a unit range: set ppm.channel.{name}.unit_min and unit_max too"),
            ));
        }
    }
    let us_lo = o.unit_us_min.unwrap_or(min_us);
    let us_hi = o.unit_us_max.unwrap_or(max_us);
    if let Some(v) = o.unit_us_min {
        check_range(&key("unit_us_min"), v)?;
    }
    if let Some(v) = o.unit_us_max {
        check_range(&key("unit_us_max"), v)?;
    }
    if units.is_some() && us_lo >= us_hi {
        return Err(InvalidKey::new(
            key("unit_us_min"),
            format!(
                "{us_lo} us is not below unit_us_max = {us_hi} us (they default to the channel's min_us and max_us; use reverse = true to swap the direction)"
            ),
        ));
    }
    if !o.trim_us.is_finite() || o.trim_us.abs() > TRIM_MAX_US {
        return Err(InvalidKey::new(
            key("trim_us"),
            format!(
                "{} us is outside -{TRIM_MAX_US}..={TRIM_MAX_US} us",
                o.trim_us
            ),
        ));
    }
    Ok(UnitMapping {
        units,
        us_lo,
        us_hi,
        reverse: o.reverse,
        trim_us: o.trim_us,
    })
}

fn check_range(key: &str, v: f64) -> Result<(), InvalidKey> {
    if v.is_finite() && (CHANNEL_MIN_US..=CHANNEL_MAX_US).contains(&v) {
        Ok(())
    } else {
        Err(InvalidKey::new(
            key,
            format!(
                "{v} us is outside {CHANNEL_MIN_US}..={CHANNEL_MAX_US} us, the channel periods transmitters accept"
            ),
        ))
    }
}

/// Channel names in transmitter order: the four stick channels as `order`
/// places them, then `aux1`, `aux2`, ...
pub fn channel_names(order: &str, channels: usize) -> Result<Vec<String>, InvalidKey> {
    let letters: Vec<char> = order.chars().map(|c| c.to_ascii_uppercase()).collect();
    let mut sorted = letters.clone();
    sorted.sort_unstable();
    if sorted != ['A', 'E', 'R', 'T'] {
        return Err(InvalidKey::new(
            "ppm.order",
            format!(
                "`{order}` must hold each of the letters A, E, T, R once (e.g. AETR, TAER, ATER)"
            ),
        ));
    }
    Ok((0..channels)
        .map(|i| match letters.get(i) {
            Some('A') => "ail".to_string(),
            Some('E') => "ele".to_string(),
            Some('T') => "thr".to_string(),
            Some(_) => "rud".to_string(),
            None => format!("aux{}", i - 3),
        })
        .collect())
}
