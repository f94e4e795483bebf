//! Building a CRSF [`FrameModel`]: the `[ppm]` section against the
//! flight-controller firmware of `ppm.receiver` and the line rate of
//! `ppm.crsf_baud`.

use super::build::{model, resolve_channels, ChannelLimits, Wire};
use super::{us_to_ns, FrameModel, InvalidKey, PpmSection, LATE_EDGE_GUARD_US};
use crate::crsf::{self, CrsfReceiver};
use crate::receiver::{Receiver, ReceiverChoice};
use crate::signal::Timing;
use crate::wire::crsf::{
    CrsfFor, CrsfTarget, CrsfWire, BAUD_DEFAULT, BAUD_RANGE, FOLLOW_GAP_MAX_DEFAULT_US,
    GAP_LEAST_US, GAP_MARGIN_US, GAP_MAX_US, MODULE_BAUDS, MODULE_BAUD_DEFAULT,
    MODULE_GAP_LEAST_US, RESYNC_US,
};
use crate::wire::WireModel;

/// A CRSF model: 16 channels whose values the firmware of `ppm.receiver`
/// reads (all three under `any`), encoded for it, at `ppm.crsf_baud`, with
/// idle lines between frames that put a firmware knocked out of step back
/// in step. The PPM keys `pulse_us` and `late_edge_guard_us` are not used.
pub(crate) fn build(ppm: &PpmSection) -> Result<FrameModel, InvalidKey> {
    let encode_for = match ppm.receiver {
        ReceiverChoice::Any => CrsfFor::Any,
        ReceiverChoice::One(Receiver::Betaflight) => CrsfFor::One(CrsfReceiver::Betaflight),
        ReceiverChoice::One(Receiver::ArduPilot) => CrsfFor::One(CrsfReceiver::ArduPilot),
        ReceiverChoice::One(r @ (Receiver::EdgeTx | Receiver::OpenTx)) => {
            return Err(InvalidKey::new(
                "ppm.receiver",
                format!(
                    "`{}` under protocol = \"crsf\": EdgeTX and OpenTX take no CRSF on their trainer port (nor on an AUX serial port); CRSF goes to a flight controller: set ppm.receiver to betaflight, ardupilot or any (all of them), or use protocol = \"ppm\" or \"sbus\" for a radio",
                    r.name()
                ),
            ))
        }
    };
    let under = format!(
        "protocol = \"crsf\" and ppm.receiver = \"{}\"",
        encode_for.name()
    );
    if ppm.channels() as usize != crsf::CHANNELS {
        return Err(InvalidKey::new(
            "ppm.channels",
            format!(
                "{}: a CRSF RC frame carries {} channels, so with protocol = \"crsf\" ppm.channels is {} (remove the key; a command with fewer values fills the rest with the channel defaults)",
                ppm.channels(),
                crsf::CHANNELS,
                crsf::CHANNELS
            ),
        ));
    }
    if ppm.crsf_target == CrsfTarget::Module {
        return build_module(ppm, encode_for);
    }
    let baud = ppm.crsf_baud.unwrap_or(BAUD_DEFAULT);
    if !(BAUD_RANGE.0..=BAUD_RANGE.1).contains(&baud) {
        return Err(InvalidKey::new(
            "ppm.crsf_baud",
            format!(
                "{baud} is outside {}..={}: Betaflight and iNav read CRSF at 420000 (the default), ArduPilot at 416666 or 420000",
                BAUD_RANGE.0, BAUD_RANGE.1
            ),
        ));
    }
    let wire = CrsfWire::new(encode_for, baud);
    let (names, limits) = channels_read_by(ppm, encode_for, &under)?;
    let least = GAP_LEAST_US as f64;
    let gap_min = ppm.follow_sync_min_us.unwrap_or(least);
    if !gap_min.is_finite() || gap_min < least || gap_min > GAP_MAX_US {
        return Err(InvalidKey::new(
            "ppm.follow_sync_min_us",
            format!(
                "{gap_min} us: the idle line between CRSF frames must be {least}..={GAP_MAX_US} us (more than the {RESYNC_US} us after which Betaflight and iNav restart their framing, so a lost byte costs one frame, with {GAP_MARGIN_US} us for a frame that leaves late)"
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
                "{gap_max} us: the longest idle line between CRSF frames must be {gap_min}..={GAP_MAX_US} us (from ppm.follow_sync_min_us to well inside the firmware's signal-loss time, 100 ms on Betaflight)"
            ),
        ));
    }
    let wire_us = wire.frame_wire_ns() as f64 / 1e3;
    let period = ppm.frame_us();
    let (period_lo, period_hi) = ((wire_us + least).ceil(), (wire_us + GAP_MAX_US).floor());
    if !period.is_finite() || period < period_lo || period > period_hi {
        return Err(InvalidKey::new(
            "ppm.frame_us",
            format!(
                "{period} us: the CRSF grid period must be {period_lo}..={period_hi} us at {baud} baud (an RC frame and link statistics take {wire_us} us on the wire, and {least} us of idle line follow; 4000 is the default)"
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
            wire: WireModel::Crsf(wire),
        },
    ))
}

/// A CRSF model to an ExpressLRS transmitter module (`ppm.crsf_target =
/// "module"`): RC frames to 0xEE alone, at `ppm.crsf_baud` (400 000 by
/// default), on a grid whatever `ppm.timing` says (the module wants frames
/// at its own rate, which the grid follows), every `ppm.frame_us` (4000 by
/// default) until the module's first timing correction. The values are
/// encoded for the flight controller behind the module's link
/// (`ppm.receiver`): ExpressLRS passes the raw values on.
fn build_module(ppm: &PpmSection, encode_for: CrsfFor) -> Result<FrameModel, InvalidKey> {
    let baud = ppm.crsf_baud.unwrap_or(MODULE_BAUD_DEFAULT);
    if !MODULE_BAUDS.contains(&baud) {
        return Err(InvalidKey::new(
            "ppm.crsf_baud",
            format!(
                "{baud}: an ExpressLRS module reads a handset at 400000 (the default), 115200, 921600, 1870000 or 2250000 only (it also searches 3750000 and 5250000, above what a Pi's UART makes)"
            ),
        ));
    }
    if ppm.crsf_model_id > crsf::module::MODEL_ID_MAX {
        return Err(InvalidKey::new(
            "ppm.crsf_model_id",
            format!(
                "{} is outside 0..={}: the model (receiver) ID a radio gives its module",
                ppm.crsf_model_id,
                crsf::module::MODEL_ID_MAX
            ),
        ));
    }
    let wire = CrsfWire::module(encode_for, baud, ppm.crsf_model_id);
    let under = format!("ppm.receiver = \"{}\"", encode_for.name());
    let (names, limits) = channels_read_by(ppm, encode_for, &under)?;
    let least = MODULE_GAP_LEAST_US as f64;
    let wire_us = wire.frame_wire_ns() as f64 / 1e3;
    let period = ppm.frame_us();
    let (period_lo, period_hi) = ((wire_us + least).ceil(), GAP_MAX_US);
    if !period.is_finite() || period < period_lo || period > period_hi {
        return Err(InvalidKey::new(
            "ppm.frame_us",
            format!(
                "{period} us: the period of CRSF frames to a module before its first timing correction must be {period_lo}..={period_hi} us at {baud} baud (an RC frame takes {wire_us} us on the wire; 4000 is the default, EdgeTX's at 400000 baud)"
            ),
        ));
    }
    let mut m = model(
        ppm,
        names,
        &limits,
        Wire {
            frame_ns: us_to_ns(period),
            follow_sync_ns: (us_to_ns(least), us_to_ns(GAP_MAX_US)),
            sync_window_ns: (us_to_ns(least), us_to_ns(GAP_MAX_US)),
            late_edge_guard_ns: us_to_ns(LATE_EDGE_GUARD_US),
            wire: WireModel::Crsf(wire),
        },
    );
    m.timing = Timing::Grid;
    Ok(m)
}

/// The channels of `[ppm]`, each one's limits within the values every
/// firmware `encode_for` covers reads (`under`: how a message names that
/// choice).
fn channels_read_by(
    ppm: &PpmSection,
    encode_for: CrsfFor,
    under: &str,
) -> Result<(Vec<String>, Vec<ChannelLimits>), InvalidKey> {
    let (names, limits) = resolve_channels(ppm)?;
    let (lo, hi) = encode_for.value_range_us();
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
            format!("{v} us: the CRSF values every firmware of {under} reads are {lo}..={hi} us: {rule} {key} to {nearest} us"),
        ));
    }
    Ok((names, limits))
}
