//! Payload types carried through iceoryx2 shared memory, and service names.
//!
//! Payloads are `#[repr(C)]`, fixed size and `Copy`, with an explicit type
//! name, so both processes agree on the layout without any serialisation.

use crate::frame::{Channels, FrameModel, MAX_CHANNELS};
use crate::protocol::Command;
use iceoryx2::prelude::{
    FileName, LogLevel, NodeBuilder, NodeName, SemanticString, ServiceName, SignalHandlingMode,
    ZeroCopySend,
};

/// The iceoryx2 node type both processes use (inter-process, shared memory).
pub type Node = iceoryx2::node::Node<iceoryx2::service::ipc::Service>;
/// The command service both processes open with [`open_command_service`].
pub type CommandService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<
    iceoryx2::service::ipc::Service,
    CommandSample,
    (),
>;

/// The wake-up event service udp-ingress notifies after each command it
/// publishes; ppmd listens to it for `follow` timing.
pub type WakeService =
    iceoryx2::service::port_factory::event::PortFactory<iceoryx2::service::ipc::Service>;

/// Prefix of every shared-memory file of ppm (in /dev/shm and the root).
const PREFIX: &[u8] = b"ppm_";

/// Newest command, published by `udp-ingress` for `ppmd`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ppm::CommandSample")]
#[repr(C)]
pub struct CommandSample {
    /// Number of this command among those the publishing ingress has
    /// published (1, 2, ...); restarts at 1 with a new ingress.
    pub ingress_seq: u64,
    /// The sender's `seq`, valid when `has_seq` is 1.
    pub seq: u64,
    /// CLOCK_MONOTONIC time the datagram was received, ns.
    pub recv_mono_ns: u64,
    /// CLOCK_REALTIME time the datagram was received, ns since the Unix epoch.
    pub recv_real_ns: u64,
    /// Process id of the publishing ingress.
    pub ingress_pid: u32,
    /// 1 when the sender gave a `seq`.
    pub has_seq: u32,
    /// Number of valid entries in `values_ns`.
    pub channel_count: u32,
    /// How many values the ingress clamped to their channel's limits.
    pub clamped: u32,
    /// Channel values in ns, transmitter order, defaults filled in.
    pub values_ns: [u32; MAX_CHANNELS],
    /// [`FrameModel::fingerprint`] of the model the ingress made it under.
    pub model: u64,
}

impl CommandSample {
    /// A sample carrying `cmd`, parsed under the model with fingerprint
    /// `model`, received at the given times.
    pub fn new(
        cmd: &Command,
        model: u64,
        ingress_seq: u64,
        recv_mono_ns: u64,
        recv_real_ns: u64,
    ) -> Self {
        let mut values_ns = [0; MAX_CHANNELS];
        let v = cmd.channels.as_ns();
        values_ns[..v.len()].copy_from_slice(v);
        CommandSample {
            ingress_seq,
            seq: cmd.seq.unwrap_or(0),
            recv_mono_ns,
            recv_real_ns,
            ingress_pid: std::process::id(),
            has_seq: cmd.seq.is_some() as u32,
            channel_count: v.len() as u32,
            clamped: cmd.clamped,
            values_ns,
            model,
        }
    }

    /// Whether a daemon whose timing loop started at `started_ns` may fly
    /// this command at `now_ns` with a failsafe limit of `after_ns`: only a
    /// command received (by udp-ingress, CLOCK_MONOTONIC) since the start,
    /// and no older than the limit. A service's history can offer the last
    /// command of an earlier run to a daemon that starts later: that one
    /// never flies.
    pub fn fresh(&self, started_ns: u64, now_ns: u64, after_ns: u64) -> bool {
        self.recv_mono_ns >= started_ns && now_ns.saturating_sub(self.recv_mono_ns) <= after_ns
    }

    /// The sender's `seq`, if any.
    pub fn seq(&self) -> Option<u64> {
        (self.has_seq != 0).then_some(self.seq)
    }

