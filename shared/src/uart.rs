//! Bytes as a UART carries them, in the format a protocol names
//! ([`UartFormat`]: baud rate, parity, stop bits; always 8 data bits, least
//! significant first, after one start bit): what the serial line sets its
//! tty to, the simulated line draws as a waveform, and a test reads back.
//! A plain UART idles high and starts each character with a low start bit;
//! an inverted line is the same waveform upside down, idling low.
//!
//! [`edges`] writes bytes sent back to back as the line's edges;
//! [`decode`] ([`Reader`]) reads them back as a UART receiver does: it finds
//! each start bit by the edge that leaves the idle level, samples every bit
//! in its middle, and checks the parity and stop bits.

use crate::signal::Level;

/// Parity, as a UART and the terminal settings hold it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parity {
    /// No parity bit (`PARENB` clear).
    None,
    /// Even parity (`PARENB` set, `PARODD` clear).
    Even,
    /// Odd parity (`PARENB` and `PARODD` set).
    Odd,
}

/// The most bits a character has: start, 8 data, parity, 2 stop.
pub const MAX_CHARACTER_BITS: usize = 12;

/// How a protocol's bytes go on a UART: 8 data bits, this rate, parity and
/// stop bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UartFormat {
    /// Bits per second.
    pub baud: u32,
    /// The parity bit.
    pub parity: Parity,
    /// Stop bits, 1 or 2.
    pub stop_bits: u8,
}

impl UartFormat {
    /// Bits on the wire per byte: start, 8 data, parity, stop.
    pub const fn character_bits(&self) -> u64 {
        1 + 8 + !matches!(self.parity, Parity::None) as u64 + self.stop_bits as u64
    }

    /// Where bit `k` (from 0) of a stream sent back to back starts, ns from
    /// the stream's start (whole ns, truncated: a bit need not be a whole
    /// number of ns).
    pub const fn bit_start_ns(&self, k: u64) -> u64 {
        k * 1_000_000_000 / self.baud as u64
    }

    /// How long `bytes` bytes take sent back to back, ns.
    pub const fn wire_ns(&self, bytes: usize) -> u64 {
        self.bit_start_ns(bytes as u64 * self.character_bits())
    }

    /// As a terminal program names it: `100000 baud 8E2`.
    pub fn describe(&self) -> String {
        let p = match self.parity {
            Parity::None => 'N',
            Parity::Even => 'E',
            Parity::Odd => 'O',
        };
        format!("{} baud 8{p}{}", self.baud, self.stop_bits)
    }

    /// The line levels of one character, start bit first, for a line idling
    /// at `idle`: the first [`Self::character_bits`] of the array (the rest
    /// idle).
    pub fn character(&self, byte: u8, idle: Level) -> [Level; MAX_CHARACTER_BITS] {
        let mut bits = [true; MAX_CHARACTER_BITS];
        bits[0] = false;
        for (i, b) in bits[1..9].iter_mut().enumerate() {
            *b = byte >> i & 1 == 1;
        }
        let odd_ones = byte.count_ones() % 2 == 1;
        match self.parity {
            Parity::None => {}
            Parity::Even => bits[9] = odd_ones,
            Parity::Odd => bits[9] = !odd_ones,
        }
        // A plain UART's 1 is high: the idle level. Inverted, a 1 is low.
        bits.map(|one| if one { idle } else { idle.opposite() })
    }

    /// The level of every bit of `bytes` sent back to back, first bit
    /// first, for a line idling at `idle`.
    pub fn waveform<'a>(&self, bytes: &'a [u8], idle: Level) -> impl Iterator<Item = Level> + 'a {
        let f = *self;
        let n = f.character_bits() as usize;
        bytes
            .iter()
            .flat_map(move |&b| f.character(b, idle).into_iter().take(n))
    }
}

