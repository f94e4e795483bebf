//! A receiver reading a line edge by edge, whatever the protocol: PPM as
//! the receiver's capture times it, SBUS and CRSF as a UART in the wire's
//! format and the firmware's framing read them. What the tools that decode
//! a trace (`ppm-watch`, `jitter --trace`) ask, instead of branching on the
//! protocol themselves.

use super::uart::{self, UartFormat};
use super::Protocol;
use crate::crsf::{self, CrsfReceiver};
use crate::receiver::{Receiver, ReceiverDecoder, TIMED_EDGE};
use crate::sbus::{self, SbusReceiver};
use crate::signal::Level;

/// CRSF's UART format at its default rate.
const CRSF_UART: UartFormat = UartFormat {
    baud: super::crsf::BAUD_DEFAULT,
    parity: uart::Parity::None,
    stop_bits: 1,
};

/// What the receiver made of a frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reading {
    /// It uses these values.
    Frame {
        /// When the frame started (PPM) or was taken (its last byte's
        /// end), ns.
        at_ns: u64,
        /// Its channel values, ns.
        channels_ns: Vec<u64>,
        /// The PPM decoder saw the frame whole (its closing sync); always
        /// true for a frame of bytes.
        complete: bool,
    },
    /// It took a frame and did not use its values, for this reason.
    Refused {
        /// When, ns.
        at_ns: u64,
        /// Why, in a few words.
        why: &'static str,
    },
}

/// A receiver reading one line; see the [module](self).
#[derive(Debug, Clone)]
pub enum LineReader {
    /// PPM.
    Ppm(ReceiverDecoder),
    /// SBUS.
    Sbus {
        /// Whose framing and values.
        receiver: SbusReceiver,
        /// The UART.
        uart: uart::Reader,
        /// The firmware's framing.
        framer: sbus::Framer,
    },
    /// CRSF.
    Crsf {
        /// Whose framing and values.
        receiver: CrsfReceiver,
        /// The UART.
        uart: uart::Reader,
        /// The firmware's framing.
        framer: crsf::Framer,
    },
}

impl LineReader {
    /// A reader of a `protocol` line idling at `idle`, as `receiver` reads
    /// it (`None`: the protocol's usual one: EdgeTX for PPM and SBUS, iNav
    /// for CRSF, which reads every encoding exactly), a UART at `baud` (the
    /// protocol's own when `None`). Errs, saying which it reads, for a
    /// receiver whose reading of the protocol is not modelled.
    pub fn new(
        protocol: Protocol,
        receiver: Option<Receiver>,
        idle: Level,
        baud: Option<u32>,
    ) -> Result<LineReader, String> {
        // A rate of 0 (a damaged header) is no rate: the protocol's own.
        let baud = baud.filter(|&b| b > 0);
        let format = |f: UartFormat| UartFormat {
            baud: baud.unwrap_or(f.baud),
            ..f
        };
        Ok(match protocol {
            Protocol::Ppm => LineReader::Ppm(ReceiverDecoder::new(
                receiver.unwrap_or(Receiver::EdgeTx),
                TIMED_EDGE,
            )),
            Protocol::Sbus => {
                let receiver = match receiver.unwrap_or(Receiver::EdgeTx) {
                    Receiver::EdgeTx => SbusReceiver::EdgeTx,
                    Receiver::Betaflight => SbusReceiver::Betaflight2026,
                    Receiver::ArduPilot => SbusReceiver::ArduPilot,
                    Receiver::OpenTx => {
                        return Err("OpenTX's SBUS input is not modelled: read it as edgetx, betaflight or ardupilot".into())
                    }
                };
                LineReader::Sbus {
                    receiver,
                    uart: uart::Reader::new(format(sbus::uart::FORMAT), idle),
                    framer: sbus::Framer::new(receiver),
                }
            }
            Protocol::Crsf => {
                let receiver = match receiver {
                    None => CrsfReceiver::Inav,
                    Some(Receiver::Betaflight) => CrsfReceiver::Betaflight,
                    Some(Receiver::ArduPilot) => CrsfReceiver::ArduPilot,
                    Some(r @ (Receiver::EdgeTx | Receiver::OpenTx)) => {
                        return Err(format!(
                            "{} takes no CRSF: read a CRSF line as betaflight or ardupilot (or the default, iNav's reading)",
                            r.name()
                        ))
                    }
                };
                LineReader::Crsf {
                    receiver,
                    uart: uart::Reader::new(format(CRSF_UART), idle),
                    framer: crsf::Framer::new(receiver),
                }
            }
        })
    }

    /// The UART format of a protocol of bytes (`None` for PPM).
    pub fn uart_format(&self) -> Option<UartFormat> {
        match self {
            LineReader::Ppm(_) => None,
            LineReader::Sbus { uart, .. } | LineReader::Crsf { uart, .. } => Some(uart.format()),
        }
    }

