//! `ppm-send`: sends a JSON command to one or more udp-ingress instances at a
//! steady rate (optionally sweeping channels, numbering and signing each
//! datagram), forwards JSON lines from standard input, or asks each for its
//! status.

use anyhow::{bail, Context, Result};
use clap::Parser;
use ppm_shared::auth::AuthKey;
use ppm_tools::send::{check_command, Sweep, Template};
use ppm_tools::status::{parse, query, readable, resolve};
use ppm_tools::{parse_duration, with_seq, with_to};
use std::io::BufRead;
use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Send channel commands to udp-ingress.
///
/// With COMMAND (or --sweep), sends it RATE times a second (until --count,
/// --duration or Ctrl-C). Without, forwards each line of standard input as
/// one datagram. Every datagram goes to every --to target.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// Where to send: HOST:PORT. Repeat it to send every command to each
    /// target (each gets its own `seq` numbering).
    #[arg(long, value_name = "HOST:PORT", required = true)]
    to: Vec<String>,
    /// Commands per second when repeating COMMAND.
    #[arg(long, default_value_t = 50.0, value_name = "HZ")]
    rate: f64,
    /// Stop after this many commands (each sent to every target).
    #[arg(long, value_name = "N", conflicts_with = "duration")]
    count: Option<u64>,
    /// Stop after this long (e.g. 10s, 500ms).
    #[arg(long, value_name = "TIME", value_parser = parse_duration)]
    duration: Option<Duration>,
    /// Number the datagrams with `seq`, per target, starting from the time in
    /// microseconds (so a restarted sender is never taken for a stale one).
    #[arg(long)]
    seq: bool,
    /// Sign every command with the key in FILE (64 hex characters, mode 600),
    /// for a udp-ingress with `ingress.auth_key`. Implies --seq; needs --name.
    #[arg(long, value_name = "FILE")]
    auth_key: Option<PathBuf>,
    /// The name of the output the commands are for (its `name` in the
    /// ingress's configuration): every command carries it as `to`, and the
    /// ingress refuses a command for another output. Needed with
    /// --auth-key (the name is signed). Once for every --to, or once per
    /// --to in the same order.
    #[arg(long, value_name = "NAME")]
    name: Vec<String>,
    /// Move channel CH (a number from 1, or a name such as thr or aux1) in a
    /// triangle between MIN and MAX us with period PERIOD, e.g. 3:1000:2000:4s.
    /// Repeatable. Other channels come from COMMAND, or take their defaults.
    #[arg(long, value_name = "CH:MIN:MAX:PERIOD", value_parser = Sweep::parse)]
    sweep: Vec<Sweep>,
    /// The ingress's channel order (`ppm.order`), used to name a numbered
    /// --sweep channel when there is no COMMAND or it names its channels.
    #[arg(long, default_value = "AETR", value_name = "ORDER")]
    order: String,
    /// Ask each target for its status (`{"get": "status"}`) and print the
    /// replies, instead of sending commands.
    #[arg(long, conflicts_with_all = ["command", "sweep", "seq", "auth_key", "name", "raw", "count", "duration"])]
    status: bool,
    /// How long --status waits for each reply.
    #[arg(long, default_value = "1s", value_parser = parse_duration, value_name = "TIME", requires = "status")]
    timeout: Duration,
    /// Send COMMAND (or each line) as it is, without checking it (for tests:
    /// otherwise a command udp-ingress would refuse under any configuration
    /// stops ppm-send, or a line is skipped, with the reason).
    #[arg(long, conflicts_with_all = ["seq", "auth_key", "name", "sweep"])]
    raw: bool,
    /// The command, e.g. '[1500, 1500, 1000, 1500]' or '{"thr": 1200}'.
    command: Option<String>,
}

fn main() {
    let ok = Cli::parse().run();
    match ok {
        Ok(true) => {}
        Ok(false) => std::process::exit(1),
        Err(e) => {
            eprintln!("ppm-send: {e:#}");
            std::process::exit(1);
        }
    }
}

/// One destination with its own socket, output name and `seq` numbering.
struct Target {
    label: String,
    /// The output its commands are for (`to`), if given.
    output: Option<String>,
    addr: SocketAddr,
    socket: UdpSocket,
    seq: u64,
    failing: bool,
    failures: u64,
}

impl Target {
    fn new(label: &str, output: Option<String>, first_seq: u64) -> Result<Target> {
        let addr = resolve(label)?;
        let bind: SocketAddr = if addr.is_ipv4() {
            "0.0.0.0:0"
        } else {
            "[::]:0"
        }
        .parse()?;
        Ok(Target {
            label: label.to_owned(),
            output,
            addr,
            socket: UdpSocket::bind(bind).context("opening a UDP socket")?,
            seq: first_seq,
            failing: false,
            failures: 0,
        })
    }

    /// Sends one datagram; a failure is reported once until sending works
    /// again, and the other targets are still served.
    fn send(&mut self, bytes: &[u8]) {
        match self.socket.send_to(bytes, self.addr) {
            Ok(_) => self.failing = false,
            Err(e) => {
                self.failures += 1;
                if !self.failing {
                    eprintln!("ppm-send: sending to {} ({}): {e}", self.label, self.addr);
                    self.failing = true;
                }
            }
        }
    }
}

/// How each command is finished for a target: addressed, numbered, signed.
struct Finish {
    numbered: bool,
    key: Option<AuthKey>,
}

