//! The read-back as udp-ingress reports it: ppmd's read-back thread
//! publishes a [`ReadbackSample`] (what the radio transmits, and whether it
//! is ppm's: `following`, `overridden`, `no_input`) at every frame it reads,
//! every state change and every tenth of a second; udp-ingress keeps the
//! newest, puts it in every status reply ([`Readback::status`]), and tells
//! the groundstation of each state change at once ([`Readback::seen`]):
//! a JSON event to the sender of the newest accepted JSON command
//! ([`Readback::event`]), a STATUSTEXT to the MAVLink peers
//! ([`statustext`]).
//!
//! A change is a sample whose `changes` counter (or state) differs from the
//! last one seen: a reader that missed a sample (the service keeps only the
//! newest) still sees the counter has moved. The first sample seen is no
//! change: it is where udp-ingress starts from.
//!
//! No sender gets more event bytes than [`REPLY_MAX_RATIO`] times what its
//! accepted JSON commands had (a credit, as MAVLink peers have; capped at
//! [`CREDIT_MAX`]), unless it lies in `ingress.status_allow`.
//!
//! Logic only, without I/O; its tests are in `src/readback/tests.rs`.

use crate::peers::{CREDIT_MAX, REPLY_MAX_RATIO};
use ppm_shared::capture::{CaptureCounts, ReadbackState};
use ppm_shared::frame::MAX_CHANNELS;
use ppm_shared::ipc::ReadbackSample;
use ppm_shared::mavlink::telemetry::{MAV_SEVERITY_NOTICE, MAV_SEVERITY_WARNING};
use ppm_shared::status::ReadbackStatus;
use std::net::SocketAddr;

/// A read-back older than this (ppmd publishes one at least every tenth of
/// a second) is `stale` in status replies: ppmd stopped, or hangs.
pub const READBACK_STALE_AFTER_NS: u64 = 1_000_000_000;

/// The newest frame read is RC_CHANNELS' only while it began no longer ago
/// than this (as the line's: [`crate::LINE_STALE_AFTER_NS`]).
pub const READBACK_FRAME_STALE_AFTER_NS: u64 = crate::LINE_STALE_AFTER_NS;

/// One state change, as seen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Change {
    /// The state before (the last one seen), a [`ReadbackState`] code.
    pub from: u32,
    /// The sample that carried it.
    pub sample: ReadbackSample,
}

/// Counters of the events sent to JSON senders.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct EventCounters {
    /// Events handed to the socket.
    pub sent: u64,
    /// Events not sent: the sender had not earned them, or the socket's
    /// buffer was full.
    pub held: u64,
}

/// Who gets the JSON events: the sender of the newest accepted JSON
/// command, and what it has earned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Target {
    addr: SocketAddr,
    credit: usize,
    exempt: bool,
}

/// The read-back of one output, as seen from udp-ingress.
#[derive(Debug, Clone)]
pub struct Readback {
    /// The input read (`ppmd.readback`), as the configuration names it.
    input: String,
    /// It is a pilot's radio (`ppmd.pilot`): its states say who flies.
    pilot: bool,
    newest: Option<ReadbackSample>,
    target: Option<Target>,
    counters: EventCounters,
}

impl Readback {
    /// A read-back of `input` (`ppmd.readback`), nothing seen yet.
    pub fn new(input: String) -> Readback {
        Readback {
            input,
            pilot: false,
            newest: None,
            target: None,
            counters: EventCounters::default(),
        }
    }

    /// Takes sample `s` (the newest ppmd published): the change it carries,
    /// if its state or its `changes` differ from the last sample's. The
    /// first sample is no change.
    pub fn seen(&mut self, s: ReadbackSample) -> Option<Change> {
        let last = self.newest.replace(s)?;
        (last.changes != s.changes || last.state != s.state).then_some(Change {
            from: last.state,
            sample: s,
        })
    }

    /// The newest sample seen, if any.
    pub fn newest(&self) -> Option<&ReadbackSample> {
        self.newest.as_ref()
    }

