//! `udp-ingress`: receives JSON commands over UDP, keeps only the newest
//! valid one per wake-up, and publishes it to ppmd through shared memory.
//!
//! [`Intake`] holds the logic (parse, stale check, counters, newest-wins,
//! status queries and their replies) without any I/O, so it is tested
//! directly; the binary wires it to a non-blocking mio socket, an iceoryx2
//! publisher and a subscriber to ppmd's timing snapshots.
//!
//! With a key ([`Intake::with_auth`]) only signed commands with a `seq`
//! greater than the last accepted one are applied; [`seqfile`] keeps that
//! `seq` across restarts. Without a key, the `seq` gate forgets once no
//! command was accepted for [`Intake::forget_seq_after`] (the failsafe's
//! `after_ms`): one datagram with a huge `seq` cannot lock numbered commands
//! out for longer. With an allowlist ([`Intake::with_allowlist`])
//! datagrams from other sources are dropped before they are parsed.

pub mod seqfile;
pub mod server;

use ipnet::IpNet;
use ppm_shared::auth::{self, AuthKey};
use ppm_shared::frame::FrameModel;
use ppm_shared::ipc::TimingSnapshot;
use ppm_shared::line::LineState;
use ppm_shared::protocol::{self, Command, Reject, RejectReason, SeqGate, STATUS_REPLY_MAX_RATIO};
use serde_json::{json, Value};
use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};

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
    /// A status query: answer it with [`Intake::status`] (nothing changed).
    Status,
}

/// A read-only query a datagram may carry instead of a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Query {
    /// `{"get": "status"}`: the counters and ppmd's timing summary.
    Status,
}

/// Recognises a query, before a datagram is parsed as a command.
///
/// `None`: not a query (no `"get"` key in a JSON object), parse it as a
/// command. `Some(Err(_))`: an object with a `get` key that is not exactly
/// `{"get": "status"}`, rejected as `bad_shape`. The parsed keys decide, so
/// `{"\u0067et": "status"}` is a status query; a command that cannot have a
/// `get` key ([`protocol::may_have_key`]) is not parsed twice.
pub fn query(datagram: &[u8]) -> Option<Result<Query, Reject>> {
    if !protocol::may_have_key(datagram, "get") {
        return None;
    }
    let Ok(Value::Object(map)) = serde_json::from_slice::<Value>(datagram) else {
        return None;
    };
    let get = map.get("get")?;
    let bad = |detail: String| {
        Some(Err(Reject {
            reason: RejectReason::BadShape,
            detail,
        }))
    };
    if let Some(k) = map.keys().find(|k| *k != "get") {
        return bad(format!(
            "unexpected key `{k}` beside `get`: a status query is {{\"get\": \"status\"}} alone"
        ));
    }
    match get.as_str() {
        Some("status") => Some(Ok(Query::Status)),
        _ => bad(format!(
            "unknown query {get}: the only query is {{\"get\": \"status\"}}"
        )),
    }
}

/// What a status query gets ([`status_answer`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StatusAnswer {
    /// The whole reply.
    Full,
    /// `{"pad_to": N}`: the query must be at least N bytes for the reply.
    PadTo(usize),
    /// Nothing: even `{"pad_to": N}` would be more than 3 times the query.
    Nothing,
}

