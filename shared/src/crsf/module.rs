//! The handset side of CRSF: what a radio sends an ExpressLRS (or
//! Crossfire) transmitter module in its bay, and what the module answers.
//!
//! - RC frames go to the module's address, 0xEE, with the flight
//!   controller's layout ([`super::encode_rc_to`]).
//! - Every 200 ms the module answers with a timing correction
//!   ([`Correction`]): `C8 0D 3A EA EE 10 RATE OFFSET CRC` (ExpressLRS
//!   `CRSFHandset::sendSyncPacketToTX`; type 0x3A, sub-type 0x10, to 0xEA
//!   from 0xEE; `forwardMessage` puts the sync byte 0xC8 first on a serial
//!   port, whatever the destination), `RATE`
//!   the period it wants between RC frames and `OFFSET` how long before its
//!   radio's packet timer the last RC frames were whole, less a 100 us
//!   margin, both signed 32-bit big-endian in tenths of a microsecond
//!   (EdgeTX `telemetry/crossfire.cpp` reads them so).
//! - [`HandsetParser`] frames bytes as the module does
//!   (`CRSFHandset::handleInput`): the frames ppm writes are checked with it.

use super::{crc8, ADDRESS_RADIO_TRANSMITTER, ADDRESS_TRANSMITTER, MAX_FRAME_LEN};

/// Frame type of the handset's commands and the module's answers
/// (`CRSF_FRAMETYPE_HANDSET`).
pub const TYPE_HANDSET: u8 = 0x3A;
/// Sub-type of a timing correction (`CRSF_HANDSET_SUBCMD_TIMING`).
pub const SUBTYPE_TIMING: u8 = 0x10;
/// How often the module sends a correction, ms
/// (`OpenTXsyncPacketInterval`).
pub const CORRECTION_EVERY_MS: u64 = 200;
/// The margin the module keeps: OFFSET is the measured lead less this, in
/// tenths of a microsecond (`OpenTXsyncOffsetSafeMargin`, 100 us).
pub const SAFE_MARGIN_TENTHS: i32 = 1_000;
/// Frame type of a command (`COMMAND_ID`).
pub const TYPE_COMMAND: u8 = 0x32;
/// A command's CRSF sub-command (`SUBCOMMAND_CRSF`).
pub const SUBCOMMAND_CRSF: u8 = 0x10;
/// The command that selects the model (receiver) ID
/// (`COMMAND_MODEL_SELECT_ID`).
pub const COMMAND_MODEL_SELECT_ID: u8 = 0x05;
/// The highest model ID (EdgeTX's receiver numbers are 0..=63).
pub const MODEL_ID_MAX: u8 = 63;
/// Bytes of the model ID command.
pub const MODEL_ID_FRAME_LEN: usize = 10;

/// The model ID command a handset sends the module (EdgeTX
/// `createCrossfireModelIDFrame`): `C8 08 32 EE EA 10 05 ID CRC_BA CRC`, to
/// the module from the handset, its command checked by [`crc8_ba`] over
/// type to ID and the frame by the CRC-8/DVB-S2 over type to that. The
/// module starts its radio at once on it (rather than after its start-up
/// wait) and uses the ID for model match.
pub fn model_id_frame(id: u8) -> [u8; MODEL_ID_FRAME_LEN] {
    let mut f = [
        super::ADDRESS_FLIGHT_CONTROLLER,
        8,
        TYPE_COMMAND,
        ADDRESS_TRANSMITTER,
        ADDRESS_RADIO_TRANSMITTER,
        SUBCOMMAND_CRSF,
        COMMAND_MODEL_SELECT_ID,
        id,
        0,
        0,
    ];
    f[8] = crc8_ba(&f[2..8]);
    f[9] = crc8(&f[2..9]);
    f
}

/// CRC-8 with polynomial 0xBA (initial 0, no reflection): what CRSF
/// commands carry inside their frame (EdgeTX `crc8_BA`).
pub fn crc8_ba(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |mut crc, &b| {
        crc ^= b;
        for _ in 0..8 {
            crc = if crc & 0x80 != 0 {
                (crc << 1) ^ 0xBA
            } else {
                crc << 1
            };
        }
        crc
    })
}

/// The module's default line rate from a handset (EdgeTX's default for
/// an external ExpressLRS module; the module searches this first).
pub const HANDSET_BAUD: u32 = 400_000;

