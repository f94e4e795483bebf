//! The status reply: what udp-ingress answers to `{"get": "status"}` (see
//! docs/status.md, "Status queries").
//!
//! One type for both sides of the contract: udp-ingress builds a
//! [`StatusReply`] and sends [`StatusReply::to_json`]; ppm-status, ppm-bench,
//! jitter and the tests read it back with `serde_json::from_str`. A member
//! renamed here is renamed for the writer and every reader at once.
//!
//! Members added since the first replies (`uptime_s`, `receiver`,
//! `status_short`, `publish_latency_us`, `seq_resets` and a few inside
//! `ppmd`) read as their default (zero, empty, absent) when an older
//! udp-ingress did not send them, so the tools still read its replies; a
//! reply without one of the others is not a status reply, and readers
//! refuse it.

use crate::protocol::RejectReason;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;

/// The whole reply to a status query.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusReply {
    /// The output's name.
    pub name: String,
    /// How long udp-ingress has run, s (to the ms).
    #[serde(default)]
    pub uptime_s: f64,
    /// How its receive thread runs (absent from replies of an older udp-ingress).
    #[serde(default)]
    pub receiver: Option<ReceiverStatus>,
    /// The counters of datagrams received.
    pub datagrams: Datagrams,
    /// Status queries received.
    pub status_requests: u64,
    /// Status replies not sent (send buffer full, or too many at once).
    pub status_dropped: u64,
    /// Status queries answered with `{"pad_to": N}`, or not at all.
    #[serde(default)]
    pub status_short: u64,
    /// The MAVLink side: datagrams without a command, ppm's replies.
    #[serde(default)]
    pub mavlink: MavlinkStatus,
    /// Age of the newest valid command, ms (to the us); `null` before the first.
    pub newest_command_age_ms: Option<f64>,
    /// The `seq` of the newest command applied that had one (the last
    /// numbered JSON command): commands without one, MAVLink's among them,
    /// leave it; `null` before the first.
    pub newest_seq: Option<u64>,
    /// Kernel receive to published, us, of every published command.
    #[serde(default)]
    pub publish_latency_us: PublishLatency,
    /// ppmd's timing summary; `null` without a fresh snapshot.
    pub ppmd: Option<PpmdStatus>,
    /// True when ppmd's newest snapshot is too old to be reported.
    pub ppmd_stale: bool,
    /// What the radio transmits, read back from the output's `readback`
    /// input; absent when none is configured (or from an older udp-ingress).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub readback: Option<ReadbackStatus>,
    /// What the flight controller sends back on a CRSF output's serial
    /// port; absent for other outputs (or from an older udp-ingress).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub telemetry: Option<crate::crsf::report::TelemetryStatus>,
}

/// The `readback` member of a status reply: whether the radio transmits
/// ppm's values (see docs/readback.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReadbackStatus {
    /// `following` (the radio transmits ppm's values, within the
    /// tolerance), `overridden` (it transmits something else: the
    /// instructor has control), `no_input` (no whole frame read for 1 s),
    /// or `stale` (ppmd has published nothing for a second).
    pub state: String,
    /// The input read (`ppmd.readback`).
    pub input: String,
    /// Time since the state last changed, ms; `null` before the first change.
    pub since_ms: Option<f64>,
    /// State changes since ppmd started.
    pub changes: u64,
    /// Edges read.
    pub edges: u64,
    /// Whole frames read.
    pub frames: u64,
    /// Frames read that carried ppm's values.
    pub matched: u64,
    /// Frames read that carried something else.
    pub mismatched: u64,
    /// Frames refused, by reason (`runts`, `noise`, `out_of_window`, ...).
    pub refused: BTreeMap<String, u64>,
    /// The newest frame read, us per channel.
    pub ch_us: Vec<f64>,
    /// Largest difference between it and the nearest value ppm's line
    /// carried, us.
    pub max_diff_us: Option<f64>,
    /// Age of the newest read-back sample, ms.
    pub age_ms: f64,
}

