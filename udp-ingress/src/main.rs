//! `udp-ingress`: receives JSON commands over UDP and publishes the newest
//! valid one to ppmd through iceoryx2 shared memory. It answers status
//! queries (`{"get": "status"}`) with its counters and ppmd's timing summary.
//! Optionally it applies only signed commands (`--auth-key`) and takes
//! datagrams only from some sources (`--allow`).
//!
//! The receive thread sleeps in mio's poll until datagrams arrive (the
//! default), or with `ingress.busy_poll` spins on the socket and never
//! sleeps; it may be pinned to a CPU (`ingress.cpu`) and run SCHED_FIFO
//! (`ingress.priority`).

use anyhow::{Context, Result};
use clap::Parser;
use ppm_shared::config::{parse_net, Config, IngressCpu};
use ppm_shared::daemon::DaemonArgs;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use udp_ingress::server::Server;

/// UDP command receiver: keeps the newest valid command and hands it to ppmd
/// through shared memory.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Cli {
    #[command(flatten)]
    daemon: DaemonArgs,
    /// Output name; must match ppmd's. Overrides `name`; with `[[outputs]]`
    /// in the configuration, picks that output (its listen address, channels
    /// and units).
    #[arg(long)]
    name: Option<String>,
    /// Address and port to receive on. Overrides `ingress.listen`.
    #[arg(long, value_name = "ADDR:PORT")]
    listen: Option<SocketAddr>,
    /// Apply only commands signed with the key in FILE (64 hex characters,
    /// mode 600). Overrides `ingress.auth_key`.
    #[arg(long, value_name = "FILE")]
    auth_key: Option<PathBuf>,
    /// Take datagrams only from this address block (repeatable, e.g.
    /// 10.0.0.0/24, ::1/128). Replaces `ingress.allow`.
    #[arg(long, value_name = "CIDR", value_parser = parse_net)]
    allow: Vec<ipnet::IpNet>,
    /// SCHED_FIFO priority of the receive thread, 1..=99 and below
    /// `rt.priority`; 0: the normal scheduler. Overrides `ingress.priority`.
    #[arg(long, value_name = "PRIO")]
    priority: Option<u8>,
    /// Pin the receive thread to this CPU, or `none`. Overrides `ingress.cpu`.
    #[arg(long, value_name = "CPU|none")]
    cpu: Option<IngressCpu>,
    /// Spin on the socket instead of sleeping: lower latency for one whole
    /// CPU; pin it (--cpu) to a CPU other than ppmd's. Sets `ingress.busy_poll`.
    #[arg(long)]
    busy_poll: bool,
    /// Run on when the receive thread's priority or CPU cannot be had,
    /// logging DEGRADED RUN. Sets `rt.allow_degraded`.
    #[arg(long)]
    allow_degraded: bool,
}

fn main() {
    let cli = Cli::parse();
    cli.daemon.init_logging();
    if let Err(e) = run(cli) {
        log::error!("{e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    // With [[outputs]] in the file, --name picks this ingress's output.
    let mut cfg =
        Config::load_or_default(cli.daemon.config.as_deref())?.select(cli.name.as_deref())?;
    if let Some(listen) = cli.listen {
        cfg.ingress.listen = listen;
    }
    if let Some(key) = cli.auth_key {
        cfg.ingress.auth_key = Some(key);
    }
    if !cli.allow.is_empty() {
        cfg.ingress.allow = cli.allow.iter().map(|n| n.to_string()).collect();
    }
    if let Some(p) = cli.priority {
        cfg.ingress.priority = p;
    }
    if let Some(cpu) = cli.cpu {
        cfg.ingress.cpu = cpu;
    }
    cfg.ingress.busy_poll |= cli.busy_poll;
    cfg.rt.allow_degraded |= cli.allow_degraded;
    let model = cfg.validate()?;
    let server = Server::open(&cfg, model)?;
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    server.run(&stop)
}
