//! The documentation matches the code: the example configuration lists
//! every key with its real default, and the configuration table and sample
//! error message of docs/configuration.md are the ones the code has; the
//! README's Python sender flies the line; every relative link in README.md
//! and docs/*.md leads to a file, and to a heading there, that exists.

use ppm_shared::config::Config;
use std::path::Path;

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

fn read(file: &str) -> String {
    std::fs::read_to_string(format!("{ROOT}/{file}")).unwrap_or_else(|e| panic!("{file}: {e}"))
}

/// The documentation as a whole: README.md and every docs/*.md, as (path
/// from the repository root, text).
fn documentation() -> Vec<(String, String)> {
    let mut docs: Vec<String> = std::fs::read_dir(format!("{ROOT}/docs"))
        .expect("docs/")
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.ends_with(".md"))
        .map(|n| format!("docs/{n}"))
        .collect();
    docs.sort();
    assert!(!docs.is_empty(), "docs/ holds the reference");
    std::iter::once("README.md".to_string())
        .chain(docs)
        .map(|f| {
            let text = read(&f);
            (f, text)
        })
        .collect()
}

/// The text of a `## ` section (up to the next `## `) of a file.
fn section(file: &str, heading: &str) -> String {
    let text = read(file);
    let start = text
        .find(&format!("\n## {heading}\n"))
        .unwrap_or_else(|| panic!("{file} has \"## {heading}\""));
    let rest = &text[start + 1..];
    let end = rest[3..].find("\n## ").map_or(rest.len(), |e| e + 3);
    rest[..end].to_string()
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
fn docs_document_every_key_of_the_example() {
    let example: toml::Value = toml::from_str(&read("ppm.example.toml")).unwrap();
    let mut all = vec![];
    keys("", &example, &mut all);
    assert!(all.len() >= 17, "{all:?}");
    let table = read("docs/configuration.md");
    for k in all {
        assert!(
            table.contains(&format!("| `{k}` |")),
            "docs/configuration.md's configuration table lacks `{k}`"
        );
    }
}

#[test]
fn docs_error_example_is_the_real_message() {
    let err = Config::parse("[ppm]\nframe_us = 19000")
        .unwrap()
        .validate()
        .unwrap_err();
    assert!(
        read("docs/configuration.md").contains(&err.to_string()),
        "docs/configuration.md shows another message than:\n{err}"
    );
}

/// The Python sender of the README's quick start, run as written (but aimed
/// at this test's port) against the real pipeline.
#[test]
fn readme_python_sender_flies_the_line() {
    use nix::sys::signal::Signal;
    use ppm_tests::{python3, read_trace, Sandbox, PYTHON_PACKAGE};
    use std::time::Duration;

    let quick_start = section("README.md", "Quick start");
    let code = quick_start
        .split("```python\n")
        .nth(1)
        .and_then(|s| s.split("```").next())
        .expect("the README's quick start has a python block");
    let sb = Sandbox::new("python");
    let code = code.replace("5005", &sb.port.to_string());
    let cfg = sb.config("");
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.start_ppmd(&cfg, "line.trace");
    let _ingress = sb.start_ingress(&cfg, &[]);
    // The snippet imports the package from the source tree (`import ppm`).
    python3(&sb.dir, PYTHON_PACKAGE, &["-c", &code]);
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
fn docs_several_outputs_example_is_valid() {
    let docs = read("docs/configuration.md");
    let section = docs
        .split("## Several vehicles from one board")
        .nth(1)
        .expect("docs/configuration.md has the section");
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

/// The paragraphs of a markdown text outside fenced code blocks.
fn paragraphs(text: &str) -> Vec<String> {
    let mut out = vec![String::new()];
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            out.push(String::new());
        } else if line.trim().is_empty() {
            out.push(String::new());
        } else if !fenced {
            let last = out.last_mut().unwrap();
            last.push_str(line);
            last.push('\n');
        }
    }
    out.retain(|p| !p.is_empty());
    out
}

/// GitHub's anchor for a heading: lowercase, spaces to `-`, punctuation
/// other than `-` and `_` dropped.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The anchors of a markdown file's headings; a repeated heading gets `-1`,
/// `-2`, ... as on GitHub.
fn anchors(text: &str) -> Vec<String> {
    let mut out: Vec<String> = vec![];
    for line in paragraphs(text).iter().flat_map(|p| p.lines()) {
        let level = line.len() - line.trim_start_matches('#').len();
        if (1..=6).contains(&level) && line[level..].starts_with(' ') {
            let base = anchor(&line[level..]);
            let mut a = base.clone();
            for n in 1.. {
                if !out.contains(&a) {
                    break;
                }
                a = format!("{base}-{n}");
            }
            out.push(a);
        }
    }
    out
}

/// The targets of a markdown text's links and images (`[text](target)`),
/// code spans and fenced blocks left out.
fn link_targets(text: &str) -> Vec<String> {
    let mut out = vec![];
    for p in paragraphs(text) {
        let prose: String = p.split('`').step_by(2).collect();
        for (i, _) in prose.match_indices("](") {
            let rest = &prose[i + 2..];
            if let Some(end) = rest.find(')') {
                let target = rest[..end].split_whitespace().next().unwrap_or("");
                out.push(target.to_string());
            }
        }
    }
    out
}

#[test]
fn anchors_follow_githubs_rules() {
    assert_eq!(
        anchor("udp-ingress's receive thread"),
        "udp-ingresss-receive-thread"
    );
    assert_eq!(
        anchor("Frame timing: grid or follow"),
        "frame-timing-grid-or-follow"
    );
    assert_eq!(
        anchor("A PREEMPT_RT Raspberry Pi"),
        "a-preempt_rt-raspberry-pi"
    );
    assert_eq!(
        anchors("# A\n```\n# not a heading\n```\n## A\n"),
        ["a", "a-1"]
    );
    assert_eq!(
        link_targets("[a](x.md#b) `[c](not-a-link)` ![d](img/e.svg)\n"),
        ["x.md#b", "img/e.svg"]
    );
}

/// Every relative link in README.md and docs/*.md points to a file or
/// directory that exists, and every `#anchor` to a heading of its file.
#[test]
fn every_relative_link_resolves() {
    let mut checked = 0;
    let mut broken = vec![];
    for (file, text) in documentation() {
        let dir = Path::new(&file).parent().unwrap();
        for target in link_targets(&text) {
            if target.contains("://") || target.starts_with("mailto:") {
                continue;
            }
            checked += 1;
            let (path, fragment) = match target.split_once('#') {
                Some((path, fragment)) => (path, Some(fragment)),
                None => (target.as_str(), None),
            };
            let to = if path.is_empty() {
                Path::new(&file).to_path_buf()
            } else {
                dir.join(path)
            };
            let full = Path::new(ROOT).join(&to);
            if !full.exists() {
                broken.push(format!("{file}: `{target}`: no {}", to.display()));
                continue;
            }
            if let Some(fragment) = fragment {
                let text = std::fs::read_to_string(&full).unwrap_or_default();
                let is_markdown = full.extension().is_some_and(|e| e == "md");
                if !is_markdown || !anchors(&text).iter().any(|a| a == fragment) {
                    broken.push(format!(
                        "{file}: `{target}`: no heading #{fragment} in {}",
                        to.display()
                    ));
                }
            }
        }
    }
    assert!(checked >= 40, "only {checked} links found");
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}
