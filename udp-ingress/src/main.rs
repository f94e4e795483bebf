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
use ppm_shared::config::DEFAULT_NAME;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use udp_ingress::cli::Cli;
use udp_ingress::server::Server;

fn main() {
    let cli = Cli::parse();
    cli.daemon.init_logging();
    if let Err(e) = run(cli) {
        log::error!("{e:#}");
        std::process::exit(ppm_shared::daemon::exit_status(&e, |_| false));
    }
}

fn run(cli: Cli) -> Result<()> {
    let (shared, output, inert) = cli.resolve()?;
    for key in &inert {
        log::warn!("{key}");
    }
    if output.ingress.auth_key.is_some() && output.name == DEFAULT_NAME {
        // Signed commands are bound to the output's name: every board left
        // at the default name accepts the others' commands under one key.
        log::warn!(
            "signed commands are bound to the output name '{DEFAULT_NAME}', the default: \
             another board with the same key and name accepts this one's commands; \
             give this output a name of its own (`name`, `udp-ingress --name`) \
             or each board its own key"
        );
    }
    let server = Server::open(&shared, output)?;
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone()).context("installing signal handler")?;
    }
    server.run(&stop)
}