impl Finish {
    fn datagram(&self, command: &serde_json::Value, target: &mut Target) -> Result<Vec<u8>> {
        let addressed;
        let command = match &target.output {
            Some(name) => {
                addressed = with_to(command, name)?;
                &addressed
            }
            None => command,
        };
        let v = if self.numbered {
            target.seq += 1;
            with_seq(command, target.seq)?
        } else {
            command.clone()
        };
        let text = v.to_string();
        Ok(match &self.key {
            Some(k) => k.envelope(&text).into_bytes(),
            None => text.into_bytes(),
        })
    }
}

impl Cli {
    /// True when every datagram (or status query) went out.
    fn run(self) -> Result<bool> {
        if self.status {
            return self.status_of_each();
        }
        let outputs = self.outputs()?;
        let key = self.auth_key.as_deref().map(AuthKey::load).transpose()?;
        let finish = Finish {
            numbered: self.seq || key.is_some(),
            key,
        };
        let now_us = SystemTime::now().duration_since(UNIX_EPOCH)?.as_micros() as u64;
        let mut targets = self
            .to
            .iter()
            .zip(outputs)
            .map(|(t, output)| Target::new(t, output, now_us))
            .collect::<Result<Vec<_>>>()?;
        let deadline = self.duration.map(|d| Instant::now() + d);
        let done = |sent: u64| {
            self.count.is_some_and(|c| sent >= c) || deadline.is_some_and(|d| Instant::now() >= d)
        };
        let mut sent = 0u64;
        if self.command.is_some() || !self.sweep.is_empty() {
            if !(self.rate > 0.0 && self.rate.is_finite()) {
                bail!("--rate must be a positive number of commands per second");
            }
            let period = Duration::from_secs_f64(1.0 / self.rate);
            let raw = self.raw.then(|| self.command.clone().unwrap_or_default());
            // Checks COMMAND and the sweeps before the first send.
            let template = match &raw {
                Some(_) => None,
                None => Some(Template::new(
                    self.command.as_deref(),
                    &self.sweep,
                    &self.order,
                )?),
            };
            if let Some(t) = template.as_ref() {
                let first = t.at(0.0);
                check_command(&first.to_string())?;
                if finish.numbered {
                    with_seq(&first, 0)?;
                }
                for name in targets.iter().filter_map(|t| t.output.as_deref()) {
                    with_to(&first, name).context("COMMAND")?;
                }
            }
            let start = Instant::now();
            while !done(sent) {
                let t = sent as f64 / self.rate;
                for target in &mut targets {
                    let bytes = match (&raw, &template) {
                        (Some(r), _) => r.as_bytes().to_vec(),
                        (None, Some(tpl)) => finish.datagram(&tpl.at(t), target)?,
                        (None, None) => unreachable!("a template without --raw"),
                    };
                    target.send(&bytes);
                }
                sent += 1;
                let next = start + period.mul_f64(sent as f64);
                if let Some(wait) = next.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
        } else {
            for line in std::io::stdin().lock().lines() {
                let line = line.context("reading standard input")?;
                if line.trim().is_empty() {
                    continue;
                }
                if done(sent) {
                    break;
                }
                let command = if self.raw {
                    None
                } else {
                    match serde_json::from_str::<serde_json::Value>(&line) {
                        Ok(v) => match check_command(&line) {
                            Ok(()) => Some(v),
                            Err(e) => {
                                eprintln!("ppm-send: skipped: {e:#}");
                                continue;
                            }
                        },
                        Err(e) => {
                            eprintln!("ppm-send: skipped: `{line}` is not JSON: {e}");
                            continue;
                        }
                    }
                };
                for target in &mut targets {
                    let bytes = match &command {
                        None => line.as_bytes().to_vec(),
                        Some(v) => match finish.datagram(v, target) {
                            Ok(b) => b,
                            Err(e) => {
                                eprintln!("ppm-send: skipped: {e:#}");
                                break;
                            }
                        },
                    };
                    target.send(&bytes);
                }
                sent += 1;
            }
        }
        let mut all_sent = true;
        for t in targets.iter().filter(|t| t.failures > 0) {
            eprintln!(
                "ppm-send: {} of {sent} datagrams to {} were not sent",
                t.failures, t.label
            );
            all_sent = false;
        }
        Ok(all_sent)
    }

    /// The output name of each `--to` target, in order: `--name` once for
    /// all, once per target, or not at all (not with `--auth-key`).
    fn outputs(&self) -> Result<Vec<Option<String>>> {
        for name in &self.name {
            if ppm_shared::config::validate_name(name).is_err() {
                bail!("--name `{name}`: an output name is 1..=64 letters, digits, `-` or `_`");
            }
        }
        match self.name.len() {
            0 if self.auth_key.is_some() => bail!(
                "--auth-key needs --name NAME, the name of the output the commands are for (its `name` in the ingress's configuration): it is signed with each command, and the ingress refuses commands for another output"
            ),
            0 => Ok(vec![None; self.to.len()]),
            1 => Ok(vec![Some(self.name[0].clone()); self.to.len()]),
            n if n == self.to.len() => Ok(self.name.iter().cloned().map(Some).collect()),
            n => bail!(
                "{n} --name for {} --to: give one name for every target, or one per --to in the same order",
                self.to.len()
            ),
        }
    }

    /// `--status`: one query to each target, each reply printed readably.
    fn status_of_each(&self) -> Result<bool> {
        let mut all = true;
        for (i, label) in self.to.iter().enumerate() {
            if self.to.len() > 1 {
                println!("{}== {label} ==", if i > 0 { "\n" } else { "" });
            }
            let reply = resolve(label).and_then(|to| {
                let text = query(to, self.timeout)?;
                Ok(readable(&parse(&text, to)?))
            });
            match reply {
                Ok(text) => print!("{text}"),
                Err(e) => {
                    eprintln!("ppm-send: {label}: {e:#}");
                    all = false;
                }
            }
        }
        Ok(all)
    }
}
