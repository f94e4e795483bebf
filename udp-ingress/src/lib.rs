//! `udp-ingress`: receives JSON commands over UDP, keeps only the newest
//! valid one per wake-up, and publishes it to ppmd through shared memory.
//!
//! [`Intake`] holds the logic (parse, stale check, counters, newest-wins,
//! status queries and their replies) without any I/O, so it is tested
//! directly; the binary wires it to a non-blocking mio socket, an iceoryx2
//! publisher and a subscriber to ppmd's timing snapshots.
//!
//! With a key ([`Intake::with_auth`]) only signed commands for this output
//! (their `to` is its name) with a `seq` greater than the last accepted one
//! are applied; a signed command for another output is refused before the
//! `seq` gate sees it. [`seqfile`] keeps that
//! `seq` across restarts. Without a key, the `seq` gate forgets once no
//! command was accepted for [`Intake::forget_seq_after`] (the failsafe's
//! `after_ms`): one datagram with a huge `seq` cannot lock numbered commands
//! out for longer. With an allowlist ([`Intake::with_allowlist`])
//! datagrams from other sources are dropped before they are parsed.
//!
//! - [`Intake`], [`query`], [`status_answer`]: the logic, without I/O; its
//!   status reply is [`ppm_shared::status::StatusReply`], the type the tools
//!   read it back with.
//! - [`cli`]: the command line, lowered with the file into what runs.
//! - [`server`]: the receive loop around it: socket, publisher, replies.
//! - [`peers`]: the MAVLink groundstations it answers, and what they get.
//! - [`readback`]: ppmd's read-back (what the radio transmits) as status
//!   replies, JSON events and STATUSTEXTs report it.
//! - [`telemetry`]: a CRSF flight controller's telemetry as status replies
//!   and MAVLink messages report it.
//! - [`seqfile`]: the last accepted `seq`, kept across restarts.
//!
//! Its unit tests are in `src/tests/`.

pub mod cli;
pub mod peers;
mod query;
pub mod readback;
pub mod seqfile;
pub mod server;
pub mod telemetry;

pub use query::{pad_to_text, query, status_answer, Query, StatusAnswer};

use ipnet::IpNet;
use ppm_shared::auth::{self, AuthKey};
use ppm_shared::frame::{FrameModel, MAX_CHANNELS};
use ppm_shared::ipc::{LineSample, ReadbackSample, TelemetrySample, TimingSnapshot};
use ppm_shared::line::LineState;
use ppm_shared::mavlink;
use ppm_shared::mavlink::telemetry::MAV_SEVERITY_INFO;
use ppm_shared::protocol::{self, Command, Reject, RejectReason, SeqGate, To};
use ppm_shared::status::{
    Datagrams, EdgeError, MavlinkStatus, PpmdStatus, PublishLatency, ReceiverStatus, Rejected,
    StatusReply,
};
use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};

/// A line sample whose frame started longer ago than this says no frame
/// goes out now (ppmd publishes the newest every tenth of a second while
/// frames go out).
pub const LINE_STALE_AFTER_NS: u64 = 300_000_000;

/// A ppmd timing snapshot older than this is not reported as ppmd's state
/// (ppmd publishes one a second; older means it stopped or hangs).
pub const PPMD_STALE_AFTER_NS: u64 = 3_000_000_000;

/// Counters of everything the ingress received.
///
/// Every received datagram ends up in exactly one of `published`,
/// `superseded`, `stale` or `rejected` (once the wake-up's newest command is
/// published). Status queries are not commands: they are counted in
/// `status_requests` only, never in `received`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Counters {
    /// Datagrams received, status queries excepted (a malformed query is
    /// counted here and as rejected).
    pub received: u64,
    /// Valid commands published to ppmd.
    pub published: u64,
    /// Valid commands replaced by a newer one from the same wake-up before publishing.
    pub superseded: u64,
    /// Rejected datagrams, by [`RejectReason::index`].
    pub rejected: [u64; RejectReason::ALL.len()],
    /// Commands dropped because their `seq` was not greater than the last applied.
    pub stale: u64,
    /// Times the `seq` gate forgot the last `seq` (no key, and no command
    /// accepted for `failsafe.after_ms`): the command then applied instead
    /// of being stale.
    pub seq_resets: u64,
    /// Accepted commands with at least one value clamped.
    pub clamped_commands: u64,
    /// Values clamped in all accepted commands.
    pub clamped_values: u64,
    /// Status queries (`{"get": "status"}`) received.
    pub status_requests: u64,
    /// Status replies not sent (the socket's send buffer was full, or too
    /// many queries arrived in one wake-up).
    pub status_dropped: u64,
    /// Status queries answered with `{"pad_to": N}` instead of the reply:
    /// too short for it from a source outside `ingress.status_allow`.
    pub status_short: u64,
    /// MAVLink datagrams without a command (HEARTBEATs, requests): counted
    /// here only, never in `received`.
    pub mavlink_no_command: u64,
    /// Well-formed MAVLink frames ppm ignores ([`mavlink::IGNORED`]).
    pub mavlink_ignored: u64,
}

