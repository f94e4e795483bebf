//! ppmd's command line: its options, and how they override the
//! configuration file: [`Cli::plan`] lowers both into the [`Plan`] ppmd runs. `--output` takes `SPEC` for the one output, or
//! `NAME=SPEC` for each of several (outputs of the file's `[[outputs]]`, or
//! made from the file's settings when it has none).

use clap::Parser;
use ppm_shared::config::{
    validate_name, Config, ConfigError, ConfigFile, Inert, OutputSpec, Plan, Program, Timing,
};
use ppm_shared::daemon::DaemonArgs;
use std::path::PathBuf;

/// Real-time trainer-signal daemon: takes the newest command from
/// udp-ingress once per frame and emits it as PPM (a GPIO line or SPI) or
/// SBUS (a UART or SPI).
#[derive(Parser, Debug)]
#[command(version)]
pub struct Cli {
    #[command(flatten)]
    pub daemon: DaemonArgs,
    /// Output name; must match udp-ingress's. Overrides `name`; with
    /// `[[outputs]]` in the configuration, runs that output alone.
    #[arg(long)]
    pub name: Option<String>,
    /// `sim` (trace in ppm-NAME.trace), `sim:PATH`, `gpio:CHIP:LINE` (CHIP:
    /// a path, name or label such as pinctrl-bcm2711; LINE: an offset or a
    /// name such as GPIO18), `gpio:LINE` (the chip that has a line of
    /// that name), `spi:DEVICE` (a spidev device such as
    /// /dev/spidev0.0, MOSI as the line; runs alone), or `serial:DEVICE`
    /// (a UART such as /dev/ttyAMA0, for `ppm.protocol = "sbus"`). Overrides
    /// `ppmd.output`. Repeat as `--output NAME=SPEC` to drive several
    /// outputs from one timing thread, each fed by its own
    /// `udp-ingress --name NAME`.
    #[arg(long, value_name = "[NAME=]SPEC")]
    pub output: Vec<String>,
    /// Run even when a real-time setting cannot be had (the run is then
    /// marked degraded). Sets `rt.allow_degraded`.
    #[arg(long)]
    pub allow_degraded: bool,
    /// Append one JSON line per emitted frame and line-state change to FILE.
    /// Overrides `ppmd.frame_log`.
    #[arg(long, value_name = "FILE")]
    pub frame_log: Option<PathBuf>,
    /// When frames start: `follow` (the default: a fresh command starts its
    /// frame as soon as the sync allows) or `grid` (one every
    /// `ppm.frame_us`). Overrides `ppm.timing`, for every output.
    #[arg(long, value_name = "grid|follow")]
    pub timing: Option<Timing>,
    /// Append an HdrHistogram interval log of edge error and write duration
    /// (nanoseconds, one interval a second) to FILE.
    #[arg(long, value_name = "FILE")]
    pub hdr_log: Option<PathBuf>,
}

impl Cli {
    /// What ppmd runs: the file (`--config`, or every default without one)
    /// with these options applied ([`Cli::apply`]), resolved and checked.
    pub fn plan(&self) -> Result<Plan, ConfigError> {
        self.resolve().map(|(plan, _)| plan)
    }

    /// [`Cli::plan`], and the keys the file sets that do nothing for ppmd
    /// in it (`ppm.frame_us` under follow timing, ...), to warn about.
    pub fn resolve(&self) -> Result<(Plan, Vec<Inert>), ConfigError> {
        let file = Config::load_or_default(self.daemon.config.as_deref())?;
        let cfg = self.apply(file)?;
        let plan = Plan::resolve(&cfg)?;
        Ok((plan, cfg.inert_keys(Program::Ppmd)))
    }

    /// Applies these options to `cfg`: `--name` picks that output alone
    /// (with `[[outputs]]`), `--output` sets the lines ([`apply_cli_outputs`]),
    /// `--allow-degraded` and `--timing` reach every output, and
    /// `--frame-log` sets the one output's frame log (with several, each
    /// output's entry names its own).
    pub fn apply(&self, mut cfg: ConfigFile) -> Result<ConfigFile, ConfigError> {
        if let Some(name) = self.name.as_deref() {
            cfg = cfg.select(Some(name))?.into();
        }
        apply_cli_outputs(&mut cfg, &self.output)?;
        cfg.rt.allow_degraded |= self.allow_degraded;
        if let Some(t) = self.timing {
            cfg.ppm.timing = t;
            cfg.set.note_option("ppm.timing", "--timing");
        }
        let degraded = cfg.rt.allow_degraded;
        for out in cfg.outputs.iter_mut().map(|e| &mut e.config) {
            out.rt.allow_degraded = degraded;
            if let Some(t) = self.timing {
                out.ppm.timing = t;
                out.set.note_option("ppm.timing", "--timing");
            }
        }
        if let Some(path) = &self.frame_log {
            if !cfg.outputs.is_empty() {
                return Err(ConfigError::Usage(
                    "--frame-log with several outputs: set frame_log in each output's [[outputs]] entry instead".into(),
                ));
            }
            cfg.ppmd.frame_log = Some(path.clone());
            cfg.set.note_option("ppmd.frame_log", "--frame-log");
        }
        Ok(cfg)
    }
}