    /// The name of the firmware whose reading this is.
    pub fn reads_as(&self) -> &'static str {
        match self {
            LineReader::Ppm(d) => d.receiver().name(),
            LineReader::Sbus { receiver, .. } => receiver.name(),
            LineReader::Crsf { receiver, .. } => receiver.name(),
        }
    }

    /// Feeds the edge to `level` at `at_ns`: what the receiver makes of the
    /// frame it completes, if any (a CRSF receiver's link statistics are no
    /// reading).
    pub fn push(&mut self, at_ns: u64, level: Level) -> Option<Reading> {
        match self {
            LineReader::Ppm(d) => d.push(at_ns, level).map(|f| Reading::Frame {
                at_ns: f.start_ns,
                channels_ns: f.channels_ns,
                complete: f.complete,
            }),
            LineReader::Sbus {
                receiver,
                uart,
                framer,
            } => {
                let c = uart.push(at_ns, level)?;
                let taken = framer.push(c.byte, c.end_ns)?;
                Some(sbus_reading(*receiver, &taken))
            }
            LineReader::Crsf {
                receiver,
                uart,
                framer,
            } => {
                let c = uart.push(at_ns, level)?;
                let taken = framer.push(c.byte, c.end_ns)?;
                crsf_reading(*receiver, &taken)
            }
        }
    }

    /// The line stayed idle up to `now_ns` (or ended): a character still
    /// being read ends, a receiver that takes a frame at an idle line
    /// (EdgeTX's SBUS) takes it, and a trainer input hands on the channels
    /// of a PPM frame no sync closed.
    pub fn idle(&mut self, now_ns: u64) -> Option<Reading> {
        match self {
            LineReader::Ppm(d) => d.finish().map(|f| Reading::Frame {
                at_ns: f.start_ns,
                channels_ns: f.channels_ns,
                complete: f.complete,
            }),
            LineReader::Sbus {
                receiver,
                uart,
                framer,
            } => {
                if let Some(c) = uart.finish() {
                    if let Some(t) = framer.push(c.byte, c.end_ns) {
                        return Some(sbus_reading(*receiver, &t));
                    }
                }
                let t = framer.idle(now_ns)?;
                Some(sbus_reading(*receiver, &t))
            }
            LineReader::Crsf {
                receiver,
                uart,
                framer,
            } => {
                let c = uart.finish()?;
                let taken = framer.push(c.byte, c.end_ns)?;
                crsf_reading(*receiver, &taken)
            }
        }
    }
}

/// What CRSF receiver `r` makes of frame `t` (its link statistics are no
/// reading).
fn crsf_reading(r: CrsfReceiver, t: &crsf::Taken) -> Option<Reading> {
    match r.verdict(t) {
        crsf::Verdict::Used { channels_ns } => Some(Reading::Frame {
            at_ns: t.at_ns,
            channels_ns: channels_ns.to_vec(),
            complete: true,
        }),
        crsf::Verdict::LinkStatistics(_) => None,
        crsf::Verdict::Ignored => Some(Reading::Refused {
            at_ns: t.at_ns,
            why: "frame ignored (not RC channels to the flight controller)",
        }),
    }
}

/// What SBUS receiver `r` makes of frame `t`.
fn sbus_reading(r: SbusReceiver, t: &sbus::Taken) -> Reading {
    match r.verdict(&t.frame) {
        sbus::Verdict::Used(v) => Reading::Frame {
            at_ns: t.at_ns,
            channels_ns: v.channels_ns.to_vec(),
            complete: true,
        },
        sbus::Verdict::Invalid => Reading::Refused {
            at_ns: t.at_ns,
            why: "invalid frame (header or end byte)",
        },
        sbus::Verdict::NoSignal => Reading::Refused {
            at_ns: t.at_ns,
            why: "failsafe flag: no signal",
        },
        sbus::Verdict::Failsafe => Reading::Refused {
            at_ns: t.at_ns,
            why: "failsafe",
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The edges of `bytes` on a line idling high, 8N1 at 420 000 baud,
    /// from `start_ns`.
    fn crsf_edges(bytes: &[u8], start_ns: u64) -> Vec<(u64, Level)> {
        uart::edges(CRSF_UART, bytes, start_ns, Level::High).collect()
    }

    /// Every RC frame of a stream reads back, the last one too (its CRC is
    /// the character still being read when the stream ends); link
    /// statistics are no reading; a trace of EdgeTX is refused by name.
    #[test]
    fn a_crsf_stream_reads_back_to_its_last_frame() {
        let raw: [u16; 16] = std::array::from_fn(|i| 200 + 100 * i as u16);
        let rc = crsf::encode_rc(&raw);
        let link = crsf::LinkStatistics::WIRED.encode();
        let mut edges = Vec::new();
        for k in 0..3u64 {
            let start = 1_000_000 + k * 4_000_000;
            edges.extend(crsf_edges(&rc, start));
            if k < 2 {
                edges.extend(crsf_edges(&link, start + 700_000));
            }
        }
        let mut r = LineReader::new(
            Protocol::Crsf,
            Some(Receiver::Betaflight),
            Level::High,
            None,
        )
        .unwrap();
        assert_eq!(r.uart_format(), Some(CRSF_UART));
        let mut frames: Vec<Reading> = edges.iter().filter_map(|&(t, l)| r.push(t, l)).collect();
        frames.extend(r.idle(20_000_000));
        assert_eq!(frames.len(), 3, "{frames:?}");
        for f in &frames {
            let Reading::Frame { channels_ns, .. } = f else {
                panic!("{f:?}")
            };
            let want: Vec<u64> = raw
                .iter()
                .map(|&v| CrsfReceiver::Betaflight.read_ns(v))
                .collect();
            assert_eq!(channels_ns, &want);
        }
        let e = LineReader::new(Protocol::Crsf, Some(Receiver::EdgeTx), Level::High, None);
        assert!(e.unwrap_err().contains("edgetx takes no CRSF"));
    }
}
