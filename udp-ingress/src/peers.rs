//! The MAVLink groundstations udp-ingress talks back to: after a peer's
//! first good MAVLink datagram, a HEARTBEAT a second in the peer's MAVLink
//! version, so that a groundstation sees ppm as a vehicle; RC_CHANNELS
//! (what the radio transmits, read back, with a read-back; the values on
//! the line without one) and SERVO_OUTPUT_RAW (the values on the line),
//! each at `mavlink.rc_channels_hz` or the rate the peer asks for
//! (MAV_CMD_SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM); a STATUSTEXT for
//! each read-back state change and flight mode change
//! ([`Peers::announce`]); with a CRSF output's telemetry, SYS_STATUS (the
//! battery), ATTITUDE and GPS_RAW_INT as new frames of each come from the
//! flight controller, each at most every [`TELEMETRY_MIN_EVERY`]; a COMMAND_ACK to
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
//! Its tests are in `src/peers/tests.rs`.

use ppm_shared::crsf::report;
use ppm_shared::crsf::Telemetry;
use ppm_shared::ipc::TelemetrySample;
use ppm_shared::mavlink::telemetry;
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
/// The shortest interval between two telemetry messages of a kind
/// (SYS_STATUS, ATTITUDE, GPS_RAW_INT): a flight controller may send
/// attitude 50 times a second; a groundstation's display needs 10.
pub const TELEMETRY_MIN_EVERY: Duration = Duration::from_millis(100);

/// The telemetry kinds sent to peers ([`report::BATTERY`] as SYS_STATUS,
/// [`report::ATTITUDE`], [`report::GPS`] as GPS_RAW_INT).
const TELEMETRY_SENT: [usize; 3] = [report::BATTERY, report::ATTITUDE, report::GPS];

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
    /// Per [`TELEMETRY_SENT`] kind: the reader's count of it when it was
    /// last sent, and when the next may go.
    telemetry: [(u64, Option<Instant>); 3],
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
    /// With a CRSF output's telemetry: ppmd's newest sample of it.
    pub telemetry: Option<&'a TelemetrySample>,
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
            telemetry: [(0, None); 3],
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
        if let Some(t) = line.telemetry {
            self.telemetry(now, t, signing, ts, out);
        }
    }

    /// The telemetry messages due at `now` from sample `s`, to every peer
    /// with the credit for them beyond [`HEARTBEATS_KEPT`] HEARTBEATs: one
    /// of a kind when the flight controller sent a new frame of it since
    /// the last one and [`TELEMETRY_MIN_EVERY`] has passed.
    fn telemetry(
        &mut self,
        now: Instant,
        s: &TelemetrySample,
        mut signing: Option<&mut mavlink::Signing>,
        ts: u64,
        out: &mut Vec<(SocketAddr, Vec<u8>)>,
    ) {
        let counts = s.counts();
        for (k, kind) in TELEMETRY_SENT.into_iter().enumerate() {
            let count = match kind {
                report::BATTERY => counts.battery,
                report::ATTITUDE => counts.attitude,
                _ => counts.gps,
            };
            let (told, next) = self.telemetry[k];
            if count == told || next.is_some_and(|t| now < t) {
                continue;
            }
            let Some((at, t)) = s.newest(kind) else {
                continue;
            };
            self.telemetry[k] = (count, Some(now + TELEMETRY_MIN_EVERY));
            let (spec, payload): (&mavlink::Spec, Vec<u8>) = match t {
                Telemetry::Battery(b) => (
                    &mavlink::SYS_STATUS,
                    telemetry::crsf_sys_status(&b).to_vec(),
                ),
                Telemetry::Attitude(a) => (
                    &mavlink::ATTITUDE,
                    telemetry::crsf_attitude(&a, at).to_vec(),
                ),
                Telemetry::Gps(g) => (
                    &mavlink::GPS_RAW_INT,
                    telemetry::crsf_gps_raw_int(&g, at).to_vec(),
                ),
                _ => continue,
            };
            for i in 0..self.peers.len() {
                let kept =
                    HEARTBEATS_KEPT * heartbeat_len(self.peers[i].version, signing.is_some());
                let s = signing.as_deref_mut();
                self.reply_keeping(i, spec, &payload, kept, s, ts, out);
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
mod tests;
