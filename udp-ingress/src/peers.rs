//! The MAVLink groundstations udp-ingress talks back to: after a peer's
//! first good MAVLink datagram, a HEARTBEAT a second in the peer's MAVLink
//! version, so that a groundstation sees ppm as a vehicle; and to a
//! PARAM_REQUEST_LIST, ppm's one parameter, `PPM_CHANNELS` (the channel
//! count), which QGroundControl waits for before it offers its joystick.
//!
//! No peer gets more than [`REPLY_MAX_RATIO`] times the bytes it sent (a
//! credit, capped at [`CREDIT_MAX`] bytes), unless it lies in
//! `ingress.status_allow`: a forged source address earns its victim at most
//! three times what the forger sent, as status replies do. A peer silent
//! for [`PEER_TIMEOUT`] gets nothing more; at most [`MAX_PEERS`] are kept,
//! the one heard from longest ago making room.
//!
//! Logic only, without I/O: the server sends what [`Peers::due`] gives.

use ppm_shared::mavlink::{self, HEARTBEAT, PARAM_VALUE};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// Most peers kept.
pub const MAX_PEERS: usize = 4;
/// A peer not heard from for this long gets no more replies.
pub const PEER_TIMEOUT: Duration = Duration::from_secs(5);
/// The HEARTBEAT interval.
pub const HEARTBEAT_EVERY: Duration = Duration::from_secs(1);
/// A peer earns this many bytes of replies for each byte it sent.
pub const REPLY_MAX_RATIO: usize = 3;
/// Most reply bytes a peer can have earned and not used.
pub const CREDIT_MAX: usize = 4_096;

/// ppm's HEARTBEAT type: MAV_TYPE_GENERIC (0), a vehicle of no particular
/// kind (an RC vehicle flown through its transmitter).
pub const MAV_TYPE: u8 = 0;
/// ppm's HEARTBEAT autopilot: MAV_AUTOPILOT_GENERIC (0).
pub const MAV_AUTOPILOT: u8 = 0;

/// The line's state as MAV_STATE: STANDBY (3) while silent, ACTIVE (4)
/// while commands fly, CRITICAL (5) in the failsafe.
pub fn mav_state(line: Option<ppm_shared::line::LineState>) -> u8 {
    use ppm_shared::line::LineState;
    match line {
        Some(LineState::Active) => 4,
        Some(LineState::Failsafe) => 5,
        _ => 3,
    }
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Peer {
    addr: SocketAddr,
    version: u8,
    last_heard: Instant,
    credit: usize,
    exempt: bool,
    /// It asked for the parameters.
    params_due: bool,
}

/// Counters of the replies.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplyCounters {
    /// Frames sent (handed to the socket).
    pub sent: u64,
    /// Frames not sent: the peer had not earned them (or the socket's
    /// buffer was full).
    pub held: u64,
}

/// The peers and their HEARTBEAT schedule.
#[derive(Debug)]
pub struct Peers {
    peers: Vec<Peer>,
    system_id: u8,
    component_id: u8,
    /// The PARAM_VALUE payload of `PPM_CHANNELS`.
    param_value: [u8; 25],
    next_heartbeat: Option<Instant>,
    seq: u8,
    counters: ReplyCounters,
}

impl Peers {
    /// No peers yet; replies come from `system_id` / `component_id`, for
    /// an output of `channels` channels.
    pub fn new(system_id: u8, component_id: u8, channels: usize) -> Peers {
        // PARAM_VALUE: value (f32), count 1, index 0, id (16 chars), type
        // REAL32 (9).
        let mut param_value = [0u8; 25];
        param_value[..4].copy_from_slice(&(channels as f32).to_le_bytes());
        param_value[4] = 1;
        param_value[8..20].copy_from_slice(b"PPM_CHANNELS");
        param_value[24] = 9;
        Peers {
            peers: Vec::with_capacity(MAX_PEERS),
            system_id,
            component_id,
            param_value,
            next_heartbeat: None,
            seq: 0,
            counters: ReplyCounters::default(),
        }
    }

    /// A good MAVLink datagram of `len` bytes in `version` came from `addr`
    /// (`exempt`: it lies in `ingress.status_allow`).
    pub fn heard(&mut self, addr: SocketAddr, version: u8, len: usize, exempt: bool, now: Instant) {
        let earned = len.saturating_mul(REPLY_MAX_RATIO);
        if let Some(p) = self.peers.iter_mut().find(|p| p.addr == addr) {
            p.version = version;
            p.last_heard = now;
            p.credit = (p.credit + earned).min(CREDIT_MAX);
            p.exempt = exempt;
            return;
        }
        if self.peers.len() == MAX_PEERS {
            let oldest = (0..self.peers.len())
                .min_by_key(|&i| self.peers[i].last_heard)
                .expect("MAX_PEERS > 0");
            self.peers.swap_remove(oldest);
        }
        self.peers.push(Peer {
            addr,
            version,
            last_heard: now,
            credit: earned.min(CREDIT_MAX),
            exempt,
            params_due: false,
        });
        // The first HEARTBEAT goes out at once: a groundstation shows the
        // vehicle without waiting a second.
        if self.next_heartbeat.is_none_or(|t| t > now) {
            self.next_heartbeat = Some(now);
        }
    }

