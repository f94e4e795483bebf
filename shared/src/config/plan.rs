//! The lowering: a configuration (the file with a program's command line
//! applied) resolves once into a [`Plan`], every key checked. Both programs
//! run the plan; nothing after it reads the file's sections for settings an
//! output could set differently.

use super::keys::SetKeys;
use super::merge::{ConfigFile, OutputEntry, MAX_OUTPUTS};
use super::schema::{Config, FailsafeSection, IngressSection, IpcSection, OutputSpec, RtSection};
use super::ConfigError;
use crate::frame::FrameModel;
use std::path::PathBuf;

/// What a program runs: the settings its outputs share, and each output,
/// resolved and checked ([`Plan::resolve`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// The settings of the whole process.
    pub shared: Shared,
    /// The outputs, in the file's (or the command line's) order; at least one.
    pub outputs: Vec<OutputPlan>,
}

/// The settings every output of one process shares: the top-level ones no
/// `[[outputs]]` entry can set.
#[derive(Debug, Clone, PartialEq)]
pub struct Shared {
    /// `[rt]`: ppmd's timing thread (udp-ingress reads `rt.cpu`, `rt.priority`
    /// and `rt.allow_degraded` too).
    pub rt: RtSection,
    /// `[ipc]`: where both processes keep their shared-memory files.
    pub ipc: IpcSection,
    /// `ppmd.frame_log_max_mb`: the size a frame log is rotated at, MiB.
    pub frame_log_max_mb: u64,
    /// `ppmd.trace_max_mb`: the size a sim trace is rotated at, MiB.
    pub trace_max_mb: u64,
    /// `ppmd.spi_hz`: the bit rate of an `spi:` output, Hz.
    pub spi_hz: u32,
    /// The top-level keys the file set, to name them in messages.
    pub keys: SetKeys,
}

/// One output, resolved: its name, frame model, line, and its ingress and
/// failsafe settings.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputPlan {
    /// Its name (`udp-ingress --name` and ppmd's shared-memory services).
    pub name: String,
    /// Its signal, built from its `[ppm]`.
    pub model: FrameModel,
    /// Where its signal goes (`ppmd.output`, parsed).
    pub output: OutputSpec,
    /// Its frame log (`ppmd.frame_log`), if any.
    pub frame_log: Option<PathBuf>,
    /// Its read-back (`ppmd.readback`), if any.
    pub readback: Option<ReadbackPlan>,
    /// Its pilot's radio (`ppmd.pilot`), if any.
    pub pilot: Option<PilotPlan>,
    /// Its `[ingress]`.
    pub ingress: IngressSection,
    /// `ingress.allow`, parsed.
    pub allow: Vec<ipnet::IpNet>,
    /// `ingress.status_allow`, parsed.
    pub status_allow: Vec<ipnet::IpNet>,
    /// The file the last accepted signed `seq` is kept in
    /// ([`Config::seq_file`]).
    pub seq_file: PathBuf,
    /// Its `[failsafe]`.
    pub failsafe: FailsafeSection,
    /// Its `[mavlink]`, resolved against its channels.
    pub mavlink: crate::mavlink::Settings,
    /// The keys its file (or a command-line option) set, to name them in
    /// messages: `plan.keys.name("ppmd.frame_log")`.
    pub keys: SetKeys,
}

impl Plan {
    /// Resolves `cfg` (a file with the command line applied): validates every
    /// output (see [`Config::validate`]) and what outputs must not share:
    /// names, listen addresses, lines, trace, frame-log and seq files. Errors
    /// name the key (`outputs[1].ppm.channels`, or the top-level key an
    /// output inherits).
    pub fn resolve(cfg: &ConfigFile) -> Result<Plan, ConfigError> {
        let entries = cfg.entries();
        if entries.len() > MAX_OUTPUTS {
            return Err(ConfigError::invalid(
                "outputs",
                format!(
                    "{} outputs; one ppmd drives at most {MAX_OUTPUTS}",
                    entries.len()
                ),
            ));
        }
        let several = entries.len() > 1;
        let mut outputs = Vec::with_capacity(entries.len());
        for (i, entry) in entries.iter().enumerate() {
            let c = &entry.config;
            let plan = c.lower().map_err(|e| entry.locate(i, e))?;
            if several && matches!(plan.output, OutputSpec::Spi { .. }) {
                return Err(entry.locate(
                    i,
                    ConfigError::invalid(
                        "ppmd.output",
                        format!(
                            "`{}` with other outputs: an spi output's transfer holds the timing thread for the frame, so it runs alone (start one ppmd per spi output)",
                            c.ppmd.output
                        ),
                    ),
                ));
            }
            for (j, other) in entries[..i].iter().enumerate() {
                clash(entry, other, j).map_err(|e| entry.locate(i, e))?;
            }
            outputs.push(plan);
        }
        Ok(Plan {
            shared: Shared {
                rt: cfg.rt.clone(),
                ipc: cfg.ipc.clone(),
                frame_log_max_mb: cfg.ppmd.frame_log_max_mb,
                trace_max_mb: cfg.ppmd.trace_max_mb,
                spi_hz: cfg.ppmd.spi_hz,
                keys: cfg.set.clone(),
            },
            outputs,
        })
    }

