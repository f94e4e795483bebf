//! `ppm-watch`: decodes the simulated line's trace as a receiver's firmware
//! would and shows the channel values, live or once: PPM as the receiver's
//! capture reads it, SBUS and CRSF (a trace whose header says `protocol
//! sbus` or `protocol crsf`) as its UART and framing read them
//! ([`ppm_shared::wire::reader::LineReader`]).

use anyhow::{Context, Result};
use clap::Parser;
use ppm_shared::frame::{Level, Protocol};
use ppm_shared::receiver::{Receiver, ReceiverChoice};
use ppm_shared::trace::parse_line;
use ppm_shared::wire::reader::{LineReader, Reading};
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
    /// ardupilot (default: the one ppmd's configuration names in the trace;
    /// when that is `any`, edgetx, or for CRSF iNav's reading).
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
        let trace = ppm_shared::trace::Trace::read(text.as_bytes())?;
        let mut reader = header.reader(cli.receiver)?;
        let mut shown = Vec::new();
        let mut last = 0;
        for e in &trace.edges {
            last = if cli.actual {
                e.actual_ns
            } else {
                e.scheduled_ns
            };
            shown.extend(reader.push(last, e.level).map(|r| header.show(&r)));
        }
        shown.extend(reader.idle(last + 1_000_000_000).map(|r| header.show(&r)));
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

/// What the trace's `#` header says.
#[derive(Default)]
struct Header {
    idle: Option<Level>,
    names: Vec<String>,
    receiver: Option<ReceiverChoice>,
    protocol: Protocol,
    baud: Option<u32>,
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
        } else if let Some(v) = line.trim().strip_prefix("# baud ") {
            self.baud = v.trim().parse().ok().filter(|&b: &u32| b > 0);
        }
    }

    /// The reader of this trace's line, as `receiver` reads it (by default
    /// the one the header names; the protocol's usual one for `any`).
    fn reader(&self, receiver: Option<Receiver>) -> Result<LineReader> {
        let receiver = receiver.or(match self.receiver {
            Some(ReceiverChoice::One(r)) => Some(r),
            _ => None,
        });
        // A UART idles high unless the header says otherwise; the PPM
        // receivers time the rising edge whatever the idle level.
        let idle = self.idle.unwrap_or(Level::High);
        LineReader::new(self.protocol, receiver, idle, self.baud).map_err(anyhow::Error::msg)
    }

    /// The line shown for what the receiver made of a frame.
    fn show(&self, r: &Reading) -> String {
        match r {
            Reading::Frame {
                at_ns,
                channels_ns,
                complete,
            } => self.format(*at_ns, channels_ns, *complete),
            Reading::Refused { at_ns, why } => format!("{:>14.6} s  {why}", *at_ns as f64 / 1e9),
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
    let mut decoder: Option<LineReader> = None;
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
                decoder = Some(header.reader(cli.receiver)?);
            }
            let d = decoder.as_mut().expect("made above");
            let t = if cli.actual {
                edge.actual_ns
            } else {
                edge.scheduled_ns
            };
            if let Some(shown) = d.push(t, edge.level).map(|r| header.show(&r)) {
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
