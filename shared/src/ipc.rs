//! Payload types carried through iceoryx2 shared memory, and service names.
//!
//! Payloads are `#[repr(C)]`, fixed size and `Copy`, with an explicit type
//! name, so both processes agree on the layout without any serialisation.

use crate::frame::{Channels, FrameModel, MAX_CHANNELS};
use crate::protocol::Command;
use iceoryx2::prelude::ZeroCopySend;

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
pub fn command_service(name: &str) -> String {
    format!("ppm/{name}/command")
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