impl Counters {
    /// All rejected datagrams.
    pub fn rejected_total(&self) -> u64 {
        self.rejected.iter().sum()
    }

    /// One line: `received 10 published 8 ... rejected{invalid_json=1 ...}`.
    pub fn summary(&self) -> String {
        let rejected: Vec<String> = RejectReason::ALL
            .iter()
            .filter(|r| self.rejected[r.index()] > 0)
            .map(|r| format!("{}={}", r.as_str(), self.rejected[r.index()]))
            .collect();
        format!(
            "received {} published {} superseded {} stale {} (seq resets {}) clamped {} (values {}) rejected {} [{}] status requests {} (dropped {})",
            self.received,
            self.published,
            self.superseded,
            self.stale,
            self.seq_resets,
            self.clamped_commands,
            self.clamped_values,
            self.rejected_total(),
            rejected.join(" "),
            self.status_requests,
            self.status_dropped
        )
    }
}

/// A valid command with its receive times.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Received {
    /// The command.
    pub command: Command,
    /// CLOCK_MONOTONIC receive time, ns.
    pub mono_ns: u64,
    /// CLOCK_REALTIME receive time, ns.
    pub real_ns: u64,
}

/// What happened to one datagram.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// Valid: it is now the newest command.
    Accepted,
    /// Valid but stale (`seq` not greater than the last applied).
    Stale,
    /// Rejected; the string is a log line when the rate limit allows one.
    Rejected(RejectReason, Option<String>),
    /// A query: answer a status query with [`Intake::status`], a
    /// telemetry query with [`Intake::telemetry_answer`] (nothing changed).
    Status(Query),
    /// MAVLink without a command: HEARTBEATs, a request for the
    /// parameters (nothing changed).
    NoCommand,
}

/// True when `ip` lies in one of `nets`, or `nets` is empty (no allowlist).
/// An IPv4 sender seen on a dual-stack socket (`::ffff:10.0.0.5`) matches
/// IPv4 blocks.
pub fn allowed(nets: &[IpNet], ip: IpAddr) -> bool {
    nets.is_empty() || in_blocks(nets, ip)
}

/// True when `ip` lies in one of `nets` (none when `nets` is empty); an
/// IPv4 sender seen on a dual-stack socket matches IPv4 blocks.
pub(crate) fn in_blocks(nets: &[IpNet], ip: IpAddr) -> bool {
    let canonical = ip.to_canonical();
    nets.iter()
        .any(|n| n.contains(&ip) || n.contains(&canonical))
}

/// Parse, check and keep the newest command; count everything.
pub struct Intake {
    /// The output's name: what a command's `to` must be.
    name: String,
    model: FrameModel,
    mavlink: mavlink::Settings,
    peers: peers::Peers,
    /// MAVLink 2 signing (`mavlink.key_file`).
    signing: Option<mavlink::Signing>,
    /// `ingress.status_allow`: peers there get MAVLink replies without
    /// earning them.
    status_allow: Vec<IpNet>,
    key: Option<AuthKey>,
    allow: Vec<IpNet>,
    /// The `seq` of the last command that passed the gate.
    last_seq: Option<u64>,
    /// The `seq` of the newest command applied that had one (not the floor
    /// of a restart): the status reply's `newest_seq`. Commands without
    /// one, MAVLink's among them, leave it as it is.
    newest_seq: Option<u64>,
    gate: SeqGate,
    /// Without a key: how long without an accepted command before the
    /// gate forgets (`None`: never).
    forget_seq: Option<Duration>,
    /// When the last command was accepted.
    last_accepted: Option<Instant>,
    newest: Option<Received>,
    latest: Option<Received>,
    counters: Counters,
    log: RejectLog,
    latency: hdrhistogram::Histogram<u64>,
    /// The read-back (`ppmd.readback`), if any.
    readback: Option<readback::Readback>,
    /// The flight controller's CRSF telemetry, if the output reads it.
    telemetry: Option<telemetry::Telemetry>,
}