/// A timing correction from the module.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Correction {
    /// The period the module wants between RC frames, 0.1 us.
    pub rate_tenths: i32,
    /// How long before the module's packet timer the RC frames were whole,
    /// less the module's 100 us margin, 0.1 us: the next period should be
    /// longer by this (shorter when negative).
    pub offset_tenths: i32,
}

impl Correction {
    /// The bytes of a whole frame's payload (after the type byte), if it
    /// is a timing correction: `EA EE 10 RATE OFFSET` (9 + 2 bytes; a
    /// longer payload is read, the specification lets frames grow).
    pub fn from_payload(payload: &[u8]) -> Option<Correction> {
        if payload.len() < 11 || payload[2] != SUBTYPE_TIMING {
            return None;
        }
        let at = |i: usize| {
            i32::from_be_bytes([payload[i], payload[i + 1], payload[i + 2], payload[i + 3]])
        };
        Some(Correction {
            rate_tenths: at(3),
            offset_tenths: at(7),
        })
    }

    /// The whole frame a module sends: to the handset (0xEA), starting
    /// with the sync byte 0xC8 as every frame on its serial port does.
    pub fn encode(&self) -> [u8; 15] {
        let mut f = [0u8; 15];
        f[0] = super::ADDRESS_FLIGHT_CONTROLLER;
        f[1] = 13;
        f[2] = TYPE_HANDSET;
        f[3] = ADDRESS_RADIO_TRANSMITTER;
        f[4] = ADDRESS_TRANSMITTER;
        f[5] = SUBTYPE_TIMING;
        f[6..10].copy_from_slice(&self.rate_tenths.to_be_bytes());
        f[10..14].copy_from_slice(&self.offset_tenths.to_be_bytes());
        f[14] = crc8(&f[2..14]);
        f
    }

    /// The period asked for, ns (0 when it is not positive).
    pub fn rate_ns(&self) -> u64 {
        u64::try_from(self.rate_tenths).map_or(0, |t| t * 100)
    }

    /// The offset, ns.
    pub fn offset_ns(&self) -> i64 {
        i64::from(self.offset_tenths) * 100
    }
}

/// The module's reading of a handset's bytes, ported from ExpressLRS
/// `CRSFHandset::handleInput` and `alignBufferToSync`: bytes are buffered
/// (at most 64), the buffer is aligned to its first 0xEE or 0xC8, a frame
/// whose total length (`len + 2`) is outside 4..=64 is dropped at that
/// byte, and a whole frame is taken when its CRC holds (a bad one is
/// counted and its bytes dropped). No time-out: the module frames by bytes
/// alone.
#[derive(Debug, Clone)]
pub struct HandsetParser {
    buf: [u8; MAX_FRAME_LEN],
    n: usize,
    /// Frames whose CRC held (`GoodPktsCount`).
    pub good: u64,
    /// Frames whose CRC did not (`BadPktsCount`).
    pub bad: u64,
}

impl Default for HandsetParser {
    fn default() -> Self {
        HandsetParser {
            buf: [0; MAX_FRAME_LEN],
            n: 0,
            good: 0,
            bad: 0,
        }
    }
}

impl HandsetParser {
    /// Reads `bytes` as they arrive; `on` gets every frame taken.
    pub fn feed(&mut self, mut bytes: &[u8], mut on: impl FnMut(&[u8])) {
        while !bytes.is_empty() {
            let take = bytes.len().min(MAX_FRAME_LEN - self.n);
            self.buf[self.n..self.n + take].copy_from_slice(&bytes[..take]);
            self.n += take;
            bytes = &bytes[take..];
            self.align(0);
            // handleInput takes at most one frame per call, and is called
            // again while bytes wait; looping here is the same.
            while self.n >= 3 {
                let total = usize::from(self.buf[1]) + 2;
                if !(4..=MAX_FRAME_LEN).contains(&total) {
                    self.align(1);
                    continue;
                }
                if self.n < total {
                    break;
                }
                if crc8(&self.buf[2..total - 1]) == self.buf[total - 1] {
                    self.good += 1;
                    on(&self.buf[..total]);
                } else {
                    self.bad += 1;
                }
                self.buf.copy_within(total..self.n, 0);
                self.n -= total;
                self.align(0);
            }
        }
    }

