//! `ppm-status`: asks a running udp-ingress for its status (`{"get":
//! "status"}`) and prints the reply, readably or as the raw JSON.

use anyhow::{Context, Result};
use clap::Parser;
use ppm_tools::parse_duration;
use ppm_tools::status::{parse, query, readable, resolve};
use std::time::Duration;

/// Ask udp-ingress (and, through it, ppmd) how things are going.
///
/// Sends one status query and prints the reply. Read-only: a query never
/// changes anything, and needs no signature when udp-ingress has a key.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// The udp-ingress to ask: HOST:PORT (its `ingress.listen`).
    #[arg(long, value_name = "HOST:PORT")]
    to: String,
    /// How long to wait for the reply (e.g. 500ms, 2s).
    #[arg(long, default_value = "1s", value_parser = parse_duration, value_name = "TIME")]
    timeout: Duration,
    /// Print the reply as it came: one JSON object.
    #[arg(long)]
    json: bool,
}

fn main() {
    if let Err(e) = run(Cli::parse()) {
        eprintln!("ppm-status: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let to = resolve(&cli.to)?;
    let text = query(to, cli.timeout)?;
    if cli.json {
        serde_json::from_str::<serde_json::Value>(&text)
            .with_context(|| format!("the reply from {to} is not JSON: {text}"))?;
        println!("{text}");
    } else {
        print!("{}", readable(&parse(&text, to)?));
    }
    Ok(())
}
