//! `ppm-web`: a live web view of every output of the board, read-only.
//!
//! - [`Settings::resolve`]: the configuration and the flags, resolved once
//!   into what to show, where to listen and whom to answer.
//! - [`run`]: binds, starts the [`reader`], serves until SIGINT or SIGTERM.
//! - [`reader`]: the threads that read the shared memory and the status
//!   replies, as the other tools do (never the timing loop).
//! - [`state`]: the JSON the page polls (`GET /api/state`).
//! - [`http`]: the socket, the allowlist, the routes.
//! - [`assets`]: the page (`tools/web/`), built into the binary.
//! - [`Exit`]: the exit statuses, each a kind of fault.

pub mod assets;
pub mod http;
pub mod reader;
pub mod state;

use anyhow::{Context, Result};
use ppm_shared::config::{Config, ConfigError, Plan};
use reader::{Reader, Watched};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Where ppm-web listens unless told otherwise: this machine only.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:5080";
/// Whom ppm-web answers unless told otherwise: this machine only (as
/// udp-ingress's `ingress.status_allow`).
pub const DEFAULT_ALLOW: [&str; 2] = ["127.0.0.0/8", "::1/128"];

/// ppm-web's exit statuses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Exit {
    /// Stopped by SIGINT or SIGTERM.
    Stopped = 0,
    /// A fault a restart may cure.
    Failure = 1,
    /// A flag that does not parse, or an output name the configuration
    /// lacks.
    Usage = 2,
    /// The port is in use (EX_TEMPFAIL: try again later, or another port).
    Busy = 75,
    /// The configuration is at fault, or `--listen` names an address this
    /// machine does not have or a port it may not take (EX_CONFIG).
    Config = 78,
}

/// The exit status for `e`, the error `run` or [`Settings::resolve`] ended
/// with.
pub fn exit_status(e: &anyhow::Error) -> Exit {
    for cause in e.chain() {
        if let Some(b) = cause.downcast_ref::<http::BindError>() {
            return match b {
                http::BindError::Busy(_) => Exit::Busy,
                http::BindError::NoSuchAddress(_) | http::BindError::NotPermitted(_) => {
                    Exit::Config
                }
                http::BindError::Other(..) => Exit::Failure,
            };
        }
        if let Some(c) = cause.downcast_ref::<ConfigError>() {
            return match c {
                ConfigError::Usage(_) => Exit::Usage,
                _ => Exit::Config,
            };
        }
    }
    Exit::Failure
}

/// What ppm-web runs: the outputs to show, the address to listen on, the
/// clients to answer.
#[derive(Debug, Clone)]
pub struct Settings {
    /// The outputs, in the configuration's order.
    pub outputs: Vec<Watched>,
    /// The shared-memory root (`ipc.root`).
    pub root: PathBuf,
    /// Where to listen.
    pub listen: SocketAddr,
    /// The clients answered.
    pub allow: Vec<ipnet::IpNet>,
}

