//! The SPI half of the real-kernel test (a helper module of vm.rs): ppmd's
//! `spi:` output read back from the gpio_value trace of the spi-gpio
//! master's lines, transfer by transfer, in bit time.

use super::{logged_frames, read, COMMAND_US};
use ppm_shared::decode::{decode, DecoderLimits};
use ppm_shared::frame::Level;
use std::path::Path;

// ---------------------------------------------------------------- spi output
//
// ppmd's `spi:` output drives the kernel's spi-gpio master, which bit-banges
// SCK, MOSI and CS (lines of a second gpio-sim chip) through gpiolib, so the
// gpio_value tracepoint records every bit. The host rebuilds each transfer
// (CS low) from the trace, MOSI sampled at each rising SCK edge (mode 0),
// and reads the frame in it in bit time: bit k is the line during
// [k/hz, (k+1)/hz) after the transfer's start. spi-gpio clocks as fast as
// gpiolib goes whatever the rate, so real time says nothing about the bits;
// between transfers it is real time (the sync), where only the line's
// silence and a sync's minimum length are checked.

/// The SPI bus of spi_lines.txt: global GPIO numbers as the trace shows
/// them (chip base + offset), the bit rate ppmd was given, the SPI mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct SpiLines {
    pub(crate) sck: u32,
    pub(crate) mosi: u32,
    pub(crate) cs: u32,
    pub(crate) hz: u32,
    pub(crate) mode: u32,
}

pub(crate) fn parse_spi_lines(text: &str) -> SpiLines {
    let get = |key: &str| -> u32 {
        text.lines()
            .find_map(|l| l.strip_prefix(key)?.strip_prefix(' ')?.trim().parse().ok())
            .unwrap_or_else(|| panic!("no `{key} N` in spi_lines.txt:\n{text}"))
    };
    SpiLines {
        sck: get("sck"),
        mosi: get("mosi"),
        cs: get("cs"),
        hz: get("hz"),
        mode: get("mode"),
    }
}

/// `(time_us, gpio, value)` of every value set on one of `gpios`, in trace
/// order (the text trace's microsecond times are enough here).
pub(crate) fn trace_sets(text: &str, gpios: &[u32]) -> Vec<(u64, u32, u8)> {
    text.lines()
        .filter_map(|l| {
            let (head, rest) = l.split_once(": gpio_value: ")?;
            let mut f = rest.split_whitespace();
            let gpio: u32 = f.next()?.parse().ok()?;
            if f.next()? != "set" || !gpios.contains(&gpio) {
                return None;
            }
            let value: u8 = f.next()?.parse().ok()?;
            let (s, us) = head.rsplit(' ').next()?.split_once('.')?;
            let t = s.parse::<u64>().ok()? * 1_000_000 + us.parse::<u64>().ok()?;
            Some((t, gpio, value))
        })
        .collect()
}

/// One transfer: CS low from `start_us` to `end_us` (trace time), `bits`
/// the MOSI level at each rising SCK edge in between.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct SpiTransfer {
    pub(crate) start_us: u64,
    pub(crate) end_us: u64,
    pub(crate) bits: Vec<u8>,
}

/// The bus as the trace shows it: the transfers, and what the lines did
/// where mode 0 wants them quiet.
#[derive(Debug, Default)]
pub(crate) struct SpiBus {
    pub(crate) transfers: Vec<SpiTransfer>,
    /// MOSI's level at the end of each transfer (it stays there until the next).
    pub(crate) mosi_after: Vec<Option<u8>>,
    /// Times MOSI changed while CS was high.
    pub(crate) mosi_changes_outside: Vec<u64>,
    /// Rising SCK edges while CS was high.
    pub(crate) sck_rises_outside: usize,
    /// CS changes while SCK was high (mode 0: SCK idles low).
    pub(crate) cs_with_sck_high: usize,
}