impl Intake {
    /// An intake for the output named `name` (commands whose `to` names
    /// another output are refused) with the channels of `model`, logging
    /// each reject reason at most once per `log_interval`.
    pub fn new(name: &str, model: FrameModel, log_interval: Duration) -> Intake {
        Intake {
            name: name.to_owned(),
            mavlink: mavlink::Settings::defaults_for(&model),
            peers: peers::Peers::new(1, 1, model.channels(), mavlink::RC_CHANNELS_HZ),
            signing: None,
            status_allow: Vec::new(),
            model,
            key: None,
            allow: Vec::new(),
            last_seq: None,
            newest_seq: None,
            gate: SeqGate::default(),
            forget_seq: None,
            last_accepted: None,
            newest: None,
            latest: None,
            counters: Counters::default(),
            log: RejectLog::new(log_interval),
            latency: hdrhistogram::Histogram::new_with_bounds(1, 60_000_000_000, 3)
                .expect("valid histogram bounds"),
            readback: None,
            telemetry: None,
        }
    }

    /// The output has a read-back of `input` (`ppmd.readback`, as the
    /// configuration names it): status replies carry it, its state changes
    /// go to the groundstation ([`Intake::readback`]), and RC_CHANNELS
    /// carry what the radio transmits.
    pub fn with_readback(mut self, input: String) -> Intake {
        self.readback = Some(readback::Readback::new(input));
        self
    }

    /// The output has a pilot's radio `input` (`ppmd.pilot`), whose
    /// states come on the read-back's service: as a read-back's, with
    /// STATUSTEXTs that say who flies ([`readback::pilot_statustext`]).
    pub fn with_pilot(mut self, input: String) -> Intake {
        self.readback = Some(readback::Readback::pilot(input));
        self
    }

    /// Applies only commands signed with `key` ([`auth`]) for this output
    /// (`to` is its name) that carry a `seq` greater than the last accepted
    /// one and than `floor` (the last one accepted before a restart). A
    /// signed command for another output, or naming none, is refused before
    /// its `seq` is looked at: it never moves the gate. Status queries stay
    /// unsigned.
    pub fn with_auth(mut self, key: AuthKey, floor: Option<u64>) -> Intake {
        if floor.is_some() {
            self.gate.admit(floor);
            self.last_seq = floor;
        }
        self.key = Some(key);
        self
    }

    /// Without a key, lets the `seq` gate forget the last `seq` once no
    /// command was accepted for `after` (give it `failsafe.after_ms`: by
    /// then the line has taken its failsafe action). A numbered command that
    /// would be stale is then applied, and the gate starts again from its
    /// `seq`: a sender that restarted its count, or one forged datagram with
    /// a huge `seq`, locks numbered commands out for at most `after`. With a
    /// key ([`Intake::with_auth`]) the gate never forgets: replays stay
    /// refused.
    pub fn forget_seq_after(mut self, after: Duration) -> Intake {
        self.forget_seq = Some(after);
        self
    }

    /// MAVLink commands are for this system and component, and
    /// MANUAL_CONTROL drives these channels ([`mavlink::Settings`]).
    pub fn with_mavlink(mut self, settings: mavlink::Settings) -> Intake {
        self.peers = peers::Peers::new(
            settings.system_id,
            settings.component_id,
            self.model.channels(),
            settings.rc_channels_hz,
        )
        .with_mav_type(settings.vehicle_type.mav_type());
        self.mavlink = settings;
        self
    }

    /// Takes only MAVLink frames signed with `key` (MAVLink 2 signing,
    /// `mavlink.key_file`) at timestamps above `floor` (the newest accepted
    /// before a restart, from `mavlink.timestamp_file`), and signs the
    /// replies. MAVLink commands then apply whether or not
    /// `ingress.auth_key` is set.
    pub fn with_mavlink_signing(mut self, key: AuthKey, floor: Option<u64>) -> Intake {
        let signing = mavlink::Signing::new(key);
        self.signing = Some(match floor {
            Some(f) => signing.with_floor(f),
            None => signing,
        });
        self
    }

    /// With MAVLink signing, the newest signing timestamp accepted (or the
    /// floor it started with): what a restarted ingress must refuse up to.
    pub fn mavlink_newest_ts(&self) -> Option<u64> {
        self.signing.as_ref().and_then(|s| s.newest())
    }

