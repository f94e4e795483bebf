//! The receive loop of udp-ingress: the non-blocking socket (mio), the
//! [`Intake`], the publisher to ppmd, the status replies, and with a
//! read-back the events of its state changes ([`crate::readback`]).
//! The binary parses its options and calls [`Server::open`] and
//! [`Server::run`].
//!
//! - here: the loop ([`Server::run`]): drain the socket, publish the newest
//!   command, answer status queries, send the MAVLink replies.
//! - `open.rs`: setting it up from the resolved output ([`Server::open`]):
//!   the key and state files, the socket, the shared-memory ports, the
//!   receive thread's priority and CPU.
//!
//! Its tests are in `src/server/tests.rs`.

use crate::seqfile::SeqFile;
use crate::{pad_to_text, status_answer, Intake, Outcome, Query, ReceiveThread, StatusAnswer};
use anyhow::{Context, Result};
use iceoryx2::port::update_connections::UpdateConnections;
use mio::net::UdpSocket;
use mio::{Events, Poll, Token};
use ppm_shared::ipc::{
    self, CommandSample, LineSample, PublishError, ReadbackSample, TelemetrySample, TimingSnapshot,
};
use ppm_shared::logging::Chain;
use ppm_shared::time::{now_ns, realtime_ns};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::time::{Duration, Instant};

mod open;

#[cfg(test)]
mod tests;

const SOCKET: Token = Token(0);
/// Longest wait for datagrams; on each wake-up the publisher also offers its
/// last sample to subscribers that connected since (a restarted ppmd).
const POLL_TIMEOUT: Duration = Duration::from_millis(20);
/// Longest wait with a read-back (`ppmd.readback`): a state change ppmd
/// publishes is seen, and told to the groundstation, at most this much
/// later while no datagram comes (sooner when one does).
pub const READBACK_POLL_TIMEOUT: Duration = Duration::from_millis(5);
/// Largest UDP payload.
const MAX_DATAGRAM: usize = 65_536;
/// Longest a drain goes on before the newest command so far is published.
const DRAIN_PUBLISH_EVERY: Duration = Duration::from_micros(200);
/// How often the counters are logged while datagrams arrive.
const REPORT_EVERY: Duration = Duration::from_secs(60);
/// Longest interval between writes of the last accepted signed `seq` to the
/// seq file while commands arrive: a crash forgets at most this much.
const SEQ_SAVE_EVERY: Duration = Duration::from_millis(100);
/// Most status queries answered per wake-up; more are counted as dropped
/// (a flood of queries must not delay the commands).
const MAX_STATUS_PER_WAKE: usize = 32;
/// Status replies per second at most (and in one burst): a reply is about
/// 40 times larger than the query, so an open port must not become a
/// traffic amplifier. Queries beyond it are counted as dropped.
const STATUS_REPLIES_PER_S: f64 = 50.0;

/// A token bucket for status replies.
struct ReplyBudget {
    tokens: f64,
    last: Instant,
}

impl ReplyBudget {
    fn new() -> ReplyBudget {
        ReplyBudget {
            tokens: STATUS_REPLIES_PER_S,
            last: Instant::now(),
        }
    }

