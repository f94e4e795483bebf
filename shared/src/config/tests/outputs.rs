//! `[[outputs]]`: entries over the top level, their errors, and the plan.

use crate::config::*;
use std::path::PathBuf;

/// Two outputs, plane and rover, over shared top-level settings.
const TWO_OUTPUTS: &str = include_str!("../../../testdata/two-outputs.toml");

#[test]
fn outputs_inherit_the_top_level_and_override_it() {
    let cfg = Config::parse(TWO_OUTPUTS).unwrap();
    let outs = Plan::resolve(&cfg).unwrap().outputs;
    assert_eq!(outs.len(), 2);
    // The plan's models, and the entries' sections they were built from.
    let (pm, rm) = (&outs[0].model, &outs[1].model);
    let (plane, rover) = (&cfg.outputs[0].config, &cfg.outputs[1].config);
    assert_eq!(
        (outs[0].name.as_str(), outs[1].name.as_str()),
        ("plane", "rover")
    );
    assert_eq!(outs[0].frame_log, plane.ppmd.frame_log);
    assert_eq!(outs[1].failsafe, rover.failsafe);
    assert_eq!(plane.name, "plane");
    assert_eq!(plane.ppmd.output, "sim:plane.trace");
    assert_eq!(plane.ppmd.frame_log, Some(PathBuf::from("plane.jsonl")));
    assert_eq!(plane.ingress.listen.port(), 5005);
    assert_eq!(pm.channels(), 8);
    assert_eq!(plane.failsafe.after_ms, 150);
    assert_eq!(plane.failsafe.action, FailsafeAction::Silence);
    assert_eq!(rover.ppmd.output, "gpio:gpiochip0:18");
    assert_eq!(rover.ppmd.frame_log, None);
    assert_eq!(rover.ingress.listen.port(), 5006);
    assert_eq!(rm.channels(), 6);
    assert_eq!(rm.names()[..4], ["thr", "ail", "ele", "rud"]);
    assert_eq!(rm.frame_ns(), 20_000_000);
    assert_eq!(rover.failsafe.after_ms, 150, "inherited");
    assert_eq!(rover.failsafe.action, FailsafeAction::Hold);
    // ppm.channel merges key by key: rover keeps the inherited ail reverse.
    assert!(rover.ppm.channel["ail"].reverse);
    assert_eq!(rover.ppm.channel["thr"].max_us, Some(1900.0));
    assert!(!plane.ppm.channel.contains_key("thr"));
    // The shared sections stay shared.
    assert_eq!(plane.rt, rover.rt);
    assert_eq!(plane.ipc, rover.ipc);
}

fn refusal(text: &str) -> ConfigError {
    match Config::parse(text) {
        Ok(c) => Plan::resolve(&c)
            .map(|_| ())
            .expect_err(&text[text.len().saturating_sub(300)..]),
        Err(e) => e,
    }
}

#[test]
fn output_entries_are_checked_and_named() {
    let with = |extra: &str| format!("{TWO_OUTPUTS}{extra}");
    let e = refusal(&TWO_OUTPUTS.replace("channels = 6", "channels = 17"));
    assert_eq!(e.key(), Some("outputs[1].ppm.channels"), "{e}");
    let e = refusal(&TWO_OUTPUTS.replace("\"0.0.0.0:5006\"", "\"0.0.0.0:5005\""));
    assert_eq!(e.key(), Some("outputs[1].ingress.listen"), "{e}");
    assert!(e.to_string().contains("`plane`"), "{e}");
    let e = refusal(&TWO_OUTPUTS.replace("name = \"rover\"", "name = \"plane\""));
    assert_eq!(e.key(), Some("outputs[1].name"), "{e}");
    let e = refusal(&TWO_OUTPUTS.replace("gpio:gpiochip0:18", "sim:plane.trace"));
    assert_eq!(e.key(), Some("outputs[1].output"), "{e}");
    let e = refusal(&TWO_OUTPUTS.replace("name = \"rover\"\n", ""));
    assert_eq!(e.key(), Some("outputs[1].name"), "{e}");
    // An inherited value that fails for one output keeps its own key.
    let e = refusal(&TWO_OUTPUTS.replace(
        "order = \"AETR\"",
        "order = \"AETR\"\ntiming = \"grid\"\nchannels = 12",
    ));
    assert_eq!(e.key(), Some("ppm.frame_us"), "{e}");
    assert!(e.to_string().contains("output `plane`"), "{e}");
    // Two outputs keeping their MAVLink timestamps in one file (inherited:
    // the top-level key).
    let e = refusal(&with("[mavlink]\ntimestamp_file = \"/var/lib/ppm/ts\"\n"));
    assert_eq!(e.key(), Some("mavlink.timestamp_file"), "{e}");
    assert!(e.to_string().contains("output `plane`"), "{e}");
    let e = refusal(&with("[rt]\npriority = 100\n"));
    assert_eq!(e.key(), Some("rt.priority"), "{e}");
    let e = refusal(&format!("name = \"x\"\n{TWO_OUTPUTS}"));
    assert_eq!(e.key(), Some("name"), "{e}");
    let e = refusal(&TWO_OUTPUTS.replace("frame_log = \"plane.jsonl\"", "rt.priority = 10"));
    assert!(
        e.to_string().contains("outputs[0]: unknown key `rt`"),
        "{e}"
    );
    let e = refusal(&TWO_OUTPUTS.replace("channels = 6", "chanels = 6"));
    assert!(
        e.to_string().contains("outputs[1]") && e.to_string().contains("chanels"),
        "{e}"
    );
    let many: String = (0..9)
        .map(|i| {
            format!(
                "[[outputs]]\nname = \"o{i}\"\ningress.listen = \"127.0.0.1:{}\"\n",
                6000 + i
            )
        })
        .collect();
    assert_eq!(refusal(&many).key(), Some("outputs"));
}

#[test]
fn select_picks_one_output() {
    let cfg = Config::parse(TWO_OUTPUTS).unwrap();
    assert_eq!(cfg.select(Some("rover")).unwrap().ppm.channels, Some(6));
    let e = cfg.select(None).unwrap_err().to_string();
    assert!(
        e.contains("2 outputs (plane, rover)") && e.contains("--name"),
        "{e}"
    );
    let e = cfg.select(Some("boat")).unwrap_err().to_string();
    assert!(
        e.contains("no output `boat`") && e.contains("plane, rover"),
        "{e}"
    );
    // Without [[outputs]] --name renames the one output.
    assert_eq!(ConfigFile::default().select(Some("x")).unwrap().name, "x");
    assert_eq!(ConfigFile::default().output_names(), ["ppm"]);
}