    /// How many peers are kept (those heard from within [`PEER_TIMEOUT`]
    /// at the last [`Peers::due`]).
    pub fn known(&self) -> usize {
        self.peers.len()
    }

    /// Peer `addr` (just [`Peers::heard`]) asked for the parameters: the
    /// next [`Peers::due`] answers.
    pub fn request_params(&mut self, addr: SocketAddr) {
        if let Some(p) = self.peers.iter_mut().find(|p| p.addr == addr) {
            p.params_due = true;
        }
    }

    /// The frames due at `now` and where they go (appended to `out`): a
    /// HEARTBEAT for each live peer with the credit for it, once per
    /// [`HEARTBEAT_EVERY`]. `state` is the line's MAV_STATE ([`mav_state`]).
    ///
    /// With `signing` (`mavlink.key_file`), every frame is signed, at the
    /// clock's signature timestamp `ts` or after.
    pub fn due(
        &mut self,
        now: Instant,
        state: u8,
        mut signing: Option<&mut mavlink::Signing>,
        ts: u64,
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) {
        self.peers
            .retain(|p| now.saturating_duration_since(p.last_heard) < PEER_TIMEOUT);
        let param = self.param_value;
        for i in 0..self.peers.len() {
            if std::mem::take(&mut self.peers[i].params_due) {
                self.reply(i, &PARAM_VALUE, &param, signing.as_deref_mut(), ts, out);
            }
        }
        let Some(at) = self.next_heartbeat else {
            return;
        };
        if now < at {
            return;
        }
        if self.peers.is_empty() {
            self.next_heartbeat = None;
            return;
        }
        // The next one a whole interval after this one was due, or after
        // now when the loop fell behind by more than an interval.
        let next = at + HEARTBEAT_EVERY;
        self.next_heartbeat = Some(if next > now {
            next
        } else {
            now + HEARTBEAT_EVERY
        });
        // custom_mode 0, type, autopilot, base_mode 0, system_status,
        // mavlink_version 3.
        let payload = [0, 0, 0, 0, MAV_TYPE, MAV_AUTOPILOT, 0, state, 3];
        for i in 0..self.peers.len() {
            self.reply(i, &HEARTBEAT, &payload, signing.as_deref_mut(), ts, out);
        }
    }

    /// One frame from ppm to peer `i`, numbered, in its version or signed
    /// with `signing` if given, handed on (to `out`) if the peer earned it.
    fn reply(
        &mut self,
        i: usize,
        spec: &mavlink::Spec,
        payload: &[u8],
        signing: Option<&mut mavlink::Signing>,
        ts: u64,
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) {
        let seq = self.seq;
        self.seq = self.seq.wrapping_add(1);
        let header = (seq, self.system_id, self.component_id);
        let frame = match signing {
            Some(s) => s.frame(header, spec, payload, ts),
            None => mavlink::frame(self.peers[i].version, header, spec, payload),
        };
        let p = &mut self.peers[i];
        if !p.exempt && p.credit < frame.len() {
            self.counters.held += 1;
            return;
        }
        if !p.exempt {
            p.credit -= frame.len();
        }
        self.counters.sent += 1;
        out.push((p.addr, frame));
    }

    /// A frame [`Peers::due`] gave could not be sent.
    pub fn not_sent(&mut self) {
        self.counters.sent -= 1;
        self.counters.held += 1;
    }