    fn take(&mut self) -> bool {
        let now = Instant::now();
        let refill = now.duration_since(self.last).as_secs_f64() * STATUS_REPLIES_PER_S;
        self.tokens = (self.tokens + refill).min(STATUS_REPLIES_PER_S);
        self.last = now;
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

type Publisher = ipc::Publisher<CommandSample>;
type Notifier = iceoryx2::port::notifier::Notifier<iceoryx2::service::ipc::Service>;
type Subscriber<T> = iceoryx2::port::subscriber::Subscriber<iceoryx2::service::ipc::Service, T, ()>;
type StatsSubscriber = Subscriber<TimingSnapshot>;
/// The receive loop: the socket, the intake, the publisher.
pub struct Server {
    /// mio's poll, `None` when busy-polling.
    poll: Option<Poll>,
    socket: UdpSocket,
    publisher: Publisher,
    notifier: Notifier,
    _wake: ipc::WakeService,
    stats: Option<StatsSubscriber>,
    intake: Intake,
    /// The seq file (`ingress.seq_file`, with `ingress.auth_key`), and
    /// whether its last write failed.
    seq_file: Option<(SeqFile, bool)>,
    /// The MAVLink timestamp file (`mavlink.timestamp_file`, with
    /// `mavlink.key_file`), and whether its last write failed.
    mavlink_ts_file: Option<(SeqFile, bool)>,
    started: Instant,
    thread: ReceiveThread,
    buf: Vec<u8>,
    cmsg: Vec<u8>,
    /// Queries of this wake-up: their sources, sizes and what they ask.
    status_to: Vec<(SocketAddr, usize, Query)>,
    /// `ingress.status_allow`.
    status_allow: Vec<ipnet::IpNet>,
    ppmd_snapshot: Option<TimingSnapshot>,
    /// ppmd's newest line samples (RC_CHANNELS), and the newest.
    line: Option<Subscriber<LineSample>>,
    line_sample: Option<LineSample>,
    /// ppmd's read-back samples, with a read-back (the intake keeps the
    /// newest).
    readback: Option<Subscriber<ReadbackSample>>,
    /// ppmd's telemetry samples, with a CRSF serial output (the intake
    /// keeps the newest).
    telemetry: Option<Subscriber<TelemetrySample>>,
    /// How long the loop waits for datagrams at most: [`POLL_TIMEOUT`], or
    /// [`READBACK_POLL_TIMEOUT`] with a read-back.
    idle_every: Duration,
    /// Set while ppmd runs (it had published the snapshot service when this
    /// ingress started) but no snapshot of it has come yet: until then, at
    /// most until this time, status queries wait, so that a restarted
    /// ingress does not answer `"ppmd": null` while ppmd flies. ppmd hands
    /// its last snapshot to a new subscriber within a tenth of a second
    /// (one just started publishes its first a second after its start); one
    /// that sends none in 3 s is stale anyway.
    awaiting_ppmd: Option<Instant>,
    reply_budget: ReplyBudget,
    /// MAVLink replies due, and where they go.
    mavlink_out: Vec<(SocketAddr, Vec<u8>)>,
    ingress_seq: u64,
    fingerprint: u64,
    publish_errors: u64,
    last_report: Instant,
    reported_received: u64,
}

impl Server {
    /// Receives everything pending, keeping the newest valid command and
    /// noting status queries; returns how many datagrams it received.
    fn drain(&mut self) -> usize {
        // Drain everything pending: only the newest valid command is published.
        // Under a flood the socket may never run dry; the newest so far is
        // then published every DRAIN_PUBLISH_EVERY, so it never gets old.
        let mut drain_started = Instant::now();
        let mut n_received = 0;
        loop {
            if drain_started.elapsed() >= DRAIN_PUBLISH_EVERY {
                publish(
                    &mut self.intake,
                    (&self.publisher, &self.notifier),
                    self.fingerprint,
                    &mut self.ingress_seq,
                    &mut self.publish_errors,
                );
                // A flood does not hold back a read-back change either.
                if self.readback_changes() {
                    self.mavlink_replies();
                }
                drain_started = Instant::now();
            }
            let (n, from, kernel_real) = match receive(&self.socket, &mut self.buf, &mut self.cmsg)
            {
                Ok(Some(got)) => got,
                Ok(None) => break,
                Err(e) => {
                    log::warn!("receive error: {e}");
                    break;
                }
            };
            n_received += 1;
            // Stamped with the kernel's receive time (SO_TIMESTAMPNS, on
            // CLOCK_REALTIME), carried over to CLOCK_MONOTONIC for ppmd.
            let (mono_now, real_now) = (now_ns(), realtime_ns());
            let (mono, real) = match kernel_real {
                Some(k) => (mono_now.saturating_sub(real_now.saturating_sub(k)), k),
                None => (mono_now, real_now),
            };
            match self
                .intake
                .offer(&self.buf[..n], from, mono, real, Instant::now())
            {
                Outcome::Rejected(_, Some(line)) => log::warn!("{line}"),
                Outcome::Stale => log::debug!("stale command from {from} dropped"),
                Outcome::Status(q) if self.status_to.len() < MAX_STATUS_PER_WAKE => {
                    self.status_to.push((from, n, q))
                }
                Outcome::Status(_) => self.intake.status_dropped(),
                _ => {}
            }
        }
        n_received
    }

    /// After a drain: publishes its newest command (or offers the last one
    /// to subscribers that connected since), answers the status queries,
    /// saves the seq and logs the counters now and then.
    fn settle(&mut self) {
        if !publish(
            &mut self.intake,
            (&self.publisher, &self.notifier),
            self.fingerprint,
            &mut self.ingress_seq,
            &mut self.publish_errors,
        ) {
            if let Err(e) = self.publisher.update_connections() {
                log::debug!("updating connections: {e}");
            }
        }
        if let Some(until) = self.awaiting_ppmd {
            if let Some(sub) = &self.stats {
                newest_snapshot(sub, &mut self.ppmd_snapshot);
            }
            if self.ppmd_snapshot.is_some() {
                self.awaiting_ppmd = None;
            } else if Instant::now() >= until {
                self.awaiting_ppmd = None;
                log::warn!(
                    "ppmd publishes its timing snapshots but sent none within 3 s of this start: status replies say \"ppmd\": null until one comes"
                );
            }
        }
        self.readback_changes();
        if let Some(sub) = &self.telemetry {
            let mut sample = None;
            newest(sub, &mut sample, "telemetry sample");
            if let Some(s) = sample {
                self.intake.telemetry(s);
            }
        }
        // Answered after publishing, so the counters add up.
        if !self.status_to.is_empty() && self.awaiting_ppmd.is_none() {
            if let Some(sub) = &self.stats {
                newest_snapshot(sub, &mut self.ppmd_snapshot);
            }
            let now = now_ns();
            let status = self
                .status_to
                .iter()
                .any(|q| q.2 == Query::Status)
                .then(|| {
                    self.intake
                        .status(
                            self.started.elapsed(),
                            &self.thread,
                            now,
                            self.ppmd_snapshot.as_ref(),
                        )
                        .to_json()
                });
            let telemetry = self
                .status_to
                .iter()
                .any(|q| q.2 == Query::Telemetry)
                .then(|| self.intake.telemetry_answer(now));
            for (to, query_len, q) in self.status_to.drain(..) {
                if !self.reply_budget.take() {
                    self.intake.status_dropped();
                    continue;
                }
                let reply = match q {
                    Query::Status => status.as_deref(),
                    Query::Telemetry => telemetry.as_deref(),
                }
                .unwrap_or_default();
                let short;
                let answer =
                    match status_answer(reply.len(), query_len, to.ip(), &self.status_allow) {
                        StatusAnswer::Full => reply.as_bytes(),
                        StatusAnswer::PadTo(n) => {
                            self.intake.status_short();
                            short = pad_to_text(n);
                            short.as_bytes()
                        }
                        StatusAnswer::Nothing => {
                            self.intake.status_short();
                            continue;
                        }
                    };
                match self.socket.send_to(answer, to) {
                    Ok(_) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        self.intake.status_dropped()
                    }
                    Err(e) => {
                        log::debug!("status reply to {to}: {e}");
                        self.intake.status_dropped();
                    }
                }
            }
        }
        self.mavlink_replies();
        let now = Instant::now();
        save(&mut self.seq_file, self.intake.last_seq(), now);
        save(
            &mut self.mavlink_ts_file,
            self.intake.mavlink_newest_ts(),
            now,
        );
        let received = self.intake.counters().received;
        if self.last_report.elapsed() >= REPORT_EVERY && received != self.reported_received {
            log::info!("{}", self.intake.counters().summary());
            self.last_report = Instant::now();
            self.reported_received = received;
        }
    }

    /// Takes ppmd's read-back samples published since (with a read-back)
    /// and sends the JSON event of each state change they carry to the
    /// sender of the newest accepted JSON command; the STATUSTEXTs wait in
    /// the intake for [`Server::mavlink_replies`]. True when a state
    /// changed.
    fn readback_changes(&mut self) -> bool {
        let Some(sub) = &self.readback else {
            return false;
        };
        let mut changed = false;
        loop {
            let sample = match sub.receive() {
                Ok(Some(sample)) => *sample.payload(),
                Ok(None) => break,
                Err(e) => {
                    log::debug!("receiving ppmd's read-back sample: {e}");
                    break;
                }
            };
            let Some((change, event)) = self.intake.readback(sample) else {
                continue;
            };
            changed = true;
            // Debug only: a flapping radio changes state at its frame rate;
            // ppmd's read-back log keeps every change.
            log::debug!(
                "read-back: {} (was {}; {} changes)",
                crate::readback::state_name(change.sample.state),
                crate::readback::state_name(change.from),
                change.sample.changes
            );
            if let Some((to, text)) = event {
                if let Err(e) = self.socket.send_to(text.as_bytes(), to) {
                    log::debug!("read-back event to {to}: {e}");
                    self.intake.readback_event_not_sent();
                }
            }
        }
        changed
    }

    /// Sends the MAVLink replies due (HEARTBEATs and parameters to the
    /// groundstations heard from), with ppmd's newest snapshot.
    fn mavlink_replies(&mut self) {
        if let Some(sub) = &self.stats {
            newest_snapshot(sub, &mut self.ppmd_snapshot);
        }
        if let Some(sub) = &self.line {
            newest(sub, &mut self.line_sample, "line sample");
        }
        self.intake.mavlink_due(
            (Instant::now(), now_ns(), realtime_ns()),
            (self.ppmd_snapshot.as_ref(), self.line_sample.as_ref()),
            &mut self.mavlink_out,
        );
        for (to, frame) in self.mavlink_out.drain(..) {
            if let Err(e) = self.socket.send_to(&frame, to) {
                log::debug!("MAVLink reply to {to}: {e}");
                self.intake.mavlink_not_sent();
            }
        }
    }

    /// At the end: saves the seq and the MAVLink timestamp, and logs the
    /// counters.
    fn finish(mut self) {
        let last = [self.intake.last_seq(), self.intake.mavlink_newest_ts()];
        for (f, n) in [&mut self.seq_file, &mut self.mavlink_ts_file]
            .into_iter()
            .zip(last)
        {
            if let Some((f, _)) = f {
                if let Err(e) = f.flush(n) {
                    log::warn!(
                        "cannot write the {} {}: {e}",
                        f.kind().what,
                        f.path().display()
                    );
                }
            }
        }
        log::info!(
            "stopped: {}, publish errors {}",
            self.intake.counters().summary(),
            self.publish_errors
        );
        if let Some(rb) = self.intake.readback_state() {
            let c = rb.counters();
            log::info!("read-back events: sent {}, held {}", c.sent, c.held);
        }
    }

    /// The address the socket is bound to.
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.socket.local_addr()
    }
}
/// Writes `n` to the state file `file` when due ([`SeqFile::note`]); says
/// once when writing starts to fail (the flag beside the file), and again
/// after it worked.
fn save(file: &mut Option<(SeqFile, bool)>, n: Option<u64>, now: Instant) {
    let Some((f, failed)) = file else { return };
    match f.note(n, now) {
        Ok(_) => *failed = false,
        Err(e) if !*failed => {
            *failed = true;
            log::warn!(
                "cannot write the {} {}: {e}; after a restart, replays of commands accepted since could be accepted",
                f.kind().what,
                f.path().display()
            );
        }
        Err(_) => {}
    }
}
/// Replaces `newest` with the newest snapshot ppmd published since, if any.
fn newest_snapshot(sub: &StatsSubscriber, newest_so_far: &mut Option<TimingSnapshot>) {
    newest(sub, newest_so_far, "timing snapshot")
}

