//! SBUS bytes as a line carries them: a UART's 8E2 characters (a start bit,
//! 8 data bits least significant first, an even parity bit, 2 stop bits) at
//! 100 000 baud, 10 us a bit. A plain UART idles high and starts each
//! character with a low start bit; true ("inverted") SBUS is the same
//! waveform upside down, idling low.
//!
//! [`waveform`] writes a frame's bytes as line levels, bit by bit (the
//! simulated line's trace of an SBUS output; an SPI output's bitstream);
//! [`decode`] reads a waveform back as a UART receiver does: it finds each
//! start bit by the edge that leaves the idle level, samples every bit in its
//! middle, and checks parity and both stop bits.

use super::{BAUD, BYTE_BITS};
use crate::signal::Level;

/// One bit on the wire, ns: 10 us.
pub const BIT_NS: u64 = 1_000_000_000 / BAUD;

/// The line levels of one character, start bit first, for a UART idling at
/// `idle` (a plain UART's `High`; true SBUS `Low`).
pub fn character(byte: u8, idle: Level) -> [Level; BYTE_BITS as usize] {
    let parity = byte.count_ones() % 2 == 1;
    let mut bits = [true; BYTE_BITS as usize];
    bits[0] = false;
    for (i, b) in bits[1..9].iter_mut().enumerate() {
        *b = byte >> i & 1 == 1;
    }
    bits[9] = parity;
    // A plain UART's 1 is high: the idle level. Inverted, a 1 is low.
    bits.map(|one| if one { idle } else { idle.opposite() })
}

/// The level of every bit of `bytes` sent back to back, first bit first,
/// for a line idling at `idle`: [`BYTE_BITS`] bits a byte.
pub fn waveform(bytes: &[u8], idle: Level) -> impl Iterator<Item = Level> + '_ {
    bytes.iter().flat_map(move |&b| character(b, idle))
}

/// The edges of `bytes` sent back to back from `start_ns` on a line that
/// rests at `idle` before and after: each `(time, level after it)`, at bit
/// boundaries, only where the level changes; the last one returns the line
/// to `idle`.
pub fn edges(bytes: &[u8], start_ns: u64, idle: Level) -> impl Iterator<Item = (u64, Level)> + '_ {
    waveform(bytes, idle)
        .chain(std::iter::once(idle))
        .enumerate()
        .scan(idle, move |level, (k, l)| {
            let changed = l != *level;
            *level = l;
            Some(changed.then_some((start_ns + k as u64 * BIT_NS, l)))
        })
        .flatten()
}

/// One character a UART receiver read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Character {
    /// Its data bits.
    pub byte: u8,
    /// Where its start bit began, ns.
    pub start_ns: u64,
    /// Where its second stop bit ends, ns (what [`super::Framer::push`]
    /// takes).
    pub end_ns: u64,
    /// Its start bit held through its middle, and its parity bit made the
    /// count of ones even.
    pub parity_ok: bool,
    /// Both stop bits were at the idle level.
    pub stop_ok: bool,
}

/// Reads `edges` (`(time, level after it)`, in time order) of a line
/// idling at `idle` as a 100 000 baud 8E2 UART receiver ([`Reader`]), the
/// line staying at its last level after the last edge.
pub fn decode(edges: &[(u64, Level)], idle: Level) -> Vec<Character> {
    let mut r = Reader::new(idle);
    let mut out: Vec<Character> = edges.iter().filter_map(|&(t, l)| r.push(t, l)).collect();
    out.extend(r.finish());
    out
}

/// A UART receiver at 100 000 baud, 8E2, fed a line's edges as they come:
/// each start bit at an edge away from the idle level (the line before the
/// first edge is idle), every bit sampled in its middle, the next start bit
/// looked for after the middle of the last stop bit. A character is known
/// once an edge comes after its last sample (or at [`Reader::finish`]).
#[derive(Debug, Clone)]
pub struct Reader {
    idle: Level,
    /// The level after the last edge.
    level: Level,
    /// The character being read: where its start bit began, and the level
    /// at each of its samples taken so far.
    start: Option<u64>,
    samples: [Level; BYTE_BITS as usize],
    taken: usize,
    /// No start bit before this.
    searched_to: u64,
}

impl Reader {
    /// A receiver of a line idling at `idle`.
    pub fn new(idle: Level) -> Reader {
        Reader {
            idle,
            level: idle,
            start: None,
            samples: [idle; BYTE_BITS as usize],
            taken: 0,
            searched_to: 0,
        }
    }

    /// The line went to `level` at `t_ns` (edges in time order): the
    /// character this completes, if any.
    pub fn push(&mut self, t_ns: u64, level: Level) -> Option<Character> {
        let done = self.sample_until(t_ns);
        self.level = level;
        if self.start.is_none() && level != self.idle && t_ns >= self.searched_to {
            self.start = Some(t_ns);
            self.taken = 0;
        }
        done
    }

    /// The line stays at its last level: the character in progress, if
    /// any.
    pub fn finish(&mut self) -> Option<Character> {
        self.sample_until(u64::MAX)
    }

    /// Takes the samples of the character in progress that fall before
    /// `t_ns` (the line at its level until then); the character when its
    /// last one is taken.
    fn sample_until(&mut self, t_ns: u64) -> Option<Character> {
        let start = self.start?;
        while self.taken < BYTE_BITS as usize {
            let at = start + self.taken as u64 * BIT_NS + BIT_NS / 2;
            if at >= t_ns {
                return None;
            }
            self.samples[self.taken] = self.level;
            self.taken += 1;
        }
        self.start = None;
        self.searched_to = start + (BYTE_BITS - 1) * BIT_NS + BIT_NS / 2;
        // A one is the idle level.
        let bits = self.samples.map(|l| l == self.idle);
        let byte = (0..8).fold(0u8, |acc, i| acc | (u8::from(bits[1 + i]) << i));
        let ones = bits[1..10].iter().filter(|&&b| b).count();
        Some(Character {
            byte,
            start_ns: start,
            end_ns: start + BYTE_BITS * BIT_NS,
            parity_ok: ones % 2 == 0 && !bits[0],
            stop_ok: bits[10] && bits[11],
        })
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
