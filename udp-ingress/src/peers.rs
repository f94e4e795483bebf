//! The MAVLink groundstations udp-ingress talks back to: after a peer's
//! first good MAVLink datagram, a HEARTBEAT a second in the peer's MAVLink
//! version, so that a groundstation sees ppm as a vehicle; RC_CHANNELS
//! (what the radio transmits, read back, with a read-back; the values on
//! the line without one) and SERVO_OUTPUT_RAW (the values on the line),
//! each at `mavlink.rc_channels_hz` or the rate the peer asks for
//! (MAV_CMD_SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM); a STATUSTEXT for
//! each read-back state change ([`Peers::announce`]); a COMMAND_ACK to
//! each COMMAND_LONG; and to a PARAM_REQUEST_LIST, ppm's one parameter,
//! `PPM_CHANNELS` (the channel count), which QGroundControl waits for
//! before it offers its joystick.
//!
//! No peer gets more than [`REPLY_MAX_RATIO`] times the bytes it sent (a
//! credit, capped at [`CREDIT_MAX`] bytes), unless it lies in
//! `ingress.status_allow`: a forged source address earns its victim at most
//! three times what the forger sent, as status replies do. RC_CHANNELS and
//! SERVO_OUTPUT_RAW leave [`HEARTBEATS_KEPT`] HEARTBEATs' worth of the
//! credit unspent (a STATUSTEXT one HEARTBEAT's, and waits for the credit
//! it needs), so a
//! groundstation that sends little (its own HEARTBEAT a second) gets ppm's
//! every second, whatever the phase of its datagrams against ppm's timers.
//! A peer silent
//! for [`PEER_TIMEOUT`] gets nothing more; at most [`MAX_PEERS`] are kept,
//! the one heard from longest ago making room.
//!
//! Logic only, without I/O: the server sends what [`Peers::due`] gives.

use ppm_shared::mavlink::{
    self, CommandLong, Header, Message, COMMAND_ACK, HEARTBEAT, PARAM_VALUE, PROTOCOL_VERSION,
    RC_CHANNELS, SERVO_OUTPUT_RAW, STATUSTEXT,
};
use std::collections::VecDeque;
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
/// RC_CHANNELS leave this many of a peer's HEARTBEATs' worth of its credit
/// unspent: what the peer earned goes to ppm's HEARTBEAT first, whenever
/// its own datagrams come. One would do for a peer whose datagrams keep
/// their phase against ppm's beat; two also pay for a beat in a second
/// that brought none of them (its datagram a little late, the next
/// second's two), as jitter and drift between two clocks bring.
pub const HEARTBEATS_KEPT: usize = 2;
/// Most reply bytes a peer can have earned and not used.
pub const CREDIT_MAX: usize = 4_096;
/// Most STATUSTEXT chunks kept for a peer that has not earned them yet;
/// the oldest makes room (counted as held).
pub const TEXTS_KEPT: usize = 8;

/// The shortest RC_CHANNELS (or SERVO_OUTPUT_RAW) interval a peer can ask
/// for (ppmd publishes its line every tenth of a second).
pub const RC_CHANNELS_MIN_EVERY: Duration =
    Duration::from_millis(1_000 / mavlink::RC_CHANNELS_MAX_HZ as u64);
/// MAV_RESULT_ACCEPTED.
pub const MAV_RESULT_ACCEPTED: u8 = 0;
/// MAV_RESULT_DENIED: a command ppm knows, with a parameter it cannot
/// take (a message it does not send).
pub const MAV_RESULT_DENIED: u8 = 2;
/// MAV_RESULT_UNSUPPORTED: a command ppm does not know.
pub const MAV_RESULT_UNSUPPORTED: u8 = 3;

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
    /// COMMAND_ACKs due: command, result, and the sender (system,
    /// component).
    acks: Vec<(u16, u8, (u8, u8))>,
    /// Its RC_CHANNELS.
    rc: Stream,
    /// Its SERVO_OUTPUT_RAW.
    servo: Stream,
    /// STATUSTEXT payloads not sent yet (not yet earned), oldest first.
    texts: VecDeque<[u8; 54]>,
    /// It asked for PROTOCOL_VERSION.
    protocol_now: bool,
    /// The sequence number of the next frame it gets (counted per peer,
    /// and only for frames sent, so that it sees no gap).
    seq: u8,
}

/// A message a peer gets at an interval (RC_CHANNELS, SERVO_OUTPUT_RAW).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Stream {
    /// Its interval (`None`: none).
    every: Option<Duration>,
    /// When the next is due.
    next: Instant,
    /// It asked for one now (MAV_CMD_REQUEST_MESSAGE).
    now: bool,
}

impl Stream {
    fn new(every: Option<Duration>, now: Instant) -> Stream {
        Stream {
            every,
            next: now,
            now: false,
        }
    }

    /// Whether one is due at `now`, and whether it was asked for (an
    /// answer, earned by its request); moves the schedule on.
    fn due(&mut self, now: Instant) -> Option<bool> {
        let scheduled = self.every.filter(|_| now >= self.next);
        if let Some(every) = scheduled {
            self.next = later(self.next, every, now);
        }
        let asked = std::mem::take(&mut self.now);
        (asked || scheduled.is_some()).then_some(asked)
    }
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
    /// The RC_CHANNELS interval of a peer that did not ask for one.
    rc_default: Option<Duration>,
    /// The HEARTBEAT's MAV_TYPE (`mavlink.vehicle_type`; by default
    /// MAV_TYPE_GENERIC, 0: a vehicle of no particular kind).
    mav_type: u8,
    /// The `id` of the next STATUSTEXT sent in chunks (never 0).
    text_id: u16,
    counters: ReplyCounters,
}

/// Channel values of one frame, for the replies.
#[derive(Debug, Clone, Copy)]
pub struct Frame<'a> {
    /// The values, us (empty: no frame).
    pub values_us: &'a [u16],
    /// The frame's start on CLOCK_MONOTONIC, us (RC_CHANNELS'
    /// `time_boot_ms` in ms, SERVO_OUTPUT_RAW's `time_usec`).
    pub at_us: u64,
}

/// What the line carries now (and what the radio transmits), for the
/// replies.
#[derive(Debug, Clone, Copy)]
pub struct LineNow<'a> {
    /// The line's MAV_STATE ([`mav_state`]).
    pub state: u8,
    /// The newest frame on the line (SERVO_OUTPUT_RAW; and RC_CHANNELS
    /// without a read-back).
    pub line: Frame<'a>,
    /// With a read-back: the newest frame the radio transmits
    /// (RC_CHANNELS); `None` without one.
    pub radio: Option<Frame<'a>>,
}