    /// MAVLink peers in `nets` (`ingress.status_allow`) get replies without
    /// earning them ([`peers`]).
    pub fn with_status_allow(mut self, nets: Vec<IpNet>) -> Intake {
        self.status_allow = nets;
        self
    }

    /// Takes `sample`, the newest read-back ppmd published (without a
    /// read-back configured, nothing): the state change it carries, if its
    /// `changes` counter (or state) moved ([`readback::Readback::seen`]),
    /// with the JSON event for the sender of the newest accepted JSON
    /// command and where it goes, if it has earned it. Every MAVLink peer
    /// gets the change's STATUSTEXT at the next [`Intake::mavlink_due`].
    pub fn readback(
        &mut self,
        sample: ReadbackSample,
    ) -> Option<(readback::Change, Option<(SocketAddr, String)>)> {
        let rb = self.readback.as_mut()?;
        let change = rb.seen(sample)?;
        let (severity, text) = rb.statustext(&self.name, &change);
        self.peers.announce(severity, &text);
        Some((change, rb.event(&self.name, &change)))
    }

    /// The output reads a flight controller's CRSF telemetry from `port`:
    /// status replies carry it, MAVLink peers get it
    /// ([`Intake::telemetry`]).
    pub fn with_telemetry(mut self, port: String) -> Intake {
        self.telemetry = Some(telemetry::Telemetry::new(port));
        self
    }

    /// Takes `sample`, the newest telemetry ppmd published (without
    /// telemetry, nothing); a new flight mode is told to every MAVLink
    /// peer as a STATUSTEXT at the next [`Intake::mavlink_due`].
    pub fn telemetry(&mut self, sample: TelemetrySample) {
        let Some(t) = self.telemetry.as_mut() else {
            return;
        };
        if let Some(mode) = t.seen(sample) {
            let text = telemetry::statustext(&self.name, &mode);
            self.peers.announce(MAV_SEVERITY_INFO, &text);
        }
    }

    /// The answer to `{"get": "telemetry"}` at CLOCK_MONOTONIC
    /// `now_mono_ns`: `{"name": ..., "telemetry": ...}`, the status reply's
    /// member alone (`null` for an output without telemetry).
    pub fn telemetry_answer(&self, now_mono_ns: u64) -> String {
        let t = self.telemetry.as_ref().map(|t| t.status(now_mono_ns));
        serde_json::json!({ "name": self.name, "telemetry": t }).to_string()
    }

    /// An event [`Intake::readback`] gave could not be sent.
    pub fn readback_event_not_sent(&mut self) {
        if let Some(rb) = &mut self.readback {
            rb.event_not_sent();
        }
    }

    /// The read-back, if the output has one.
    pub fn readback_state(&self) -> Option<&readback::Readback> {
        self.readback.as_ref()
    }

    /// Drops datagrams from sources outside `nets` (`not_allowed`) before
    /// parsing them; status queries too. Empty: any source.
    pub fn with_allowlist(mut self, nets: Vec<IpNet>) -> Intake {
        self.allow = nets;
        self
    }

    /// The `seq` of the last accepted command (or the floor given to
    /// [`Intake::with_auth`]): what a restarted ingress must not accept again.
    pub fn last_seq(&self) -> Option<u64> {
        self.last_seq
    }