impl StatusReply {
    /// The reply's text, as sent: one JSON object with its keys sorted
    /// at every level (as replies have always had them, whatever the
    /// order of the fields here).
    pub fn to_json(&self) -> String {
        serde_json::to_value(self)
            .expect("a status reply has only string keys")
            .to_string()
    }
}

impl fmt::Display for StatusReply {
    /// The reply's text ([`StatusReply::to_json`]).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_json())
    }
}

/// How udp-ingress's receive thread runs: the `receiver` member.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ReceiverStatus {
    /// `epoll` (sleeps until datagrams arrive) or `busy_poll` (spins).
    pub wait: String,
    /// `fifo` (SCHED_FIFO) or `other`.
    pub policy: String,
    /// SCHED_FIFO priority obtained; 0 under the normal scheduler.
    #[serde(default)]
    pub priority: u64,
    /// The CPU it is pinned to, if any.
    #[serde(default)]
    pub cpu: Option<u64>,
    /// A setting asked for could not be had (a degraded run).
    #[serde(default)]
    pub degraded: bool,
}

/// The `datagrams` member: what became of every datagram received.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Datagrams {
    /// Datagrams received, status queries excepted.
    pub received: u64,
    /// Valid commands handed to ppmd.
    pub applied: u64,
    /// Rejected datagrams, by reason.
    pub rejected: Rejected,
    /// Accepted commands with at least one value clamped.
    pub clamped: u64,
    /// Values clamped in all accepted commands.
    pub clamped_values: u64,
    /// Commands whose `seq` was not greater than the last applied.
    pub stale: u64,
    /// Times the `seq` gate forgot the last `seq`.
    #[serde(default)]
    pub seq_resets: u64,
    /// Valid commands replaced by a newer one before publishing.
    pub superseded: u64,
}

/// Rejected datagrams by reason: an object from each reason's name
/// ([`RejectReason::as_str`]) to its count. Reasons this build does not
/// know (from a newer udp-ingress) are kept.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Rejected(pub BTreeMap<String, u64>);

impl Rejected {
    /// Every reason with its count, from counts indexed by [`RejectReason::index`].
    pub fn from_counts(counts: &[u64; RejectReason::ALL.len()]) -> Rejected {
        Rejected(
            RejectReason::ALL
                .iter()
                .map(|r| (r.as_str().to_string(), counts[r.index()]))
                .collect(),
        )
    }

    /// The count of one reason (0 when the reply lacks it).
    pub fn count(&self, reason: RejectReason) -> u64 {
        self.0.get(reason.as_str()).copied().unwrap_or(0)
    }

    /// All rejected datagrams.
    pub fn total(&self) -> u64 {
        self.0.values().sum()
    }
}

/// The `mavlink` member.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MavlinkStatus {
    /// MAVLink datagrams without a command (HEARTBEATs, requests): not in
    /// `datagrams.received`.
    pub no_command: u64,
    /// Well-formed MAVLink frames of messages a groundstation sends any
    /// vehicle that ppm does not act on (SYSTEM_TIME, TIMESYNC, mission and
    /// parameter requests, ...): read and ignored, not rejected.
    pub ignored: u64,
    /// Groundstations getting replies (heard from within 5 s).
    pub peers: u64,
    /// Reply frames sent (HEARTBEAT, RC_CHANNELS, COMMAND_ACK,
    /// PARAM_VALUE).
    pub sent: u64,
    /// Reply frames not sent: not earned by what the peer sent, or the
    /// socket's buffer was full.
    pub held: u64,
}

/// The `publish_latency_us` member: kernel receive to published, us.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PublishLatency {
    /// Commands published.
    pub count: u64,
    /// Median, us.
    pub p50: f64,
    /// 99th percentile, us.
    pub p99: f64,
    /// Largest, us.
    pub max: f64,
}