    /// An accepted JSON command of `len` bytes came from `from` (`exempt`:
    /// it lies in `ingress.status_allow`): it is now the events' target, and
    /// has earned [`REPLY_MAX_RATIO`] times `len` more.
    pub fn commanded_by(&mut self, from: SocketAddr, len: usize, exempt: bool) {
        let earned = len.saturating_mul(REPLY_MAX_RATIO);
        self.target = Some(match self.target {
            Some(t) if t.addr == from => Target {
                credit: (t.credit + earned).min(CREDIT_MAX),
                exempt,
                ..t
            },
            _ => Target {
                addr: from,
                credit: earned.min(CREDIT_MAX),
                exempt,
            },
        });
    }

    /// The event datagram for `change` of output `name`, and where it goes:
    /// the sender of the newest accepted JSON command, if it has earned it.
    /// Counted as sent, or held (none earned it).
    pub fn event(&mut self, name: &str, change: &Change) -> Option<(SocketAddr, String)> {
        let target = self.target.as_mut()?;
        let text = event_text(name, change);
        if !target.exempt && target.credit < text.len() {
            self.counters.held += 1;
            return None;
        }
        if !target.exempt {
            target.credit -= text.len();
        }
        self.counters.sent += 1;
        Some((target.addr, text))
    }

    /// An event [`Readback::event`] gave could not be sent.
    pub fn event_not_sent(&mut self) {
        self.counters.sent -= 1;
        self.counters.held += 1;
    }

    /// The events' counters so far.
    pub fn counters(&self) -> EventCounters {
        self.counters
    }

    /// The newest frame read, us (rounded), and its start on
    /// CLOCK_MONOTONIC, us, while it began no longer than
    /// [`READBACK_FRAME_STALE_AFTER_NS`] before `now_mono_ns`: what
    /// RC_CHANNELS carries. `None`: no such frame (RC_CHANNELS then says
    /// no channels).
    pub fn frame_us(&self, now_mono_ns: u64) -> Option<([u16; MAX_CHANNELS], usize, u64)> {
        let s = self.newest.as_ref()?;
        let n = (s.channels as usize).min(MAX_CHANNELS);
        if n == 0
            || s.start_mono_ns == 0
            || now_mono_ns.saturating_sub(s.start_mono_ns) > READBACK_FRAME_STALE_AFTER_NS
        {
            return None;
        }
        let mut us = [0u16; MAX_CHANNELS];
        for (u, &ns) in us.iter_mut().zip(&s.values_ns[..n]) {
            *u = ((ns as u64 + 500) / 1_000).min(u16::MAX as u64) as u16;
        }
        Some((us, n, s.start_mono_ns / 1_000))
    }

    /// The `readback` member of a status reply at CLOCK_MONOTONIC
    /// `now_mono_ns`, udp-ingress having run for `waited_ns`: the newest
    /// sample's, `stale` when it is older than [`READBACK_STALE_AFTER_NS`].
    /// Before the first sample: `stale`, every count 0, no frame, and as
    /// its age how long udp-ingress has waited for one.
    pub fn status(&self, now_mono_ns: u64, waited_ns: u64) -> ReadbackStatus {
        let ms = |ns: u64| round3(ns as f64 / 1e6);
        let us = |ns: u64| round3(ns as f64 / 1e3);
        let s = self.newest.unwrap_or_default();
        let age_ns = match &self.newest {
            Some(s) => now_mono_ns.saturating_sub(s.published_mono_ns),
            None => waited_ns,
        };
        let state = match ReadbackState::from_code(s.state) {
            _ if self.newest.is_none() || age_ns > READBACK_STALE_AFTER_NS => "stale",
            Some(state) => state.name(),
            None => "unknown",
        };
        let n = (s.channels as usize).min(MAX_CHANNELS);
        ReadbackStatus {
            state: state.into(),
            input: self.input.clone(),
            since_ms: (s.changes > 0 && s.changed_mono_ns > 0)
                .then(|| ms(now_mono_ns.saturating_sub(s.changed_mono_ns))),
            changes: s.changes,
            edges: s.edges,
            frames: s.frames,
            matched: s.matched,
            mismatched: s.mismatched,
            refused: CaptureCounts::default()
                .reasons()
                .iter()
                .zip(s.refused)
                .map(|((name, _), n)| (name.to_string(), n))
                .collect(),
            ch_us: s.values_ns[..n].iter().map(|&v| us(v as u64)).collect(),
            max_diff_us: (s.max_diff_ns != u32::MAX).then(|| us(s.max_diff_ns as u64)),
            age_ms: ms(age_ns),
        }
    }
}