    /// `alignBufferToSync(start)`: the buffer from its first 0xEE or 0xC8
    /// at or after `start`, or empty.
    fn align(&mut self, start: usize) {
        match self.buf[start.min(self.n)..self.n]
            .iter()
            .position(|&b| b == ADDRESS_TRANSMITTER || b == super::ADDRESS_FLIGHT_CONTROLLER)
        {
            Some(i) => {
                let i = i + start;
                self.buf.copy_within(i..self.n, 0);
                self.n -= i;
            }
            None => self.n = 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::crsf::{encode_rc_to, TelemetryReader, RC_FRAME_LEN};

    /// A module's correction for 5000 us and -1234.5 us, its CRC computed
    /// apart from the crate (CRC-8/DVB-S2 in a few lines of Python).
    const SYNC: [u8; 15] = [
        0xC8, 0x0D, 0x3A, 0xEA, 0xEE, 0x10, 0x00, 0x00, 0xC3, 0x50, 0xFF, 0xFF, 0xCF, 0xC7, 0x4F,
    ];

    #[test]
    fn the_model_id_command_is_edgetxs() {
        // EdgeTX's crc8tab_BA at 1, 2, 0x10, 0x80 and 0xFF.
        let t: Vec<u8> = [1u8, 2, 0x10, 0x80, 0xFF]
            .iter()
            .map(|&i| crc8_ba(&[i]))
            .collect();
        assert_eq!(t, [0xBA, 0xCE, 0x98, 0xE6, 0x44]);
        // Both CRCs computed apart from the crate (a few lines of Python).
        assert_eq!(
            model_id_frame(0),
            [0xC8, 0x08, 0x32, 0xEE, 0xEA, 0x10, 0x05, 0x00, 0xDC, 0x4D]
        );
        assert_eq!(
            model_id_frame(7),
            [0xC8, 0x08, 0x32, 0xEE, 0xEA, 0x10, 0x05, 0x07, 0x8E, 0xCC]
        );
        // The module's framing takes it.
        let mut p = HandsetParser::default();
        let mut taken = 0;
        p.feed(&model_id_frame(63), |_| taken += 1);
        assert_eq!((taken, p.bad), (1, 0));
    }

    #[test]
    fn a_correction_is_the_bytes_a_module_sends() {
        let c = Correction {
            rate_tenths: 50_000,
            offset_tenths: -12_345,
        };
        assert_eq!(c.encode(), SYNC);
        assert_eq!((c.rate_ns(), c.offset_ns()), (5_000_000, -1_234_500));
        let mut reader = TelemetryReader::new();
        reader.feed(&[0x00, 0x12], |_, _| panic!("no telemetry"));
        reader.feed(&SYNC, |_, _| panic!("no telemetry"));
        assert_eq!(reader.take_timing(), Some(c));
        assert_eq!(reader.take_timing(), None, "taken once");
        assert_eq!((reader.counts().other, reader.counts().bad_crc), (1, 0));
        // Another sub-type, or a bad CRC: no correction.
        let mut other = SYNC;
        other[5] = 0x11;
        other[14] = crc8(&other[2..14]);
        let mut bad = SYNC;
        bad[9] ^= 1;
        reader.feed(&other, |_, _| {});
        reader.feed(&bad, |_, _| {});
        assert_eq!(reader.take_timing(), None);
        assert_eq!(reader.counts().bad_crc, 1);
        assert_eq!(Correction::from_payload(&SYNC[3..13]), None, "short");
    }

    #[test]
    fn the_module_frames_rc_frames_after_junk_bad_lengths_and_bad_crcs() {
        let raw: [u16; 16] = std::array::from_fn(|i| 172 + 100 * i as u16);
        let rc = encode_rc_to(ADDRESS_TRANSMITTER, &raw);
        assert_eq!(&rc[..3], &[0xEE, 24, 0x16]);
        let mut bad_crc = rc;
        bad_crc[RC_FRAME_LEN - 1] ^= 0x55;
        let mut stream = vec![0x00, 0x17, 0x42];
        stream.extend_from_slice(&rc);
        // A start byte whose length is out of 4..=64: dropped at it.
        stream.extend_from_slice(&[0xEE, 0x01]);
        stream.extend_from_slice(&bad_crc);
        stream.extend_from_slice(&rc);
        stream.extend_from_slice(&SYNC);
        // Fed a byte at a time and in one piece: the same frames.
        for pieces in [1, stream.len()] {
            let mut p = HandsetParser::default();
            let mut taken = Vec::new();
            for chunk in stream.chunks(pieces) {
                p.feed(chunk, |f| taken.push(f.to_vec()));
            }
            assert_eq!(
                taken,
                [rc.to_vec(), rc.to_vec(), SYNC.to_vec()],
                "pieces of {pieces}"
            );
            assert_eq!((p.good, p.bad), (3, 1));
        }
    }
}
