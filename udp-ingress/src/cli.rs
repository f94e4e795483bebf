//! udp-ingress's command line: its options, and how they override the
//! configuration file: [`Cli::plan`] lowers both into the one output this
//! udp-ingress serves and the settings it shares.

use clap::Parser;
use ppm_shared::config::{
    parse_net, Config, ConfigError, ConfigFile, Inert, IngressCpu, OutputPlan, Plan, Program,
    Shared,
};
use ppm_shared::daemon::DaemonArgs;
use std::net::SocketAddr;
use std::path::PathBuf;

/// UDP command receiver: keeps the newest valid command and hands it to ppmd
/// through shared memory.
#[derive(Parser, Debug)]
#[command(version)]
pub struct Cli {
    #[command(flatten)]
    pub daemon: DaemonArgs,
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

impl Cli {
    /// What this udp-ingress runs: the file (`--config`, or every default
    /// without one), its output (`--name` picks one of `[[outputs]]`) with
    /// these options applied, resolved and checked.
    pub fn plan(&self) -> Result<(Shared, OutputPlan), ConfigError> {
        self.resolve().map(|(shared, output, _)| (shared, output))
    }

    /// [`Cli::plan`], and the keys the file sets that do nothing for
    /// udp-ingress in it (`ingress.seq_file` without a key, ...), to warn
    /// about.
    pub fn resolve(&self) -> Result<(Shared, OutputPlan, Vec<Inert>), ConfigError> {
        let file = Config::load_or_default(self.daemon.config.as_deref())?;
        // A file with [[outputs]] is checked whole, by the check ppmd makes:
        // a file ppmd refuses (two outputs on one listen address, ...) is
        // refused here too, naming the same key.
        if !file.outputs.is_empty() {
            Plan::resolve(&file)?;
        }
        let mut cfg = ConfigFile::from(file.select(self.name.as_deref())?);
        if let Some(listen) = self.listen {
            cfg.ingress.listen = listen;
            cfg.set.note_option("ingress.listen", "--listen");
        }
        if let Some(key) = &self.auth_key {
            cfg.ingress.auth_key = Some(key.clone());
            cfg.set.note_option("ingress.auth_key", "--auth-key");
        }
        if !self.allow.is_empty() {
            cfg.ingress.allow = self.allow.iter().map(|n| n.to_string()).collect();
            cfg.set.note_option("ingress.allow", "--allow");
        }
        if let Some(p) = self.priority {
            cfg.ingress.priority = p;
            cfg.set.note_option("ingress.priority", "--priority");
        }
        if let Some(cpu) = self.cpu {
            cfg.ingress.cpu = cpu;
            cfg.set.note_option("ingress.cpu", "--cpu");
        }
        cfg.ingress.busy_poll |= self.busy_poll;
        cfg.rt.allow_degraded |= self.allow_degraded;
        let (shared, output) = Plan::resolve_one(&cfg)?;
        Ok((shared, output, cfg.inert_keys(Program::Ingress)))
    }
}