/// The name of state `code` ([`ReadbackState::name`]; `unknown` for a code
/// this build does not know).
pub fn state_name(code: u32) -> &'static str {
    ReadbackState::from_code(code).map_or("unknown", ReadbackState::name)
}

/// The JSON event of `change` of output `name`, its keys sorted (as status
/// replies have them):
/// `{"changed_mono_ns":T,"changes":N,"event":"readback","from":"following","name":"pi","state":"overridden"}`.
pub fn event_text(name: &str, change: &Change) -> String {
    serde_json::json!({
        "event": "readback",
        "name": name,
        "state": state_name(change.sample.state),
        "from": state_name(change.from),
        "changes": change.sample.changes,
        "changed_mono_ns": change.sample.changed_mono_ns,
    })
    .to_string()
}

impl Readback {
    /// A pilot's radio's states (`ppmd.pilot`) on the read-back's service,
    /// `input` as the configuration names it.
    pub fn pilot(input: String) -> Readback {
        Readback {
            pilot: true,
            ..Readback::new(input)
        }
    }

    /// The STATUSTEXT of `change` of output `name`: a read-back's
    /// ([`statustext`]), or a pilot's radio's ([`pilot_statustext`]).
    pub fn statustext(&self, name: &str, change: &Change) -> (u8, String) {
        match self.pilot {
            true => pilot_statustext(name, change),
            false => statustext(name, change),
        }
    }
}

/// The STATUSTEXT of `change` of a pilot's radio of output `name`: WARNING
/// for `overridden` ("ppm NAME: the pilot has control") and `no_input`
/// ("ppm NAME: no pilot's radio, no command goes out"), NOTICE for
/// `following` ("ppm NAME: the groundstation has control").
pub fn pilot_statustext(name: &str, change: &Change) -> (u8, String) {
    let (severity, what) = match ReadbackState::from_code(change.sample.state) {
        Some(ReadbackState::Following) => (MAV_SEVERITY_NOTICE, "the groundstation has control"),
        Some(ReadbackState::Overridden) => (MAV_SEVERITY_WARNING, "the pilot has control"),
        Some(ReadbackState::NoInput) => (
            MAV_SEVERITY_WARNING,
            "no pilot's radio, no command goes out",
        ),
        None => (MAV_SEVERITY_WARNING, "pilot's radio state unknown"),
    };
    (severity, format!("ppm {name}: {what}"))
}

/// The STATUSTEXT of `change` of output `name`: its severity (a
/// MAV_SEVERITY) and text: WARNING for `overridden` ("ppm NAME: overridden
/// (instructor has control)") and `no_input` ("ppm NAME: no read-back
/// input"), NOTICE for `following` ("ppm NAME: following").
pub fn statustext(name: &str, change: &Change) -> (u8, String) {
    let (severity, what) = match ReadbackState::from_code(change.sample.state) {
        Some(ReadbackState::Following) => (MAV_SEVERITY_NOTICE, "following"),
        Some(ReadbackState::Overridden) => {
            (MAV_SEVERITY_WARNING, "overridden (instructor has control)")
        }
        Some(ReadbackState::NoInput) => (MAV_SEVERITY_WARNING, "no read-back input"),
        None => (MAV_SEVERITY_WARNING, "read-back state unknown"),
    };
    (severity, format!("ppm {name}: {what}"))
}

/// Rounded to three decimals (ms to the us, us to the ns).
fn round3(v: f64) -> f64 {
    (v * 1e3).round() / 1e3
}

#[cfg(test)]
pub(crate) mod tests;