    /// The plan of a configuration of one output (a file without
    /// `[[outputs]]`, or the one output udp-ingress's `--name` picked
    /// with [`ConfigFile::select`]): the shared settings and that output.
    pub fn resolve_one(cfg: &ConfigFile) -> Result<(Shared, OutputPlan), ConfigError> {
        let Plan { shared, outputs } = Plan::resolve(&cfg.select(None)?.into())?;
        let [output] = <[OutputPlan; 1]>::try_from(outputs)
            .expect("a configuration without [[outputs]] has one output");
        Ok((shared, output))
    }
}

/// What `entry` must not share with `other`, the `j`th output (an error
/// about `entry`'s key).
fn clash(entry: &OutputEntry, other: &OutputEntry, j: usize) -> Result<(), ConfigError> {
    let (c, o) = (&entry.config, &other.config);
    let clash = |key: &str, what: String| {
        Err(ConfigError::invalid(
            key,
            format!("{what}, as output `{}` (outputs[{j}])", o.name),
        ))
    };
    if o.name == c.name {
        return clash("name", format!("`{}` is used twice", c.name));
    }
    // Outputs made on ppmd's command line have no udp-ingress settings of
    // their own; their ingresses are started apart.
    if o.ingress.listen == c.ingress.listen && entry.in_file() && other.in_file() {
        return clash(
            "ingress.listen",
            format!(
                "{} is the same address (each output has its own udp-ingress and port)",
                c.ingress.listen
            ),
        );
    }
    if output_target(c) == output_target(o) {
        return clash(
            "ppmd.output",
            format!("`{}` is the same line", c.ppmd.output),
        );
    }
    if c.ppmd.frame_log.is_some() && c.ppmd.frame_log == o.ppmd.frame_log {
        return clash("ppmd.frame_log", "the same frame log file".into());
    }
    if c.seq_file() == o.seq_file() {
        return clash(
            "ingress.seq_file",
            format!("{} is the same seq file", c.seq_file().display()),
        );
    }
    let ts = c.mavlink_timestamp_file();
    if ts == o.mavlink_timestamp_file() {
        return clash(
            "mavlink.timestamp_file",
            format!("{} is the same timestamp file", ts.display()),
        );
    }
    Ok(())
}

/// What output `c` writes to, to find two outputs on one line or file.
fn output_target(c: &Config) -> Option<OutputSpec> {
    match c.output().ok()? {
        // One trace file however its frames are written.
        OutputSpec::Sim { path, .. } => Some(OutputSpec::Sim {
            path: Some(path.unwrap_or_else(|| PathBuf::from(format!("ppm-{}.trace", c.name)))),
            whole: false,
        }),
        spec => Some(spec),
    }
}

/// An output's read-back: `ppmd.readback`, `ppmd.readback_log` and
/// `[readback]`, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadbackPlan {
    /// The input read.
    pub input: crate::capture::InputSpec,
    /// The read-back log, if any.
    pub log: Option<PathBuf>,
    /// What the decoder is told.
    pub capture: crate::capture::CaptureSettings,
    /// How frames read are judged.
    pub matching: crate::capture::MatchSettings,
}

/// An output's pilot's radio: `ppmd.pilot` and `[pilot]`, checked. The
/// radio's trainer signal (PPM) is read like a read-back's; while its
/// takeover switch is on, the pilot's channels go out instead of the
/// groundstation's.
#[derive(Debug, Clone, PartialEq)]
pub struct PilotPlan {
    /// The input read.
    pub input: crate::capture::InputSpec,
    /// What the decoder is told.
    pub capture: crate::capture::CaptureSettings,
    /// The takeover switch's channel, 0-based (`pilot.switch_channel` less 1).
    pub switch_channel: usize,
    /// The pilot flies while the switch channel reads above this, ns.
    pub switch_above_ns: u64,
}

impl OutputPlan {
    /// Whether it drives a transmitter module (`ppm.crsf_target =
    /// "module"`), whose timing corrections its grid follows.
    pub fn drives_module(&self) -> bool {
        matches!(self.model.wire(), crate::wire::WireModel::Crsf(c) if c.target() == crate::wire::crsf::CrsfTarget::Module)
    }

    /// The tty whose receive side carries what the flight controller sends
    /// back (CRSF telemetry): a `serial:` output of a protocol that has
    /// telemetry; `None` for every other output.
    pub fn telemetry_port(&self) -> Option<&std::path::Path> {
        match (&self.output, self.model.protocol()) {
            (OutputSpec::Serial { device }, crate::wire::Protocol::Crsf) => Some(device),
            _ => None,
        }
    }

    /// Refuses a busy-polling receive thread pinned to the CPU of ppmd's
    /// timing thread: `rt_cpu` is `rt.cpu` resolved on this machine.
    pub fn check_busy_poll_cpu(&self, rt_cpu: Option<usize>) -> Result<(), ConfigError> {
        super::check::busy_poll_cpu(&self.ingress, rt_cpu)
    }
}
