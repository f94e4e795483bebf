//! `ppm-watch`: decodes the simulated line's trace as a receiver's firmware
//! would and shows the channel values, live or once: PPM as the receiver's
//! capture reads it, SBUS (a trace whose header says `protocol sbus`) as its
//! UART and framing read it.

use anyhow::{Context, Result};
use clap::Parser;
use ppm_shared::frame::{Level, Protocol};
use ppm_shared::receiver::{Receiver, ReceiverChoice, ReceiverDecoder, TIMED_EDGE};
use ppm_shared::sbus::{uart, Framer, SbusReceiver, Taken, Verdict};
use ppm_shared::trace::{parse_line, Trace};
use ppm_tools::parse_duration;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Decode a ppmd sim trace as a receiver does and print the channels.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// The trace file written by `ppmd --output sim:PATH`.
    trace: PathBuf,
    /// Decode the whole file once, print every frame, and exit.
    #[arg(long)]
    once: bool,
    /// While following, print at most one frame per this interval.
    #[arg(long, default_value = "200ms", value_parser = parse_duration)]
    every: Duration,
    /// Decode by actual edge times instead of scheduled times.
    #[arg(long)]
    actual: bool,
    /// Decode as this receiver does: edgetx, opentx, betaflight or
    /// ardupilot (default: the one ppmd's configuration names in the trace,
    /// edgetx when that is `any`).
    #[arg(long, value_name = "RECEIVER")]
    receiver: Option<Receiver>,
}

