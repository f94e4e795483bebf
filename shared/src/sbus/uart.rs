//! SBUS bytes as a line carries them: a UART's 8E2 characters (a start bit,
//! 8 data bits least significant first, an even parity bit, 2 stop bits) at
//! 100 000 baud, 10 us a bit. A plain UART idles high and starts each
//! character with a low start bit; true ("inverted") SBUS is the same
//! waveform upside down, idling low.
//!
//! The UART itself is [`crate::uart`]'s, in SBUS's [`FORMAT`].
//!
//! [`waveform`] writes a frame's bytes as line levels, bit by bit (the
//! simulated line's trace of an SBUS output; an SPI output's bitstream);
//! [`decode`] reads a waveform back as a UART receiver does: it finds each
//! start bit by the edge that leaves the idle level, samples every bit in its
//! middle, and checks parity and both stop bits.

use super::{BAUD, BYTE_BITS};
use crate::signal::Level;
use crate::uart::{self as generic, Parity, UartFormat};

pub use crate::uart::Character;

/// SBUS's UART format: 100 000 baud, 8E2.
pub const FORMAT: UartFormat = UartFormat {
    baud: BAUD as u32,
    parity: Parity::Even,
    stop_bits: 2,
};

/// One bit on the wire, ns: 10 us.
pub const BIT_NS: u64 = 1_000_000_000 / BAUD;

/// The line levels of one character, start bit first, for a UART idling at
/// `idle` (a plain UART's `High`; true SBUS `Low`).
pub fn character(byte: u8, idle: Level) -> [Level; BYTE_BITS as usize] {
    FORMAT.character(byte, idle)
}

/// The level of every bit of `bytes` sent back to back, first bit first,
/// for a line idling at `idle`: [`BYTE_BITS`] bits a byte.
pub fn waveform(bytes: &[u8], idle: Level) -> impl Iterator<Item = Level> + '_ {
    FORMAT.waveform(bytes, idle)
}

/// The edges of `bytes` sent back to back from `start_ns` on a line that
/// rests at `idle` before and after: each `(time, level after it)`, at bit
/// boundaries, only where the level changes; the last one returns the line
/// to `idle` ([`generic::edges`] in SBUS's [`FORMAT`]).
pub fn edges(bytes: &[u8], start_ns: u64, idle: Level) -> impl Iterator<Item = (u64, Level)> + '_ {
    generic::edges(FORMAT, bytes, start_ns, idle)
}

/// Reads `edges` (`(time, level after it)`, in time order) of a line
/// idling at `idle` as a 100 000 baud 8E2 UART receiver ([`Reader`]), the
/// line staying at its last level after the last edge.
pub fn decode(edges: &[(u64, Level)], idle: Level) -> Vec<Character> {
    generic::decode(FORMAT, edges, idle)
}

/// A UART receiver at 100 000 baud, 8E2 ([`generic::Reader`] in SBUS's
/// [`FORMAT`]).
#[derive(Debug, Clone)]
pub struct Reader(generic::Reader);

impl Reader {
    /// A receiver of a line idling at `idle`.
    pub fn new(idle: Level) -> Reader {
        Reader(generic::Reader::new(FORMAT, idle))
    }

    /// The line went to `level` at `t_ns` (edges in time order): the
    /// character this completes, if any.
    pub fn push(&mut self, t_ns: u64, level: Level) -> Option<Character> {
        self.0.push(t_ns, level)
    }

    /// The line stays at its last level: the character in progress, if
    /// any.
    pub fn finish(&mut self) -> Option<Character> {
        self.0.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_character_is_start_data_lsb_first_even_parity_two_stops() {
        use Level::{High as H, Low as L};
        // 0x0F: four ones, so parity 0.
        assert_eq!(character(0x0F, H), [L, H, H, H, H, L, L, L, L, L, H, H]);
        // 0x01: one one, parity 1.
        assert_eq!(character(0x01, H), [L, H, L, L, L, L, L, L, L, H, H, H]);
        // Inverted: the same, upside down.
        assert_eq!(character(0x01, L), character(0x01, H).map(Level::opposite));
    }

    #[test]
    fn every_byte_decodes_back_in_both_polarities_with_its_times() {
        let bytes: Vec<u8> = (0..=255).collect();
        for idle in [Level::High, Level::Low] {
            let e: Vec<_> = edges(&bytes, 1_000, idle).collect();
            let got = decode(&e, idle);
            assert_eq!(got.len(), 256, "{idle:?}");
            for (i, c) in got.iter().enumerate() {
                assert_eq!(c.byte, i as u8);
                assert!(c.parity_ok && c.stop_ok);
                assert_eq!(c.start_ns, 1_000 + i as u64 * 120_000);
                assert_eq!(c.end_ns, c.start_ns + 120_000);
            }
            assert_eq!(e.last().unwrap().1, idle, "ends at the idle level");
        }
    }

    #[test]
    fn a_flipped_parity_bit_or_a_short_stop_is_seen() {
        let idle = Level::High;
        let mut bits: Vec<Level> = character(0x55, idle).to_vec();
        bits[9] = bits[9].opposite();
        let to_edges = |bits: &[Level]| {
            let mut level = idle;
            let mut e = vec![];
            for (k, &l) in bits.iter().chain([idle].iter()).enumerate() {
                if l != level {
                    e.push((k as u64 * BIT_NS, l));
                    level = l;
                }
            }
            e
        };
        let c = decode(&to_edges(&bits), idle);
        assert_eq!(
            (c[0].byte, c[0].parity_ok, c[0].stop_ok),
            (0x55, false, true)
        );
        let mut bits: Vec<Level> = character(0x55, idle).to_vec();
        bits[11] = idle.opposite();
        let c = decode(&to_edges(&bits), idle);
        assert!(!c[0].stop_ok);
    }
}