    /// The channels, if the sample was made under this very channel model
    /// (same count, order, limits, defaults and units); `None` means the
    /// publisher was configured differently.
    pub fn channels(&self, model: &FrameModel) -> Option<Channels> {
        let n = self.channel_count as usize;
        (n == model.channels() && self.model == model.fingerprint())
            .then(|| Channels::from_ns(&self.values_ns[..n]))
    }
}

/// The iceoryx2 service carrying the newest command of output `name`.
pub fn command_service_name(name: &str) -> String {
    format!("ppm/{name}/command")
}

/// The iceoryx2 event service that signals a new command of output `name`.
pub fn wake_service_name(name: &str) -> String {
    format!("ppm/{name}/command-wake")
}

/// The iceoryx2 service carrying ppmd's timing snapshots of output `name`.
pub fn stats_service_name(name: &str) -> String {
    format!("ppm/{name}/stats")
}

/// The iceoryx2 service carrying the newest frame output `name`'s line
/// carried whole.
pub fn line_service_name(name: &str) -> String {
    format!("ppm/{name}/line")
}

/// The newest frame ppmd's line carried whole (or glitched, as carried),
/// published by ppmd's monitor when a new one went out, at most every
/// tenth of a second, on [`line_service_name`]: what udp-ingress reports
/// to MAVLink groundstations as RC_CHANNELS. Aborted frames are not
/// published: receivers keep what they had.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("ppm::LineSample")]
#[repr(C)]
pub struct LineSample {
    /// Its number among ppmd's frames (1, 2, ...; restarts with ppmd).
    pub frame: u64,
    /// CLOCK_MONOTONIC time of its first edge, ns.
    pub start_mono_ns: u64,
    /// Number of valid entries in `values_ns`.
    pub channels: u32,
    /// The line state it went out in: 1 active, 2 failsafe.
    pub state: u32,
    /// The values the line carried, ns, transmitter order.
    pub values_ns: [u32; MAX_CHANNELS],
}

/// The line sample service.
pub type LineService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<
    iceoryx2::service::ipc::Service,
    LineSample,
    (),
>;

/// Opens (or creates) the newest-only line sample service of output `name`.
pub fn open_line_service(node: &Node, name: &str) -> Result<LineService, IpcError> {
    open_newest_only(node, &line_service_name(name))
}

/// The iceoryx2 service carrying output `name`'s read-back: what the radio
/// transmits, read from ppmd's `readback` input, and whether it is ppm's.
pub fn readback_service_name(name: &str) -> String {
    format!("ppm/{name}/readback")
}

/// Refusal reasons a [`ReadbackSample`] counts, in
/// [`crate::capture::CaptureCounts::reasons`]' order.
pub const READBACK_REASONS: usize = crate::capture::decode::REASONS;

/// Output `name`'s read-back, published by ppmd's read-back thread at every
/// frame it reads and every state change (and every tenth of a second
/// while nothing is read), on [`readback_service_name`]: what udp-ingress
/// reports in status replies, to JSON senders and to MAVLink peers.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("ppm::ReadbackSample")]
#[repr(C)]
pub struct ReadbackSample {
    /// CLOCK_MONOTONIC time of publication, ns.
    pub published_mono_ns: u64,
    /// The state: a [`crate::capture::ReadbackState`] code (0 `no_input`,
    /// 1 `following`, 2 `overridden`).
    pub state: u32,
    /// Channels in the newest frame read (valid entries of `values_ns`).
    pub channels: u32,
    /// State changes so far (a reader that sees this grow knows the state
    /// changed, even between two samples it read).
    pub changes: u64,
    /// CLOCK_MONOTONIC time of the newest state change, ns (0: none yet).
    pub changed_mono_ns: u64,
    /// Edges read from the input.
    pub edges: u64,
    /// Whole frames read.
    pub frames: u64,
    /// Frames read that carried ppm's values (within the tolerance).
    pub matched: u64,
    /// Frames read that carried something else.
    pub mismatched: u64,
    /// Frames refused, by reason ([`READBACK_REASONS`]; names from
    /// [`crate::capture::CaptureCounts::reasons`]).
    pub refused: [u64; READBACK_REASONS],
    /// CLOCK_MONOTONIC time the newest frame read began, ns (0: none yet).
    pub start_mono_ns: u64,
    /// The newest frame read, ns per channel, in the order read.
    pub values_ns: [u32; MAX_CHANNELS],
    /// Largest difference between the newest frame read and the nearest
    /// value ppm's line carried, per channel, ns.
    pub max_diff_ns: u32,
    /// Padding (0).
    pub reserved: u32,
}