/// The interval of `hz` messages a second (`None` for 0), no shorter than
/// [`RC_CHANNELS_MIN_EVERY`].
fn every_of_hz(hz: f64) -> Option<Duration> {
    (hz > 0.0).then(|| Duration::from_secs_f64(1.0 / hz).max(RC_CHANNELS_MIN_EVERY))
}

impl Peers {
    /// No peers yet; replies come from `system_id` / `component_id`, for
    /// an output of `channels` channels, with RC_CHANNELS `rc_hz` times a
    /// second to a peer that asks for no other rate.
    pub fn new(system_id: u8, component_id: u8, channels: usize, rc_hz: u8) -> Peers {
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
            rc_default: every_of_hz(rc_hz as f64),
            mav_type: 0,
            text_id: 1,
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
            acks: Vec::new(),
            rc: Stream::new(self.rc_default, now),
            servo: Stream::new(self.rc_default, now),
            texts: VecDeque::new(),
            protocol_now: false,
            seq: 0,
        });
        // The first HEARTBEAT goes out at once: a groundstation shows the
        // vehicle without waiting a second.
        if self.next_heartbeat.is_none_or(|t| t > now) {
            self.next_heartbeat = Some(now);
        }
    }

    /// Its HEARTBEAT says it is a vehicle of MAV_TYPE `mav_type`.
    pub fn with_mav_type(mut self, mav_type: u8) -> Peers {
        self.mav_type = mav_type;
        self
    }

    /// How many peers are kept (those heard from within [`PEER_TIMEOUT`]
    /// at the last [`Peers::due`]).
    pub fn known(&self) -> usize {
        self.peers.len()
    }

    /// Peer `addr` (just [`Peers::heard`]) sent request `message` (header
    /// `h`): the next [`Peers::due`] answers it. Requests for another
    /// system or component are not answered.
    pub fn request(&mut self, addr: SocketAddr, h: &Header, message: &Message) {
        let ours = |s: u8, c: u8| {
            mavlink::addressed(s, self.system_id) && mavlink::addressed(c, self.component_id)
        };
        let rc_default = self.rc_default;
        let Some(p) = self.peers.iter_mut().find(|p| p.addr == addr) else {
            return;
        };
        match *message {
            Message::ParamRequestList(s, c) if ours(s, c) => p.params_due = true,
            Message::RequestDataStream(r)
                if ours(r.target_system, r.target_component)
                    && (r.stream == mavlink::MAV_DATA_STREAM_ALL
                        || r.stream == mavlink::MAV_DATA_STREAM_RC_CHANNELS) =>
            {
                let every = if r.start {
                    every_of_hz(r.rate_hz as f64)
                } else {
                    None
                };
                p.rc.every = every;
                p.servo.every = every;
            }
            Message::CommandLong(c) if ours(c.target_system, c.target_component) => {
                let result = command_result(&c, p, rc_default);
                if p.acks.len() < 8 {
                    p.acks.push((c.command, result, (h.sysid, h.compid)));
                }
            }
            _ => {}
        }
    }

    /// A STATUSTEXT of `text` at `severity` (a MAV_SEVERITY) for every
    /// peer, in chunks if it is longer than one carries
    /// ([`mavlink::statustext_payloads`]): the next [`Peers::due`] sends
    /// it to each that has earned it; one that has not gets it once it has
    /// (at most [`TEXTS_KEPT`] chunks wait, the oldest making room).
    pub fn announce(&mut self, severity: u8, text: &str) {
        let payloads = mavlink::statustext_payloads(severity, text, self.text_id);
        if payloads.len() > 1 {
            self.text_id = self.text_id.checked_add(1).unwrap_or(1);
        }
        for p in &mut self.peers {
            for payload in &payloads {
                if p.texts.len() == TEXTS_KEPT {
                    p.texts.pop_front();
                    self.counters.held += 1;
                }
                p.texts.push_back(*payload);
            }
        }
    }

    /// The frames due at `now` and where they go (appended to `out`), to
    /// each live peer with the credit for it: answers to its requests first
    /// (PARAM_VALUE, COMMAND_ACK, PROTOCOL_VERSION, an RC_CHANNELS or
    /// SERVO_OUTPUT_RAW asked for: each request earns three times its
    /// size, more than its answer), then the STATUSTEXTs announced, from
    /// what is left beyond one HEARTBEAT (one not earned yet waits), then a
    /// HEARTBEAT once per [`HEARTBEAT_EVERY`], then its RC_CHANNELS and
    /// SERVO_OUTPUT_RAW when due, from what is left beyond
    /// [`HEARTBEATS_KEPT`] HEARTBEATs: a groundstation that earns little
    /// keeps getting the HEARTBEAT, even when its datagrams come just after
    /// ppm's beat and an RC_CHANNELS is due before the next. `line` is what
    /// the line carries (and the radio transmits).
    ///
    /// With `signing` (`mavlink.key_file`), every frame is signed, at the
    /// clock's signature timestamp `ts` or after.
    pub fn due(
        &mut self,
        now: Instant,
        line: LineNow<'_>,
        mut signing: Option<&mut mavlink::Signing>,
        ts: u64,
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) {
        let mut dropped = 0;
        self.peers.retain(|p| {
            let live = now.saturating_duration_since(p.last_heard) < PEER_TIMEOUT;
            if !live {
                dropped += p.texts.len() as u64;
            }
            live
        });
        self.counters.held += dropped;
        let param = self.param_value;
        let radio = line.radio.unwrap_or(line.line);
        let rc = mavlink::rc_channels_payload((radio.at_us / 1_000) as u32, radio.values_us);
        let servo =
            mavlink::servo_output_raw_payload(line.line.at_us as u32, 0, line.line.values_us);
        for i in 0..self.peers.len() {
            if std::mem::take(&mut self.peers[i].params_due) {
                self.reply(i, &PARAM_VALUE, &param, signing.as_deref_mut(), ts, out);
            }
            for (command, result, to) in std::mem::take(&mut self.peers[i].acks) {
                let ack = mavlink::command_ack_payload(command, result, to);
                self.reply(i, &COMMAND_ACK, &ack, signing.as_deref_mut(), ts, out);
            }
            if std::mem::take(&mut self.peers[i].protocol_now) {
                let v = mavlink::protocol_version_payload();
                self.reply(i, &PROTOCOL_VERSION, &v, signing.as_deref_mut(), ts, out);
            }
            let keep = heartbeat_len(self.peers[i].version, signing.is_some());
            while let Some(text) = self.peers[i].texts.front().copied() {
                let frame = self.build(i, &STATUSTEXT, &text, signing.as_deref_mut(), ts);
                if !self.earned(i, frame.len() + keep) {
                    break;
                }
                self.peers[i].texts.pop_front();
                self.send(i, frame, out);
            }
        }
        self.heartbeats(now, line.state, signing.as_deref_mut(), ts, out);
        for i in 0..self.peers.len() {
            let kept = HEARTBEATS_KEPT * heartbeat_len(self.peers[i].version, signing.is_some());
            // One asked for is an answer, earned by its request; the
            // stream's leave the HEARTBEATs' bytes, and SERVO_OUTPUT_RAW
            // those of the peer's next RC_CHANNELS too.
            if let Some(asked) = self.peers[i].rc.due(now) {
                let keep = if asked { 0 } else { kept };
                self.reply_keeping(i, &RC_CHANNELS, &rc, keep, signing.as_deref_mut(), ts, out);
            }
            let p = &self.peers[i];
            let rc_next = match p.rc.every {
                Some(_) => rc_channels_len(p.version, signing.is_some()),
                None => 0,
            };
            if let Some(asked) = self.peers[i].servo.due(now) {
                let keep = if asked { 0 } else { kept + rc_next };
                let s = signing.as_deref_mut();
                self.reply_keeping(i, &SERVO_OUTPUT_RAW, &servo, keep, s, ts, out);
            }
        }
    }

    /// A HEARTBEAT to each peer, if one is due at `now`.
    fn heartbeats(
        &mut self,
        now: Instant,
        state: u8,
        mut signing: Option<&mut mavlink::Signing>,
        ts: u64,
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) {
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
        self.next_heartbeat = Some(later(at, HEARTBEAT_EVERY, now));
        // custom_mode 0, type, autopilot, base_mode 0, system_status,
        // mavlink_version 3.
        let payload = [0, 0, 0, 0, self.mav_type, MAV_AUTOPILOT, 0, state, 3];
        for i in 0..self.peers.len() {
            self.reply(i, &HEARTBEAT, &payload, signing.as_deref_mut(), ts, out);
        }
    }

    /// One frame from ppm to peer `i`, numbered, in its version (MAVLink 2
    /// for a message MAVLink 1 cannot carry) or signed with `signing` if
    /// given, handed on (to `out`) if the peer earned it.
    fn reply(
        &mut self,
        i: usize,
        spec: &mavlink::Spec,
        payload: &[u8],
        signing: Option<&mut mavlink::Signing>,
        ts: u64,
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) {
        self.reply_keeping(i, spec, payload, 0, signing, ts, out);
    }

    /// [`Peers::reply`], handed on only if the peer earned it and `keep`
    /// bytes more (kept for its HEARTBEATs: see [`HEARTBEATS_KEPT`]): true
    /// when it was.
    #[allow(clippy::too_many_arguments)]
    fn reply_keeping(
        &mut self,
        i: usize,
        spec: &mavlink::Spec,
        payload: &[u8],
        keep: usize,
        signing: Option<&mut mavlink::Signing>,
        ts: u64,
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) -> bool {
        let frame = self.build(i, spec, payload, signing, ts);
        let earned = self.earned(i, frame.len() + keep);
        if earned {
            self.send(i, frame, out);
        } else {
            self.counters.held += 1;
        }
        earned
    }

    /// One frame from ppm to peer `i`, with its next number, in its version
    /// (MAVLink 2 for a message MAVLink 1 cannot carry) or signed with
    /// `signing` if given.
    fn build(
        &mut self,
        i: usize,
        spec: &mavlink::Spec,
        payload: &[u8],
        signing: Option<&mut mavlink::Signing>,
        ts: u64,
    ) -> Vec<u8> {
        let header = (self.peers[i].seq, self.system_id, self.component_id);
        match signing {
            Some(s) => s.frame(header, spec, payload, ts),
            // MAVLink 1 carries no extension fields.
            None if self.peers[i].version == 1 && spec.id <= 255 => {
                mavlink::frame(1, header, spec, &payload[..spec.v1_len as usize])
            }
            None => mavlink::frame(2, header, spec, payload),
        }
    }

    /// Whether peer `i` has earned `bytes` of replies.
    fn earned(&self, i: usize, bytes: usize) -> bool {
        let p = &self.peers[i];
        p.exempt || p.credit >= bytes
    }

    /// Hands `frame` to peer `i` on (to `out`): spends its credit, numbers
    /// its next frame, counts it sent.
    fn send(&mut self, i: usize, frame: Vec<u8>, out: &mut Vec<(SocketAddr, Vec<u8>)>) {
        let p = &mut self.peers[i];
        if !p.exempt {
            p.credit -= frame.len();
        }
        p.seq = p.seq.wrapping_add(1);
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

/// The length of ppm's HEARTBEAT to a peer of MAVLink `version`, `signed`
/// or not: 17 bytes in MAVLink 1, 21 in MAVLink 2 (its last payload byte,
/// the MAVLink version 3, is never trimmed), 34 signed.
pub fn heartbeat_len(version: u8, signed: bool) -> usize {
    let payload = HEARTBEAT.max_len as usize;
    match (version, signed) {
        (_, true) => 10 + payload + 2 + mavlink::SIGNATURE_LEN,
        (1, false) => 6 + payload + 2,
        _ => 10 + payload + 2,
    }
}

/// The length of ppm's RC_CHANNELS to a peer of MAVLink `version`,
/// `signed` or not: 50 bytes in MAVLink 1, 54 in MAVLink 2 (its last
/// payload byte, RSSI 255, is never trimmed), 67 signed.
pub fn rc_channels_len(version: u8, signed: bool) -> usize {
    let payload = RC_CHANNELS.max_len as usize;
    match (version, signed) {
        (_, true) => 10 + payload + 2 + mavlink::SIGNATURE_LEN,
        (1, false) => 6 + payload + 2,
        _ => 10 + payload + 2,
    }
}

/// The next time of something every `every`, last due `at`: a whole
/// interval after `at`, or after `now` when the loop fell behind by more
/// than an interval.
fn later(at: Instant, every: Duration, now: Instant) -> Instant {
    let next = at + every;
    if next > now {
        next
    } else {
        now + every
    }
}

/// The longest RC_CHANNELS (or SERVO_OUTPUT_RAW) interval a peer can ask
/// for (as ArduPilot clamps its message intervals).
pub const RC_CHANNELS_MAX_EVERY: Duration = Duration::from_secs(60);

/// The MAV_RESULT of COMMAND_LONG `c` from peer `p`, which it changes:
/// MAV_CMD_SET_MESSAGE_INTERVAL of RC_CHANNELS or SERVO_OUTPUT_RAW sets the
/// peer's interval of that message (param2 in us: -1 none, 0 `rc_default`,
/// any other positive, infinity included, clamped to
/// [`RC_CHANNELS_MIN_EVERY`]..=[`RC_CHANNELS_MAX_EVERY`]; any other
/// negative, or a value that is not a number, is denied);
/// MAV_CMD_REQUEST_MESSAGE of either or of PROTOCOL_VERSION, and
/// MAV_CMD_REQUEST_PROTOCOL_VERSION, send one at once. Both are denied for
/// another message; every other command is unsupported.
fn command_result(c: &CommandLong, p: &mut Peer, rc_default: Option<Duration>) -> u8 {
    let [message, param2, ..] = c.params;
    let stream = if message == RC_CHANNELS.id as f32 {
        Some(&mut p.rc)
    } else if message == SERVO_OUTPUT_RAW.id as f32 {
        Some(&mut p.servo)
    } else {
        None
    };
    match (c.command, stream) {
        (mavlink::MAV_CMD_SET_MESSAGE_INTERVAL, Some(stream)) => match param2 {
            -1.0 => {
                stream.every = None;
                MAV_RESULT_ACCEPTED
            }
            0.0 => {
                stream.every = rc_default;
                MAV_RESULT_ACCEPTED
            }
            // Infinity too: over 60 s, so 60 s, as the docs say and as
            // ArduPilot takes it on its boards (its float-to-int32 cast
            // saturates, and it clamps what is over 60 s).
            us if us > 0.0 => {
                let every = Duration::from_micros(us.min(1e12) as u64);
                stream.every = Some(every.clamp(RC_CHANNELS_MIN_EVERY, RC_CHANNELS_MAX_EVERY));
                MAV_RESULT_ACCEPTED
            }
            _ => MAV_RESULT_DENIED,
        },
        (mavlink::MAV_CMD_REQUEST_MESSAGE, Some(stream)) => {
            stream.now = true;
            MAV_RESULT_ACCEPTED
        }
        (mavlink::MAV_CMD_REQUEST_MESSAGE, None) if message == PROTOCOL_VERSION.id as f32 => {
            p.protocol_now = true;
            MAV_RESULT_ACCEPTED
        }
        (mavlink::MAV_CMD_REQUEST_PROTOCOL_VERSION, _) => {
            p.protocol_now = true;
            MAV_RESULT_ACCEPTED
        }
        (mavlink::MAV_CMD_SET_MESSAGE_INTERVAL | mavlink::MAV_CMD_REQUEST_MESSAGE, _) => {
            MAV_RESULT_DENIED
        }
        _ => MAV_RESULT_UNSUPPORTED,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line in MAV_STATE `s` carrying no frame.
    fn state(s: u8) -> LineNow<'static> {
        LineNow {
            state: s,
            line: Frame {
                values_us: &[],
                at_us: 0,
            },
            radio: None,
        }
    }

    /// A groundstation's header: system 255, component 190.
    const GCS: Header = Header {
        version: 2,
        seq: 0,
        sysid: 255,
        compid: 190,
        msgid: 76,
        signed: false,
    };

    fn command_long(target: u8, command: u16, p1: f32, p2: f32) -> Message {
        Message::CommandLong(CommandLong {
            target_system: target,
            target_component: 0,
            command,
            confirmation: 0,
            params: [p1, p2, 0.0, 0.0, 0.0, 0.0, 0.0],
        })
    }

    /// The message id and payload of frame `f` (MAVLink 1 or 2, unsigned).
    fn id_and_payload(f: &[u8]) -> (u8, &[u8]) {
        match f[0] {
            mavlink::STX_V1 => (f[5], &f[6..f.len() - 2]),
            _ => (f[7], &f[10..f.len() - 2]),
        }
    }

    /// The RC_CHANNELS in `out`: (port, time_boot_ms, chancount, chan1..).
    fn rc_channels(out: &[(SocketAddr, Vec<u8>)]) -> Vec<(u16, u32, u8, Vec<u16>)> {
        out.iter()
            .filter(|(_, f)| id_and_payload(f).0 == RC_CHANNELS.id as u8)
            .map(|(a, f)| {
                let mut whole = id_and_payload(f).1.to_vec();
                whole.resize(42, 0);
                let chan = (0..whole[40] as usize)
                    .map(|i| u16::from_le_bytes([whole[4 + 2 * i], whole[5 + 2 * i]]))
                    .collect();
                let ms = u32::from_le_bytes([whole[0], whole[1], whole[2], whole[3]]);
                (a.port(), ms, whole[40], chan)
            })
            .collect()
    }

    /// The COMMAND_ACKs in `out`: (port, command, result, target system,
    /// target component).
    fn acks(out: &[(SocketAddr, Vec<u8>)]) -> Vec<(u16, u16, u8, u8, u8)> {
        out.iter()
            .filter(|(_, f)| id_and_payload(f).0 == COMMAND_ACK.id as u8)
            .map(|(a, f)| {
                let mut p = id_and_payload(f).1.to_vec();
                p.resize(10, 0);
                (a.port(), u16::from_le_bytes([p[0], p[1]]), p[2], p[8], p[9])
            })
            .collect()
    }

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
        let mut p = Peers::new(1, 1, 8, 0);
        let mut out = vec![];
        p.due(t, state(3), None, 0, &mut out);
        assert!(out.is_empty(), "no peer, no heartbeat");
        p.heard(addr(1), 2, 40, false, t);
        p.heard(addr(2), 1, 40, false, t);
        p.due(t, state(4), None, 0, &mut out);
        assert_eq!(heartbeats(&out), [(1, 2), (2, 1)]);
        // From ppm's ids, GENERIC type and autopilot, the line's state.
        let (h, _, _) = mavlink::read_frame(&out[0].1).unwrap();
        assert_eq!((h.sysid, h.compid, h.seq), (1, 1, 0));
        let payload = &out[0].1[10..19];
        assert_eq!(payload, [0, 0, 0, 0, 0, MAV_AUTOPILOT, 0, 4, 3]);
        out.clear();
        p.due(t + Duration::from_millis(999), state(4), None, 0, &mut out);
        assert!(out.is_empty(), "one a second");
        for s in 1..5u64 {
            // Peer 1 keeps talking; peer 2 fell silent at t.
            p.heard(addr(1), 2, 40, false, t + Duration::from_secs(s));
            p.due(t + Duration::from_secs(s), state(4), None, 0, &mut out);
        }
        let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
        assert_eq!(ports, [1, 2, 1, 2, 1, 2, 1, 2], "{out:?}");
        out.clear();
        p.due(t + Duration::from_secs(5), state(4), None, 0, &mut out);
        let ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
        assert_eq!(ports, [1], "peer 2 silent for PEER_TIMEOUT");
        assert_eq!(p.known(), 1);
        assert_eq!(p.counters(), ReplyCounters { sent: 11, held: 0 });
    }

    #[test]
    fn a_peer_gets_at_most_three_times_what_it_sent_unless_exempt() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8, 0);
        let mut out = vec![];
        // One forged 10-byte datagram earns 30 bytes: one MAVLink 2
        // HEARTBEAT (21 bytes), not two.
        p.heard(addr(1), 2, 10, false, t);
        p.heard(addr(2), 2, 10, true, t);
        for s in 0..4u64 {
            p.due(
                t + Duration::from_millis(1_000 * s),
                state(3),
                None,
                0,
                &mut out,
            );
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
        let mut p = Peers::new(1, 1, 8, 0);
        let mut out = vec![];
        p.request(addr(1), &GCS, &Message::ParamRequestList(1, 1));
        p.due(t, state(3), None, 0, &mut out);
        assert!(out.is_empty(), "only a peer is answered");
        p.heard(addr(1), 2, 14, false, t);
        p.request(addr(1), &GCS, &Message::ParamRequestList(1, 1));
        p.due(t, state(3), None, 0, &mut out);
        // The PARAM_VALUE (numbered 0) first; the HEARTBEAT is held: the
        // 14-byte request earned 42 bytes, the PARAM_VALUE took 37.
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].1, PYMAVLINK_PARAM_VALUE);
        assert_eq!(p.counters(), ReplyCounters { sent: 1, held: 1 });
        // Once per request.
        out.clear();
        p.heard(addr(1), 2, 14, false, t + Duration::from_secs(1));
        p.due(t + Duration::from_secs(1), state(3), None, 0, &mut out);
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
        let mut p = Peers::new(1, 1, 8, 0);
        for i in 0..=MAX_PEERS as u16 {
            p.heard(addr(i), 2, 100, false, t + Duration::from_millis(i as u64));
        }
        let mut out = vec![];
        p.due(t + Duration::from_millis(10), state(3), None, 0, &mut out);
        let mut ports: Vec<u16> = out.iter().map(|(a, _)| a.port()).collect();
        ports.sort();
        assert_eq!(ports, (1..=MAX_PEERS as u16).collect::<Vec<_>>());
    }

    #[test]
    fn rc_channels_carry_the_line_at_the_default_rate_or_the_one_asked_for() {
        let t = Instant::now();
        let ms = Duration::from_millis;
        let mut p = Peers::new(1, 1, 8, 4);
        let values = [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800];
        let line = LineNow {
            state: 4,
            line: Frame {
                values_us: &values,
                at_us: 12_345_000,
            },
            radio: None,
        };
        p.heard(addr(1), 2, 4_000, false, t);
        p.heard(addr(2), 2, 4_000, false, t);
        let mut out = vec![];
        // Every 10 ms for a second: 4 each at the default 4 Hz (at once,
        // then every 250 ms), exact values, count 8.
        for k in 0..100 {
            p.due(t + ms(10 * k), line, None, 0, &mut out);
        }
        let rc = rc_channels(&out);
        assert_eq!(rc.len(), 8, "{rc:?}");
        assert!(rc
            .iter()
            .all(|(_, ms, n, c)| (*ms, *n, &c[..]) == (12_345, 8, &values[..])));
        // Peer 1 asks for 10 Hz (100000 us); peer 2 for none (-1).
        p.request(addr(1), &GCS, &command_long(1, 511, 65.0, 100_000.0));
        p.request(addr(2), &GCS, &command_long(0, 511, 65.0, -1.0));
        out.clear();
        let t1 = t + ms(1_000);
        for s in [1, 2] {
            p.heard(addr(s), 2, 4_000, false, t1);
        }
        for k in 0..100 {
            p.due(t1 + ms(10 * k), line, None, 0, &mut out);
        }
        let ports: Vec<u16> = rc_channels(&out).iter().map(|r| r.0).collect();
        assert_eq!(ports, [1; 10], "10 Hz to peer 1, none to peer 2");
        assert_eq!(
            acks(&out),
            [
                (1, 511, MAV_RESULT_ACCEPTED, 255, 190),
                (2, 511, 0, 255, 190)
            ]
        );
        // 50 Hz is more than ppmd reports: 10 Hz. 0 is the default again;
        // REQUEST_DATA_STREAM (all streams) at 2 Hz, then stopped.
        let rate = |p: &mut Peers, m: &Message, t: Instant| -> usize {
            p.heard(addr(1), 2, 4_000, false, t);
            p.request(addr(1), &GCS, m);
            let mut out = vec![];
            for k in 0..100 {
                p.due(t + ms(10 * k), line, None, 0, &mut out);
            }
            rc_channels(&out).len()
        };
        let stream = |start, rate_hz| {
            Message::RequestDataStream(mavlink::RequestDataStream {
                target_system: 1,
                target_component: 1,
                stream: mavlink::MAV_DATA_STREAM_ALL,
                rate_hz,
                start,
            })
        };
        let s = |n: u64| t + Duration::from_secs(n);
        assert_eq!(
            rate(&mut p, &command_long(1, 511, 65.0, 20_000.0), s(2)),
            10
        );
        assert_eq!(rate(&mut p, &command_long(1, 511, 65.0, 0.0), s(3)), 4);
        assert_eq!(rate(&mut p, &stream(true, 2), s(4)), 2);
        assert_eq!(rate(&mut p, &stream(false, 2), s(5)), 0);
        // Another stream (MAV_DATA_STREAM_POSITION, 6) changes nothing.
        let position = Message::RequestDataStream(mavlink::RequestDataStream {
            stream: 6,
            ..match stream(true, 10) {
                Message::RequestDataStream(r) => r,
                _ => unreachable!(),
            }
        });
        assert_eq!(rate(&mut p, &position, s(6)), 0);
        // One now, on request, whatever the rate.
        assert_eq!(rate(&mut p, &command_long(1, 512, 65.0, 0.0), s(7)), 1);
    }

    /// SERVO_OUTPUT_RAW: the line's values (RC_CHANNELS the radio's, with
    /// a read-back) at the default rate, its own interval, or one asked
    /// for; REQUEST_DATA_STREAM sets both.
    #[test]
    fn servo_output_raw_carries_the_line_at_its_own_rate() {
        let t = Instant::now();
        let ms = Duration::from_millis;
        let mut p = Peers::new(1, 1, 8, 4);
        let values = [1100, 1200, 1300, 1400];
        let radio = [1900, 1900];
        let line = LineNow {
            state: 4,
            line: Frame {
                values_us: &values,
                at_us: 5_000_123,
            },
            radio: Some(Frame {
                values_us: &radio,
                at_us: 6_000_000,
            }),
        };
        let second = |p: &mut Peers, from: Instant| {
            p.heard(addr(1), 2, 4_000, false, from);
            let mut out = vec![];
            for k in 0..100 {
                p.due(from + ms(10 * k), line, None, 0, &mut out);
            }
            out
        };
        let servo = |out: &[(SocketAddr, Vec<u8>)]| -> Vec<(u32, u8, Vec<u16>)> {
            out.iter()
                .filter(|(_, f)| id_and_payload(f).0 == SERVO_OUTPUT_RAW.id as u8)
                .map(|(_, f)| {
                    let mut w = id_and_payload(f).1.to_vec();
                    w.resize(37, 0);
                    let u = |at: usize| u16::from_le_bytes([w[at], w[at + 1]]);
                    let mut s: Vec<u16> = (0..8).map(|i| u(4 + 2 * i)).collect();
                    s.extend((0..8).map(|i| u(21 + 2 * i)));
                    (u32::from_le_bytes([w[0], w[1], w[2], w[3]]), w[20], s)
                })
                .collect()
        };
        let out = second(&mut p, t);
        let mut want = values.to_vec();
        want.resize(16, 0);
        assert_eq!(servo(&out), vec![(5_000_123, 0, want); 4]);
        let rc = rc_channels(&out);
        assert_eq!(rc.len(), 4);
        assert_eq!(rc[0], (1, 6_000, 2, vec![1900, 1900]), "the radio's");
        // Its own interval: 10 Hz; RC_CHANNELS keep theirs.
        p.request(addr(1), &GCS, &command_long(1, 511, 36.0, 100_000.0));
        let out = second(&mut p, t + ms(1_000));
        assert_eq!(acks(&out), [(1, 511, MAV_RESULT_ACCEPTED, 255, 190)]);
        assert_eq!((servo(&out).len(), rc_channels(&out).len()), (10, 4));
        // None, and one asked for.
        p.request(addr(1), &GCS, &command_long(1, 511, 36.0, -1.0));
        assert_eq!(servo(&second(&mut p, t + ms(2_000))).len(), 0);
        p.request(addr(1), &GCS, &command_long(1, 512, 36.0, 0.0));
        assert_eq!(servo(&second(&mut p, t + ms(3_000))).len(), 1);
        // REQUEST_DATA_STREAM of the RC channels: both at 2 Hz.
        let stream = Message::RequestDataStream(mavlink::RequestDataStream {
            target_system: 1,
            target_component: 1,
            stream: mavlink::MAV_DATA_STREAM_RC_CHANNELS,
            rate_hz: 2,
            start: true,
        });
        p.request(addr(1), &GCS, &stream);
        let out = second(&mut p, t + ms(4_000));
        assert_eq!((servo(&out).len(), rc_channels(&out).len()), (2, 2));
    }

    #[test]
    fn no_frame_on_the_line_is_a_count_of_zero() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8, 10);
        p.heard(addr(1), 2, 1_000, false, t);
        let mut out = vec![];
        p.due(t, state(3), None, 0, &mut out);
        let rc = rc_channels(&out);
        assert_eq!(rc, [(1, 0, 0, vec![])]);
        // Every channel UINT16_MAX (unused), RSSI 255 (unknown): the
        // MAVLink 2 frame keeps them all.
        let f = &out.iter().find(|(_, f)| f[7] == 65).unwrap().1;
        assert_eq!(f[1], 42);
        assert!(f[14..50].iter().all(|&b| b == 0xff));
        assert_eq!((f[50], f[51]), (0, 255));
    }

    #[test]
    fn commands_are_acknowledged_for_this_system_only() {
        let t = Instant::now();
        let mut p = Peers::new(7, 1, 8, 0);
        p.heard(addr(1), 1, 4_000, false, t);
        // MAV_CMD_REQUEST_MESSAGE of AUTOPILOT_VERSION (148): not sent by
        // ppm, denied; MAV_CMD_COMPONENT_ARM_DISARM (400): unsupported;
        // one for system 8: not answered.
        p.request(addr(1), &GCS, &command_long(7, 512, 148.0, 0.0));
        p.request(addr(1), &GCS, &command_long(0, 400, 1.0, 0.0));
        p.request(addr(1), &GCS, &command_long(8, 400, 1.0, 0.0));
        p.request(addr(1), &GCS, &command_long(7, 511, 0.0, 1e6));
        let mut out = vec![];
        p.due(t, state(3), None, 0, &mut out);
        // In MAVLink 1, without the extension fields (the target).
        assert_eq!(
            acks(&out),
            [
                (1, 512, MAV_RESULT_DENIED, 0, 0),
                (1, 400, MAV_RESULT_UNSUPPORTED, 0, 0),
                (1, 511, MAV_RESULT_DENIED, 0, 0),
            ]
        );
        // 3 bytes.
        let (_, f) = out.iter().find(|(_, f)| f[5] == 77).unwrap();
        assert_eq!((f[0], f[1]), (mavlink::STX_V1, 3));
        assert!(mavlink::read_frame(f).is_err(), "ppm's to send, not take");
        // A request from a source that is not a peer is not answered.
        p.request(addr(9), &GCS, &command_long(7, 400, 1.0, 0.0));
        out.clear();
        p.due(t, state(3), None, 0, &mut out);
        assert!(acks(&out).is_empty());
    }

    #[test]
    fn a_groundstation_that_sends_only_its_heartbeat_keeps_getting_ppms() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8, 4);
        let values = [1500; 8];
        let line = LineNow {
            state: 4,
            line: Frame {
                values_us: &values,
                at_us: 0,
            },
            radio: None,
        };
        let mut out = vec![];
        // Its 21-byte HEARTBEAT each second earns 63 bytes: ppm's HEARTBEAT
        // (21) every second, RC_CHANNELS (54) with what is left, before
        // SERVO_OUTPUT_RAW.
        for k in 0..1_000u64 {
            let now = t + Duration::from_millis(10 * k);
            if k % 100 == 0 {
                p.heard(addr(1), 2, 21, false, now);
            }
            p.due(now, line, None, 0, &mut out);
        }
        let beats = out.iter().filter(|(_, f)| f[7] == 0).count();
        assert_eq!(beats, 10, "one a second");
        let rc = rc_channels(&out).len();
        assert!((5..=10).contains(&rc), "{rc} RC_CHANNELS");
        // SERVO_OUTPUT_RAW take only what is left beyond the next
        // RC_CHANNELS: here, nothing.
        assert_eq!(out.iter().filter(|(_, f)| f[7] == 36).count(), 0);
        let sent: usize = out.iter().map(|(_, f)| f.len()).sum();
        assert!(sent <= 10 * 63, "{sent} bytes");
        // Its frames are numbered 0, 1, 2, ... without a gap, whatever
        // was held.
        let seqs: Vec<u8> = out.iter().map(|(_, f)| f[4]).collect();
        assert_eq!(seqs, (0..seqs.len() as u8).collect::<Vec<_>>());
        assert!(p.counters().held > 0);
    }

    /// How a groundstation's own HEARTBEAT a second comes against ppm's
    /// beat, in the phase test below.
    #[derive(Debug, Clone, Copy)]
    enum Clock {
        /// Every 1000 ms exactly.
        Exact,
        /// Every 1000 ms, each up to 200 ms early or late (a second may
        /// bring none of them, the next two: one HEARTBEAT kept back is
        /// not enough then).
        Jitter,
        /// Every 997 ms: its phase slides 60 ms in 20 s.
        Drift,
    }

    /// A groundstation that sends only its own HEARTBEAT, once a second (as
    /// QGroundControl may, joystick off), whatever the phase of its
    /// datagrams against ppm's beat (set by another groundstation heard
    /// first), 0 to 995 ms in 5 ms steps, sent exactly, with jitter or
    /// drifting, in MAVLink 1, 2 and signed: ppm's HEARTBEAT every second
    /// for 20 s, RC_CHANNELS from what is left, and never more than 3 times
    /// the bytes it sent. Simulated time, 1 ms steps: `due` runs every 20 ms
    /// (the receive loop's poll timeout) and after each of its datagrams,
    /// as the server drains, then settles. (Before RC_CHANNELS kept the
    /// HEARTBEAT's bytes, 11 HEARTBEATs came in 20 s at some phases.)
    #[test]
    fn a_heartbeat_every_second_whatever_the_phase_of_the_peers_own() {
        let values = [1500; 8];
        let line = LineNow {
            state: 4,
            line: Frame {
                values_us: &values,
                at_us: 0,
            },
            radio: None,
        };
        let ms = |n: u64| Duration::from_millis(n);
        let mut worst_rc = usize::MAX;
        for (version, signed) in [(2u8, false), (1, false), (2, true)] {
            // The groundstation's HEARTBEAT, as it sends it.
            let own = match (version, signed) {
                (1, _) => 17,
                (_, false) => 21,
                (_, true) => 34,
            };
            for clock in [Clock::Exact, Clock::Jitter, Clock::Drift] {
                for offset in (0..1_000u64).step_by(10) {
                    let t = Instant::now();
                    let mut p = Peers::new(1, 1, 8, 4);
                    let mut signing = signed
                        .then(|| mavlink::Signing::new(ppm_shared::auth::AuthKey::new([7; 32])));
                    // Its first datagram, when it connects, starts ppm's
                    // beat (a HEARTBEAT at once, then one a second); its
                    // own timer then sends at `offset` into each second.
                    let mut lcg = offset * 2_654_435_761 + 1;
                    let sends: Vec<u64> = std::iter::once(0)
                        .chain((1..=21u64).map(|k| match clock {
                            Clock::Exact => offset + 1_000 * k,
                            Clock::Drift => offset + 997 * k,
                            Clock::Jitter => {
                                lcg = lcg.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                                offset + 1_000 * k + 200 - (lcg >> 33) % 401
                            }
                        }))
                        .collect();
                    let last = 20_000;
                    let (mut earned, mut got) = (0usize, 0usize);
                    let mut beats = vec![];
                    let mut rc = 0;
                    let mut next = 0;
                    for now_ms in 0..=last {
                        let now = t + ms(now_ms);
                        let mut wake = now_ms % 20 == 0;
                        while next < sends.len() && sends[next] == now_ms {
                            p.heard(addr(1), version, own, false, now);
                            earned += own;
                            next += 1;
                            wake = true;
                        }
                        if !wake {
                            continue;
                        }
                        let mut out = vec![];
                        p.due(now, line, signing.as_mut(), now_ms, &mut out);
                        for (_, f) in out.iter().filter(|(a, _)| a.port() == 1) {
                            let (v, s, id) = frame_kind(f);
                            assert_eq!((v, s), (if signed { 2 } else { version }, signed));
                            got += f.len();
                            match id {
                                0 => beats.push(now_ms),
                                65 => rc += 1,
                                36 => {}
                                other => panic!("message {other}"),
                            }
                        }
                        let what = format!("{version} {signed} {clock:?} at {offset} ms");
                        assert!(
                            got <= REPLY_MAX_RATIO * earned,
                            "{what}: {got} bytes for {earned} at {now_ms} ms"
                        );
                    }
                    let what = format!("MAVLink {version}, signed {signed}, {clock:?}, at {offset} ms: beats {beats:?}");
                    // One a second, none missed, for 20 s.
                    let want: Vec<u64> = (0..=20).map(|s| s * 1_000).collect();
                    assert_eq!(beats, want, "{what}");
                    worst_rc = worst_rc.min(rc);
                }
            }
        }
        // What is left beyond the HEARTBEAT buys RC_CHANNELS: at least 42
        // bytes a second (MAVLink 1: 51 earned, 17 for the HEARTBEAT), 0.68
        // RC_CHANNELS (50 bytes in MAVLink 1) a second.
        assert!(worst_rc >= 11, "{worst_rc} RC_CHANNELS in 20 s");
    }

    /// A frame's MAVLink version, whether it is signed, and its message.
    fn frame_kind(f: &[u8]) -> (u8, bool, u32) {
        match f[0] {
            mavlink::STX_V1 => (1, false, f[5] as u32),
            _ => (
                2,
                f[2] & mavlink::IFLAG_SIGNED != 0,
                u32::from_le_bytes([f[7], f[8], f[9], 0]),
            ),
        }
    }

    /// An RC_CHANNELS asked for (MAV_CMD_REQUEST_MESSAGE) is an answer,
    /// earned by its request: it needs no HEARTBEATs' bytes left over, as
    /// those of the stream do.
    #[test]
    fn an_rc_channels_asked_for_is_earned_by_its_request() {
        let t = Instant::now();
        let values = [1500; 8];
        let line = LineNow {
            state: 4,
            line: Frame {
                values_us: &values,
                at_us: 0,
            },
            radio: None,
        };
        let mut p = Peers::new(1, 1, 8, 0);
        // A MAVLink 2 COMMAND_LONG (trimmed) is 43 bytes: it earns 129, the
        // COMMAND_ACK (22), ppm's first HEARTBEAT (21) and the RC_CHANNELS
        // (54) take 97; 42 more kept would be 139.
        let request = command_long(1, 512, 65.0, 0.0);
        let (_, payload) = request.encode();
        let len = mavlink::frame(2, (0, 255, 190), &mavlink::COMMAND_LONG, &payload).len();
        assert_eq!(len, 43);
        p.heard(addr(1), 2, len, false, t);
        p.request(addr(1), &GCS, &request);
        let mut out = vec![];
        p.due(t, line, None, 0, &mut out);
        assert_eq!(acks(&out), [(1, 512, MAV_RESULT_ACCEPTED, 255, 190)]);
        assert_eq!(rc_channels(&out).len(), 1, "{out:?}");
        assert_eq!(p.counters(), ReplyCounters { sent: 3, held: 0 });
    }

    #[test]
    fn heartbeat_len_is_the_heartbeats() {
        let mut s = mavlink::Signing::new(ppm_shared::auth::AuthKey::new([7; 32]));
        let payload = [0, 0, 0, 0, 0, MAV_AUTOPILOT, 0, 4, 3];
        for version in [1, 2] {
            let f = mavlink::frame(version, (0, 1, 1), &HEARTBEAT, &payload);
            assert_eq!(heartbeat_len(version, false), f.len());
            let f = s.frame((0, 1, 1), &HEARTBEAT, &payload, 1);
            assert_eq!(heartbeat_len(version, true), f.len());
            let rc = mavlink::rc_channels_payload(1, &[]);
            let f = mavlink::frame(version, (0, 1, 1), &RC_CHANNELS, &rc);
            assert_eq!(rc_channels_len(version, false), f.len());
            let f = s.frame((0, 1, 1), &RC_CHANNELS, &rc, 1);
            assert_eq!(rc_channels_len(version, true), f.len());
        }
    }

    #[test]
    fn any_interval_a_peer_asks_for_is_taken_or_denied_never_a_fault() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8, 4);
        for (param2, result) in [
            (f32::NAN, MAV_RESULT_DENIED),
            (f32::NEG_INFINITY, MAV_RESULT_DENIED),
            (f32::INFINITY, MAV_RESULT_ACCEPTED),
            (-2.0, MAV_RESULT_DENIED),
            (f32::MAX, MAV_RESULT_ACCEPTED),
            (1e30, MAV_RESULT_ACCEPTED),
            (1.0, MAV_RESULT_ACCEPTED),
        ] {
            p.heard(addr(1), 2, 4_000, false, t);
            p.request(addr(1), &GCS, &command_long(1, 511, 65.0, param2));
            let mut out = vec![];
            p.due(t, state(3), None, 0, &mut out);
            assert_eq!(acks(&out), [(1, 511, result, 255, 190)], "{param2}");
        }
        // The last asked for 1 us: 10 Hz at most (counted over the second
        // second). f32::MAX before it: every 60 s.
        let mut out = vec![];
        for k in 1..=200 {
            if k == 101 {
                out.clear();
            }
            let now = t + Duration::from_millis(10 * k);
            p.due(now, state(3), None, 0, &mut out);
        }
        assert_eq!(rc_channels(&out).len(), 10);
        p.request(addr(1), &GCS, &command_long(1, 511, 65.0, f32::MAX));
        let mut out = vec![];
        let later = t + Duration::from_secs(2);
        p.heard(addr(1), 2, 4_000, false, later);
        for k in 0..300 {
            p.due(
                later + Duration::from_millis(10 * k),
                state(3),
                None,
                0,
                &mut out,
            );
        }
        assert_eq!(rc_channels(&out).len(), 1, "one, then a minute later");
    }

    /// An infinite interval is over 60 s: taken as 60 s, as the docs say
    /// of any interval over it (and as ArduPilot takes it), not denied. -1
    /// stops them; minus infinity and NaN are denied and change nothing.
    #[test]
    fn an_infinite_interval_is_a_minute() {
        let t = Instant::now();
        let ms = Duration::from_millis;
        let mut p = Peers::new(1, 1, 8, 4);
        p.heard(addr(1), 2, 4_000, false, t);
        let mut out = vec![];
        p.due(t, state(3), None, 0, &mut out);
        assert_eq!(rc_channels(&out).len(), 1, "the first at once");
        for (param2, result) in [
            (f32::INFINITY, MAV_RESULT_ACCEPTED),
            (f32::NEG_INFINITY, MAV_RESULT_DENIED),
            (f32::NAN, MAV_RESULT_DENIED),
        ] {
            p.request(addr(1), &GCS, &command_long(1, 511, 65.0, param2));
            let mut out = vec![];
            p.due(t + ms(1), state(3), None, 0, &mut out);
            assert_eq!(acks(&out), [(1, 511, result, 255, 190)], "{param2}");
        }
        // The next one due (at 250 ms, the default 4 Hz) goes out, then
        // one a minute: 3 in 3 minutes.
        let mut out = vec![];
        for k in 1..=18_000u64 {
            let now = t + ms(10 * k);
            if k % 400 == 0 {
                p.heard(addr(1), 2, 4_000, false, now);
            }
            p.due(now, state(3), None, 0, &mut out);
        }
        assert_eq!(rc_channels(&out).len(), 3, "at 0.25, 60.25 and 120.25 s");
    }

    #[test]
    fn a_request_for_the_protocol_version_gets_mavlink_2() {
        let t = Instant::now();
        let mut p = Peers::new(1, 1, 8, 0);
        // A MAVLink 1 peer: PROTOCOL_VERSION still goes out in MAVLink 2.
        p.heard(addr(1), 1, 4_000, false, t);
        p.request(addr(1), &GCS, &command_long(1, 512, 300.0, 0.0));
        p.request(addr(1), &GCS, &command_long(1, 519, 0.0, 0.0));
        let mut out = vec![];
        p.due(t, state(3), None, 0, &mut out);
        assert_eq!(
            acks(&out),
            [
                (1, 512, MAV_RESULT_ACCEPTED, 0, 0),
                (1, 519, MAV_RESULT_ACCEPTED, 0, 0)
            ]
        );
        let v: Vec<&Vec<u8>> = out
            .iter()
            .map(|(_, f)| f)
            .filter(|f| f[0] == mavlink::STX_V2 && f[7..10] == [0x2c, 0x01, 0])
            .collect();
        assert_eq!(v.len(), 1, "one, for both requests");
        let mut payload = v[0][10..v[0].len() - 2].to_vec();
        payload.resize(22, 0);
        assert_eq!(payload, mavlink::protocol_version_payload());
        assert_eq!(payload[..6], [200, 0, 100, 0, 200, 0]);
        let crc = mavlink::frame_crc(&PROTOCOL_VERSION, &v[0][1..v[0].len() - 2]);
        assert_eq!(v[0][v[0].len() - 2..], crc.to_le_bytes());
    }
}