    /// Takes one datagram received at the given times. The source is checked
    /// first, then a status query is recognised and only counted
    /// ([`Outcome::Status`]).
    pub fn offer(
        &mut self,
        datagram: &[u8],
        from: SocketAddr,
        mono_ns: u64,
        real_ns: u64,
        now: Instant,
    ) -> Outcome {
        let is_mavlink = mavlink::is_mavlink(datagram);
        let parsed = if !allowed(&self.allow, from.ip()) {
            Err(Reject {
                reason: RejectReason::NotAllowed,
                detail: format!("source {} is not in ingress.allow", from.ip()),
            })
        } else if is_mavlink {
            match self.mavlink_command(datagram, from, real_ns, now) {
                Ok(Some(command)) => Ok(command),
                Ok(None) => {
                    self.counters.mavlink_no_command += 1;
                    return Outcome::NoCommand;
                }
                Err(r) => Err(r),
            }
        } else {
            match query(datagram) {
                Some(Ok(q)) => {
                    self.counters.status_requests += 1;
                    return Outcome::Status(q);
                }
                Some(Err(r)) => Err(r),
                None => self.command(datagram).map_err(|r| {
                    // Not UTF-8, so no JSON: bytes before a good MAVLink
                    // frame are MAVLink junk, as they are between frames.
                    match r.reason {
                        RejectReason::InvalidUtf8 => {
                            mavlink::junk_before_frame(datagram).unwrap_or(r)
                        }
                        _ => r,
                    }
                }),
            }
        };
        self.counters.received += 1;
        match parsed {
            Err(r) => self.reject(r, from, now),
            Ok(command) if !self.gate.admit(command.seq) && !self.forget(command.seq, now) => {
                if self.key.is_some() {
                    let detail = format!(
                        "seq {} is not greater than the last accepted {}",
                        command.seq.unwrap_or(0),
                        self.last_seq.unwrap_or(0)
                    );
                    return self.reject(
                        Reject {
                            reason: RejectReason::Replay,
                            detail,
                        },
                        from,
                        now,
                    );
                }
                self.counters.stale += 1;
                Outcome::Stale
            }
            Ok(command) => {
                self.last_accepted = Some(now);
                if let (Some(rb), false) = (&mut self.readback, is_mavlink) {
                    let exempt = in_blocks(&self.status_allow, from.ip());
                    rb.commanded_by(from, datagram.len(), exempt);
                }
                if command.seq.is_some() {
                    self.last_seq = command.seq;
                    self.newest_seq = command.seq;
                }
                if command.clamped > 0 {
                    self.counters.clamped_commands += 1;
                    self.counters.clamped_values += command.clamped as u64;
                }
                if self.newest.is_some() {
                    self.counters.superseded += 1;
                }
                let r = Received {
                    command,
                    mono_ns,
                    real_ns,
                };
                self.newest = Some(r);
                self.latest = Some(r);
                Outcome::Accepted
            }
        }
    }

    /// For a command the gate refused: true (and the gate restarted from
    /// `seq`) when there is no key and no command was accepted for the
    /// forget interval.
    fn forget(&mut self, seq: Option<u64>, now: Instant) -> bool {
        if self.key.is_some() || !self.quiet(now) {
            return false;
        }
        self.gate = SeqGate::default();
        self.gate.admit(seq);
        self.counters.seq_resets += 1;
        true
    }

    /// True when no command was accepted for the forget interval (the
    /// failsafe's `after_ms`), or none ever was; never without the interval.
    fn quiet(&self, now: Instant) -> bool {
        match (self.forget_seq, self.last_accepted) {
            (Some(after), Some(t)) => now.saturating_duration_since(t) >= after,
            (Some(_), None) => true,
            (None, _) => false,
        }
    }

    /// Counts a rejected datagram and, when the rate limit allows, gives a log line.
    fn reject(&mut self, r: Reject, from: SocketAddr, now: Instant) -> Outcome {
        self.counters.rejected[r.reason.index()] += 1;
        let line = self.log.note(r.reason, now).map(|suppressed| {
            let more = if suppressed > 0 {
                format!(" ({suppressed} more of this kind not logged)")
            } else {
                String::new()
            };
            format!("rejected datagram from {from}: {r}{more}")
        });
        Outcome::Rejected(r.reason, line)
    }

    /// Parses a datagram that is not a query: a signed one (checked against
    /// the key and this output's name) or a plain command (refused as
    /// `unsigned` when a key is set; without one, refused as `wrong_output`
    /// when its `to` names another output).
    fn command(&self, datagram: &[u8]) -> Result<Command, Reject> {
        let fail = |reason, detail: &str| {
            Err(Reject {
                reason,
                detail: detail.into(),
            })
        };
        let Some(key) = &self.key else {
            return match auth::envelope(datagram) {
                Some(_) => fail(
                    RejectReason::BadShape,
                    "signed datagram but no auth key configured (ingress.auth_key, --auth-key)",
                ),
                None => protocol::parse_for(datagram, &self.model, To::AbsentOr(&self.name)),
            };
        };
        match auth::envelope(datagram) {
            Some(envelope) => {
                let envelope = envelope?;
                // auth::envelope reads it with serde_json's `Value`, which
                // keeps the last of two alike keys: a second `msg` or `mac`
                // is refused here, as in the command.
                protocol::json(datagram)?;
                envelope.open(key, &self.name, &self.model)
            }
            None => match protocol::parse(datagram, &self.model) {
                Err(r)
                    if matches!(
                        r.reason,
                        RejectReason::InvalidUtf8
                            | RejectReason::InvalidJson
                            | RejectReason::DuplicateKey
                    ) =>
                {
                    Err(r)
                }
                _ => fail(
                    RejectReason::Unsigned,
                    r#"commands must be signed, {"msg": "<command>", "mac": "<hex HMAC-SHA256>"}: ingress.auth_key is set"#,
                ),
            },
        }
    }

