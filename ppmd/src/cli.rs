//! ppmd's `--output` arguments: `SPEC` for the one output, or `NAME=SPEC`
//! for each of several (outputs of the file's `[[outputs]]`, or made from
//! the file's settings when it has none).

use ppm_shared::config::{validate_name, Config, ConfigError, OutputSpec};

/// Applies ppmd's `--output` arguments to `cfg`: one `SPEC` sets the one output's
/// `ppmd.output`; `NAME=SPEC` (repeatable) sets output NAME's, or, when
/// the file has no `[[outputs]]`, makes one output per argument with the
/// file's settings.
pub fn apply_cli_outputs(cfg: &mut Config, args: &[String]) -> Result<(), ConfigError> {
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
                    let mut c = cfg.clone();
                    c.name = name.to_string();
                    c.ppmd.output = spec.to_string();
                    cfg.push_cli_output(c);
                }
                return Ok(());
            }
            for (name, spec) in pairs {
                let names = cfg.output_names().join(", ");
                let out = cfg.outputs.iter_mut().find(|c| c.name == name).ok_or_else(|| {
                    ConfigError::Usage(format!(
                        "--output {name}=...: no output `{name}` in the configuration's [[outputs]] ({names})"
                    ))
                })?;
                out.ppmd.output = spec.to_string();
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

    const TWO_OUTPUTS: &str = r#"
[ppm]
order = "AETR"
[ppm.channel.ail]
reverse = true
[failsafe]
after_ms = 150

[[outputs]]
name = "plane"
output = "sim:plane.trace"
frame_log = "plane.jsonl"
ingress.listen = "0.0.0.0:5005"

[[outputs]]
name = "rover"
output = "gpio:gpiochip0:18"
[outputs.ingress]
listen = "0.0.0.0:5006"
[outputs.ppm]
channels = 6
order = "TAER"
frame_us = 20000.0
[outputs.ppm.channel.thr]
max_us = 1900.0
[outputs.failsafe]
action = "hold"
"#;

    #[test]
    fn cli_outputs() {
        let args = |a: &[&str]| a.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let mut c = Config::default();
        apply_cli_outputs(&mut c, &args(&["gpio:0:18"])).unwrap();
        assert_eq!(c.ppmd.output, "gpio:0:18");
        assert!(c.outputs.is_empty());
        let mut c = Config::default();
        apply_cli_outputs(&mut c, &args(&["a=sim:a.trace", "b=sim"])).unwrap();
        let outs = c.validate_outputs().unwrap();
        assert_eq!(outs.len(), 2);
        assert_eq!(
            (outs[0].0.name.as_str(), outs[0].0.ppmd.output.as_str()),
            ("a", "sim:a.trace")
        );
        assert_eq!(
            (outs[1].0.name.as_str(), outs[1].0.ppmd.output.as_str()),
            ("b", "sim")
        );
        // Both inherit the default listen address: ppmd does not listen, and
        // each output's udp-ingress gets its own --listen.
        assert_eq!(outs[0].0.ingress.listen, outs[1].0.ingress.listen);
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
        let e = apply_cli_outputs(&mut Config::default(), &args(&["sim", "sim:x"])).unwrap_err();
        assert!(e.to_string().contains("more than once"), "{e}");
        assert_eq!(split_named_output("sim:/a=b"), None);
        assert_eq!(split_named_output("a=sim:/x"), Some(("a", "sim:/x")));
    }
}
