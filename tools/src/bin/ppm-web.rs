//! `ppm-web`: serves a live, read-only web view of every output of the
//! board (see docs/web.md). The logic is in `ppm_tools::web`.

use clap::Parser;
use ppm_tools::web::{self, Exit, Settings, DEFAULT_LISTEN};
use std::net::SocketAddr;
use std::path::PathBuf;

/// See every output live in a browser: channels, line state, counters, edge error.
///
/// Serves a page (and `GET /api/state`, its JSON) that shows, for each
/// output, the newest command, what the line carried and what the radio
/// transmits, the line's state, the counters of ppmd and udp-ingress, and
/// the edge error of the last seconds, 20 times a second. It reads the
/// shared memory and status replies the other tools read; it cannot send
/// commands or change anything. Every byte of the page comes from ppm-web:
/// it works with no network.
#[derive(Parser, Debug)]
#[command(version)]
struct Cli {
    /// ppm configuration: the outputs, their shared-memory root and their
    /// udp-ingress addresses (default: the built-in defaults).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Show only this output (repeatable; default: every output of the
    /// configuration).
    #[arg(long, value_name = "NAME")]
    name: Vec<String>,
    /// Where to listen: ADDR:PORT (port 0: any free port, said at start).
    #[arg(long, value_name = "ADDR:PORT", default_value = DEFAULT_LISTEN)]
    listen: SocketAddr,
    /// Answer clients from this address block only (repeatable; default
    /// 127.0.0.0/8 and ::1/128: this machine only).
    #[arg(long, value_name = "CIDR", value_parser = parse_net)]
    allow: Vec<ipnet::IpNet>,
}

fn parse_net(s: &str) -> Result<ipnet::IpNet, String> {
    ppm_shared::config::parse_net(s)
}

fn main() {
    let cli = Cli::parse();
    let result = Settings::resolve(cli.config.as_deref(), &cli.name, cli.listen, cli.allow)
        .and_then(web::run);
    if let Err(e) = result {
        eprintln!("ppm-web: {e:#}");
        std::process::exit(web::exit_status(&e) as i32);
    }
    std::process::exit(Exit::Stopped as i32);
}
