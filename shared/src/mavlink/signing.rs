//! MAVLink 2 signing with one key ([`Signing`]): the signature of what
//! comes in checked, its timestamp growing per stream, and what goes out
//! signed.

use super::framing::{build_frame, Header, IFLAG_SIGNED, SIGNATURE_LEN};
use super::specs::Spec;
use crate::protocol::{reject, Reject, RejectReason};

/// MAVLink 2 signing's epoch: 2015-01-01T00:00:00Z, in Unix seconds.
pub const SIGNING_EPOCH_UNIX_S: u64 = 1_420_070_400;
/// A stream not seen before is taken only with a timestamp at most this far
/// behind ppm's (60 s, in the signature's 10 us units), as the MAVLink C
/// library takes it.
pub const NEW_STREAM_MAX_LAG: u64 = 6_000_000;
/// Most signing streams (system, component, link) remembered; the one
/// updated longest ago makes room.
pub const MAX_STREAMS: usize = 32;

/// A signature timestamp (10 us units since 2015) for a CLOCK_REALTIME time.
pub fn signing_timestamp(unix_ns: u64) -> u64 {
    unix_ns.saturating_sub(SIGNING_EPOCH_UNIX_S * 1_000_000_000) / 10_000
}

/// One signing stream: a (system, component, link) and its last
/// timestamp.
#[derive(Debug, Clone, Copy)]
struct Stream {
    id: (u8, u8, u8),
    last: u64,
    /// When it was last updated (a count of accepted frames).
    touched: u64,
}

/// MAVLink 2 message signing with one key: checks what comes in (the
/// signature, and a timestamp that grows per stream) and signs what goes
/// out. Its timestamp is the newest of the clock's and every one accepted.
#[derive(Debug, Clone)]
pub struct Signing {
    key: crate::auth::AuthKey,
    streams: Vec<Stream>,
    updates: u64,
    timestamp: u64,
    /// A stream not seen since the start needs a timestamp above this: the
    /// newest accepted before a restart ([`Signing::with_floor`]).
    floor: u64,
    /// The newest timestamp accepted, if any.
    newest: Option<u64>,
}

impl Signing {
    /// Signing with `key` (a key file's 32 bytes, as pymavlink and MAVProxy
    /// take them).
    pub fn new(key: crate::auth::AuthKey) -> Signing {
        Signing {
            key,
            streams: Vec::new(),
            updates: 0,
            timestamp: 0,
            floor: 0,
            newest: None,
        }
    }

    /// After a restart: every frame needs a timestamp above `floor`, the
    /// newest accepted before ([`Signing::newest`], kept in a file), so
    /// that no frame accepted, or signed, before the restart is taken
    /// again.
    pub fn with_floor(mut self, floor: u64) -> Signing {
        self.floor = floor;
        self.timestamp = self.timestamp.max(floor);
        self
    }

    /// The newest timestamp accepted since the start (or the floor).
    pub fn newest(&self) -> Option<u64> {
        self.newest.or((self.floor > 0).then_some(self.floor))
    }

    fn signature(&self, signed: &[u8]) -> [u8; 6] {
        use sha2::{Digest, Sha256};
        let mut h = Sha256::new();
        h.update(self.key.bytes());
        h.update(signed);
        let d = h.finalize();
        [d[0], d[1], d[2], d[3], d[4], d[5]]
    }

    /// Checks one frame (`frame`: its bytes, signature included) received
    /// when the clock's timestamp was `now` ([`signing_timestamp`]):
    /// `unsigned` without a signature (and every MAVLink 1 frame), `bad_mac`
    /// when the signature is not the key's, `replay` when its timestamp is
    /// not above its stream's last, or (a new stream) more than
    /// [`NEW_STREAM_MAX_LAG`] behind ppm's.
    pub fn check(&mut self, frame: &[u8], header: &Header, now: u64) -> Result<(), Reject> {
        if header.version == 1 {
            return Err(reject(
                RejectReason::Unsigned,
                "a MAVLink 1 frame: mavlink.key_file is set, so frames must be signed with its key, and only MAVLink 2 carries a signature: send MAVLink 2 (pymavlink writes it only with MAVLINK20=1 set in the environment before it is imported; MAVProxy does unless started with --mavversion 1.0)",
            ));
        }
        if !header.signed {
            return Err(reject(
                RejectReason::Unsigned,
                "an unsigned MAVLink 2 frame: mavlink.key_file is set, so frames must be signed with its key (pymavlink: setup_signing(key, sign_outgoing=True); MAVProxy: signing key PASSPHRASE)",
            ));
        }
        let n = frame.len();
        let sig = &frame[n - SIGNATURE_LEN..];
        let want = self.signature(&frame[..n - 6]);
        let diff = want
            .iter()
            .zip(&sig[7..])
            .fold(0u8, |d, (a, b)| d | (a ^ b));
        if diff != 0 {
            return Err(reject(
                RejectReason::BadMac,
                "the MAVLink signature is not that of mavlink.key_file's key",
            ));
        }
        let link = sig[0];
        let ts = u64::from_le_bytes([sig[1], sig[2], sig[3], sig[4], sig[5], sig[6], 0, 0]);
        self.timestamp = self.timestamp.max(now);
        let id = (header.sysid, header.compid, link);
        self.updates += 1;
        match self.streams.iter_mut().find(|s| s.id == id) {
            Some(s) if ts <= s.last => {
                return Err(reject(
                    RejectReason::Replay,
                    format!(
                        "signed timestamp {ts} of system {}, component {}, link {link} is not above its last, {}",
                        id.0, id.1, s.last
                    ),
                ))
            }
            Some(s) => {
                s.last = ts;
                s.touched = self.updates;
            }
            None if ts <= self.floor => {
                return Err(reject(
                    RejectReason::Replay,
                    format!(
                        "signed timestamp {ts} of system {}, component {}, link {link} is not above {}, the newest accepted before udp-ingress started",
                        id.0, id.1, self.floor
                    ),
                ))
            }
            None if ts + NEW_STREAM_MAX_LAG < self.timestamp => {
                return Err(reject(
                    RejectReason::Replay,
                    format!(
                        "a new signing stream (system {}, component {}, link {link}) whose timestamp {ts} is more than a minute behind ppm's {}",
                        id.0, id.1, self.timestamp
                    ),
                ))
            }
            None => {
                if self.streams.len() == MAX_STREAMS {
                    let oldest = (0..self.streams.len())
                        .min_by_key(|&i| self.streams[i].touched)
                        .expect("MAX_STREAMS > 0");
                    self.streams.swap_remove(oldest);
                }
                self.streams.push(Stream {
                    id,
                    last: ts,
                    touched: self.updates,
                });
            }
        }
        self.timestamp = self.timestamp.max(ts);
        self.newest = Some(self.newest.map_or(ts, |n| n.max(ts)));
        Ok(())
    }

    /// One signed MAVLink 2 frame (link 0) of `spec`'s message with
    /// `payload`, at a timestamp above every one used or seen and the
    /// clock's `now`.
    pub fn frame(
        &mut self,
        header: (u8, u8, u8),
        spec: &Spec,
        payload: &[u8],
        now: u64,
    ) -> Vec<u8> {
        let mut out = build_frame(2, IFLAG_SIGNED, header, spec, payload);
        self.timestamp = self.timestamp.max(now) + 1;
        out.push(0);
        out.extend_from_slice(&self.timestamp.to_le_bytes()[..6]);
        let sig = self.signature(&out);
        out.extend_from_slice(&sig);
        out
    }
}
