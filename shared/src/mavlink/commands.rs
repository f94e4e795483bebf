//! What the command messages, RC_CHANNELS_OVERRIDE and MANUAL_CONTROL, do
//! to the channels ([`command()`]): keep, release, set (checked and
//! clamped as a JSON value is), or drive from a joystick's axes and
//! buttons.

use super::message::Message;
use super::settings::{addressed, Settings, Thrust};
use crate::frame::{Channels, FrameModel, MAX_CHANNELS};
use crate::protocol::{reject, Command, Reject, RejectReason, VALUE_MAX_US, VALUE_MIN_US};

/// The command a message carries, for a line now carrying `current` (the
/// values "keep" keeps).
pub fn command(
    message: &Message,
    model: &FrameModel,
    settings: &Settings,
    current: &Channels,
) -> Result<Command, Reject> {
    let n = model.channels();
    let mut ns = [0u32; MAX_CHANNELS];
    ns[..n].copy_from_slice(current.as_ns());
    let mut clamped = 0;
    let target = |system: u8| -> Result<(), Reject> {
        if addressed(system, settings.system_id) {
            Ok(())
        } else {
            Err(reject(
                RejectReason::WrongOutput,
                format!(
                    "target system {system}: this is system {} (mavlink.system_id)",
                    settings.system_id
                ),
            ))
        }
    };
    match message {
        Message::Heartbeat
        | Message::ParamRequestList(..)
        | Message::RequestDataStream(_)
        | Message::CommandLong(_)
        | Message::Ignored(_) => return Err(reject(RejectReason::BadShape, "not a command")),
        Message::RcOverride(o) => {
            target(o.target_system)?;
            let c = o.target_component;
            if !addressed(c, settings.component_id) {
                return Err(reject(
                    RejectReason::WrongOutput,
                    format!(
                        "target component {c}: this is component {} (mavlink.component_id)",
                        settings.component_id
                    ),
                ));
            }
            for (i, &v) in o.chan.iter().enumerate() {
                let (keep, release) = if i < 8 {
                    (v == u16::MAX, v == 0)
                } else {
                    (v == u16::MAX || v == 0, v == u16::MAX - 1)
                };
                if keep {
                    continue;
                }
                if i >= n {
                    if release {
                        continue;
                    }
                    return Err(reject(
                        RejectReason::TooManyValues,
                        format!("chan{}_raw is {v} but the frame has {n} channels", i + 1),
                    ));
                }
                if release {
                    ns[i] = model.default_ns(i);
                    continue;
                }
                let us = v as f64;
                if !(VALUE_MIN_US..=VALUE_MAX_US).contains(&us) {
                    return Err(reject(
                        RejectReason::OutOfRange,
                        format!(
                            "chan{}_raw is {v} us, outside {VALUE_MIN_US}..={VALUE_MAX_US}",
                            i + 1
                        ),
                    ));
                }
                let (c, was) = model.clamp(i, v as u32 * 1_000);
                ns[i] = c;
                clamped += was as u32;
            }
        }
        Message::ManualControl(m) => {
            target(m.target)?;
            for (axis, (&v, ch)) in m.axes.iter().zip(settings.axes).enumerate() {
                let Some(i) = ch else { continue };
                if v == i16::MAX {
                    continue;
                }
                let norm = if axis == 2 && settings.thrust == Thrust::Positive {
                    v as f64 / 500.0 - 1.0
                } else {
                    v as f64 / 1000.0
                };
                let (c, was) = model.norm_to_ns(i, norm);
                ns[i] = c;
                clamped += was as u32;
            }
            for (b, &i) in settings.buttons.iter().enumerate() {
                ns[i] = if m.buttons & (1 << b) != 0 {
                    model.max_ns(i)
                } else {
                    model.min_ns(i)
                };
            }
        }
    }
    Ok(Command {
        seq: None,
        channels: Channels::from_ns(&ns[..n]),
        clamped,
    })
}
