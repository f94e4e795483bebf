//! `ppm-send`: sends a JSON command to udp-ingress at a steady rate, or
//! forwards JSON lines from standard input.

use anyhow::{bail, Context, Result};
use clap::Parser;
use ppm_tools::{parse_duration, with_seq};
use std::io::BufRead;
use std::net::{SocketAddr, ToSocketAddrs, UdpSocket};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Send channel commands to udp-ingress.
///
/// With COMMAND, sends it RATE times a second (until --count, --duration or
/// Ctrl-C). Without, forwards each line of standard input as one datagram.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Cli {
    /// Where to send: HOST:PORT.
    #[arg(long, value_name = "HOST:PORT")]
    to: String,
    /// Datagrams per second when repeating COMMAND.
    #[arg(long, default_value_t = 50.0, value_name = "HZ")]
    rate: f64,
    /// Stop after this many datagrams.
    #[arg(long, value_name = "N", conflicts_with = "duration")]
    count: Option<u64>,
    /// Stop after this long (e.g. 10s, 500ms).
    #[arg(long, value_name = "TIME", value_parser = parse_duration)]
    duration: Option<Duration>,
    /// Number the datagrams with `seq` (starting from the time in microseconds,
    /// so a restarted sender is never taken for a stale one).
    #[arg(long)]
    seq: bool,
    /// Send COMMAND as it is, without checking that it is JSON (for tests).
    #[arg(long)]
    raw: bool,
    /// The command, e.g. '[1500, 1500, 1000, 1500]' or '{"thr": 1200}'.
    command: Option<String>,
}

fn main() {
    if let Err(e) = run(Cli::parse()) {
        eprintln!("ppm-send: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let to: SocketAddr = cli
        .to
        .to_socket_addrs()
        .with_context(|| format!("resolving {}", cli.to))?
        .next()
        .with_context(|| format!("{} resolves to no address", cli.to))?;
    let bind: SocketAddr = if to.is_ipv4() { "0.0.0.0:0" } else { "[::]:0" }.parse()?;
    let socket = UdpSocket::bind(bind).context("opening a UDP socket")?;
    let mut seq = SystemTime::now().duration_since(UNIX_EPOCH)?.as_micros() as u64;
    let mut encode = |text: &str| -> Result<Vec<u8>> {
        if cli.raw {
            return Ok(text.as_bytes().to_vec());
        }
        let v: serde_json::Value =
            serde_json::from_str(text).with_context(|| format!("`{text}` is not JSON"))?;
        let v = if cli.seq {
            seq += 1;
            with_seq(&v, seq)?
        } else {
            v
        };
        Ok(v.to_string().into_bytes())
    };
    let deadline = cli.duration.map(|d| Instant::now() + d);
    let done = |sent: u64| {
        cli.count.is_some_and(|c| sent >= c) || deadline.is_some_and(|d| Instant::now() >= d)
    };
    let mut sent = 0u64;
    match &cli.command {
        Some(command) => {
            if !(cli.rate > 0.0 && cli.rate.is_finite()) {
                bail!("--rate must be a positive number of datagrams per second");
            }
            let period = Duration::from_secs_f64(1.0 / cli.rate);
            let start = Instant::now();
            let fixed = encode(command)?; // also checks COMMAND before the first send
            while !done(sent) {
                let bytes = if cli.seq {
                    encode(command)?
                } else {
                    fixed.clone()
                };
                socket
                    .send_to(&bytes, to)
                    .with_context(|| format!("sending to {to}"))?;
                sent += 1;
                let next = start + period.mul_f64(sent as f64);
                if let Some(wait) = next.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
        }
        None => {
            for line in std::io::stdin().lock().lines() {
                let line = line.context("reading standard input")?;
                if line.trim().is_empty() {
                    continue;
                }
                if done(sent) {
                    break;
                }
                match encode(&line) {
                    Ok(bytes) => {
                        socket
                            .send_to(&bytes, to)
                            .with_context(|| format!("sending to {to}"))?;
                        sent += 1;
                    }
                    Err(e) => eprintln!("ppm-send: skipped: {e:#}"),
                }
            }
        }
    }
    Ok(())
}