/// The edges of `bytes` sent back to back in `format` from `start_ns` on a
/// line that rests at `idle` before and after: each `(time, level after
/// it)`, at bit boundaries, only where the level changes; the last one
/// returns the line to `idle`. Allocation-free.
pub fn edges(
    format: UartFormat,
    bytes: &[u8],
    start_ns: u64,
    idle: Level,
) -> impl Iterator<Item = (u64, Level)> + '_ {
    format
        .waveform(bytes, idle)
        .chain(std::iter::once(idle))
        .enumerate()
        .scan(idle, move |level, (k, l)| {
            let changed = l != *level;
            *level = l;
            Some(changed.then_some((start_ns + format.bit_start_ns(k as u64), l)))
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
    /// Where its last stop bit ends, ns.
    pub end_ns: u64,
    /// Its start bit held through its middle, and its parity bit (if the
    /// format has one) was right.
    pub parity_ok: bool,
    /// Every stop bit was at the idle level.
    pub stop_ok: bool,
}

/// Reads `edges` (`(time, level after it)`, in time order) of a line idling
/// at `idle` as a UART receiver in `format` ([`Reader`]), the line staying
/// at its last level after the last edge.
pub fn decode(format: UartFormat, edges: &[(u64, Level)], idle: Level) -> Vec<Character> {
    let mut r = Reader::new(format, idle);
    let mut out: Vec<Character> = edges.iter().filter_map(|&(t, l)| r.push(t, l)).collect();
    out.extend(r.finish());
    out
}

/// A UART receiver fed a line's edges as they come: each start bit at an
/// edge away from the idle level (the line before the first edge is idle),
/// every bit sampled in its middle, the next start bit looked for after the
/// middle of the last stop bit. A character is known once an edge comes
/// after its last sample (or at [`Reader::finish`]).
#[derive(Debug, Clone)]
pub struct Reader {
    format: UartFormat,
    idle: Level,
    /// The level after the last edge.
    level: Level,
    /// The character being read: where its start bit began, and the level
    /// at each of its samples taken so far.
    start: Option<u64>,
    samples: [Level; MAX_CHARACTER_BITS],
    taken: usize,
    /// No start bit before this.
    searched_to: u64,
}

impl Reader {
    /// A receiver in `format` of a line idling at `idle`.
    pub fn new(format: UartFormat, idle: Level) -> Reader {
        Reader {
            format,
            idle,
            level: idle,
            start: None,
            samples: [idle; MAX_CHARACTER_BITS],
            taken: 0,
            searched_to: 0,
        }
    }

    /// The format it reads.
    pub fn format(&self) -> UartFormat {
        self.format
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

    /// The middle of bit `k` of a character starting at `start`.
    fn middle(&self, start: u64, k: u64) -> u64 {
        start + (2 * k + 1) * 1_000_000_000 / (2 * self.format.baud as u64)
    }

    /// Takes the samples of the character in progress that fall before
    /// `t_ns` (the line at its level until then); the character when its
    /// last one is taken.
    fn sample_until(&mut self, t_ns: u64) -> Option<Character> {
        let start = self.start?;
        let n = self.format.character_bits() as usize;
        while self.taken < n {
            let at = self.middle(start, self.taken as u64);
            if at >= t_ns {
                return None;
            }
            self.samples[self.taken] = self.level;
            self.taken += 1;
        }
        self.start = None;
        self.searched_to = self.middle(start, n as u64 - 1);
        // A one is the idle level.
        let bits = self.samples.map(|l| l == self.idle);
        let byte = (0..8).fold(0u8, |acc, i| acc | (u8::from(bits[1 + i]) << i));
        let data_ones = bits[1..9].iter().filter(|&&b| b).count();
        let (parity_ok, stops) = match self.format.parity {
            Parity::None => (true, 9),
            Parity::Even => (bits[9] == (data_ones % 2 == 1), 10),
            Parity::Odd => (bits[9] != (data_ones % 2 == 1), 10),
        };
        Some(Character {
            byte,
            start_ns: start,
            end_ns: start + self.format.bit_start_ns(n as u64),
            parity_ok: parity_ok && !bits[0],
            stop_ok: bits[stops..n].iter().all(|&b| b),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CRSF: UartFormat = UartFormat {
        baud: 420_000,
        parity: Parity::None,
        stop_bits: 1,
    };

    #[test]
    fn a_character_of_8n1_is_start_data_lsb_first_stop() {
        use Level::{High as H, Low as L};
        let c = CRSF.character(0x0F, H);
        assert_eq!(&c[..10], [L, H, H, H, H, L, L, L, L, H]);
        assert_eq!(CRSF.character_bits(), 10);
        assert_eq!(CRSF.describe(), "420000 baud 8N1");
        // 26 bytes at 420000 baud: 619.047 us.
        assert_eq!(CRSF.wire_ns(26), 619_047);
    }

    #[test]
    fn every_byte_decodes_back_at_420000_8n1_and_odd_parity() {
        let bytes: Vec<u8> = (0..=255).collect();
        let odd = UartFormat {
            baud: 57_600,
            parity: Parity::Odd,
            stop_bits: 2,
        };
        for f in [CRSF, odd] {
            for idle in [Level::High, Level::Low] {
                let e: Vec<_> = edges(f, &bytes, 1_000, idle).collect();
                let got = decode(f, &e, idle);
                assert_eq!(got.len(), 256, "{f:?} {idle:?}");
                for (i, c) in got.iter().enumerate() {
                    assert_eq!(c.byte, i as u8);
                    assert!(c.parity_ok && c.stop_ok, "{f:?} {i}");
                    assert_eq!(
                        c.start_ns,
                        1_000 + f.bit_start_ns(i as u64 * f.character_bits())
                    );
                }
            }
        }
    }
}
