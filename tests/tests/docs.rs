//! The documentation matches the code: the example configuration lists
//! every key with its real default, and the README's configuration table and
//! sample error message are the ones the code has.

use ppm_shared::config::Config;

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

fn read(file: &str) -> String {
    std::fs::read_to_string(format!("{ROOT}/{file}")).unwrap_or_else(|e| panic!("{file}: {e}"))
}

/// Every key of a TOML table, dotted.
fn keys(prefix: &str, v: &toml::Value, out: &mut Vec<String>) {
    if let toml::Value::Table(t) = v {
        for (k, v) in t {
            let path = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            match v {
                toml::Value::Table(_) => keys(&path, v, out),
                _ => out.push(path),
            }
        }
    }
}

#[test]
fn readme_documents_every_key_of_the_example() {
    let example: toml::Value = toml::from_str(&read("ppm.example.toml")).unwrap();
    let mut all = vec![];
    keys("", &example, &mut all);
    assert!(all.len() >= 17, "{all:?}");
    let readme = read("README.md");
    for k in all {
        assert!(
            readme.contains(&format!("| `{k}` |")),
            "README's configuration table lacks `{k}`"
        );
    }
}

#[test]
fn readme_error_example_is_the_real_message() {
    let err = Config::parse("[ppm]\nframe_us = 19000")
        .unwrap()
        .validate()
        .unwrap_err();
    assert!(
        read("README.md").contains(&err.to_string()),
        "README shows another message than:\n{err}"
    );
}

/// The README's Python sender, run as written (but aimed at this test's
/// port) against the real pipeline.
#[test]
fn readme_python_sender_flies_the_line() {
    use nix::sys::signal::Signal;
    use ppm_tests::{read_trace, Sandbox};
    use std::time::Duration;

    let readme = read("README.md");
    let code = readme
        .split("```python\n")
        .nth(1)
        .and_then(|s| s.split("```").next())
        .expect("README has a python block");
    let sb = Sandbox::new("python");
    let code = code.replace("5005", &sb.port.to_string());
    let cfg = sb.config("");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let _ingress = sb.start_ingress(&cfg, &[]);
    // The snippet imports the package from the source tree (`import ppm`).
    let status = std::process::Command::new("python3")
        .arg("-c")
        .arg(&code)
        .env("PYTHONPATH", format!("{ROOT}/tools/python"))
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .status()
        .expect("python3 is needed for this test (apt-get install python3)");
    assert!(status.success());
    assert!(ppmd
        .signal_and_wait(Signal::SIGTERM, Duration::from_secs(10))
        .success());
    let frames = read_trace(&trace).decode(false);
    assert!(frames.len() >= 150, "{} frames", frames.len());
    let thr: Vec<u64> = frames.iter().map(|f| f.channels_us()[2]).collect();
    assert!(
        thr.windows(2).all(|w| w[1] >= w[0]),
        "throttle ramps up: {thr:?}"
    );
    assert!(thr[0] < 1_020 && *thr.last().unwrap() > 1_480, "{thr:?}");
    assert!(frames.iter().all(|f| f.channels_us()[..2] == [1500, 1500]));
}

#[test]
fn readme_several_outputs_example_is_valid() {
    let readme = read("README.md");
    let section = readme
        .split("## Several vehicles from one board")
        .nth(1)
        .expect("the README has the section");
    let toml = section
        .split("```toml\n")
        .nth(1)
        .and_then(|s| s.split("```").next())
        .expect("a toml block");
    let cfg = ppm_shared::config::Config::parse(toml).unwrap();
    let outs = cfg.validate_outputs().unwrap();
    let names: Vec<&str> = outs.iter().map(|(c, _)| c.name.as_str()).collect();
    assert_eq!(names, ["plane", "rover"]);
    assert_eq!(outs[1].1.names()[0], "thr");
    assert_eq!(outs[0].0.ingress.listen.port(), 5005);
    assert_eq!(outs[1].0.ingress.listen.port(), 5006);
    for (c, _) in &outs {
        assert!(section.contains(&format!("--name {}", c.name)));
    }
}