/// The read-back service.
pub type ReadbackService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<
    iceoryx2::service::ipc::Service,
    ReadbackSample,
    (),
>;

/// Opens (or creates) the newest-only read-back service of output `name`.
pub fn open_readback_service(node: &Node, name: &str) -> Result<ReadbackService, IpcError> {
    open_newest_only(node, &readback_service_name(name))
}

/// The iceoryx2 service carrying output `name`'s CRSF telemetry: what the
/// flight controller sends back on its TX line.
pub fn telemetry_service_name(name: &str) -> String {
    format!("ppm/{name}/telemetry")
}

pub use crate::crsf::sample::{TelemetrySample, TELEMETRY_COUNTS, TELEMETRY_KINDS};

/// The telemetry service.
pub type TelemetryService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<
    iceoryx2::service::ipc::Service,
    TelemetrySample,
    (),
>;

/// Opens (or creates) the newest-only telemetry service of output `name`.
pub fn open_telemetry_service(node: &Node, name: &str) -> Result<TelemetryService, IpcError> {
    open_newest_only(node, &telemetry_service_name(name))
}

/// Buckets of [`TimingSnapshot::hist_us`]: edge error 0..1000 us in 1 us steps.
pub const HIST_BUCKETS: usize = 1_000;

/// Summary of a distribution, in nanoseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("ppm::Summary")]
#[repr(C)]
pub struct Summary {
    /// Number of values.
    pub count: u64,
    /// Smallest.
    pub min: u64,
    /// Largest.
    pub max: u64,
    /// Mean (rounded).
    pub mean: u64,
    /// Median.
    pub p50: u64,
    /// 99th percentile.
    pub p99: u64,
    /// 99.9th percentile.
    pub p999: u64,
}