    /// The command a MAVLink datagram carries (`None`: none, such as
    /// HEARTBEATs only).
    /// Its "keep" values are those of the last accepted command while that
    /// is fresh (younger than the failsafe's `after_ms`, given as
    /// [`Intake::forget_seq_after`]), the channels' defaults otherwise: a
    /// "keep" never brings back a command the line has already given up.
    /// With `ingress.auth_key` set and no MAVLink signing
    /// ([`Intake::with_mavlink_signing`]), MAVLink commands are refused as
    /// `unsigned`.
    ///
    /// A datagram read whole (and signed, with signing) makes its source a
    /// peer ([`peers`]), unless it could not be checked against a key.
    fn mavlink_command(
        &mut self,
        datagram: &[u8],
        from: SocketAddr,
        real_ns: u64,
        now: Instant,
    ) -> Result<Option<Command>, Reject> {
        let ts = mavlink::signing_timestamp(real_ns);
        let d = match &mut self.signing {
            Some(s) => mavlink::read_datagram_with(datagram, |f, h| s.check(f, h, ts))?,
            None => mavlink::read_datagram(datagram)?,
        };
        // Trusted: signed with the MAVLink key, or no key at all.
        if self.signing.is_some() || self.key.is_none() {
            let exempt = in_blocks(&self.status_allow, from.ip());
            self.peers
                .heard(from, d.version, datagram.len(), exempt, now);
            for (h, m) in &d.requests {
                self.peers.request(from, h, m);
            }
        }
        for (_, m) in &d.requests {
            self.counters.mavlink_ignored += matches!(m, mavlink::Message::Ignored(_)) as u64;
        }
        let Some((_, message)) = d.command else {
            return Ok(None);
        };
        if self.key.is_some() && self.signing.is_none() {
            return Err(Reject {
                reason: RejectReason::Unsigned,
                detail: "ingress.auth_key is set and mavlink.key_file is not: MAVLink commands cannot be checked, send signed JSON commands or set mavlink.key_file".into(),
            });
        }
        let current = match self.latest {
            Some(r) if !self.quiet(now) => r.command.channels,
            _ => self.model.defaults(),
        };
        mavlink::command(&message, &self.model, &self.mavlink, &current).map(Some)
    }

    /// The MAVLink replies due at `now` (appended to `out`: where each goes,
    /// and the frame), with the line's state from `ppmd`, ppmd's newest
    /// snapshot, unless it is stale at CLOCK_MONOTONIC `now_mono_ns`, and
    /// its values from `line`, the newest frame ppmd's line carried, unless
    /// it started more than [`LINE_STALE_AFTER_NS`] ago
    /// ([`peers::Peers::due`]): SERVO_OUTPUT_RAW carries them, and so does
    /// RC_CHANNELS without a read-back; with one, RC_CHANNELS carries the
    /// newest frame read back ([`readback::Readback::frame_us`]).
    /// `real_ns` is CLOCK_REALTIME now, for the signatures' timestamps.
    pub fn mavlink_due(
        &mut self,
        (now, now_mono_ns, real_ns): (Instant, u64, u64),
        (ppmd, line): (Option<&TimingSnapshot>, Option<&LineSample>),
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) {
        let state = fresh_snapshot(ppmd, now_mono_ns).and_then(|s| LineState::from_code(s.state));
        let ts = mavlink::signing_timestamp(real_ns);
        let line =
            line.filter(|l| now_mono_ns.saturating_sub(l.start_mono_ns) <= LINE_STALE_AFTER_NS);
        let mut values_us = [0u16; MAX_CHANNELS];
        let n = line.map_or(0, |l| (l.channels as usize).min(MAX_CHANNELS));
        if let Some(l) = line {
            for (us, &ns) in values_us.iter_mut().zip(&l.values_ns[..n]) {
                *us = ((ns + 500) / 1_000).min(u16::MAX as u32) as u16;
            }
        }
        let at_ns = line.map_or(now_mono_ns, |l| l.start_mono_ns);
        let radio = self.readback.as_ref().map(|r| r.frame_us(now_mono_ns));
        let radio_frame = match &radio {
            Some(Some((us, n, at_us))) => Some(peers::Frame {
                values_us: &us[..*n],
                at_us: *at_us,
            }),
            Some(None) => Some(peers::Frame {
                values_us: &[],
                at_us: now_mono_ns / 1_000,
            }),
            None => None,
        };
        let now_line = peers::LineNow {
            state: peers::mav_state(state),
            line: peers::Frame {
                values_us: &values_us[..n],
                at_us: at_ns / 1_000,
            },
            radio: radio_frame,
            telemetry: self.telemetry.as_ref().and_then(|t| t.newest()),
        };
        self.peers
            .due(now, now_line, self.signing.as_mut(), ts, out);
    }

