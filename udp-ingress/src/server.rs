//! The receive loop of udp-ingress: the non-blocking socket (mio), the
//! [`Intake`], the publisher to ppmd, the status replies, and with a
//! read-back the events of its state changes ([`crate::readback`]).
//! The binary parses its options and calls [`Server::open`] and
//! [`Server::run`].

use crate::seqfile::{self, SeqFile};
use crate::{pad_to_text, status_answer, Intake, Outcome, ReceiveThread, StatusAnswer};
use anyhow::{Context, Result};
use iceoryx2::port::update_connections::UpdateConnections;
use mio::net::UdpSocket;
use mio::{Events, Interest, Poll, Token};
use ppm_shared::auth::{AuthKey, KeyError};
use ppm_shared::config::{fault, ConfigError, IngressSection, KeyName, OutputPlan, Shared};
use ppm_shared::ipc::{
    self, CommandSample, IpcError, LineSample, PublishError, ReadbackSample, TimingSnapshot,
};
use ppm_shared::logging::Chain;
use ppm_shared::sched;
use ppm_shared::time::{now_ns, realtime_ns};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::time::{Duration, Instant};

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

/// Pins the calling thread (the receive thread) and gives it SCHED_FIFO as
/// `[ingress]` asks. A setting that cannot be had stops the program, unless
/// a degraded run is allowed: then each is logged as DEGRADED RUN. Returns
/// what was obtained.
fn schedule_receive_thread(
    ingress: &IngressSection,
    allow_degraded: bool,
) -> Result<ReceiveThread> {
    let mut shortfalls = Vec::new();
    let mut obtained = |key: &str, r: Result<(), sched::Shortfall>| -> Result<bool> {
        match r {
            Ok(()) => Ok(true),
            Err(s) if allow_degraded => {
                shortfalls.push(s);
                Ok(false)
            }
            Err(s) => Err(anyhow::Error::new(s).context(format!("receive thread ({key})"))),
        }
    };
    let mut cpu = None;
    if let Some(c) = ingress.cpu.index() {
        if obtained(&format!("ingress.cpu = {c}"), sched::pin(c, "ingress.cpu"))? {
            cpu = Some(c);
        }
    }
    let mut priority = 0;
    if ingress.priority > 0
        && obtained(
            &format!("ingress.priority = {}", ingress.priority),
            sched::set_fifo(ingress.priority, "udp-ingress"),
        )?
    {
        priority = ingress.priority;
    }
    for s in &shortfalls {
        log::warn!("DEGRADED RUN: receive thread: {}", s.degraded());
    }
    if ingress.busy_poll {
        if cpu.is_none() {
            log::warn!(
                "busy_poll without a CPU of its own: the spinning thread may share ppmd's; pin it with ingress.cpu (or --cpu) to another CPU"
            );
        }
        if priority > 0 {
            log::warn!(
                "busy_poll at SCHED_FIFO priority {priority}: normal tasks on {} run only in the time RT throttling reserves for them (/proc/sys/kernel/sched_rt_runtime_us), and the receive thread stops while they do",
                cpu.map_or("the CPU it spins on".to_string(), |c| format!("CPU {c}"))
            );
        }
    }
    Ok(ReceiveThread {
        busy_poll: ingress.busy_poll,
        priority,
        cpu,
        degraded: !shortfalls.is_empty(),
    })
}

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
    /// Status queries of this wake-up: their sources and sizes.
    status_to: Vec<(SocketAddr, usize)>,
    /// `ingress.status_allow`.
    status_allow: Vec<ipnet::IpNet>,
    ppmd_snapshot: Option<TimingSnapshot>,
    /// ppmd's newest line samples (RC_CHANNELS), and the newest.
    line: Option<Subscriber<LineSample>>,
    line_sample: Option<LineSample>,
    /// ppmd's read-back samples, with a read-back (the intake keeps the
    /// newest).
    readback: Option<Subscriber<ReadbackSample>>,
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
                Outcome::Status if self.status_to.len() < MAX_STATUS_PER_WAKE => {
                    self.status_to.push((from, n))
                }
                Outcome::Status => self.intake.status_dropped(),
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
        // Answered after publishing, so the counters add up.
        if !self.status_to.is_empty() && self.awaiting_ppmd.is_none() {
            if let Some(sub) = &self.stats {
                newest_snapshot(sub, &mut self.ppmd_snapshot);
            }
            let reply = self
                .intake
                .status(
                    self.started.elapsed(),
                    &self.thread,
                    now_ns(),
                    self.ppmd_snapshot.as_ref(),
                )
                .to_json();
            for (to, query_len) in self.status_to.drain(..) {
                if !self.reply_budget.take() {
                    self.intake.status_dropped();
                    continue;
                }
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

/// Subscribes to ppmd's timing snapshots for status replies, and says
/// whether ppmd publishes them (runs). Status is not worth stopping for: on
/// failure, replies say `"ppmd": null`.
fn subscribe_stats(node: &ipc::Node, name: &str) -> Option<(StatsSubscriber, bool)> {
    use iceoryx2::service::port_factory::PortFactory;
    let subscribed = ipc::open_stats_service(node, name).and_then(|service| {
        let sub = service
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .map_err(|e| IpcError::new("creating the subscriber", e))?;
        Ok((sub, service.dynamic_config().number_of_publishers() > 0))
    });
    match subscribed {
        Ok(sub) => Some(sub),
        Err(e) => {
            log::warn!(
                "status replies will lack ppmd's timing: subscribing to `{}` failed: {}",
                ipc::stats_service_name(name),
                Chain(&e)
            );
            None
        }
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

/// Subscribes to ppmd's line samples for RC_CHANNELS. Not worth stopping
/// for: on failure, RC_CHANNELS says no channels are on the line.
fn subscribe_line(node: &ipc::Node, name: &str) -> Option<Subscriber<LineSample>> {
    let subscribed = ipc::open_line_service(node, name).and_then(|service| {
        service
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .map_err(|e| IpcError::new("creating the subscriber", e))
    });
    subscribed
        .map_err(|e| {
            log::warn!(
                "RC_CHANNELS will carry no channels: subscribing to `{}` failed: {}",
                ipc::line_service_name(name),
                Chain(&e)
            )
        })
        .ok()
}

/// Subscribes to ppmd's read-back samples (`ppmd.readback`). Not worth
/// stopping for: on failure, status replies say its state is `stale`, and
/// no change is told.
fn subscribe_readback(node: &ipc::Node, name: &str) -> Option<Subscriber<ReadbackSample>> {
    let subscribed = ipc::open_readback_service(node, name).and_then(|service| {
        service
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .map_err(|e| IpcError::new("creating the subscriber", e))
    });
    subscribed
        .map_err(|e| {
            log::warn!(
                "the read-back will be reported `stale` and its changes not told: subscribing to `{}` failed: {}",
                ipc::readback_service_name(name),
                Chain(&e)
            )
        })
        .ok()
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

/// Loads the key file at `path`, which `key` names. Its faults (missing,
/// not a small regular file, readable by others, not 64 hex characters)
/// are the configuration's (exit status 78, by [`KeyError`]); a key from
/// the file is named, and told where to point, a key given with
/// `--auth-key` keeps the key file's own message.
fn load_key(key: &KeyName, path: &std::path::Path) -> Result<AuthKey> {
    AuthKey::load(path).map_err(|e| match key {
        KeyName::File(k) => {
            let fix = match e {
                KeyError::Read { .. } => format!(
                    ": point {k} at the key file, a regular file this user may read holding 64 hex characters, mode 600 (`openssl rand -hex 32 > FILE; chmod 600 FILE`)"
                ),
                _ => String::new(),
            };
            anyhow::Error::new(ConfigError::Invalid {
                key: k.clone(),
                message: format!("{}{fix}", Chain(&e)),
            })
        }
        KeyName::Option(_) => anyhow::Error::new(e),
    })
}

/// Why `cfg`'s socket could not be bound: a port this user may not take
/// (EACCES: below 1024, without CAP_NET_BIND_SERVICE) is the
/// configuration's fault (exit status 78). Others may pass (exit status 1,
/// restarted a second later): the port still held by a udp-ingress that is
/// stopping, an address not yet on an interface at boot.
fn bind_error(cfg: &OutputPlan, e: std::io::Error) -> anyhow::Error {
    let listen = cfg.ingress.listen;
    match (e.kind(), cfg.keys.name("ingress.listen")) {
        (std::io::ErrorKind::PermissionDenied, key) => {
            let message = format!(
                "cannot listen on {listen}: {e}: a port below 1024 needs a privilege udp-ingress does not have (CAP_NET_BIND_SERVICE); use a port of 1024 or more"
            );
            anyhow::Error::new(match key {
                KeyName::File(k) => ConfigError::Invalid { key: k, message },
                KeyName::Option(o) => ConfigError::Usage(format!("{o} {listen}: {message}")),
            })
        }
        _ => anyhow::Error::new(e).context(format!(
            "cannot listen on {listen} (another udp-ingress there? set ingress.listen or --listen)"
        )),
    }
}

/// Sets SO_RCVBUF and returns what the kernel granted (it doubles the
/// request and caps it at net.core.rmem_max).
fn set_receive_buffer(socket: &std::net::UdpSocket, bytes: u32) -> Result<usize> {
    use nix::sys::socket::{getsockopt, setsockopt, sockopt::RcvBuf};
    setsockopt(socket, RcvBuf, &(bytes as usize)).context("setting SO_RCVBUF")?;
    let granted = getsockopt(socket, RcvBuf).context("reading SO_RCVBUF")?;
    if granted < bytes as usize {
        log::warn!(
            "receive buffer is {granted} bytes, less than the {bytes} asked for: raise net.core.rmem_max"
        );
    }
    Ok(granted)
}

impl Server {
    /// Sets up everything the receive loop needs from its resolved output
    /// `cfg` (and the `shared` settings): the key and seq file, the
    /// socket, the shared-memory publisher, the wake-up notifier and the
    /// subscription to ppmd's snapshots, then the calling thread's priority
    /// and CPU (it is the receive thread). Says what it set up in the log.
    pub fn open(shared: &Shared, cfg: OutputPlan) -> Result<Server> {
        cfg.check_busy_poll_cpu(sched::resolve_rt_cpu(shared.rt.cpu))?;
        // What the configuration names, checked before anything is opened:
        // the receive thread's CPU, the key files, the files kept across
        // restarts, the ipc root. Their faults stop udp-ingress with exit
        // status 78, naming the key.
        if let (Some(cpu), false) = (cfg.ingress.cpu.index(), shared.rt.allow_degraded) {
            sched::check_online(cpu, &cfg.keys.name("ingress.cpu"))?;
        }
        let model = cfg.model.clone();
        let allow = cfg.allow.clone();
        let status_allow = cfg.status_allow.clone();
        let key = cfg
            .ingress
            .auth_key
            .as_deref()
            .map(|path| load_key(&cfg.keys.name("ingress.auth_key"), path))
            .transpose()?;
        let (seq_file, floor) = match &key {
            Some(_) => {
                let (file, floor) = SeqFile::open_named(
                    seqfile::SEQ,
                    &cfg.keys.name("ingress.seq_file"),
                    &cfg.seq_file,
                    SEQ_SAVE_EVERY,
                )?;
                (Some(file), floor)
            }
            None => (None, None),
        };
        let mavlink_signing = match &cfg.mavlink.key_file {
            Some(path) => {
                let key = load_key(&cfg.keys.name("mavlink.key_file"), path)?;
                let ts_path = cfg
                    .mavlink
                    .timestamp_file
                    .clone()
                    .context("mavlink.timestamp_file is not resolved")?;
                let (file, floor) = SeqFile::open_named(
                    seqfile::MAVLINK_TIMESTAMP,
                    &cfg.keys.name("mavlink.timestamp_file"),
                    &ts_path,
                    SEQ_SAVE_EVERY,
                )?;
                Some((path, key, ts_path, file, floor))
            }
            None => None,
        };
        fault::ensure_dir(
            &shared.keys.name("ipc.root"),
            "the ipc root",
            &shared.ipc.root,
            "set ipc.root to a directory udp-ingress and ppmd (the same user) may create files in; under systemd /run/ppm, the units' RuntimeDirectory",
        )?;
        let listen = cfg.ingress.listen;

        let std_socket = std::net::UdpSocket::bind(listen).map_err(|e| bind_error(&cfg, e))?;
        std_socket.set_nonblocking(true)?;
        let rcvbuf = set_receive_buffer(&std_socket, cfg.ingress.recv_buffer_bytes)?;
        nix::sys::socket::setsockopt(
            &std_socket,
            nix::sys::socket::sockopt::ReceiveTimestampns,
            &true,
        )
        .context("enabling SO_TIMESTAMPNS")?;
        let mut socket = UdpSocket::from_std(std_socket);

        let node = ipc::create_node(&shared.ipc.root, &format!("udp-ingress-{}", cfg.name))?;
        let service = ipc::open_command_service(&node, &cfg.name)?;
        let publisher: Publisher = service.publisher_builder().create().map_err(|e| {
            IpcError::new(
                format!(
                    "creating publisher on `{}`",
                    ipc::command_service_name(&cfg.name)
                ),
                e,
            )
        })?;

        // After each command, a wake-up for a ppmd in follow timing (which
        // sleeps until one comes); nothing listens to it in grid timing.
        let wake = ipc::open_wake_service(&node, &cfg.name)?;
        let notifier: Notifier = wake.notifier_builder().create().map_err(|e| {
            IpcError::new(
                format!(
                    "creating notifier on `{}`",
                    ipc::wake_service_name(&cfg.name)
                ),
                e,
            )
        })?;

        let stats = subscribe_stats(&node, &cfg.name);
        // With ppmd running, status replies wait for its snapshot (see
        // `awaiting_ppmd`); commands never wait.
        let awaiting_ppmd = matches!(stats, Some((_, true)))
            .then(|| Instant::now() + Duration::from_nanos(crate::PPMD_STALE_AFTER_NS));
        let stats = stats.map(|(sub, _)| sub);
        let line = subscribe_line(&node, &cfg.name);
        let readback = cfg
            .readback
            .as_ref()
            .and_then(|_| subscribe_readback(&node, &cfg.name));
        let idle_every = match &cfg.readback {
            Some(_) => READBACK_POLL_TIMEOUT,
            None => POLL_TIMEOUT,
        };

        // The busy-polling loop never waits: it needs no poll.
        let poll = if cfg.ingress.busy_poll {
            None
        } else {
            let poll = Poll::new().context("creating mio poll")?;
            poll.registry()
                .register(&mut socket, SOCKET, Interest::READABLE)?;
            Some(poll)
        };
        // This thread receives: its priority and CPU are set here, after the
        // start-up work.
        let thread = schedule_receive_thread(&cfg.ingress, shared.rt.allow_degraded)?;
        log::info!("receive thread: {thread}");
        log::info!(
            "listening on {} (receive buffer {} bytes), {} channels ({}); publishing to `{}` (ipc root {})",
            socket.local_addr()?,
            rcvbuf,
            model.channels(),
            model.names().join(" "),
            ipc::command_service_name(&cfg.name),
            shared.ipc.root.display()
        );

        // Stamped on every command: ppmd refuses one made under another model.
        let fingerprint = model.fingerprint();
        let mut intake = Intake::new(
            &cfg.name,
            model,
            Duration::from_millis(cfg.ingress.reject_log_interval_ms),
        )
        .forget_seq_after(Duration::from_millis(cfg.failsafe.after_ms))
        .with_mavlink(cfg.mavlink.clone())
        .with_status_allow(status_allow.clone());
        if let Some(r) = &cfg.readback {
            log::info!(
                "read-back of {}: in status replies; each state change goes at once (within {} ms) to the sender of the newest JSON command and as STATUSTEXT to MAVLink peers; RC_CHANNELS carry what the radio transmits, SERVO_OUTPUT_RAW what the line carries",
                r.input,
                READBACK_POLL_TIMEOUT.as_millis()
            );
            intake = intake.with_readback(r.input.to_string());
        }
        let mut mavlink_ts_file = None;
        if let Some((path, key, ts_path, file, floor)) = mavlink_signing {
            intake = intake.with_mavlink_signing(key, floor);
            log::info!(
                "MAVLink frames must be signed (MAVLink 2) with the key in {}; replies are signed; {} (the newest is kept in {})",
                path.display(),
                match floor {
                    Some(f) => format!("signing timestamps {f} and below refused as replays"),
                    None => "no signed frame accepted before".into(),
                },
                ts_path.display()
            );
            mavlink_ts_file = Some(file);
        }
        if let (Some(key), Some(file)) = (key, &seq_file) {
            log::info!(
                "commands must be signed with the key in {} and name this output (\"to\": \"{}\"); status queries need no signature; {} (the last accepted seq is kept in {})",
                cfg.ingress.auth_key.as_ref().expect("key loaded").display(),
                cfg.name,
                match floor {
                    Some(f) => format!("seq {f} and below refused as replays"),
                    None => "no seq accepted before".into(),
                },
                file.path().display()
            );
            intake = intake.with_auth(key, floor);
        }
        if !allow.is_empty() {
            log::info!(
                "taking datagrams only from {}",
                allow
                    .iter()
                    .map(|n| n.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            intake = intake.with_allowlist(allow);
        }
        let rx = Server {
            poll,
            socket,
            publisher,
            notifier,
            _wake: wake,
            stats,
            intake,
            seq_file: seq_file.map(|f| (f, false)),
            mavlink_ts_file: mavlink_ts_file.map(|f| (f, false)),
            started: Instant::now(),
            thread,
            buf: vec![0u8; MAX_DATAGRAM],
            cmsg: nix::cmsg_space!(nix::sys::time::TimeSpec),
            status_to: Vec::with_capacity(MAX_STATUS_PER_WAKE),
            status_allow,
            ppmd_snapshot: None,
            line,
            line_sample: None,
            readback,
            idle_every,
            awaiting_ppmd,
            reply_budget: ReplyBudget::new(),
            mavlink_out: Vec::new(),
            ingress_seq: 0,
            fingerprint,
            publish_errors: 0,
            last_report: Instant::now(),
            reported_received: 0,
        };
        Ok(rx)
    }

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

#[cfg(test)]
mod tests {
    use super::*;
    use ppm_shared::config::{Config, Plan};
    use ppm_shared::daemon::{exit_status, EXIT_CONFIG, EXIT_FAILURE};

    fn plan(text: &str) -> OutputPlan {
        Plan::resolve_one(&Config::parse(text).unwrap()).unwrap().1
    }

    /// A port this user may not take is the configuration's fault (78);
    /// one still held by another process may pass (1).
    #[test]
    fn a_privileged_port_is_a_configuration_error_a_busy_one_is_not() {
        let cfg = plan("[ingress]\nlisten = \"0.0.0.0:80\"");
        let e = bind_error(&cfg, std::io::Error::from(nix::errno::Errno::EACCES));
        assert_eq!(exit_status(&e, |_| false), EXIT_CONFIG);
        let text = e.to_string();
        assert!(
            text.starts_with("config key `ingress.listen`: cannot listen on 0.0.0.0:80")
                && text.contains("use a port of 1024 or more"),
            "{text}"
        );
        let e = bind_error(&cfg, std::io::Error::from(nix::errno::Errno::EADDRINUSE));
        assert_eq!(exit_status(&e, |_| false), EXIT_FAILURE);
        let mut cfg = cfg;
        cfg.keys.note_option("ingress.listen", "--listen");
        let e = bind_error(&cfg, std::io::Error::from(nix::errno::Errno::EACCES));
        assert!(e.to_string().starts_with("--listen 0.0.0.0:80: "), "{e}");
    }

    /// A running ingress with a read-back (its receive loop, socket and
    /// shared memory under a temporary root): it waits at most
    /// READBACK_POLL_TIMEOUT for datagrams, so the read-back samples
    /// published here are seen while none comes. Each change reaches the
    /// JSON sender as one event (none for a sample without a change) and a
    /// MAVLink peer as a STATUSTEXT; the status reply carries the newest;
    /// RC_CHANNELS carry the radio's frame, SERVO_OUTPUT_RAW the line's (no
    /// ppmd here: none). No time limit is asserted: the latency of the
    /// first event is printed.
    #[test]
    fn a_running_ingress_tells_each_readback_change_while_no_datagram_comes() {
        use crate::readback::tests::{decode, rc_channels, sample, servo_output_raw, statustext};
        use ppm_shared::capture::ReadbackState::{Following, NoInput, Overridden};
        use ppm_shared::mavlink::{self, HEARTBEAT, RC_CHANNELS, SERVO_OUTPUT_RAW, STATUSTEXT};
        use std::net::UdpSocket as StdSocket;
        use std::sync::{mpsc, Arc};

        let root = std::env::temp_dir().join(format!("ppm-readback-server-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let cfg = format!(
            "name = \"rb\"\n[ingress]\nlisten = \"127.0.0.1:0\"\n[ppmd]\nreadback = \"sim:{0}/radio.trace\"\n[ipc]\nroot = \"{0}\"\n",
            root.display()
        );
        let (shared, out) = Plan::resolve_one(&Config::parse(&cfg).unwrap()).unwrap();
        // Without a read-back, the loop waits as long as it always did.
        let plain = cfg.replace("name = \"rb\"", "name = \"plain\"");
        let plain = plain[..plain.find("[ppmd]").unwrap()].to_string()
            + &plain[plain.find("[ipc]").unwrap()..];
        let (plain_shared, plain) = Plan::resolve_one(&Config::parse(&plain).unwrap()).unwrap();
        assert!(plain.readback.is_none());
        let server = Server::open(&plain_shared, plain).unwrap();
        assert_eq!(server.idle_every, POLL_TIMEOUT);
        drop(server);
        let stop = Arc::new(AtomicBool::new(false));
        let (tx, rx) = mpsc::channel();
        let running = {
            let stop = stop.clone();
            std::thread::spawn(move || {
                let server = Server::open(&shared, out).unwrap();
                tx.send((server.local_addr().unwrap(), server.idle_every))
                    .unwrap();
                server.run(&stop).unwrap();
            })
        };
        let (at, idle_every) = rx.recv_timeout(Duration::from_secs(30)).unwrap();
        assert_eq!(idle_every, READBACK_POLL_TIMEOUT);

        let node = ipc::create_node(&root, "readback-test").unwrap();
        let service = ipc::open_readback_service(&node, "rb").unwrap();
        let publisher = service.publisher_builder().create().unwrap();
        let socket = || {
            let s = StdSocket::bind("127.0.0.1:0").unwrap();
            s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
            s
        };
        let (json, gcs, query) = (socket(), socket(), socket());
        let mut buf = [0u8; 4_096];
        let mut recv = |s: &StdSocket| -> Vec<u8> {
            let n = s.recv(&mut buf).expect("a datagram within 10 s");
            buf[..n].to_vec()
        };
        // The newest readback member as a status reply has it.
        let status = |query: &StdSocket, recv: &mut dyn FnMut(&StdSocket) -> Vec<u8>| {
            query.send_to(br#"{"get":"status"}"#, at).unwrap();
            let reply: serde_json::Value = serde_json::from_slice(&recv(query)).unwrap();
            reply["readback"].clone()
        };
        // Waits until the ingress has taken a sample of `frames` frames.
        let taken = |frames: u64, recv: &mut dyn FnMut(&StdSocket) -> Vec<u8>| {
            for _ in 0..500 {
                if status(&query, recv)["frames"] == frames {
                    return;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            panic!("the ingress never took the sample of {frames} frames");
        };

        json.send_to(br#"{"ch":[1500,1500,1500,1500],"seq":1}"#, at)
            .unwrap();
        let hb = mavlink::frame(2, (0, 255, 190), &HEARTBEAT, &[0, 0, 0, 0, 6, 8, 0, 4, 3]);
        gcs.send_to(&hb, at).unwrap();
        let before = status(&query, &mut recv);
        assert_eq!(
            (&before["state"], &before["input"]),
            (
                &serde_json::json!("stale"),
                &serde_json::json!(format!("sim:{}/radio.trace", root.display()))
            )
        );

        let publish = |s: ppm_shared::ipc::ReadbackSample| {
            ipc::publish(&publisher, s).unwrap();
        };
        let t0 = now_ns();
        let mut first = sample(t0, NoInput, 0, 0);
        first.frames = 1;
        publish(first);
        taken(1, &mut recv);
        // The change, while nothing is sent to the ingress.
        let t1 = now_ns();
        publish(sample(t1, Following, 1, t1));
        let event = recv(&json);
        eprintln!(
            "first event {:.3} ms after its sample",
            (now_ns() - t1) as f64 / 1e6
        );
        assert_eq!(
            String::from_utf8(event).unwrap(),
            format!(
                r#"{{"changed_mono_ns":{t1},"changes":1,"event":"readback","from":"no_input","name":"rb","state":"following"}}"#
            )
        );
        // A sample without a change: no event (the next datagram is the
        // next change's).
        let mut same = sample(now_ns(), Following, 1, t1);
        same.frames = 260;
        publish(same);
        taken(260, &mut recv);
        let t2 = now_ns();
        publish(sample(t2, Overridden, 2, t2));
        assert_eq!(
            String::from_utf8(recv(&json)).unwrap(),
            format!(
                r#"{{"changed_mono_ns":{t2},"changes":2,"event":"readback","from":"following","name":"rb","state":"overridden"}}"#
            )
        );
        let r = status(&query, &mut recv);
        assert_eq!(
            (
                &r["state"],
                &r["changes"],
                &r["frames"],
                &r["ch_us"],
                &r["max_diff_us"]
            ),
            (
                &serde_json::json!("overridden"),
                &serde_json::json!(2),
                &serde_json::json!(250),
                &serde_json::json!([1100.4, 1499.6, 1900.0, 1500.0]),
                &serde_json::json!(12.345)
            )
        );
        assert_eq!(r["refused"]["unsynced"], 8);

        // The MAVLink peer: both STATUSTEXTs, in order; RC_CHANNELS carry
        // the radio's frame; SERVO_OUTPUT_RAW the line's (none).
        let (mut texts, mut rc, mut servo) = (vec![], None, None);
        while texts.len() < 2 || rc.is_none() || servo.is_none() {
            let (id, p) = decode(&recv(&gcs));
            match id {
                id if id == STATUSTEXT.id => texts.push(statustext(&p)),
                id if id == RC_CHANNELS.id && texts.len() == 2 => rc = Some(rc_channels(&p)),
                id if id == SERVO_OUTPUT_RAW.id => servo = Some(servo_output_raw(&p)),
                _ => {}
            }
        }
        assert_eq!(
            texts,
            [
                (5, "ppm rb: following".to_string(), 0, 0),
                (
                    4,
                    "ppm rb: overridden (instructor has control)".to_string(),
                    0,
                    0
                )
            ]
        );
        let (_, count, chan, rest_unused) = rc.unwrap();
        assert_eq!(
            (count, chan, rest_unused),
            (4, vec![1100, 1500, 1900, 1500], true)
        );
        assert_eq!(servo.unwrap().2, vec![0; 16]);

        stop.store(true, Relaxed);
        running.join().unwrap();
        drop((publisher, service, node));
        let _ = std::fs::remove_dir_all(&root);
    }

    /// A key file from the configuration is named by its key, with where
    /// to point it; one given with --auth-key keeps the key file's message.
    #[test]
    fn a_key_file_from_the_configuration_names_its_key() {
        let missing = std::path::Path::new("/nonexistent-ppm-test/k.key");
        let e = load_key(&KeyName::File("mavlink.key_file".into()), missing).unwrap_err();
        assert_eq!(exit_status(&e, |_| false), EXIT_CONFIG);
        assert_eq!(
            e.to_string(),
            "config key `mavlink.key_file`: cannot read auth key file /nonexistent-ppm-test/k.key: No such file or directory (os error 2): point mavlink.key_file at the key file, a regular file this user may read holding 64 hex characters, mode 600 (`openssl rand -hex 32 > FILE; chmod 600 FILE`)"
        );
        let e = load_key(&KeyName::Option("--auth-key"), missing).unwrap_err();
        assert_eq!(exit_status(&e, |_| false), EXIT_CONFIG);
        assert_eq!(
            format!("{e:#}"),
            "cannot read auth key file /nonexistent-ppm-test/k.key: No such file or directory (os error 2)"
        );
    }
}