/// ppmd's timing statistics, published about once a second on
/// [`stats_service_name`] for `jitter --attach` and status queries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("ppm::TimingSnapshot")]
#[repr(C)]
pub struct TimingSnapshot {
    /// Snapshot number, 1, 2, ... (restarts with ppmd).
    pub seq: u64,
    /// CLOCK_MONOTONIC time of the snapshot, ns.
    pub mono_ns: u64,
    /// Time since ppmd started, ns.
    pub uptime_ns: u64,
    /// Frame length, ns (the loop's interval); 0 in follow timing, whose
    /// frames follow the commands.
    pub frame_ns: u64,
    /// Current spin margin, ns.
    pub margin_ns: u64,
    /// Frames emitted.
    pub frames: u64,
    /// Edges written.
    pub edges: u64,
    /// Commands taken.
    pub commands: u64,
    /// Frames skipped because their start had passed.
    pub overruns: u64,
    /// Frames moved later as a whole.
    pub late_frames: u64,
    /// Commands refused: made under another channel model.
    pub mismatched: u64,
    /// Commands refused as expired: received before ppmd's loop started, or
    /// older than `failsafe.after_ms` when taken.
    pub expired: u64,
    /// Frame-log rows and HdrHistogram intervals that could not be written.
    pub log_errors: u64,
    /// Edges written more than 10 us late.
    pub late_edges: u64,
    /// Frames aborted at an edge receivers time found later than
    /// `ppm.late_edge_guard_us` (counted in `frames` too).
    pub aborted_frames: u64,
    /// Frames with an edge receivers time that reached the line later than
    /// the guard (counted in `frames` too).
    pub glitched_frames: u64,
    /// Failed writes.
    pub write_errors: u64,
    /// Entries into the failsafe action.
    pub failsafe_entries: u64,
    /// Follow timing: frames that repeated the last frame's command because
    /// no fresh one came before the longest sync.
    pub repeats: u64,
    /// Time spent spinning as a share of wall time, parts per million.
    pub spin_share_ppm: u64,
    /// Edge error (actual minus scheduled) over the last interval.
    pub last: Summary,
    /// Edge error since start.
    pub total: Summary,
    /// Output write duration since start.
    pub write: Summary,
    /// Cumulative edge error counts in 1 us buckets (bucket `i`: `i..i+1` us).
    pub hist_us: [u64; HIST_BUCKETS],
    /// Edge errors of 1000 us or more.
    pub hist_overflow: u64,
    /// ppmd's process id.
    pub pid: u32,
    /// SCHED_FIFO priority obtained (0: normal scheduler).
    pub priority: u32,
    /// Pinned CPU, or -1.
    pub cpu: i32,
    /// 1 when a real-time setting was missing (a degraded run).
    pub degraded: u32,
    /// 1 on a PREEMPT_RT kernel.
    pub preempt_rt: u32,
    /// Line state: 0 silent, 1 active, 2 failsafe.
    pub state: u32,
    /// Frame timing: 0 grid, 1 follow.
    pub timing: u32,
}

impl Default for TimingSnapshot {
    fn default() -> Self {
        TimingSnapshot {
            seq: 0,
            mono_ns: 0,
            uptime_ns: 0,
            frame_ns: 0,
            margin_ns: 0,
            frames: 0,
            edges: 0,
            commands: 0,
            overruns: 0,
            late_frames: 0,
            mismatched: 0,
            expired: 0,
            log_errors: 0,
            late_edges: 0,
            aborted_frames: 0,
            glitched_frames: 0,
            write_errors: 0,
            failsafe_entries: 0,
            repeats: 0,
            spin_share_ppm: 0,
            last: Summary::default(),
            total: Summary::default(),
            write: Summary::default(),
            hist_us: [0; HIST_BUCKETS],
            hist_overflow: 0,
            pid: 0,
            priority: 0,
            cpu: -1,
            degraded: 0,
            preempt_rt: 0,
            state: 0,
            timing: 0,
        }
    }
}

/// Setting up shared memory failed. Its message says what was being done;
/// iceoryx2's error is its [source](std::error::Error::source), so a log line
/// with the causes (`{:#}` of anyhow, [`Chain`](crate::logging::Chain))
/// shows both once.
#[derive(Debug, thiserror::Error)]
#[error("shared memory: {what}")]
pub struct IpcError {
    /// What was being done.
    pub what: String,
    /// iceoryx2's error, kept as its type.
    #[source]
    pub source: Box<dyn std::error::Error + Send + Sync>,
}

impl IpcError {
    /// `what` failed with iceoryx2's error `source`.
    pub fn new(
        what: impl Into<String>,
        source: impl std::error::Error + Send + Sync + 'static,
    ) -> IpcError {
        IpcError {
            what: what.into(),
            source: Box::new(source),
        }
    }
}