/// The `ppmd` member: a summary of ppmd's newest timing snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PpmdStatus {
    /// The line's state (`active`, `failsafe`, ...; `unknown` for a code
    /// this build does not know).
    pub state: String,
    /// `grid` or `follow`.
    #[serde(default)]
    pub timing: String,
    /// Frames emitted.
    pub frames: u64,
    /// Frames that repeated the previous command (follow timing).
    #[serde(default)]
    pub repeats: u64,
    /// Edge error (actual minus scheduled), us.
    pub edge_error_us: EdgeError,
    /// Edges that could not be met.
    pub overruns: u64,
    /// Frames that started late.
    pub late_frames: u64,
    /// Frames cut short.
    #[serde(default)]
    pub aborted_frames: u64,
    /// Frames with a glitched edge.
    #[serde(default)]
    pub glitched_frames: u64,
    /// Commands refused for another channel model.
    #[serde(default)]
    pub mismatched_commands: u64,
    /// Commands too old to apply.
    #[serde(default)]
    pub expired_commands: u64,
    /// Log rows or intervals not written.
    #[serde(default)]
    pub log_errors: u64,
    /// Times the line entered its failsafe.
    pub failsafe_entries: u64,
    /// ppmd runs without a real-time setting it asked for.
    #[serde(default)]
    pub degraded: bool,
    /// Age of the snapshot when the reply was built, ms.
    pub snapshot_age_ms: f64,
}

/// The `edge_error_us` member of [`PpmdStatus`], us.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct EdgeError {
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest.
    pub max: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The text a udp-ingress sent before the reply had a type, read and
    /// written back: the same bytes.
    #[test]
    fn a_reply_reads_and_writes_back_to_the_same_text() {
        let text = r#"{"datagrams":{"applied":2,"clamped":1,"clamped_values":2,"received":6,"rejected":{"bad_mac":0,"bad_shape":1,"invalid_json":1,"invalid_utf8":0,"mavlink_bad_crc":0,"mavlink_bad_length":0,"mavlink_junk":0,"mavlink_truncated":0,"mavlink_unknown_message":0,"no_seq":0,"no_to":0,"not_a_number":0,"not_allowed":0,"out_of_range":0,"replay":0,"too_many_values":0,"unknown_channel":0,"unsigned":0,"wrong_output":0},"seq_resets":0,"stale":1,"superseded":1},"mavlink":{"held":0,"ignored":0,"no_command":0,"peers":0,"sent":0},"name":"pi","newest_command_age_ms":7.0,"newest_seq":null,"ppmd":{"aborted_frames":4,"degraded":true,"edge_error_us":{"max":17000.4,"p50":0.031,"p99":1.25},"expired_commands":0,"failsafe_entries":3,"frames":400,"glitched_frames":5,"late_frames":2,"log_errors":0,"mismatched_commands":0,"overruns":1,"repeats":0,"snapshot_age_ms":250.0,"state":"active","timing":"grid"},"ppmd_stale":false,"publish_latency_us":{"count":0,"max":0.0,"p50":0.0,"p99":0.0},"receiver":{"cpu":1,"degraded":true,"policy":"fifo","priority":70,"wait":"busy_poll"},"status_dropped":1,"status_requests":1,"status_short":0,"uptime_s":2345.678}"#;
        let reply: StatusReply = serde_json::from_str(text).unwrap();
        assert_eq!(reply.to_json(), text);
        assert_eq!(reply.to_string(), text);
        assert_eq!(reply.datagrams.rejected.count(RejectReason::BadShape), 1);
        assert_eq!(reply.datagrams.rejected.total(), 2);
        assert_eq!(reply.ppmd.as_ref().unwrap().edge_error_us.p99, 1.25);
    }

    #[test]
    fn rejected_counts_name_every_reason() {
        let mut counts = [0; RejectReason::ALL.len()];
        counts[RejectReason::Replay.index()] = 3;
        let r = Rejected::from_counts(&counts);
        assert_eq!(r.0.len(), RejectReason::ALL.len());
        assert_eq!(r.count(RejectReason::Replay), 3);
        assert_eq!(r.count(RejectReason::NoTo), 0);
        assert_eq!(
            serde_json::to_value(&r).unwrap()["replay"],
            serde_json::json!(3)
        );
    }
}