    /// A reply [`Intake::mavlink_due`] gave could not be sent.
    pub fn mavlink_not_sent(&mut self) {
        self.peers.not_sent();
    }

    /// The newest valid command since the last call (to be published).
    pub fn take(&mut self) -> Option<Received> {
        let r = self.newest.take();
        if r.is_some() {
            self.counters.published += 1;
        }
        r
    }

    /// The counters so far.
    pub fn counters(&self) -> &Counters {
        &self.counters
    }

    /// Counts a status reply that could not be sent.
    pub fn status_dropped(&mut self) {
        self.counters.status_dropped += 1;
    }

    /// Counts a status query answered with `{"pad_to": N}` (or nothing),
    /// as too short for the reply.
    pub fn status_short(&mut self) {
        self.counters.status_short += 1;
    }

    /// Records how long the published command took from the kernel's
    /// receive timestamp to being published, ns.
    pub fn published_after(&mut self, ns: u64) {
        self.latency.saturating_record(ns);
    }

    /// Kernel receive to published, ns, of every published command.
    pub fn latency(&self) -> &hdrhistogram::Histogram<u64> {
        &self.latency
    }

    /// The reply to a status query ([`StatusReply::to_json`] is its text;
    /// see docs/status.md, "Status queries"), named with the output's name. `uptime` is the ingress's, `receiver` how its
    /// receive thread runs, `now_mono_ns` the
    /// CLOCK_MONOTONIC time of the reply, `ppmd` the newest timing snapshot
    /// received from ppmd, if any; one older than [`PPMD_STALE_AFTER_NS`]
    /// gives `"ppmd": null` and `"ppmd_stale": true`. With a read-back, its
    /// `readback` member is [`readback::Readback::status`] of the newest
    /// sample given to [`Intake::readback`].
    pub fn status(
        &self,
        uptime: Duration,
        receiver: &ReceiveThread,
        now_mono_ns: u64,
        ppmd: Option<&TimingSnapshot>,
    ) -> StatusReply {
        let c = &self.counters;
        let age_ns = |t: u64| now_mono_ns.saturating_sub(t);
        let fresh = fresh_snapshot(ppmd, now_mono_ns);
        StatusReply {
            name: self.name.clone(),
            uptime_s: round3(uptime.as_secs_f64()),
            receiver: Some(receiver.status()),
            datagrams: Datagrams {
                received: c.received,
                applied: c.published,
                rejected: Rejected::from_counts(&c.rejected),
                clamped: c.clamped_commands,
                clamped_values: c.clamped_values,
                stale: c.stale,
                seq_resets: c.seq_resets,
                superseded: c.superseded,
            },
            status_requests: c.status_requests,
            status_dropped: c.status_dropped,
            status_short: c.status_short,
            mavlink: MavlinkStatus {
                no_command: c.mavlink_no_command,
                ignored: c.mavlink_ignored,
                peers: self.peers.known() as u64,
                sent: self.peers.counters().sent,
                held: self.peers.counters().held,
            },
            newest_command_age_ms: self.latest.map(|r| round3(age_ns(r.mono_ns) as f64 / 1e6)),
            newest_seq: self.newest_seq,
            publish_latency_us: PublishLatency {
                count: self.latency.len(),
                p50: round3(self.latency.value_at_quantile(0.5) as f64 / 1e3),
                p99: round3(self.latency.value_at_quantile(0.99) as f64 / 1e3),
                max: round3(self.latency.max() as f64 / 1e3),
            },
            ppmd: fresh.map(|s| ppmd_status(s, age_ns(s.mono_ns))),
            ppmd_stale: ppmd.is_some() && fresh.is_none(),
            readback: self
                .readback
                .as_ref()
                .map(|r| r.status(now_mono_ns, uptime.as_nanos() as u64)),
            telemetry: self.telemetry.as_ref().map(|t| t.status(now_mono_ns)),
        }
    }
}