/// Rebuilds the transfers of a mode 0 bus from its lines' value changes.
/// A line's level is unknown until its first event; CS counts as high then.
pub(crate) fn spi_transfers(sets: &[(u64, u32, u8)], lines: &SpiLines) -> SpiBus {
    assert_eq!(lines.mode, 0, "only SPI mode 0 is checked");
    let mut bus = SpiBus::default();
    let (mut sck, mut mosi, mut cs) = (None::<u8>, None::<u8>, None::<u8>);
    let mut current: Option<SpiTransfer> = None;
    for &(t, gpio, v) in sets {
        if gpio == lines.cs {
            let asserted = cs == Some(0);
            if (v == 0) != asserted {
                if sck == Some(1) {
                    bus.cs_with_sck_high += 1;
                }
                if v == 0 {
                    current = Some(SpiTransfer {
                        start_us: t,
                        end_us: t,
                        bits: Vec::new(),
                    });
                } else if let Some(mut x) = current.take() {
                    x.end_us = t;
                    bus.transfers.push(x);
                    bus.mosi_after.push(mosi);
                }
            }
            cs = Some(v);
        } else if gpio == lines.sck {
            if v == 1 && sck != Some(1) {
                match current.as_mut() {
                    Some(x) => {
                        x.bits.push(mosi.unwrap_or_else(|| {
                            panic!("SCK rose at {t} us before MOSI was ever set")
                        }))
                    }
                    None => bus.sck_rises_outside += 1,
                }
            }
            sck = Some(v);
        } else if gpio == lines.mosi {
            if current.is_none() && mosi.is_some_and(|m| m != v) {
                bus.mosi_changes_outside.push(t);
            }
            mosi = Some(v);
        }
    }
    bus
}

/// A transfer's pulses (runs of 1 bits) as `(rise, fall)` bit indices; the
/// line is low before bit 0. A pulse still high at the end has fall = len.
pub(crate) fn bit_pulses(bits: &[u8]) -> Vec<(usize, usize)> {
    let mut pulses = Vec::new();
    let mut rise = None;
    for (k, &b) in bits.iter().enumerate() {
        match (b, rise) {
            (1, None) => rise = Some(k),
            (0, Some(r)) => {
                pulses.push((r, k));
                rise = None;
            }
            _ => {}
        }
    }
    if let Some(r) = rise {
        pulses.push((r, bits.len()));
    }
    pulses
}

/// A transfer read as one PPM frame, in bit time (us).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct SpiFrame {
    /// Rise-to-rise time of a lead-in pulse before the frame (a sync), if any.
    pub(crate) lead_in_us: Option<f64>,
    /// Rise-to-rise times after the frame's first pulse.
    pub(crate) channels_us: Vec<f64>,
    /// Every pulse's width, the lead-in's included.
    pub(crate) widths_us: Vec<f64>,
    /// 0 bits after the last pulse's end.
    pub(crate) tail_bits: usize,
}

/// Reads the frame of a transfer (`None`: no pulse, e.g. ppmd parking the
/// line with a zero byte). A first rise-to-rise time of 4 ms or more (a
/// sync to a receiver) is a lead-in pulse's.
pub(crate) fn spi_frame(bits: &[u8], hz: u32) -> Option<SpiFrame> {
    let pulses = bit_pulses(bits);
    let last = pulses.last()?;
    let us = |n: usize| n as f64 * 1e6 / hz as f64;
    let mut rises: Vec<usize> = pulses.iter().map(|p| p.0).collect();
    let lead_in_us = match rises[..] {
        [a, b, ..] if us(b - a) >= 4_000.0 => {
            rises.remove(0);
            Some(us(b - a))
        }
        _ => None,
    };
    Some(SpiFrame {
        lead_in_us,
        channels_us: rises.windows(2).map(|w| us(w[1] - w[0])).collect(),
        widths_us: pulses.iter().map(|&(r, f)| us(f - r)).collect(),
        tail_bits: bits.len() - last.1,
    })
}