/// Applies ppmd's `--output` arguments to `cfg`: one `SPEC` sets the one output's
/// `ppmd.output`; `NAME=SPEC` (repeatable) sets output NAME's, or, when
/// the file has no `[[outputs]]`, makes one output per argument with the
/// file's settings.
pub fn apply_cli_outputs(cfg: &mut ConfigFile, args: &[String]) -> Result<(), ConfigError> {
    let named: Vec<Option<(&str, &str)>> = args.iter().map(|a| split_named_output(a)).collect();
    match (
        named.iter().all(Option::is_some),
        named.iter().all(Option::is_none),
    ) {
        _ if args.is_empty() => Ok(()),
        (false, true) => {
            args[0]
                .parse::<OutputSpec>()
                .map_err(|m| ConfigError::Usage(format!("--output {}: {m}", args[0])))?;
            if args.len() > 1 {
                return Err(ConfigError::Usage(
                    "--output SPEC given more than once: name each output, --output NAME=SPEC"
                        .into(),
                ));
            }
            if !cfg.outputs.is_empty() {
                return Err(ConfigError::Usage(format!(
                    "the configuration has [[outputs]] ({}): say which one, --output NAME=SPEC",
                    cfg.output_names().join(", ")
                )));
            }
            cfg.ppmd.output = args[0].clone();
            cfg.set.note_option("ppmd.output", "--output");
            Ok(())
        }
        (true, false) => {
            let pairs: Vec<(&str, &str)> = named.into_iter().flatten().collect();
            for (name, spec) in &pairs {
                spec.parse::<OutputSpec>()
                    .map_err(|m| ConfigError::Usage(format!("--output {name}={spec}: {m}")))?;
            }
            if cfg.outputs.is_empty() {
                for (name, spec) in pairs {
                    let mut c = cfg.config.clone();
                    c.name = name.to_string();
                    c.ppmd.output = spec.to_string();
                    c.set.note_option("ppmd.output", "--output");
                    cfg.push_cli_output(c);
                }
                return Ok(());
            }
            for (name, spec) in pairs {
                let names = cfg.output_names().join(", ");
                let out = cfg
                    .outputs
                    .iter_mut()
                    .find(|e| e.config.name == name)
                    .ok_or_else(|| {
                        ConfigError::Usage(format!(
                            "--output {name}=...: no output `{name}` in the configuration's [[outputs]] ({names})"
                        ))
                    })?;
                out.config.ppmd.output = spec.to_string();
                out.config.set.note_option("ppmd.output", "--output");
            }
            Ok(())
        }
        _ => Err(ConfigError::Usage(
            "--output: either one SPEC or NAME=SPEC for every output, not both".into(),
        )),
    }
}

