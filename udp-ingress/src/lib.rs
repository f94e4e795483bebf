//! `udp-ingress`: receives JSON commands over UDP, keeps only the newest
//! valid one per wake-up, and publishes it to ppmd through shared memory.
//!
//! [`Intake`] holds the logic (parse, stale check, counters, newest-wins)
//! without any I/O, so it is tested directly; the binary wires it to a
//! non-blocking mio socket and an iceoryx2 publisher.

use ppm_shared::frame::FrameModel;
use ppm_shared::protocol::{self, Command, RejectReason, SeqGate};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// Counters of everything the ingress received.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Counters {
    /// Datagrams received.
    pub received: u64,
    /// Valid commands published to ppmd.
    pub published: u64,
    /// Valid commands replaced by a newer one from the same wake-up before publishing.
    pub superseded: u64,
    /// Rejected datagrams, by [`RejectReason::index`].
    pub rejected: [u64; RejectReason::ALL.len()],
    /// Commands dropped because their `seq` was not greater than the last applied.
    pub stale: u64,
    /// Accepted commands with at least one value clamped.
    pub clamped_commands: u64,
    /// Values clamped in all accepted commands.
    pub clamped_values: u64,
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
            "received {} published {} superseded {} stale {} clamped {} (values {}) rejected {} [{}]",
            self.received,
            self.published,
            self.superseded,
            self.stale,
            self.clamped_commands,
            self.clamped_values,
            self.rejected_total(),
            rejected.join(" ")
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
}

/// Parse, check and keep the newest command; count everything.
pub struct Intake {
    model: FrameModel,
    gate: SeqGate,
    newest: Option<Received>,
    counters: Counters,
    log: RejectLog,
}

impl Intake {
    /// An intake for commands of `model`, logging each reject reason at most
    /// once per `log_interval`.
    pub fn new(model: FrameModel, log_interval: Duration) -> Intake {
        Intake {
            model,
            gate: SeqGate::default(),
            newest: None,
            counters: Counters::default(),
            log: RejectLog::new(log_interval),
        }
    }

    /// Takes one datagram received at the given times.
    pub fn offer(
        &mut self,
        datagram: &[u8],
        from: SocketAddr,
        mono_ns: u64,
        real_ns: u64,
        now: Instant,
    ) -> Outcome {
        self.counters.received += 1;
        match protocol::parse(datagram, &self.model) {
            Err(r) => {
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
            Ok(command) if !self.gate.admit(command.seq) => {
                self.counters.stale += 1;
                Outcome::Stale
            }
            Ok(command) => {
                if command.clamped > 0 {
                    self.counters.clamped_commands += 1;
                    self.counters.clamped_values += command.clamped as u64;
                }
                if self.newest.is_some() {
                    self.counters.superseded += 1;
                }
                self.newest = Some(Received {
                    command,
                    mono_ns,
                    real_ns,
                });
                Outcome::Accepted
            }
        }
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