fn main() {
    if let Err(e) = run(Cli::parse()) {
        eprintln!("ppm-watch: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    if cli.once {
        let text = std::fs::read_to_string(&cli.trace)
            .with_context(|| format!("reading {}", cli.trace.display()))?;
        let mut header = Header::default();
        text.lines().for_each(|l| header.take(l));
        let trace = Trace::read(text.as_bytes())?;
        let receiver = cli.receiver.unwrap_or(trace.default_receiver());
        let shown: Vec<String> = match trace.protocol {
            Protocol::Ppm => trace
                .decode_as(receiver, cli.actual)
                .iter()
                .map(|f| header.format(f.start_ns, &f.channels_ns, f.complete))
                .collect(),
            Protocol::Sbus => {
                let r = sbus_receiver(receiver)?;
                trace
                    .sbus_taken(r, cli.actual)
                    .iter()
                    .map(|t| header.format_sbus(r, t))
                    .collect()
            }
            Protocol::Crsf => anyhow::bail!("ppm-watch does not decode CRSF traces yet"),
        };
        let mut out = std::io::stdout().lock();
        for line in shown {
            if writeln!(out, "{line}").is_err() {
                break; // reader went away (e.g. `| head`)
            }
        }
        return Ok(());
    }
    follow(&cli)
}

/// The SBUS receiver whose reading `ppm-watch` shows for `receiver`:
/// Betaflight's is 2026.6's (4.5 reads values alike).
fn sbus_receiver(receiver: Receiver) -> Result<SbusReceiver> {
    match receiver {
        Receiver::EdgeTx => Ok(SbusReceiver::EdgeTx),
        Receiver::Betaflight => Ok(SbusReceiver::Betaflight2026),
        Receiver::ArduPilot => Ok(SbusReceiver::ArduPilot),
        Receiver::OpenTx => anyhow::bail!(
            "OpenTX's SBUS input is not modelled: use --receiver edgetx, betaflight or ardupilot"
        ),
    }
}

/// What the trace's `#` header says.
#[derive(Default)]
struct Header {
    idle: Option<Level>,
    names: Vec<String>,
    receiver: Option<ReceiverChoice>,
    protocol: Protocol,
}

impl Header {
    fn take(&mut self, line: &str) {
        if let Some(v) = line.strip_prefix("# idle_level ") {
            self.idle = Some(Level::from_bit(v.trim() == "1"));
        } else if let Some(v) = line.strip_prefix("# channels ") {
            self.names = v.trim().split(',').map(str::to_string).collect();
        } else if let Some(v) = line.strip_prefix("# receiver ") {
            self.receiver = v.trim().parse().ok();
        } else if let Some(v) = line.trim().strip_prefix("# protocol ") {
            self.protocol = v.trim().parse().unwrap_or(self.protocol);
        }
    }

    /// A frame from `at_ns` with these channel values.
    fn format(&self, at_ns: u64, channels_ns: &[u64], complete: bool) -> String {
        let mut s = format!("{:>14.6} s ", at_ns as f64 / 1e9);
        for (i, ns) in channels_ns.iter().enumerate() {
            let name = self
                .names
                .get(i)
                .cloned()
                .unwrap_or_else(|| format!("ch{}", i + 1));
            s += &format!(" {name} {:7.1}", *ns as f64 / 1e3);
        }
        // A frame cut short (at a late edge, or by a gap no receiver takes)
        // has fewer channels than the trace's header names; a frame with
        // all of them is whole, whatever gap follows it (the trainer inputs
        // use each channel as it arrives).
        let want = self.names.len();
        if want > 0 && channels_ns.len() < want {
            s += &format!("  (cut short: {} of {want} channels)", channels_ns.len());
        } else if want == 0 && !complete {
            s += "  (incomplete)";
        }
        s
    }

    /// An SBUS frame `receiver` took: its values, or what it does instead.
    fn format_sbus(&self, receiver: SbusReceiver, t: &Taken) -> String {
        match receiver.verdict(&t.frame) {
            Verdict::Used(r) => self.format(t.at_ns, &r.channels_ns, true),
            v => format!(
                "{:>14.6} s  {}",
                t.at_ns as f64 / 1e9,
                match v {
                    Verdict::Invalid => "invalid frame (header or end byte)",
                    Verdict::NoSignal => "failsafe flag: no signal",
                    _ => "failsafe",
                }
            ),
        }
    }
}

/// A receiver's decoder, fed the trace's edges as they come.
enum Watcher {
    Ppm(ReceiverDecoder),
    Sbus {
        receiver: SbusReceiver,
        uart: uart::Reader,
        framer: Framer,
    },
}

impl Watcher {
    /// The line shown for the frame this edge completes, if any.
    fn push(&mut self, header: &Header, t: u64, level: Level) -> Option<String> {
        match self {
            Watcher::Ppm(d) => d
                .push(t, level)
                .map(|f| header.format(f.start_ns, &f.channels_ns, f.complete)),
            Watcher::Sbus {
                receiver,
                uart,
                framer,
            } => {
                let c = uart.push(t, level)?;
                let taken = framer.push(c.byte, c.end_ns)?;
                Some(header.format_sbus(*receiver, &taken))
            }
        }
    }
}

/// Follows the file as ppmd writes it (like `tail -f`), starting over when
/// ppmd restarts and truncates it, and going on in the new file when ppmd
/// rotates it (renames it to FILE.1 and starts FILE again).
fn follow(cli: &Cli) -> Result<()> {
    let mut file = loop {
        match File::open(&cli.trace) {
            Ok(f) => break f,
            Err(_) => std::thread::sleep(Duration::from_millis(200)),
        }
    };
    eprintln!("watching {} (Ctrl-C to stop)", cli.trace.display());
    let mut header = Header::default();
    let mut decoder: Option<Watcher> = None;
    let mut pending = String::new();
    let mut offset = 0u64;
    let mut last_print: Option<Instant> = None;
    let mut last_edge = Instant::now();
    let mut silent = true;
    let mut buf = Vec::new();
    loop {
        let len = file.metadata()?.len();
        if len < offset {
            file.seek(SeekFrom::Start(0))?;
            (offset, header, decoder) = (0, Header::default(), None);
            pending.clear();
            eprintln!("trace restarted");
        }
        buf.clear();
        offset += file.read_to_end(&mut buf)? as u64;
        if buf.is_empty() && replaced(&cli.trace, &file) {
            // The old file is read to its end: go on in the new one. The
            // edges run on, so the decoder keeps its place.
            if let Ok(f) = File::open(&cli.trace) {
                (file, offset) = (f, 0);
                pending.clear();
                continue;
            }
        }
        pending.push_str(&String::from_utf8_lossy(&buf));
        while let Some(nl) = pending.find('\n') {
            let line: String = pending.drain(..=nl).collect();
            header.take(line.trim_end());
            let Some(Ok(edge)) = parse_line(&line) else {
                continue;
            };
            last_edge = Instant::now();
            if decoder.is_none() {
                let receiver = cli.receiver.unwrap_or(match header.receiver {
                    Some(ReceiverChoice::One(r)) => r,
                    _ => Receiver::EdgeTx,
                });
                decoder = Some(match header.protocol {
                    Protocol::Ppm => Watcher::Ppm(ReceiverDecoder::new(receiver, TIMED_EDGE)),
                    Protocol::Sbus => {
                        let r = sbus_receiver(receiver)?;
                        Watcher::Sbus {
                            receiver: r,
                            uart: uart::Reader::new(header.idle.unwrap_or(Level::High)),
                            framer: Framer::new(r),
                        }
                    }
                    Protocol::Crsf => anyhow::bail!("ppm-watch does not decode CRSF traces yet"),
                });
            }
            let d = decoder.as_mut().expect("made above");
            let t = if cli.actual {
                edge.actual_ns
            } else {
                edge.scheduled_ns
            };
            if let Some(shown) = d.push(&header, t, edge.level) {
                silent = false;
                if last_print.is_none_or(|p| p.elapsed() >= cli.every) {
                    println!("{shown}");
                    last_print = Some(Instant::now());
                }
            }
        }
        if !silent && last_edge.elapsed() > Duration::from_secs(1) {
            println!("line silent: no frames");
            silent = true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Whether `path` now names another file than the one open (it was rotated
/// or recreated); false while nothing is there.
fn replaced(path: &Path, open: &File) -> bool {
    match (std::fs::metadata(path), open.metadata()) {
        (Ok(now), Ok(was)) => (now.dev(), now.ino()) != (was.dev(), was.ino()),
        _ => false,
    }
}