/// `NAME=SPEC` as ppmd's `--output` takes it, when NAME is a valid output name.
pub fn split_named_output(arg: &str) -> Option<(&str, &str)> {
    let (name, spec) = arg.split_once('=')?;
    (!name.contains(':') && validate_name(name).is_ok()).then_some((name, spec))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fixture of shared's [[outputs]] tests: plane and rover.
    const TWO_OUTPUTS: &str = include_str!("../../shared/testdata/two-outputs.toml");

    #[test]
    fn cli_outputs() {
        let args = |a: &[&str]| a.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let mut c = ConfigFile::default();
        apply_cli_outputs(&mut c, &args(&["gpio:0:18"])).unwrap();
        assert_eq!(c.ppmd.output, "gpio:0:18");
        assert!(c.outputs.is_empty());
        let mut c = ConfigFile::default();
        apply_cli_outputs(&mut c, &args(&["a=sim:a.trace", "b=sim"])).unwrap();
        let outs = Plan::resolve(&c).unwrap().outputs;
        assert_eq!(outs.len(), 2);
        let sim = |path: Option<&str>| OutputSpec::Sim {
            path: path.map(PathBuf::from),
            whole: false,
        };
        assert_eq!(
            (outs[0].name.as_str(), &outs[0].output),
            ("a", &sim(Some("a.trace")))
        );
        assert_eq!((outs[1].name.as_str(), &outs[1].output), ("b", &sim(None)));
        // Both inherit the default listen address: ppmd does not listen, and
        // each output's udp-ingress gets its own --listen.
        assert_eq!(outs[0].ingress.listen, outs[1].ingress.listen);
        let mut c = Config::parse(TWO_OUTPUTS).unwrap();
        apply_cli_outputs(&mut c, &args(&["rover=sim:r.trace"])).unwrap();
        assert_eq!(c.select(Some("rover")).unwrap().ppmd.output, "sim:r.trace");
        assert_eq!(
            c.select(Some("plane")).unwrap().ppmd.output,
            "sim:plane.trace"
        );
        for (bad, says) in [
            (&["sim"][..], "NAME=SPEC"),
            (&["boat=sim"][..], "no output `boat`"),
            (&["plane=sim", "sim"][..], "not both"),
            (&["plane=pwm:3"][..], "--output plane=pwm:3"),
        ] {
            let mut c = Config::parse(TWO_OUTPUTS).unwrap();
            let e = apply_cli_outputs(&mut c, &args(bad)).unwrap_err();
            assert!(e.to_string().contains(says), "{bad:?}: {e}");
        }
        let e =
            apply_cli_outputs(&mut ConfigFile::default(), &args(&["sim", "sim:x"])).unwrap_err();
        assert!(e.to_string().contains("more than once"), "{e}");
        assert_eq!(split_named_output("sim:/a=b"), None);
        assert_eq!(split_named_output("a=sim:/x"), Some(("a", "sim:/x")));
    }

    fn cli(args: &[&str]) -> Cli {
        Cli::try_parse_from(std::iter::once("ppmd").chain(args.iter().copied())).unwrap()
    }

    #[test]
    fn options_override_the_configuration() {
        // Nothing given: the file's settings stand.
        let two = Config::parse(TWO_OUTPUTS).unwrap();
        assert_eq!(cli(&[]).apply(two.clone()).unwrap(), two);
        // One output: each option sets its key.
        let c = cli(&[
            "--timing",
            "follow",
            "--allow-degraded",
            "--frame-log",
            "f.jsonl",
            "--output",
            "sim:x.trace",
        ])
        .apply(ConfigFile::default())
        .unwrap();
        assert_eq!(c.ppm.timing, Timing::Follow);
        assert!(c.rt.allow_degraded);
        assert_eq!(c.ppmd.frame_log, Some(PathBuf::from("f.jsonl")));
        assert_eq!(c.ppmd.output, "sim:x.trace");
        // Several: --timing and --allow-degraded reach every output; a frame
        // log of its own is each output's.
        let c = cli(&["--timing", "follow", "--allow-degraded"])
            .apply(two.clone())
            .unwrap();
        for e in &c.outputs {
            let o = &e.config;
            assert!(o.rt.allow_degraded, "{}", o.name);
        }
        let plan = Plan::resolve(&c).unwrap();
        assert_eq!(plan.outputs.len(), 2);
        assert!(plan.shared.rt.allow_degraded);
        for (e, o) in c.outputs.iter().zip(&plan.outputs) {
            assert_eq!(
                (e.config.ppm.timing, o.model.timing()),
                (Timing::Follow, Timing::Follow)
            );
        }
        let e = cli(&["--frame-log", "f.jsonl"])
            .apply(two.clone())
            .unwrap_err();
        assert!(
            e.to_string().contains("set frame_log in each output's"),
            "{e}"
        );
        // --name runs that output alone: then --frame-log is its own.
        let c = cli(&["--name", "rover", "--frame-log", "r.jsonl"])
            .apply(two)
            .unwrap();
        assert!(c.outputs.is_empty());
        assert_eq!((c.name.as_str(), c.ppm.channels), ("rover", Some(6)));
        assert_eq!(c.ppmd.frame_log, Some(PathBuf::from("r.jsonl")));
        let e = cli(&["--name", "boat"]).apply(Config::parse(TWO_OUTPUTS).unwrap());
        assert!(e.unwrap_err().to_string().contains("no output `boat`"));
    }
}