/// Replaces `newest_so_far` with the newest `what` ppmd published since, if
/// any.
fn newest<T: std::fmt::Debug + Copy + iceoryx2::prelude::ZeroCopySend>(
    sub: &Subscriber<T>,
    newest_so_far: &mut Option<T>,
    what: &str,
) {
    loop {
        match sub.receive() {
            Ok(Some(sample)) => *newest_so_far = Some(*sample.payload()),
            Ok(None) => break,
            Err(e) => {
                log::debug!("receiving ppmd's {what}: {e}");
                break;
            }
        }
    }
}

/// Publishes the newest command taken in, if any, and wakes a ppmd in
/// follow timing; false when there was none.
fn publish(
    intake: &mut Intake,
    (publisher, notifier): (&Publisher, &Notifier),
    fingerprint: u64,
    ingress_seq: &mut u64,
    errors: &mut u64,
) -> bool {
    let Some(r) = intake.take() else {
        return false;
    };
    *ingress_seq += 1;
    let sample = CommandSample::new(&r.command, fingerprint, *ingress_seq, r.mono_ns, r.real_ns);
    let sent =
        ipc::publish(publisher, sample).and_then(|_| notifier.notify().map_err(PublishError::Wake));
    match sent {
        Ok(_) => intake.published_after(realtime_ns().saturating_sub(r.real_ns)),
        Err(e) => {
            *errors += 1;
            log::warn!("publishing command failed: {}", Chain(&e));
        }
    }
    true
}