/// The spi output in the guest: ppmd on /dev/spidev0.0 (spi-gpio on
/// gpio-sim lines, see tests/vm/ppm_spi_board.c) at spi_lines.txt's rate,
/// fed the example command at 50 Hz. Every frame transfer must carry the
/// command exactly (to one bit), 300 us pulses, 8-bit words, MOSI low and
/// quiet between transfers; the first after silence with its 5 ms lead-in.
pub(crate) fn check_spi(out: &Path, flavor: &str) {
    let log = read(out, "spi_ppmd.log");
    assert_eq!(read(out, "spi_ppmd_exit.txt").trim(), "0", "{log}");
    let lines = parse_spi_lines(&read(out, "spi_lines.txt"));
    assert!(
        log.contains(&format!("spi /dev/spidev0.0 at {} Hz", lines.hz)),
        "{log}"
    );
    assert!(log.contains(" 0 write errors"), "{log}");
    let trace = read(out, "spi_trace.txt");
    let sets = trace_sets(&trace, &[lines.sck, lines.mosi, lines.cs]);
    let bus = spi_transfers(&sets, &lines);
    let hz = lines.hz;
    let bit_us = 1e6 / hz as f64;
    let pulse_us = 300.0;
    let what = |k: usize| format!("transfer {k} of the spi output on {flavor}");

    // Mode 0 on the wires: SCK low whenever CS changes and never clocking
    // outside a transfer; MOSI still between transfers.
    assert_eq!(
        bus.sck_rises_outside, 0,
        "SCK clocked with CS high on {flavor}"
    );
    assert_eq!(
        bus.cs_with_sck_high, 0,
        "CS changed with SCK high on {flavor}"
    );
    assert!(
        bus.mosi_changes_outside.is_empty(),
        "MOSI changed between transfers on {flavor} at {:?} us",
        bus.mosi_changes_outside
    );

    let mut frames: Vec<(usize, SpiFrame)> = Vec::new();
    let mut parks = Vec::new();
    for (k, x) in bus.transfers.iter().enumerate() {
        assert!(
            !x.bits.is_empty() && x.bits.len() % 8 == 0,
            "{}: {} bits, not whole bytes",
            what(k),
            x.bits.len()
        );
        match spi_frame(&x.bits, hz) {
            Some(f) => frames.push((k, f)),
            None => parks.push(k),
        }
    }
    assert!(
        frames.len() >= 40,
        "{} frame transfers (of {}) on {flavor}",
        frames.len(),
        bus.transfers.len()
    );
    // Zero-byte transfers (ppmd parks the line low when it opens the device)
    // only before the first frame or after the last.
    let (first, last) = (frames[0].0, frames[frames.len() - 1].0);
    assert!(
        parks.iter().all(|&k| k < first || k > last),
        "pulse-less transfers {parks:?} among the frames {first}..={last} on {flavor}"
    );
    let near = |got: f64, want: f64| (got - want).abs() <= bit_us + 1e-9;
    for (i, (k, f)) in frames.iter().enumerate() {
        let x = &bus.transfers[*k];
        let ok = f.channels_us.len() == COMMAND_US.len()
            && f.channels_us
                .iter()
                .zip(COMMAND_US)
                .all(|(g, w)| near(*g, w as f64))
            && f.widths_us.iter().all(|w| near(*w, pulse_us))
            && x.bits[0] == 1
            && (1..=8).contains(&f.tail_bits);
        assert!(ok, "{}: {f:?}, want {COMMAND_US:?} us, {pulse_us} us pulses, starting with a pulse, 1..=8 zero bits after the last", what(*k));
        // The lead-in: on the first frame (after silence), 5 ms before it;
        // on another only after skipped frames (reported below), 5 to 6.8
        // ms before it (moved out of a gap a trainer reads as a channel).
        let lead_in_max_us = ppmd::emitter::LEAD_IN_MAX_NS as f64 / 1_000.0;
        match f.lead_in_us {
            Some(l) if i == 0 => assert!(near(l, 5_000.0), "{}: lead-in {l} us", what(*k)),
            Some(l) => assert!(
                l + bit_us >= 5_000.0 && l <= lead_in_max_us + bit_us,
                "{}: lead-in {l} us",
                what(*k)
            ),
            None => assert!(i > 0, "{}: the first frame has no lead-in: {f:?}", what(*k)),
        }
        assert_eq!(
            bus.mosi_after[*k],
            Some(0),
            "{}: MOSI not low after it",
            what(*k)
        );
    }
    // One transfer per frame ppmd logged.
    let logged = logged_frames(out, "spi_frames.jsonl").len();
    assert_eq!(
        logged,
        frames.len(),
        "{logged} frames logged, {} frame transfers on {flavor}",
        frames.len()
    );
    // Between frames, in real time: at least the shortest sync ppmd keeps
    // (follow_sync_min_us, 5000) less 500 us. The bits take no real time to
    // speak of (spi-gpio clocks as fast as gpiolib goes: ~1.6 us a bit
    // under TCG), so only a transfer started far too soon fails this.
    let gaps: Vec<u64> = frames
        .windows(2)
        .map(|w| bus.transfers[w[1].0].start_us - bus.transfers[w[0].0].end_us)
        .collect();
    let min_gap = *gaps.iter().min().unwrap();
    assert!(
        min_gap >= 4_500,
        "a sync of {min_gap} us between transfers on {flavor}: {gaps:?}"
    );

    // The project's decoder on the same line: each transfer's edges in bit
    // time from its real start, the syncs in real time.
    let mut edges: Vec<(u64, Level)> = Vec::new();
    for (k, _) in &frames {
        let x = &bus.transfers[*k];
        let at = |bit: usize| x.start_us * 1_000 + bit as u64 * 1_000_000_000 / hz as u64;
        for (r, f) in bit_pulses(&x.bits) {
            edges.push((at(r), Level::High));
            edges.push((at(f), Level::Low));
        }
    }
    let ours = decode(edges, Level::High, DecoderLimits::default());
    let (complete, open): (Vec<_>, Vec<_>) = ours.iter().partition(|f| f.complete);
    assert_eq!(
        complete.len() + open.len(),
        frames.len(),
        "the project's decoder read {} frames (of {}) on {flavor}",
        ours.len(),
        frames.len()
    );
    // Each frame closed by the next one's sync, but for the last.
    assert!(
        open.len() <= 1 && complete.len() + 1 >= frames.len(),
        "the project's decoder left {} frames open on {flavor}",
        open.len()
    );
    for f in &ours {
        assert_eq!(
            f.channels_us(),
            COMMAND_US,
            "the project's decoder on {flavor}"
        );
    }

    // Reported, not asserted: how the bus ran in real (guest) time.
    let mut took: Vec<u64> = frames
        .iter()
        .map(|(k, _)| bus.transfers[*k].end_us - bus.transfers[*k].start_us)
        .collect();
    took.sort_unstable();
    let bits: Vec<usize> = frames
        .iter()
        .map(|(k, _)| bus.transfers[*k].bits.len())
        .collect();
    let lead_ins = frames
        .iter()
        .filter(|(_, f)| f.lead_in_us.is_some())
        .count();
    eprintln!(
        "spi output on {flavor}: {} frame transfers at {hz} Hz ({}..={} bits), {} lead-in, {} pulse-less (park) transfers; CS low for {}..{} us (median {}) of guest time a transfer, syncs {}..{} us",
        frames.len(),
        bits.iter().min().unwrap(),
        bits.iter().max().unwrap(),
        lead_ins,
        parks.len(),
        took[0],
        took[took.len() - 1],
        took[took.len() / 2],
        min_gap,
        gaps.iter().max().unwrap()
    );
}