/// The text of [`StatusAnswer::PadTo`].
pub fn pad_to_text(n: usize) -> String {
    format!(r#"{{"pad_to":{n}}}"#)
}

/// What a status query of `query_len` bytes from `from` gets, when the
/// reply is `reply_len` bytes: the reply when `from` lies in `status_allow`
/// or the reply is at most [`STATUS_REPLY_MAX_RATIO`] times the query;
/// otherwise `{"pad_to": N}` (N the query size that would earn the reply),
/// or nothing when even that is too large. A spoofed query never makes
/// the ingress send more than 3 times what it received.
pub fn status_answer(
    reply_len: usize,
    query_len: usize,
    from: IpAddr,
    status_allow: &[IpNet],
) -> StatusAnswer {
    let in_block = |ip: IpAddr| status_allow.iter().any(|n| n.contains(&ip));
    if in_block(from) || in_block(from.to_canonical()) {
        return StatusAnswer::Full;
    }
    let cap = query_len.saturating_mul(STATUS_REPLY_MAX_RATIO);
    if reply_len <= cap {
        return StatusAnswer::Full;
    }
    let need = reply_len.div_ceil(STATUS_REPLY_MAX_RATIO);
    if pad_to_text(need).len() <= cap {
        StatusAnswer::PadTo(need)
    } else {
        StatusAnswer::Nothing
    }
}

/// True when `ip` lies in one of `nets`, or `nets` is empty (no allowlist).
/// An IPv4 sender seen on a dual-stack socket (`::ffff:10.0.0.5`) matches
/// IPv4 blocks.
pub fn allowed(nets: &[IpNet], ip: IpAddr) -> bool {
    let canonical = ip.to_canonical();
    nets.is_empty()
        || nets
            .iter()
            .any(|n| n.contains(&ip) || n.contains(&canonical))
}

/// Parse, check and keep the newest command; count everything.
pub struct Intake {
    model: FrameModel,
    key: Option<AuthKey>,
    allow: Vec<IpNet>,
    /// The `seq` of the last command that passed the gate.
    last_seq: Option<u64>,
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
}

impl Intake {
    /// An intake for commands of `model`, logging each reject reason at most
    /// once per `log_interval`.
    pub fn new(model: FrameModel, log_interval: Duration) -> Intake {
        Intake {
            model,
            key: None,
            allow: Vec::new(),
            last_seq: None,
            gate: SeqGate::default(),
            forget_seq: None,
            last_accepted: None,
            newest: None,
            latest: None,
            counters: Counters::default(),
            log: RejectLog::new(log_interval),
            latency: hdrhistogram::Histogram::new_with_bounds(1, 60_000_000_000, 3)
                .expect("valid histogram bounds"),
        }
    }

    /// Applies only commands signed with `key` ([`auth`]) that carry a
    /// `seq` greater than the last accepted one and than `floor` (the last
    /// one accepted before a restart). Status queries stay unsigned.
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
        let parsed = if !allowed(&self.allow, from.ip()) {
            Err(Reject {
                reason: RejectReason::NotAllowed,
                detail: format!("source {} is not in ingress.allow", from.ip()),
            })
        } else {
            match query(datagram) {
                Some(Ok(Query::Status)) => {
                    self.counters.status_requests += 1;
                    return Outcome::Status;
                }
                Some(Err(r)) => Err(r),
                None => self.command(datagram),
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
                if command.seq.is_some() {
                    self.last_seq = command.seq;
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
        let quiet = match (self.forget_seq, self.last_accepted) {
            (Some(after), Some(t)) => now.saturating_duration_since(t) >= after,
            (Some(_), None) => true,
            (None, _) => false,
        };
        if self.key.is_some() || !quiet {
            return false;
        }
        self.gate = SeqGate::default();
        self.gate.admit(seq);
        self.counters.seq_resets += 1;
        true
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
    /// the key) or a plain command (refused as `unsigned` when a key is set).
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
                None => protocol::parse(datagram, &self.model),
            };
        };
        let envelope = match auth::envelope(datagram) {
            Some(e) => e?,
            None => {
                return match protocol::parse(datagram, &self.model) {
                    Err(r)
                        if matches!(
                            r.reason,
                            RejectReason::InvalidUtf8 | RejectReason::InvalidJson
                        ) =>
                    {
                        Err(r)
                    }
                    _ => fail(
                        RejectReason::Unsigned,
                        r#"commands must be signed, {"msg": "<command>", "mac": "<hex HMAC-SHA256>"}: ingress.auth_key is set"#,
                    ),
                };
            }
        };
        if !envelope.verify(key) {
            return fail(
                RejectReason::BadMac,
                "the MAC does not match `msg` (another key, or msg or mac changed)",
            );
        }
        let command =
            protocol::parse(envelope.msg.as_bytes(), &self.model).map_err(|r| Reject {
                reason: r.reason,
                detail: format!("in the signed msg: {}", r.detail),
            })?;
        if command.seq.is_none() {
            return fail(
                RejectReason::NoSeq,
                "a signed command needs a `seq`, greater than the last one's (replays are refused by it)",
            );
        }
        Ok(command)
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

    /// The reply to a status query: one JSON object (see docs/status.md,
    /// "Status queries"). `uptime` is the ingress's, `receiver` how its
    /// receive thread runs, `now_mono_ns` the
    /// CLOCK_MONOTONIC time of the reply, `ppmd` the newest timing snapshot
    /// received from ppmd, if any; one older than [`PPMD_STALE_AFTER_NS`]
    /// gives `"ppmd": null` and `"ppmd_stale": true`.
    pub fn status(
        &self,
        name: &str,
        uptime: Duration,
        receiver: &ReceiveThread,
        now_mono_ns: u64,
        ppmd: Option<&TimingSnapshot>,
    ) -> Value {
        let c = &self.counters;
        let rejected: serde_json::Map<String, Value> = RejectReason::ALL
            .iter()
            .map(|r| (r.as_str().to_string(), json!(c.rejected[r.index()])))
            .collect();
        let age_ns = |t: u64| now_mono_ns.saturating_sub(t);
        let fresh = ppmd.filter(|s| age_ns(s.mono_ns) <= PPMD_STALE_AFTER_NS);
        json!({
            "name": name,
            "uptime_s": round3(uptime.as_secs_f64()),
            "receiver": receiver.status(),
            "datagrams": {
                "received": c.received,
                "applied": c.published,
                "rejected": rejected,
                "clamped": c.clamped_commands,
                "clamped_values": c.clamped_values,
                "stale": c.stale,
            "seq_resets": c.seq_resets,
                "superseded": c.superseded,
            },
            "status_requests": c.status_requests,
            "status_dropped": c.status_dropped,
            "status_short": c.status_short,
            "newest_command_age_ms": self.latest.map(|r| round3(age_ns(r.mono_ns) as f64 / 1e6)),
            "newest_seq": self.latest.and_then(|r| r.command.seq),
            "publish_latency_us": {
                "count": self.latency.len(),
                "p50": round3(self.latency.value_at_quantile(0.5) as f64 / 1e3),
                "p99": round3(self.latency.value_at_quantile(0.99) as f64 / 1e3),
                "max": round3(self.latency.max() as f64 / 1e3),
            },
            "ppmd": fresh.map(|s| ppmd_status(s, age_ns(s.mono_ns))),
            "ppmd_stale": ppmd.is_some() && fresh.is_none(),
        })
    }
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
    fn status(&self) -> Value {
        json!({
            "wait": if self.busy_poll { "busy_poll" } else { "epoll" },
            "policy": if self.priority > 0 { "fifo" } else { "other" },
            "priority": self.priority,
            "cpu": self.cpu,
            "degraded": self.degraded,
        })
    }
}

/// The `ppmd` member of a status reply: a summary of one timing snapshot
/// that is `age_ns` old.
fn ppmd_status(s: &TimingSnapshot, age_ns: u64) -> Value {
    let us = |ns: u64| round3(ns as f64 / 1e3);
    json!({
        "state": LineState::from_code(s.state).map_or("unknown", LineState::name),
        "timing": if s.timing == 1 { "follow" } else { "grid" },
        "frames": s.frames,
        "repeats": s.repeats,
        "edge_error_us": {
            "p50": us(s.total.p50),
            "p99": us(s.total.p99),
            "max": us(s.total.max),
        },
        "overruns": s.overruns,
        "late_frames": s.late_frames,
        "mismatched_commands": s.mismatched,
        "log_errors": s.log_errors,
        "failsafe_entries": s.failsafe_entries,
        "degraded": s.degraded != 0,
        "snapshot_age_ms": round3(age_ns as f64 / 1e6),
    })
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
mod tests {
    use super::*;
    use ppm_shared::config::Config;

    fn intake() -> Intake {
        Intake::new(
            Config::default().validate().unwrap(),
            Duration::from_secs(1),
        )
    }

    fn from() -> SocketAddr {
        "127.0.0.1:9".parse().unwrap()
    }

    #[test]
    fn newest_valid_wins_and_rejects_change_nothing() {
        let mut i = intake();
        let t = Instant::now();
        assert_eq!(i.offer(b"[1100]", from(), 1, 1, t), Outcome::Accepted);
        assert_eq!(i.offer(b"[1200]", from(), 2, 2, t), Outcome::Accepted);
        assert!(matches!(
            i.offer(b"[1300", from(), 3, 3, t),
            Outcome::Rejected(RejectReason::InvalidJson, Some(_))
        ));
        assert!(matches!(
            i.offer(b"[9999]", from(), 4, 4, t),
            Outcome::Rejected(RejectReason::OutOfRange, Some(_))
        ));
        let r = i.take().unwrap();
        assert_eq!(r.command.channels.as_ns()[0], 1_200_000);
        assert_eq!(r.mono_ns, 2);
        assert_eq!(i.take(), None, "published once");
        let c = i.counters();
        assert_eq!(
            (c.received, c.published, c.superseded, c.rejected_total()),
            (4, 1, 1, 2)
        );
    }

    #[test]
    fn stale_seq_is_dropped_across_wakeups() {
        let mut i = intake();
        let t = Instant::now();
        assert_eq!(
            i.offer(br#"{"ch":[1100],"seq":5}"#, from(), 1, 1, t),
            Outcome::Accepted
        );
        i.take();
        assert_eq!(
            i.offer(br#"{"ch":[1200],"seq":5}"#, from(), 2, 2, t),
            Outcome::Stale
        );
        assert_eq!(
            i.offer(br#"{"ch":[1200],"seq":4}"#, from(), 3, 3, t),
            Outcome::Stale
        );
        assert_eq!(i.take(), None);
        assert_eq!(
            i.offer(br#"{"ch":[1300],"seq":6}"#, from(), 4, 4, t),
            Outcome::Accepted
        );
        assert_eq!(i.take().unwrap().command.seq, Some(6));
        assert_eq!(i.counters().stale, 2);
    }

    /// One unsigned datagram with the largest `seq` used to make every
    /// numbered command stale until the ingress restarted. Now the gate
    /// forgets once nothing was accepted for the failsafe's interval.
    #[test]
    fn without_a_key_one_huge_seq_locks_out_for_the_failsafe_interval_at_most() {
        let after = Duration::from_millis(200);
        let ms = Duration::from_millis;
        let mut i = intake().forget_seq_after(after);
        let t = Instant::now();
        let mut offer = |d: &[u8], at: Duration| i.offer(d, from(), 1, 1, t + at);
        assert_eq!(offer(br#"{"ch":[1100],"seq":5}"#, ms(0)), Outcome::Accepted);
        let huge = br#"{"ch":[1900],"seq":18446744073709551615}"#;
        assert_eq!(offer(huge, ms(10)), Outcome::Accepted);
        // The sender's next commands, every 20 ms: stale until 200 ms after
        // the last accepted one, then applied, and counted from there.
        for n in 0..9u64 {
            let d = format!(r#"{{"ch":[1200],"seq":{}}}"#, 6 + n);
            assert_eq!(offer(d.as_bytes(), ms(30 + 20 * n)), Outcome::Stale, "{n}");
        }
        assert_eq!(
            offer(br#"{"ch":[1200],"seq":15}"#, ms(210)),
            Outcome::Accepted
        );
        assert_eq!(
            offer(br#"{"ch":[1200],"seq":16}"#, ms(230)),
            Outcome::Accepted
        );
        assert_eq!(offer(br#"{"ch":[1200],"seq":15}"#, ms(240)), Outcome::Stale);
        // Commands without a seq keep the line fresh: the gate holds.
        assert_eq!(offer(br#"{"ch":[1300]}"#, ms(400)), Outcome::Accepted);
        assert_eq!(offer(br#"{"ch":[1300],"seq":1}"#, ms(590)), Outcome::Stale);
        assert_eq!(
            offer(br#"{"ch":[1300],"seq":1}"#, ms(600)),
            Outcome::Accepted
        );
        let c = i.counters();
        assert_eq!((c.stale, c.seq_resets), (11, 2));
        assert!(c.summary().contains("(seq resets 2)"), "{}", c.summary());
    }

    /// With a key the gate never forgets, however long the quiet.
    #[test]
    fn with_a_key_the_seq_gate_never_forgets() {
        let k = key();
        let mut i = intake()
            .forget_seq_after(Duration::from_millis(200))
            .with_auth(k.clone(), None);
        let t = Instant::now();
        let d = k.envelope(r#"{"ch":[1100],"seq":5}"#).into_bytes();
        assert_eq!(i.offer(&d, from(), 1, 1, t), Outcome::Accepted);
        let later = t + Duration::from_secs(3600);
        assert_eq!(
            reason(i.offer(&d, from(), 1, 1, later)),
            RejectReason::Replay
        );
        let older = k.envelope(r#"{"ch":[1100],"seq":4}"#).into_bytes();
        assert_eq!(
            reason(i.offer(&older, from(), 1, 1, later)),
            RejectReason::Replay
        );
        assert_eq!(i.counters().seq_resets, 0);
    }

    #[test]
    fn clamps_are_counted() {
        let mut i = intake();
        i.offer(b"[900, 2100, 1500]", from(), 1, 1, Instant::now());
        assert_eq!(
            (i.counters().clamped_commands, i.counters().clamped_values),
            (1, 2)
        );
        assert!(i.counters().summary().contains("clamped 1 (values 2)"));
    }

    #[test]
    fn status_query_is_recognised_before_parsing() {
        for q in [&br#"{"get":"status"}"#[..], br#" { "get" : "status" } "#] {
            assert_eq!(query(q), Some(Ok(Query::Status)), "{q:?}");
        }
        for not_a_query in [
            &b"[1500]"[..],
            br#"{"ail": 1500}"#,
            br#"{"get":"#,
            br#"["get"]"#,
            b"\xff\"get\"",
        ] {
            assert_eq!(query(not_a_query), None, "{not_a_query:?}");
        }
        let detail = |q: &[u8]| match query(q) {
            Some(Err(r)) if r.reason == RejectReason::BadShape => r.detail,
            other => panic!("{q:?}: {other:?}"),
        };
        let d = detail(br#"{"get":"config"}"#);
        assert!(
            d.contains("\"config\"") && d.contains(r#"{"get": "status"}"#),
            "{d}"
        );
        assert!(detail(br#"{"get":1}"#).contains("unknown query 1"));
        assert!(detail(br#"{"get":null}"#).contains("unknown query null"));
        let d = detail(br#"{"get":"status","seq":1}"#);
        assert!(d.contains("`seq`"), "{d}");
        assert!(detail(br#"{"ail":1500,"get":"status"}"#).contains("`ail`"));
    }

    #[test]
    fn status_answers_are_at_most_three_times_the_query_outside_status_allow() {
        let lo: Vec<IpNet> = vec!["127.0.0.0/8".parse().unwrap(), "::1/128".parse().unwrap()];
        let far: IpAddr = "203.0.113.9".parse().unwrap();
        let near: IpAddr = "127.0.0.1".parse().unwrap();
        let mapped: IpAddr = "::ffff:127.0.0.1".parse().unwrap();
        use StatusAnswer::*;
        assert_eq!(status_answer(700, 16, near, &lo), Full);
        assert_eq!(status_answer(700, 16, mapped, &lo), Full);
        assert_eq!(status_answer(700, 16, far, &lo), PadTo(234));
        assert_eq!(status_answer(700, 16, near, &[]), PadTo(234));
        assert_eq!(status_answer(700, 233, far, &lo), PadTo(234));
        assert_eq!(status_answer(700, 234, far, &lo), Full);
        assert_eq!(status_answer(702, 234, far, &lo), Full);
        assert_eq!(pad_to_text(234), r#"{"pad_to":234}"#);
        // Even {"pad_to": N} is more than 3 times a 4-byte datagram.
        assert_eq!(status_answer(700, 4, far, &lo), Nothing);
        assert_eq!(status_answer(700, 5, far, &lo), PadTo(234));
    }

    /// JSON is classified by its parsed keys: escaped spellings of `get`,
    /// `msg` and `mac` behave as the plain ones (they were taken for
    /// commands: `unknown_channel`, `unsigned`).
    #[test]
    fn escaped_keys_are_the_keys_they_spell() {
        assert_eq!(query(br#"{"\u0067et":"status"}"#), Some(Ok(Query::Status)));
        assert_eq!(
            query(br#"{"g\u0065t":"st\u0061tus"}"#),
            Some(Ok(Query::Status))
        );
        let mut i = intake();
        let t = Instant::now();
        assert_eq!(
            i.offer(br#"{"\u0067et":"status"}"#, from(), 1, 1, t),
            Outcome::Status
        );
        assert_eq!(i.counters().status_requests, 1);
        assert_eq!(i.counters().received, 0);

        let k = key();
        let mut i = intake().with_auth(k.clone(), None);
        let msg = r#"{"ch":[1100],"seq":7}"#;
        let escaped = format!(
            r#"{{"\u006dsg": {msg:?}, "m\u0061c": "{}"}}"#,
            k.sign(msg.as_bytes())
        );
        assert_eq!(
            i.offer(escaped.as_bytes(), from(), 1, 1, t),
            Outcome::Accepted,
            "{escaped}"
        );
        assert_eq!(i.take().unwrap().command.channels.as_ns()[0], 1_100_000);
        // The same with a MAC of other bytes is a forgery, not unsigned.
        let forged = escaped.replace(r#"\"ch\""#, r#"\"c\\u0068\""#);
        assert_ne!(forged, escaped);
        assert_eq!(
            reason(i.offer(forged.as_bytes(), from(), 1, 1, t)),
            RejectReason::BadMac
        );
    }

    #[test]
    fn status_query_is_counted_apart_and_changes_nothing() {
        let mut i = intake();
        let t = Instant::now();
        i.offer(br#"{"ch":[1100],"seq":3}"#, from(), 1, 1, t);
        let before = i.counters().clone();
        assert_eq!(
            i.offer(br#"{"get":"status"}"#, from(), 2, 2, t),
            Outcome::Status
        );
        assert_eq!(
            i.counters(),
            &Counters {
                status_requests: 1,
                ..before
            }
        );
        assert_eq!(i.take().unwrap().command.seq, Some(3), "still the newest");
        assert!(matches!(
            i.offer(br#"{"get":"everything"}"#, from(), 3, 3, t),
            Outcome::Rejected(RejectReason::BadShape, Some(line)) if line.contains("everything")
        ));
        let c = i.counters();
        assert_eq!(
            (c.received, c.rejected_total(), c.status_requests),
            (2, 1, 1)
        );
    }

    fn snapshot(mono_ns: u64) -> TimingSnapshot {
        let mut s = TimingSnapshot {
            mono_ns,
            frames: 400,
            overruns: 1,
            late_frames: 2,
            failsafe_entries: 3,
            degraded: 1,
            state: 1,
            ..TimingSnapshot::default()
        };
        s.total.p50 = 31;
        s.total.p99 = 1_250;
        s.total.max = 17_000_400;
        s
    }

    #[test]
    fn status_reply_is_built_from_the_counters() {
        let mut i = intake();
        let t = Instant::now();
        let at = |ms: u64| 10_000_000_000 + ms * 1_000_000;
        let plain = ReceiveThread::default();
        let empty = i.status("pi", Duration::from_millis(1500), &plain, at(10), None);
        assert_eq!(
            empty["receiver"],
            json!({"wait": "epoll", "policy": "other", "priority": 0, "cpu": null, "degraded": false})
        );
        assert_eq!(empty["newest_command_age_ms"], Value::Null);
        assert_eq!(empty["newest_seq"], Value::Null);
        assert_eq!(
            (&empty["ppmd"], &empty["ppmd_stale"]),
            (&Value::Null, &json!(false))
        );

        i.offer(br#"{"ch":[900,2100],"seq":7}"#, from(), at(100), 1, t);
        i.take();
        i.offer(br#"{"ch":[1200],"seq":6}"#, from(), at(101), 1, t);
        i.offer(br#"{"ch":[1200],"seq":8}"#, from(), at(102), 1, t);
        i.offer(b"[1300]", from(), at(103), 1, t);
        i.offer(b"[1300", from(), at(104), 1, t);
        i.offer(b"{}", from(), at(105), 1, t);
        i.offer(br#"{"get":"status"}"#, from(), at(106), 1, t);
        i.take();
        i.status_dropped();
        let now = at(110) + 400;
        let rt = ReceiveThread {
            busy_poll: true,
            priority: 70,
            cpu: Some(1),
            degraded: true,
        };
        let reply = i.status(
            "pi",
            Duration::from_millis(2_345_678),
            &rt,
            now,
            Some(&snapshot(now - 250_000_000)),
        );
        assert_eq!(
            reply,
            json!({
                "name": "pi",
                "uptime_s": 2345.678,
                "receiver": {"wait": "busy_poll", "policy": "fifo", "priority": 70, "cpu": 1, "degraded": true},
                "datagrams": {
                    "received": 6,
                    "applied": 2,
                    "rejected": {
                        "invalid_utf8": 0,
                        "invalid_json": 1,
                        "not_a_number": 0,
                        "out_of_range": 0,
                        "too_many_values": 0,
                        "unknown_channel": 0,
                        "bad_shape": 1,
                        "unsigned": 0,
                        "bad_mac": 0,
                        "no_seq": 0,
                        "replay": 0,
                        "not_allowed": 0,
                    },
                    "clamped": 1,
                    "clamped_values": 2,
                    "stale": 1,
                    "seq_resets": 0,
                    "superseded": 1,
                },
                "status_requests": 1,
                "status_dropped": 1,
                "status_short": 0,
                "newest_command_age_ms": 7.0,
                "newest_seq": null,
                "publish_latency_us": {"count": 0, "p50": 0.0, "p99": 0.0, "max": 0.0},
                "ppmd": {
                    "state": "active",
                    "timing": "grid",
                    "frames": 400,
                    "repeats": 0,
                    "edge_error_us": {"p50": 0.031, "p99": 1.25, "max": 17000.4},
                    "overruns": 1,
                    "late_frames": 2,
                    "mismatched_commands": 0,
                    "log_errors": 0,
                    "failsafe_entries": 3,
                    "degraded": true,
                    "snapshot_age_ms": 250.0,
                },
                "ppmd_stale": false,
            })
        );
        assert!(reply.to_string().len() < 1_000, "one small datagram");

        let old = snapshot(now - PPMD_STALE_AFTER_NS - 1);
        let reply = i.status("pi", Duration::ZERO, &plain, now, Some(&old));
        assert_eq!(
            (&reply["ppmd"], &reply["ppmd_stale"]),
            (&Value::Null, &json!(true))
        );
        let at_limit = snapshot(now - PPMD_STALE_AFTER_NS);
        let reply = i.status("pi", Duration::ZERO, &plain, now, Some(&at_limit));
        assert_eq!(reply["ppmd"]["snapshot_age_ms"], json!(3000.0));
    }

    fn key() -> AuthKey {
        AuthKey::new(*b"0123456789abcdef0123456789abcdef")
    }

    fn reason(o: Outcome) -> RejectReason {
        match o {
            Outcome::Rejected(r, _) => r,
            other => panic!("not rejected: {other:?}"),
        }
    }

    #[test]
    fn with_a_key_only_signed_commands_with_a_new_seq_apply() {
        use RejectReason::*;
        let k = key();
        let mut i = intake().with_auth(k.clone(), Some(100));
        let t = Instant::now();
        let signed = |msg: &str| k.envelope(msg).into_bytes();
        let mut offer = |d: &[u8]| i.offer(d, from(), 1, 1, t);
        // The floor from before a restart: 100 and below are replays.
        assert_eq!(reason(offer(&signed(r#"{"ch":[1900],"seq":100}"#))), Replay);
        assert_eq!(
            offer(&signed(r#"{"ch":[1100],"seq":101}"#)),
            Outcome::Accepted
        );
        let good = signed(r#"{"ch":[1200],"seq":102}"#);
        assert_eq!(offer(&good), Outcome::Accepted);
        assert_eq!(reason(offer(&good)), Replay, "the same datagram again");
        assert_eq!(reason(offer(br#"{"ch":[1900],"seq":200}"#)), Unsigned);
        assert_eq!(reason(offer(b"[1900]")), Unsigned);
        assert_eq!(
            reason(offer(br#"{"yaw":1}"#)),
            Unsigned,
            "unsigned before anything else"
        );
        assert_eq!(reason(offer(b"[1900")), InvalidJson);
        assert_eq!(reason(offer(b"\xff")), InvalidUtf8);
        let other_key = AuthKey::new([9; 32]);
        assert_eq!(
            reason(offer(
                other_key.envelope(r#"{"ch":[1900],"seq":300}"#).as_bytes()
            )),
            BadMac
        );
        let text = String::from_utf8(signed(r#"{"ch":[1200],"seq":400}"#)).unwrap();
        let tampered_msg = text.replace("1200", "1900");
        assert_eq!(reason(offer(tampered_msg.as_bytes())), BadMac);
        let mac_at = text.find("\"mac\":\"").unwrap() + 7;
        let mut tampered_mac = text.clone().into_bytes();
        tampered_mac[mac_at] = if tampered_mac[mac_at] == b'a' {
            b'b'
        } else {
            b'a'
        };
        assert_eq!(reason(offer(&tampered_mac)), BadMac);
        assert_eq!(reason(offer(&signed(r#"{"ch":[1900]}"#))), NoSeq);
        assert_eq!(reason(offer(&signed("[1900]"))), NoSeq);
        assert_eq!(
            reason(offer(&signed(r#"{"ch":[9000],"seq":500}"#))),
            OutOfRange
        );
        assert_eq!(reason(offer(br#"{"msg":"[1500]"}"#)), BadShape);
        assert_eq!(
            offer(br#"{"get":"status"}"#),
            Outcome::Status,
            "unsigned, read-only"
        );
        assert_eq!(i.last_seq(), Some(102));
        let r = i.take().unwrap();
        assert_eq!(
            (r.command.seq, r.command.channels.as_ns()[0]),
            (Some(102), 1_200_000)
        );
        let c = i.counters();
        let n = |r: RejectReason| c.rejected[r.index()];
        assert_eq!(
            (n(Replay), n(Unsigned), n(BadMac), n(NoSeq), n(BadShape)),
            (2, 3, 3, 2, 1)
        );
        assert_eq!(
            (c.received, c.published, c.superseded, c.stale),
            (16, 1, 1, 0)
        );
        assert_eq!(
            c.received,
            c.published + c.superseded + c.stale + c.rejected_total()
        );
    }

    #[test]
    fn without_a_key_signed_datagrams_are_bad_shape() {
        let mut i = intake();
        let d = key().envelope(r#"{"ch":[1100],"seq":1}"#);
        match i.offer(d.as_bytes(), from(), 1, 1, Instant::now()) {
            Outcome::Rejected(RejectReason::BadShape, Some(line)) => {
                assert!(
                    line.contains("signed datagram but no auth key configured"),
                    "{line}"
                )
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(i.last_seq(), None);
    }

    #[test]
    fn allowlist_matches_blocks() {
        let nets: Vec<IpNet> = ["10.0.0.0/24", "127.0.0.2/32", "fd00::/8"]
            .iter()
            .map(|s| s.parse().unwrap())
            .collect();
        let ok = |ip: &str| allowed(&nets, ip.parse().unwrap());
        assert!(ok("10.0.0.0") && ok("10.0.0.255") && ok("127.0.0.2") && ok("fd12::1"));
        assert!(!ok("10.0.1.0") && !ok("127.0.0.1") && !ok("::1") && !ok("fe80::1"));
        assert!(ok("::ffff:10.0.0.7"), "IPv4 on a dual-stack socket");
        assert!(!ok("::ffff:10.0.1.7"));
        assert!(
            allowed(&[], "192.0.2.1".parse().unwrap()),
            "empty: any source"
        );
    }

    #[test]
    fn other_sources_are_dropped_before_parsing_and_logged_rate_limited() {
        let mut i = intake().with_allowlist(vec!["127.0.0.2/32".parse().unwrap()]);
        let t = Instant::now();
        let outsider: SocketAddr = "127.0.0.1:4000".parse().unwrap();
        let insider: SocketAddr = "127.0.0.2:4000".parse().unwrap();
        let mut lines = 0;
        for k in 0..5 {
            match i.offer(br#"{"get":"status"}"#, outsider, 1, 1, t) {
                Outcome::Rejected(RejectReason::NotAllowed, line) => {
                    lines += line.is_some() as u32;
                    if k == 0 {
                        assert!(line.unwrap().contains("127.0.0.1 is not in ingress.allow"));
                    }
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(lines, 1, "one log line per interval");
        assert_eq!(i.offer(b"[1100]", insider, 1, 1, t), Outcome::Accepted);
        assert_eq!(
            i.offer(br#"{"get":"status"}"#, insider, 1, 1, t),
            Outcome::Status
        );
        let c = i.counters();
        assert_eq!(
            (
                c.received,
                c.rejected[RejectReason::NotAllowed.index()],
                c.status_requests
            ),
            (6, 5, 1)
        );
    }

    #[test]
    fn reject_log_is_rate_limited_per_reason() {
        let mut l = RejectLog::new(Duration::from_secs(1));
        let t = Instant::now();
        assert_eq!(l.note(RejectReason::InvalidJson, t), Some(0));
        assert_eq!(
            l.note(RejectReason::InvalidJson, t + Duration::from_millis(10)),
            None
        );
        assert_eq!(
            l.note(RejectReason::InvalidJson, t + Duration::from_millis(20)),
            None
        );
        assert_eq!(
            l.note(RejectReason::BadShape, t + Duration::from_millis(30)),
            Some(0)
        );
        assert_eq!(
            l.note(RejectReason::InvalidJson, t + Duration::from_millis(1001)),
            Some(2)
        );
    }
}