impl Settings {
    /// Resolves the configuration at `config` (the defaults without one):
    /// every output it has, or those named in `names`; `allow` empty means
    /// [`DEFAULT_ALLOW`].
    pub fn resolve(
        config: Option<&std::path::Path>,
        names: &[String],
        listen: SocketAddr,
        allow: Vec<ipnet::IpNet>,
    ) -> Result<Settings> {
        let cfg = Config::load_or_default(config)?;
        let plan = Plan::resolve(&cfg)?;
        let entries = cfg.entries();
        let all: Vec<&str> = plan.outputs.iter().map(|o| o.name.as_str()).collect();
        for n in names {
            if !all.contains(&n.as_str()) {
                return Err(ConfigError::Usage(format!(
                    "--name {n}: {} has no output `{n}`; it has {}",
                    config.map_or("the default configuration".to_string(), |p| p
                        .display()
                        .to_string()),
                    all.iter()
                        .map(|a| format!("`{a}`"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
                .into());
            }
        }
        let outputs = plan
            .outputs
            .iter()
            .zip(entries.iter())
            .filter(|(o, _)| names.is_empty() || names.contains(&o.name))
            .map(|(o, e)| {
                let m = &o.model;
                let k = m.channels();
                Watched {
                    name: o.name.clone(),
                    protocol: match m.protocol() {
                        ppm_shared::frame::Protocol::Ppm => "ppm",
                        ppm_shared::frame::Protocol::Sbus => "sbus",
                        ppm_shared::frame::Protocol::Crsf => "crsf",
                    },
                    output: e.config.ppmd.output.clone(),
                    channels: m.names().to_vec(),
                    min_us: (0..k).map(|i| f64::from(m.min_ns(i)) / 1e3).collect(),
                    max_us: (0..k).map(|i| f64::from(m.max_ns(i)) / 1e3).collect(),
                    model: m.fingerprint(),
                    readback: o
                        .readback
                        .as_ref()
                        .map(|r| r.input.to_string())
                        .or_else(|| o.pilot.as_ref().map(|p| p.input.to_string())),
                    status_to: status_address(o.ingress.listen),
                }
            })
            .collect();
        let allow = if allow.is_empty() {
            DEFAULT_ALLOW
                .iter()
                .map(|s| s.parse().expect("the default blocks parse"))
                .collect()
        } else {
            allow
        };
        Ok(Settings {
            outputs,
            root: plan.shared.ipc.root.clone(),
            listen,
            allow,
        })
    }
}

/// Where to ask an ingress listening on `listen` for its status: the
/// address itself, or this machine's loopback for an ingress listening on
/// every address.
pub fn status_address(listen: SocketAddr) -> SocketAddr {
    match listen.ip() {
        IpAddr::V4(a) if a.is_unspecified() => (Ipv4Addr::LOCALHOST, listen.port()).into(),
        IpAddr::V6(a) if a.is_unspecified() => (Ipv6Addr::LOCALHOST, listen.port()).into(),
        _ => listen,
    }
}

/// Serves the page until SIGINT or SIGTERM.
pub fn run(settings: Settings) -> Result<()> {
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone()).context("handling signals")?;
    }
    let listener = http::bind(settings.listen)?;
    let local = listener
        .local_addr()
        .context("reading the listening address")?;
    let server = Arc::new(
        tiny_http::Server::from_listener(listener, None)
            .map_err(|e| anyhow::anyhow!("starting the HTTP server: {e}"))?,
    );
    ppm_shared::ipc::init_ipc_logging();
    let names: Vec<String> = settings
        .outputs
        .iter()
        .map(|o| format!("`{}`", o.name))
        .collect();
    let reader = Arc::new(Reader::start(settings.outputs, settings.root, stop.clone()));
    let allow = Arc::new(settings.allow);
    eprintln!(
        "ppm-web: serving http://{local}/ (outputs {}; clients {}; page {} bytes)",
        names.join(", "),
        allow
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join(", "),
        assets::page_bytes(),
    );
    const WORKERS: usize = 2;
    let workers: Vec<_> = (0..WORKERS)
        .map(|i| {
            let (server, reader, allow) = (server.clone(), reader.clone(), allow.clone());
            std::thread::Builder::new()
                .name(format!("http-{i}"))
                .spawn(move || http::serve(&server, &reader, &allow))
                .context("starting an HTTP thread")
        })
        .collect::<Result<_>>()?;
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(100));
    }
    for _ in 0..WORKERS {
        server.unblock();
    }
    for w in workers {
        let _ = w.join();
    }
    eprintln!("ppm-web: stopped");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exit_statuses_tell_faults_apart() {
        let addr: SocketAddr = "127.0.0.1:5080".parse().unwrap();
        let e = |b| anyhow::Error::new(b).context("starting");
        assert_eq!(exit_status(&e(http::BindError::Busy(addr))), Exit::Busy);
        assert_eq!(
            exit_status(&e(http::BindError::NoSuchAddress(addr))),
            Exit::Config
        );
        assert_eq!(
            exit_status(&anyhow::Error::new(ConfigError::Usage("x".into()))),
            Exit::Usage
        );
        assert_eq!(exit_status(&anyhow::anyhow!("other")), Exit::Failure);
    }

    #[test]
    fn status_is_asked_on_loopback_for_a_wildcard_listen() {
        let a = |s: &str| s.parse::<SocketAddr>().unwrap();
        assert_eq!(status_address(a("0.0.0.0:5005")), a("127.0.0.1:5005"));
        assert_eq!(status_address(a("[::]:5005")), a("[::1]:5005"));
        assert_eq!(status_address(a("10.0.0.2:5006")), a("10.0.0.2:5006"));
    }

    #[test]
    fn names_pick_outputs_and_an_unknown_one_is_a_usage_error() {
        let s = Settings::resolve(None, &[], DEFAULT_LISTEN.parse().unwrap(), vec![]).unwrap();
        assert_eq!(s.outputs.len(), 1);
        assert_eq!(s.outputs[0].name, ppm_shared::config::DEFAULT_NAME);
        assert_eq!(s.outputs[0].channels.len(), 8);
        assert_eq!(s.allow.len(), 2);
        let e = Settings::resolve(
            None,
            &["nope".to_string()],
            DEFAULT_LISTEN.parse().unwrap(),
            vec![],
        )
        .unwrap_err();
        assert_eq!(exit_status(&e), Exit::Usage);
        assert!(e.to_string().contains("no output `nope`"), "{e}");
    }
}