/// Publishing one sample (and the wake-up after a command) failed, with
/// iceoryx2's error as the source.
#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    /// No sample could be loaned from the shared memory.
    #[error("loaning a sample")]
    Loan(#[source] iceoryx2::port::LoanError),
    /// The sample could not be delivered.
    #[error("sending the sample")]
    Send(#[source] iceoryx2::port::SendError),
    /// The wake-up after a command ([`open_wake_service`]) could not be sent.
    #[error("waking ppmd")]
    Wake(#[source] iceoryx2::port::notifier::NotifierNotifyError),
}

/// A publisher on one of the newest-only services ([`open_command_service`],
/// [`open_stats_service`], [`open_line_service`]).
pub type Publisher<T> =
    iceoryx2::port::publisher::Publisher<iceoryx2::service::ipc::Service, T, ()>;

/// Publishes `value`: loans a sample, writes `value` into it and sends it.
/// Returns how many subscribers it reached.
pub fn publish<T: ZeroCopySend + std::fmt::Debug + Copy>(
    publisher: &Publisher<T>,
    value: T,
) -> Result<usize, PublishError> {
    let sample = publisher.loan_uninit().map_err(PublishError::Loan)?;
    sample
        .write_payload(value)
        .send()
        .map_err(PublishError::Send)
}

fn ipc_err<E: std::error::Error + Send + Sync + 'static>(
    what: impl Into<String>,
) -> impl FnOnce(E) -> IpcError {
    let what = what.into();
    move |e| IpcError::new(what, e)
}

/// Sets iceoryx2's own log level from `IOX2_LOG_LEVEL` (trace, debug, info,
/// warn, error, fatal), warn when unset.
pub fn init_ipc_logging() {
    iceoryx2::prelude::set_log_level_from_env_or(LogLevel::Warn);
}

/// Creates this process's iceoryx2 node with its bookkeeping under `root`
/// (created if missing). Creating a node also removes what dead ppm
/// processes left behind.
pub fn create_node(root: &std::path::Path, node_name: &str) -> Result<Node, IpcError> {
    let mut cfg = iceoryx2::config::Config::default();
    let root_str = root.to_string_lossy();
    let root_path = iceoryx2::prelude::Path::new(root_str.as_bytes())
        .map_err(ipc_err(format!("root path `{root_str}`")))?;
    cfg.global.set_root_path(&root_path);
    cfg.global.prefix = FileName::new(PREFIX).map_err(ipc_err("prefix"))?;
    let name = NodeName::new(node_name).map_err(ipc_err(format!("node name `{node_name}`")))?;
    NodeBuilder::new()
        .name(&name)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .config(&cfg)
        .create::<iceoryx2::service::ipc::Service>()
        .map_err(ipc_err(format!("creating node under `{root_str}`")))
}

/// Opens (or creates) the newest-only command service of output `name`.
pub fn open_command_service(node: &Node, name: &str) -> Result<CommandService, IpcError> {
    open_newest_only(node, &command_service_name(name))
}

/// Opens (or creates) output `name`'s wake-up event service: udp-ingress
/// notifies it after each command it publishes, so a ppmd in `follow`
/// timing can sleep until a command comes instead of polling. Every process
/// opens it with these settings.
pub fn open_wake_service(node: &Node, name: &str) -> Result<WakeService, IpcError> {
    let service = wake_service_name(name);
    let sn = ServiceName::new(&service).map_err(ipc_err(format!("service name `{service}`")))?;
    node.service_builder(&sn)
        .event()
        // udp-ingress (and a restarted one while the old one goes), and a
        // pilot's radio's thread in ppmd.
        .max_notifiers(3)
        .max_listeners(2)
        .open_or_create()
        .map_err(ipc_err(format!("opening service `{service}`")))
}

/// The timing snapshot service.
pub type StatsService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<
    iceoryx2::service::ipc::Service,
    TimingSnapshot,
    (),
>;

/// Opens (or creates) the newest-only timing snapshot service of output `name`.
pub fn open_stats_service(node: &Node, name: &str) -> Result<StatsService, IpcError> {
    open_newest_only(node, &stats_service_name(name))
}

/// Opens (or creates) a newest-only service: the subscriber holds one sample
/// and the newest overwrites it; a late subscriber gets the last published
/// sample. Every process must open it with these very settings, so all call
/// this function.
fn open_newest_only<T: ZeroCopySend + std::fmt::Debug + Copy + 'static>(
    node: &Node,
    service: &str,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<
        iceoryx2::service::ipc::Service,
        T,
        (),
    >,
    IpcError,
> {
    let sn = ServiceName::new(service).map_err(ipc_err(format!("service name `{service}`")))?;
    node.service_builder(&sn)
        .publish_subscribe::<T>()
        .subscriber_max_buffer_size(1)
        .history_size(1)
        .enable_safe_overflow(true)
        .max_publishers(2)
        .max_subscribers(4)
        .open_or_create()
        .map_err(ipc_err(format!("opening service `{service}`")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::protocol::parse;

    #[test]
    fn publish_reaches_a_subscriber_and_errors_keep_their_source() {
        let root = std::env::temp_dir().join(format!("ppm-ipc-test-{}", std::process::id()));
        let name = format!("ipctest{}", std::process::id());
        {
            let node = create_node(&root, &format!("{name}-node")).unwrap();
            let service = open_stats_service(&node, &name).unwrap();
            let publisher = service.publisher_builder().create().unwrap();
            let subscriber = service.subscriber_builder().create().unwrap();
            let snapshot = TimingSnapshot {
                seq: 7,
                frames: 42,
                ..TimingSnapshot::default()
            };
            assert_eq!(publish(&publisher, snapshot).unwrap(), 1, "one subscriber");
            let got = subscriber.receive().unwrap().expect("the published sample");
            assert_eq!(*got.payload(), snapshot);
        }
        let _ = std::fs::remove_dir_all(&root);
        // The message says what failed; iceoryx2's error is the source.
        let e = PublishError::Loan(iceoryx2::port::LoanError::OutOfMemory);
        assert_eq!(e.to_string(), "loaning a sample");
        let source = std::error::Error::source(&e).expect("a source");
        assert_eq!(source.to_string(), "LoanError::OutOfMemory");
        let e = IpcError::new(
            "opening service `x`",
            iceoryx2::port::LoanError::OutOfMemory,
        );
        assert_eq!(e.to_string(), "shared memory: opening service `x`");
        assert!(std::error::Error::source(&e).is_some());
    }

    #[test]
    fn round_trip_and_mismatch() {
        let m = Config::default().validate().unwrap();
        let cmd = parse(br#"{"ch": [1100, 1200.5], "seq": 9}"#, &m).unwrap();
        let s = CommandSample::new(&cmd, m.fingerprint(), 1, 5, 6);
        assert_eq!(s.seq(), Some(9));
        // Received at 5: fresh from a start at or before it, while no
        // older than the limit.
        assert!(s.fresh(5, 5, 0));
        assert!(s.fresh(0, 105, 100));
        assert!(!s.fresh(0, 106, 100), "older than the limit");
        assert!(!s.fresh(6, 6, 100), "received before the start");
        assert_eq!(s.channels(&m), Some(cmd.channels));
        let four =
            Config::parse("[ppm]\nchannels = 4\nframe_us = 12500\nreceiver = 'edgetx'").unwrap();
        assert_eq!(s.channels(&four.validate().unwrap()), None);
        // Same count, another meaning: refused.
        for other in [
            "[ppm]\norder = 'TAER'",
            "[ppm]\nmax_us = 1900",
            "[ppm.channel.thr]\ndefault_us = 1100",
            "[ppm.channel.ail]\nunit_min = -1\nunit_max = 1",
            "[ppm.channel.ele]\nreverse = true",
            "[ppm.channel.rud]\ntrim_us = 3",
        ] {
            let o = Config::parse(other).unwrap().validate().unwrap();
            assert_ne!(o.fingerprint(), m.fingerprint(), "{other}");
            assert_eq!(s.channels(&o), None, "{other}");
        }
        // What does not change a command's meaning keeps the fingerprint.
        for same in [
            "[ppm]\nframe_us = 21000",
            "[ppm]\ntiming = 'follow'\npulse_us = 400",
        ] {
            let o = Config::parse(same).unwrap().validate().unwrap();
            assert_eq!(s.channels(&o), Some(cmd.channels), "{same}");
        }
    }
}
