//! Setting up the receive loop ([`Server::open`]): what the configuration
//! names checked first (the receive thread's CPU, the key files, the files
//! kept across restarts, the ipc root), then the socket, the publisher and
//! the notifier to ppmd, the subscriptions to its snapshots, line and
//! read-back samples, and last the receive thread's priority and CPU.

use super::{
    Notifier, Publisher, ReplyBudget, Server, StatsSubscriber, Subscriber, MAX_DATAGRAM,
    MAX_STATUS_PER_WAKE, POLL_TIMEOUT, READBACK_POLL_TIMEOUT, SEQ_SAVE_EVERY, SOCKET,
};
use crate::seqfile::{self, SeqFile};
use crate::{Intake, ReceiveThread};
use anyhow::{Context, Result};
use mio::net::UdpSocket;
use mio::{Interest, Poll};
use ppm_shared::auth::{AuthKey, KeyError};
use ppm_shared::config::{fault, ConfigError, IngressSection, KeyName, OutputPlan, Shared};
use ppm_shared::ipc::{self, IpcError, LineSample, ReadbackSample, TelemetrySample};
use ppm_shared::logging::Chain;
use ppm_shared::sched;
use std::time::{Duration, Instant};

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
/// Subscribes to one of ppmd's newest-only services, `service` (opened, or
/// why not), named `service_name`. Not worth stopping for: on failure, says
/// what goes without it (`without`) and gives `None`.
fn subscribe_newest<T: std::fmt::Debug + Copy + iceoryx2::prelude::ZeroCopySend + 'static>(
    service: Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<
            iceoryx2::service::ipc::Service,
            T,
            (),
        >,
        IpcError,
    >,
    service_name: String,
    without: &str,
) -> Option<Subscriber<T>> {
    let subscribed = service.and_then(|service| {
        service
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .map_err(|e| IpcError::new("creating the subscriber", e))
    });
    subscribed
        .map_err(|e| {
            log::warn!(
                "{without}: subscribing to `{service_name}` failed: {}",
                Chain(&e)
            )
        })
        .ok()
}

/// Subscribes to ppmd's line samples for RC_CHANNELS (on failure,
/// RC_CHANNELS says no channels are on the line).
fn subscribe_line(node: &ipc::Node, name: &str) -> Option<Subscriber<LineSample>> {
    subscribe_newest(
        ipc::open_line_service(node, name),
        ipc::line_service_name(name),
        "RC_CHANNELS will carry no channels",
    )
}

/// Subscribes to ppmd's read-back samples (`ppmd.readback`; on failure,
/// status replies say its state is `stale`, and no change is told).
fn subscribe_readback(node: &ipc::Node, name: &str) -> Option<Subscriber<ReadbackSample>> {
    subscribe_newest(
        ipc::open_readback_service(node, name),
        ipc::readback_service_name(name),
        "the read-back will be reported `stale` and its changes not told",
    )
}

/// Subscribes to ppmd's telemetry samples (a CRSF `serial:` output; on
/// failure, status replies say it is `stale`, and MAVLink peers get none).
fn subscribe_telemetry(node: &ipc::Node, name: &str) -> Option<Subscriber<TelemetrySample>> {
    subscribe_newest(
        ipc::open_telemetry_service(node, name),
        ipc::telemetry_service_name(name),
        "the flight controller's telemetry will be reported `stale` and not forwarded",
    )
}
/// Loads the key file at `path`, which `key` names. Its faults (missing,
/// not a small regular file, readable by others, not 64 hex characters)
/// are the configuration's (exit status 78, by [`KeyError`]); a key from
/// the file is named, and told where to point, a key given with
/// `--auth-key` keeps the key file's own message.
pub(super) fn load_key(key: &KeyName, path: &std::path::Path) -> Result<AuthKey> {
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
pub(super) fn bind_error(cfg: &OutputPlan, e: std::io::Error) -> anyhow::Error {
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
        match nix::sys::socket::setsockopt(
            &std_socket,
            nix::sys::socket::sockopt::ReceiveTimestampns,
            &true,
        ) {
            Ok(()) => {}
            // Linux always has it; an emulator of another architecture's
            // user space (qemu-user) may not.
            Err(nix::errno::Errno::ENOPROTOOPT) => log::warn!(
                "kernel receive timestamps (SO_TIMESTAMPNS) are not available here: each command is stamped when read, a little later than it arrived"
            ),
            Err(e) => return Err(anyhow::Error::new(e).context("enabling SO_TIMESTAMPNS")),
        }
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
        // A read-back and a pilot's radio publish on the same service.
        let reads_back = cfg.readback.is_some() || cfg.pilot.is_some();
        let readback = reads_back
            .then(|| subscribe_readback(&node, &cfg.name))
            .flatten();
        let telemetry = cfg
            .telemetry_port()
            .and_then(|_| subscribe_telemetry(&node, &cfg.name));
        let idle_every = match reads_back {
            true => READBACK_POLL_TIMEOUT,
            false => POLL_TIMEOUT,
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
        if let Some(p) = &cfg.pilot {
            log::info!(
                "pilot's radio {}: who flies is the read-back member of status replies (following: the groundstation; overridden: the pilot, whose takeover switch is on; no_input: no pilot's radio, so no command goes out); each change goes at once to the sender of the newest JSON command and as STATUSTEXT to MAVLink peers",
                p.input
            );
            intake = intake.with_pilot(p.input.to_string());
        }
        if let Some(port) = cfg.telemetry_port() {
            log::info!(
                "telemetry from the flight controller on {}: in status replies; SYS_STATUS, ATTITUDE and GPS_RAW_INT to MAVLink peers, a STATUSTEXT at each flight mode change",
                port.display()
            );
            intake = intake.with_telemetry(port.display().to_string());
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
            telemetry,
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
}