/// `ppmd` unless it is older than [`PPMD_STALE_AFTER_NS`] at CLOCK_MONOTONIC
/// `now_mono_ns`.
fn fresh_snapshot(ppmd: Option<&TimingSnapshot>, now_mono_ns: u64) -> Option<&TimingSnapshot> {
    ppmd.filter(|s| now_mono_ns.saturating_sub(s.mono_ns) <= PPMD_STALE_AFTER_NS)
}

/// How the receive thread runs, as obtained at start: the `receiver` member
/// of a status reply.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReceiveThread {
    /// Spins on the socket (`ingress.busy_poll`) instead of sleeping in epoll.
    pub busy_poll: bool,
    /// SCHED_FIFO priority obtained; 0 under the normal scheduler.
    pub priority: u8,
    /// The CPU it is pinned to, if any.
    pub cpu: Option<usize>,
    /// A setting asked for could not be had (a degraded run).
    pub degraded: bool,
}

impl std::fmt::Display for ReceiveThread {
    /// The start-up log's summary.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let policy = if self.priority > 0 {
            "SCHED_FIFO"
        } else {
            "SCHED_OTHER"
        };
        write!(f, "policy {policy} priority {}; ", self.priority)?;
        match self.cpu {
            Some(c) => write!(f, "CPU {c}; ")?,
            None => write!(f, "any CPU; ")?,
        }
        f.write_str(if self.busy_poll {
            "busy_poll: spins on the socket, never sleeps (takes a whole CPU)"
        } else {
            "sleeps until datagrams arrive (mio)"
        })
    }
}

impl ReceiveThread {
    fn status(&self) -> ReceiverStatus {
        ReceiverStatus {
            wait: if self.busy_poll { "busy_poll" } else { "epoll" }.into(),
            policy: if self.priority > 0 { "fifo" } else { "other" }.into(),
            priority: self.priority.into(),
            cpu: self.cpu.map(|c| c as u64),
            degraded: self.degraded,
        }
    }
}

/// The `ppmd` member of a status reply: a summary of one timing snapshot
/// that is `age_ns` old.
fn ppmd_status(s: &TimingSnapshot, age_ns: u64) -> PpmdStatus {
    let us = |ns: u64| round3(ns as f64 / 1e3);
    PpmdStatus {
        state: LineState::from_code(s.state)
            .map_or("unknown", LineState::name)
            .into(),
        timing: if s.timing == 1 { "follow" } else { "grid" }.into(),
        frames: s.frames,
        repeats: s.repeats,
        edge_error_us: EdgeError {
            p50: us(s.total.p50),
            p99: us(s.total.p99),
            max: us(s.total.max),
        },
        overruns: s.overruns,
        late_frames: s.late_frames,
        aborted_frames: s.aborted_frames,
        glitched_frames: s.glitched_frames,
        mismatched_commands: s.mismatched,
        expired_commands: s.expired,
        log_errors: s.log_errors,
        failsafe_entries: s.failsafe_entries,
        degraded: s.degraded != 0,
        snapshot_age_ms: round3(age_ns as f64 / 1e6),
    }
}

/// Rounded to three decimals (ms to the us, us to the ns).
fn round3(v: f64) -> f64 {
    (v * 1e3).round() / 1e3
}

/// Rate limit for reject log lines: at most one line per reason per interval,
/// saying how many were not logged in between.
#[derive(Debug)]
pub struct RejectLog {
    interval: Duration,
    last: [Option<Instant>; RejectReason::ALL.len()],
    suppressed: [u64; RejectReason::ALL.len()],
}

impl RejectLog {
    /// A limit of one line per reason per `interval`.
    pub fn new(interval: Duration) -> RejectLog {
        RejectLog {
            interval,
            last: [None; RejectReason::ALL.len()],
            suppressed: [0; RejectReason::ALL.len()],
        }
    }

    /// Notes a reject at `now`: `Some(n)` when a line may be logged (`n`
    /// rejects of this reason were not logged since the last line).
    pub fn note(&mut self, reason: RejectReason, now: Instant) -> Option<u64> {
        let i = reason.index();
        match self.last[i] {
            Some(t) if now.duration_since(t) < self.interval => {
                self.suppressed[i] += 1;
                None
            }
            _ => {
                self.last[i] = Some(now);
                Some(std::mem::take(&mut self.suppressed[i]))
            }
        }
    }
}

#[cfg(test)]
mod tests;
