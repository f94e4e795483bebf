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
}

impl CommandSample {
    /// A sample carrying `cmd`, received at the given times.
    pub fn new(cmd: &Command, ingress_seq: u64, recv_mono_ns: u64, recv_real_ns: u64) -> Self {
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
        }
    }

    /// The sender's `seq`, if any.
    pub fn seq(&self) -> Option<u64> {
        (self.has_seq != 0).then_some(self.seq)
    }

    /// The channels, if the sample matches the frame model (same channel
    /// count); `None` means the publisher was configured differently.
    pub fn channels(&self, model: &FrameModel) -> Option<Channels> {
        let n = self.channel_count as usize;
        (n == model.channels()).then(|| Channels::from_ns(&self.values_ns[..n]))
    }
}

/// The iceoryx2 service carrying the newest command of output `name`.
pub fn command_service_name(name: &str) -> String {
    format!("ppm/{name}/command")
}

/// Setting up shared memory failed.
#[derive(Debug, thiserror::Error)]
#[error("shared memory: {what}: {detail}")]
pub struct IpcError {
    /// What was being done.
    pub what: String,
    /// iceoryx2's error.
    pub detail: String,
}

fn ipc_err(what: impl Into<String>) -> impl FnOnce(&dyn std::fmt::Debug) -> IpcError {
    let what = what.into();
    move |e| IpcError {
        what,
        detail: format!("{e:?}"),
    }
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
        .map_err(|e| ipc_err(format!("root path `{root_str}`"))(&e))?;
    cfg.global.set_root_path(&root_path);
    cfg.global.prefix = FileName::new(PREFIX).map_err(|e| ipc_err("prefix")(&e))?;
    let name =
        NodeName::new(node_name).map_err(|e| ipc_err(format!("node name `{node_name}`"))(&e))?;
    NodeBuilder::new()
        .name(&name)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .config(&cfg)
        .create::<iceoryx2::service::ipc::Service>()
        .map_err(|e| ipc_err(format!("creating node under `{root_str}`"))(&e))
}

/// Opens (or creates) the newest-only command service of output `name`:
/// the subscriber holds one sample and the newest overwrites it; a late
/// subscriber gets the last published sample. Both processes must open it
/// with these very settings, so both call this function.
pub fn open_command_service(node: &Node, name: &str) -> Result<CommandService, IpcError> {
    let service = command_service_name(name);
    let sn =
        ServiceName::new(&service).map_err(|e| ipc_err(format!("service name `{service}`"))(&e))?;
    node.service_builder(&sn)
        .publish_subscribe::<CommandSample>()
        .subscriber_max_buffer_size(1)
        .history_size(1)
        .enable_safe_overflow(true)
        .max_publishers(2)
        .max_subscribers(4)
        .open_or_create()
        .map_err(|e| ipc_err(format!("opening service `{service}`"))(&e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::protocol::parse;

    #[test]
    fn round_trip_and_mismatch() {
        let m = Config::default().validate().unwrap();
        let cmd = parse(br#"{"ch": [1100, 1200.5], "seq": 9}"#, &m).unwrap();
        let s = CommandSample::new(&cmd, 1, 5, 6);
        assert_eq!(s.seq(), Some(9));
        assert_eq!(s.channels(&m), Some(cmd.channels));
        let four = Config::parse("[ppm]\nchannels = 4\nframe_us = 12000").unwrap();
        assert_eq!(s.channels(&four.validate().unwrap()), None);
    }
}