/// Receives one datagram without blocking: its length, sender and kernel
/// receive time (CLOCK_REALTIME ns, when the kernel gave one); `None` when
/// nothing is pending.
fn receive(
    socket: &UdpSocket,
    buf: &mut [u8],
    cmsg: &mut [u8],
) -> nix::Result<Option<(usize, SocketAddr, Option<u64>)>> {
    use nix::errno::Errno;
    use nix::sys::socket::{recvmsg, ControlMessageOwned, MsgFlags, SockaddrStorage};
    use std::os::fd::AsRawFd;
    loop {
        let mut iov = [std::io::IoSliceMut::new(buf)];
        let msg = match recvmsg::<SockaddrStorage>(
            socket.as_raw_fd(),
            &mut iov,
            Some(&mut *cmsg),
            MsgFlags::MSG_DONTWAIT,
        ) {
            Ok(m) => m,
            Err(Errno::EAGAIN) => return Ok(None),
            Err(Errno::EINTR) => continue,
            Err(e) => return Err(e),
        };
        let kernel = msg.cmsgs().ok().and_then(|mut c| {
            c.find_map(|m| match m {
                ControlMessageOwned::ScmTimestampns(ts) => {
                    Some(ts.tv_sec() as u64 * 1_000_000_000 + ts.tv_nsec() as u64)
                }
                _ => None,
            })
        });
        let from = msg.address.and_then(|a: SockaddrStorage| {
            a.as_sockaddr_in()
                .map(|v4| SocketAddr::from(std::net::SocketAddrV4::from(*v4)))
                .or_else(|| {
                    a.as_sockaddr_in6()
                        .map(|v6| SocketAddr::from(std::net::SocketAddrV6::from(*v6)))
                })
        });
        let Some(from) = from else { continue };
        return Ok(Some((msg.bytes, from, kernel)));
    }
}
impl Server {
    /// Receives and publishes until `stop` is set, then saves the seq and
    /// logs the counters.
    pub fn run(mut self, stop: &AtomicBool) -> Result<()> {
        let rx = &mut self;
        match rx.poll.take() {
            Some(mut poll) => {
                let mut events = Events::with_capacity(8);
                while !stop.load(Relaxed) {
                    if let Err(e) = poll.poll(&mut events, Some(rx.idle_every)) {
                        if e.kind() == std::io::ErrorKind::Interrupted {
                            continue;
                        }
                        return Err(e).context("waiting for datagrams");
                    }
                    rx.drain();
                    rx.settle();
                }
            }
            None => {
                // Spin: drain, publish, repeat. What a wake-up of the sleeping
                // loop does without datagrams (offering the last sample to a
                // restarted ppmd, saving the seq, the counters' log line, the
                // read-back's changes) is done every `idle_every` while
                // nothing arrives.
                let mut settled = Instant::now();
                while !stop.load(Relaxed) {
                    if rx.drain() > 0 || settled.elapsed() >= rx.idle_every {
                        rx.settle();
                        settled = Instant::now();
                    } else {
                        std::hint::spin_loop();
                    }
                }
            }
        }
        self.finish();
        Ok(())
    }
}