    /// The counters so far.
    pub fn counters(&self) -> ReplyCounters {
        self.counters
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([192, 0, 2, 1], port))
    }

    /// The port and MAVLink version of each HEARTBEAT sent.
    fn heartbeats(out: &[(SocketAddr, Vec<u8>)]) -> Vec<(u16, u8)> {
        out.iter()
            .map(|(a, f)| {
                let (h, m, len) = mavlink::read_frame(f).expect("a good frame");
                assert_eq!((m, len), (mavlink::Message::Heartbeat, f.len()));
                (a.port(), h.version)
            })
            .collect()
    }

    #[test]
    fn a_peer_gets_a_heartbeat_a_second_in_its_version_while_it_is_heard() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8);
        let mut out = vec![];
        p.due(t, 3, None, 0, &mut out);
        assert!(out.is_empty(), "no peer, no heartbeat");
        p.heard(addr(1), 2, 40, false, t);
        p.heard(addr(2), 1, 40, false, t);
        p.due(t, 4, None, 0, &mut out);
        assert_eq!(heartbeats(&out), [(1, 2), (2, 1)]);
        // From ppm's ids, GENERIC type and autopilot, the line's state.
        let (h, _, _) = mavlink::read_frame(&out[0].1).unwrap();
        assert_eq!((h.sysid, h.compid, h.seq), (1, 1, 0));
        let payload = &out[0].1[10..19];
        assert_eq!(payload, [0, 0, 0, 0, MAV_TYPE, MAV_AUTOPILOT, 0, 4, 3]);
        out.clear();
        p.due(t + Duration::from_millis(999), 4, None, 0, &mut out);
        assert!(out.is_empty(), "one a second");
        for s in 1..5u64 {
            // Peer 1 keeps talking; peer 2 fell silent at t.
            p.heard(addr(1), 2, 40, false, t + Duration::from_secs(s));
            p.due(t + Duration::from_secs(s), 4, None, 0, &mut out);
        }
        let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
        assert_eq!(ports, [1, 2, 1, 2, 1, 2, 1, 2], "{out:?}");
        out.clear();
        p.due(t + Duration::from_secs(5), 4, None, 0, &mut out);
        let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
        assert_eq!(ports, [1], "peer 2 silent for PEER_TIMEOUT");
        assert_eq!(p.known(), 1);
        assert_eq!(p.counters(), ReplyCounters { sent: 11, held: 0 });
    }

    #[test]
    fn a_peer_gets_at_most_three_times_what_it_sent_unless_exempt() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8);
        let mut out = vec![];
        // One forged 10-byte datagram earns 30 bytes: one MAVLink 2
        // HEARTBEAT (21 bytes), not two.
        p.heard(addr(1), 2, 10, false, t);
        p.heard(addr(2), 2, 10, true, t);
        for s in 0..4u64 {
            p.due(t + Duration::from_millis(1_000 * s), 3, None, 0, &mut out);
        }
        let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
        assert_eq!(ports, [1, 2, 2, 2, 2]);
        assert_eq!(p.counters(), ReplyCounters { sent: 5, held: 3 });
        let sent: usize = out
            .iter()
            .filter(|(a, _)| a.port() == 1)
            .map(|(_, f)| f.len())
            .sum();
        assert!(sent <= 10 * REPLY_MAX_RATIO);
    }

    /// pymavlink 2.4.50's param_value_send(b"PPM_CHANNELS", 8.0, 9, 1, 0)
    /// from system 1, component 1, MAVLink 2.
    const PYMAVLINK_PARAM_VALUE: [u8; 37] = [
        0xfd, 0x19, 0x00, 0x00, 0x00, 0x01, 0x01, 0x16, 0x00, 0x00, 0x00, 0x00, 0x00, 0x41, 0x01,
        0x00, 0x00, 0x00, 0x50, 0x50, 0x4d, 0x5f, 0x43, 0x48, 0x41, 0x4e, 0x4e, 0x45, 0x4c, 0x53,
        0x00, 0x00, 0x00, 0x00, 0x09, 0x34, 0x00,
    ];

    #[test]
    fn a_request_for_the_parameters_gets_ppms_one_parameter() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8);
        let mut out = vec![];
        p.request_params(addr(1));
        p.due(t, 3, None, 0, &mut out);
        assert!(out.is_empty(), "only a peer is answered");
        p.heard(addr(1), 2, 14, false, t);
        p.request_params(addr(1));
        p.due(t, 3, None, 0, &mut out);
        // The PARAM_VALUE (numbered 0) first; the HEARTBEAT is held: the
        // 14-byte request earned 42 bytes, the PARAM_VALUE took 37.
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].1, PYMAVLINK_PARAM_VALUE);
        assert_eq!(p.counters(), ReplyCounters { sent: 1, held: 1 });
        // Once per request.
        out.clear();
        p.heard(addr(1), 2, 14, false, t + Duration::from_secs(1));
        p.due(t + Duration::from_secs(1), 3, None, 0, &mut out);
        assert_eq!(out.len(), 1);
        assert_eq!(
            mavlink::read_frame(&out[0].1).unwrap().1,
            mavlink::Message::Heartbeat
        );
    }

    #[test]
    fn the_line_state_is_the_heartbeats_system_status() {
        use ppm_shared::line::LineState;
        assert_eq!(mav_state(None), 3);
        assert_eq!(mav_state(Some(LineState::Silent)), 3);
        assert_eq!(mav_state(Some(LineState::Active)), 4);
        assert_eq!(mav_state(Some(LineState::Failsafe)), 5);
    }

    #[test]
    fn the_peer_heard_longest_ago_makes_room() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8);
        for i in 0..=MAX_PEERS as u16 {
            p.heard(addr(i), 2, 100, false, t + Duration::from_millis(i as u64));
        }
        let mut out = vec![];
        p.due(t + Duration::from_millis(10), 3, None, 0, &mut out);
        let mut ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
        ports.sort();
        assert_eq!(ports, (1..=MAX_PEERS as u16).collect::<Vec<_>>());
    }
}
