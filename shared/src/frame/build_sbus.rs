//! Building an SBUS [`FrameModel`]: the `[ppm]` section against the SBUS
//! receivers of `ppm.receiver`.

use super::build::{model, receiver_key, resolve_channels, Wire};
use super::{us_to_ns, FrameModel, InvalidKey, PpmSection, LATE_EDGE_GUARD_US};
use crate::sbus::{
    self,
    timing::{SbusChoice, FOLLOW_GAP_MAX_DEFAULT_US, FRAME_WIRE_US, GAP_MARGIN_US, GAP_MAX_US},
};
use crate::wire::{SbusWire, WireModel};

/// An SBUS model: 16 channels whose values every SBUS receiver of
/// `ppm.receiver` reads, encoded for one of them, and idle lines between
/// frames each of them takes. The PPM keys `pulse_us` and
/// `late_edge_guard_us` are not used.
pub(crate) fn build(ppm: &PpmSection) -> Result<FrameModel, InvalidKey> {
    let choice = SbusChoice::new(ppm.receiver).map_err(|m| {
        InvalidKey::new(
            "ppm.receiver",
            format!("`{}` under protocol = \"sbus\": {m}", ppm.receiver.name()),
        )
    })?;
    let under = format!("protocol = \"sbus\" and {}", receiver_key(ppm.receiver));
    if ppm.channels() as usize != sbus::CHANNELS {
        return Err(InvalidKey::new(
            "ppm.channels",
            format!(
                "{}: an SBUS frame carries {} channels, so with protocol = \"sbus\" ppm.channels is {} (remove the key; a command with fewer values fills the rest with the channel defaults)",
                ppm.channels(),
                sbus::CHANNELS,
                sbus::CHANNELS
            ),
        ));
    }
    let (names, limits) = resolve_channels(ppm)?;
    let (lo, hi) = choice.value_range_us();
    for l in &limits {
        let (key, v, rule, nearest) = if l.min_us < lo as f64 {
            (&l.min_key, l.min_us, "raise", lo)
        } else if l.max_us > hi as f64 {
            (&l.max_key, l.max_us, "lower", hi)
        } else {
            continue;
        };
        return Err(InvalidKey::new(
            key,
            format!(
                "{v} us: the SBUS values every receiver of {under} reads as they were sent are {lo}..={hi} us (encoded for {}): {rule} {key} to {nearest} us",
                choice.encode_for().name()
            ),
        ));
    }
    let least = choice.least_gap_us() as f64;
    let gap_min = ppm.follow_sync_min_us.unwrap_or(choice.default_gap_us());
    if !gap_min.is_finite() || gap_min < least || gap_min > GAP_MAX_US {
        return Err(InvalidKey::new(
            "ppm.follow_sync_min_us",
            format!(
                "{gap_min} us: the idle line between SBUS frames must be {least}..={GAP_MAX_US} us under {under} (the receivers' least, with {GAP_MARGIN_US} us for a frame that leaves late)"
            ),
        ));
    }
    let gap_max = ppm
        .follow_sync_max_us
        .unwrap_or(FOLLOW_GAP_MAX_DEFAULT_US.max(gap_min));
    if !gap_max.is_finite() || gap_max > GAP_MAX_US || gap_max < gap_min {
        return Err(InvalidKey::new(
            "ppm.follow_sync_max_us",
            format!(
                "{gap_max} us: the longest idle line between SBUS frames must be {gap_min}..={GAP_MAX_US} us (from ppm.follow_sync_min_us to well inside the receivers' signal-loss time)"
            ),
        ));
    }
    let period = ppm.frame_us();
    let (period_lo, period_hi) = (FRAME_WIRE_US + least, FRAME_WIRE_US + GAP_MAX_US);
    if !period.is_finite() || period < period_lo || period > period_hi {
        return Err(InvalidKey::new(
            "ppm.frame_us",
            format!(
                "{period} us: the SBUS grid period must be {period_lo}..={period_hi} us under {under} (a frame takes {FRAME_WIRE_US} us on the wire, and the receivers need {least} us of idle line after it; 7000 and 14000 are common periods)"
            ),
        ));
    }
    Ok(model(
        ppm,
        names,
        &limits,
        Wire {
            frame_ns: us_to_ns(period),
            follow_sync_ns: (us_to_ns(gap_min), us_to_ns(gap_max)),
            sync_window_ns: (us_to_ns(least), us_to_ns(GAP_MAX_US)),
            late_edge_guard_ns: us_to_ns(LATE_EDGE_GUARD_US),
            wire: WireModel::Sbus(SbusWire { choice }),
        },
    ))
}
