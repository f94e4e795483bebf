//! The documentation matches the code: the example configuration lists
//! every key with its real default, and the configuration table and sample
//! error message of docs/configuration.md are the ones the code has; the
//! README's Python sender flies the line; every relative link in README.md
//! and docs/*.md leads to a file, and to a heading there, that exists; the
//! synopsis of docs/programs.md lists every option of every program; the
//! documented datagrams parse as documented (accepted, or the reject
//! reason given) and the documented command lines parse with the programs'
//! own argument parsers.

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
    let err = Config::parse("[ppm]\ntiming = \"grid\"\nframe_us = 19000")
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

    let code = ppm_tests::python_block("README.md", "## Quick start");
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
    // Over 200 frames on the grid. ppmd runs here without real-time
    // priority, so on a loaded machine many are aborted at a late edge (cut
    // short, never a wrong value; CI's machine cut a third of them): how
    // many is the machine's business, what every frame carries is the
    // test's. Each frame, whole or cut short, carries the sender's first
    // two channels; each that carried the throttle (whole, or cut short
    // after it), its ramp, in order.
    let trace = read_trace(&trace);
    for f in &trace.decode(false) {
        let ch = f.channels_us();
        let n = ch.len().min(2);
        assert_eq!(ch[..n], [1500, 1500][..n], "a frame at {}", f.start_ns);
    }
    let thr = ppm_tests::channel_of_frames(&trace, 2);
    // Two frames are the least a ramp shows in.
    assert!(thr.len() >= 2, "{} frames carried the throttle", thr.len());
    assert!(
        thr.windows(2).all(|w| w[1] >= w[0]),
        "throttle ramps up: {thr:?}"
    );
    assert!(
        thr.iter().all(|t| (1_000..=1_498).contains(t)),
        "throttle within the ramp: {thr:?}"
    );
    assert!(thr.last().unwrap() - thr[0] > 250, "{thr:?}");
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
    let outs = ppm_shared::config::Plan::resolve(&cfg).unwrap().outputs;
    let names: Vec<&str> = outs.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, ["plane", "rover"]);
    assert_eq!(outs[1].model.names()[0], "thr");
    assert_eq!(outs[0].ingress.listen.port(), 5005);
    assert_eq!(outs[1].ingress.listen.port(), 5006);
    for o in &outs {
        assert!(section.contains(&format!("--name {}", o.name)));
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

/// The synopsis block of docs/programs.md: each program with the text of
/// its lines (a program may have several synopses, and a synopsis
/// continues on indented lines).
fn synopses() -> Vec<(String, String)> {
    let programs = section("docs/programs.md", "Programs");
    let block = programs
        .split("```\n")
        .nth(1)
        .expect("docs/programs.md's Programs section opens with a code block");
    let mut out: Vec<(String, String)> = vec![];
    for line in block.lines() {
        if line.starts_with(' ') {
            out.last_mut()
                .expect("a continuation line after a program's line")
                .1
                .push_str(line);
        } else if let Some((program, rest)) = line.split_once(' ') {
            match out.iter_mut().find(|(p, _)| p == program) {
                Some((_, text)) => text.push_str(rest),
                None => out.push((program.to_string(), rest.to_string())),
            }
        }
    }
    out
}

/// The options a program's `--help` lists: (short, long), without
/// `--help` and `--version`.
fn help_options(program: &str) -> Vec<(Option<String>, String)> {
    let out = std::process::Command::new(ppm_tests::bin(program))
        .arg("--help")
        .output()
        .unwrap_or_else(|e| panic!("{program} --help: {e}"));
    assert!(out.status.success(), "{program} --help: {out:?}");
    let mut options = vec![];
    for line in String::from_utf8(out.stdout).unwrap().lines() {
        let t = line.trim_start();
        if !line.starts_with(' ') || !t.starts_with('-') {
            continue;
        }
        let (short, rest) = match t.strip_prefix('-').and_then(|r| r.split_once(", ")) {
            Some((s, rest)) if s.len() == 1 => (Some(format!("-{s}")), rest),
            _ => (None, t),
        };
        let Some(long) = rest.strip_prefix("--") else {
            continue;
        };
        let long: String = long
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
            .collect();
        if long != "help" && long != "version" {
            options.push((short, format!("--{long}")));
        }
    }
    options
}

/// True when `text` has the option `opt` as a whole word (`--json` in
/// `[--json=FILE]`, not `--json` in `--json-file`).
fn names(text: &str, opt: &str) -> bool {
    text.match_indices(opt).any(|(i, _)| {
        let before = text[..i].chars().last();
        let after = text[i + opt.len()..].chars().next();
        !before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '-')
            && !after.is_some_and(|c| c.is_ascii_alphanumeric() || c == '-')
    })
}

/// Every option a program's `--help` shows is in docs/programs.md's
/// synopsis (by its long or its short name), and every program there has
/// its line.
#[test]
fn the_synopsis_lists_every_option_of_every_program() {
    let synopses = synopses();
    let programs: Vec<&str> = synopses.iter().map(|(p, _)| p.as_str()).collect();
    assert_eq!(programs, ppm_tests::PROGRAMS);
    let mut missing = vec![];
    for (program, text) in &synopses {
        let options = help_options(program);
        assert!(options.len() >= 3, "{program}: {options:?}");
        for (short, long) in options {
            if !names(text, &long) && !short.as_deref().is_some_and(|s| names(text, s)) {
                missing.push(format!("{program} {long}"));
            }
        }
    }
    assert!(
        missing.is_empty(),
        "docs/programs.md's synopsis lacks: {}",
        missing.join(", ")
    );
    // Every output kind is in ppmd's --help and its synopsis.
    let help = std::process::Command::new(ppm_tests::bin("ppmd"))
        .arg("--help")
        .output()
        .unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    for (kind, synopsis) in [
        ("sim", "sim"),
        ("gpio:CHIP:LINE", "gpio:[CHIP:]LINE"),
        ("gpio:LINE", "gpio:[CHIP:]LINE"),
        ("spi:DEVICE", "spi:DEVICE"),
        ("serial:DEVICE", "serial:DEVICE"),
    ] {
        assert!(help.contains(kind), "ppmd --help lacks {kind}");
        assert!(
            synopses[0].1.contains(synopsis),
            "ppmd's synopsis lacks {synopsis}"
        );
    }
}

/// The code spans of a markdown table row's cells.
fn code_spans(cell: &str) -> Vec<String> {
    cell.split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect()
}

/// The rows of the markdown tables in `text`, as cells, under the header
/// whose first cell is `first`.
fn table_rows(text: &str, first: &str) -> Vec<Vec<String>> {
    let mut out = vec![];
    let mut inside = false;
    for line in text.lines().map(str::trim) {
        if !line.starts_with('|') {
            inside = false;
            continue;
        }
        let cells: Vec<String> = line
            .trim_matches('|')
            .split(" | ")
            .map(|c| c.trim().to_string())
            .collect();
        if cells[0] == first {
            inside = true;
        } else if inside && !cells[0].starts_with("---") {
            out.push(cells);
        }
    }
    out
}

/// A code span that is a datagram (JSON text), not a key or a file name.
fn is_datagram(span: &str) -> bool {
    span.starts_with(['[', '{', '"', '-']) || span.starts_with(|c: char| c.is_ascii_digit())
}

/// The wire protocol's examples, as documented in README.md and
/// docs/protocol.md, parse to what the docs say: each form's example is
/// accepted, each reject reason's examples are rejected for that reason,
/// and the engineering-units example maps to the microseconds given.
#[test]
fn documented_datagrams_parse_as_documented() {
    use ppm_shared::protocol::parse;
    let protocol = read("docs/protocol.md");
    // The docs' unit-range block (ail -15..15), and one on ele for the
    // forms table's `{"units": {"ail": 3.0, "ele": -2}}`.
    let units = protocol
        .split("```toml\n")
        .nth(1)
        .and_then(|s| s.split("```").next())
        .expect("docs/protocol.md has the unit-range block");
    let model = Config::parse(&format!(
        "{units}\n[ppm.channel.ele]\nunit_min = -20.0\nunit_max = 20.0\n"
    ))
    .unwrap()
    .validate()
    .unwrap();
    let mut checked = 0;
    for file in ["README.md", "docs/protocol.md"] {
        let wire = section(file, "The wire protocol");
        let forms = table_rows(&wire, "form");
        assert_eq!(forms.len(), 5, "{file}: five forms");
        for row in forms {
            for d in code_spans(row.last().unwrap())
                .into_iter()
                .filter(|s| is_datagram(s))
            {
                assert!(
                    parse(d.as_bytes(), &model).is_ok(),
                    "{file}: the form example {d} is rejected: {:?}",
                    parse(d.as_bytes(), &model)
                );
                checked += 1;
            }
        }
    }
    let rejects = table_rows(&section("docs/protocol.md", "The wire protocol"), "reason");
    assert!(rejects.len() >= 9, "{rejects:?}");
    for row in rejects {
        let reason = &code_spans(&row[0])[0];
        for d in code_spans(row.last().unwrap())
            .into_iter()
            .filter(|s| is_datagram(s))
        {
            // The examples are at the rover's udp-ingress (an output named
            // `rover`; the wrong_output row sends a command for the plane).
            let got = ppm_shared::protocol::parse_for(
                d.as_bytes(),
                &model,
                ppm_shared::protocol::To::AbsentOr("rover"),
            )
            .map_err(|r| r.reason.as_str());
            assert_eq!(got.err(), Some(reason.as_str()), "docs/protocol.md: {d}");
            checked += 1;
        }
    }
    assert!(checked >= 20, "only {checked} documented datagrams");
    // "Then `{"units": {"ail": 3.0}}` is 1600 us".
    assert!(protocol.contains(r#"Then `{"units": {"ail": 3.0}}` is 1600 us"#));
    let cmd = parse(br#"{"units": {"ail": 3.0}}"#, &model).unwrap();
    assert_eq!(cmd.channels.as_ns()[0], 1_600_000);
}

/// Splits a shell command line into words: single and double quotes, a
/// trailing `# comment`; `None` for a line with pipes, redirections or
/// substitutions (not a plain command).
fn shell_words(line: &str) -> Option<Vec<String>> {
    let (mut words, mut word, mut quote, mut started) = (vec![], String::new(), None, false);
    for c in line.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), c) => word.push(c),
            (None, '\'' | '"') => {
                quote = Some(c);
                started = true;
            }
            (None, '#') if !started => break,
            (None, '|' | '<' | '>' | '$' | '`' | ';') => return None,
            (None, c) if c.is_whitespace() => {
                if started {
                    words.push(std::mem::take(&mut word));
                    started = false;
                }
            }
            (None, c) => {
                word.push(c);
                started = true;
            }
        }
    }
    if started {
        words.push(word);
    }
    Some(words)
}

/// The documented command lines of ppm's programs: (file, line, program,
/// arguments), from the `sh` blocks of README.md and docs/*.md (after
/// `sudo`, a path such as `target/release/`, `&&`, or
/// `cargo run ... --bin PROGRAM [-- ARGS]`).
fn documented_commands() -> Vec<(String, String, String, Vec<String>)> {
    let mut out = vec![];
    for (file, text) in documentation() {
        let mut sh = false;
        for line in text.lines() {
            let t = line.trim();
            if let Some(lang) = t.strip_prefix("```") {
                sh = !sh && matches!(lang, "sh" | "bash" | "shell");
                continue;
            }
            if !sh {
                continue;
            }
            let Some(words) = shell_words(t) else {
                continue;
            };
            for part in words.split(|w| w == "&&") {
                let mut w: Vec<&str> = part.iter().map(String::as_str).collect();
                if w.first() == Some(&"sudo") {
                    w.remove(0);
                }
                let (program, args) = match w.first() {
                    Some(&"cargo") if w.get(1) == Some(&"run") => {
                        let Some(i) = w.iter().position(|a| *a == "--bin") else {
                            continue;
                        };
                        let args = match w.iter().position(|a| *a == "--") {
                            Some(j) => w[j + 1..].to_vec(),
                            None => vec![],
                        };
                        (w[i + 1], args)
                    }
                    Some(first) => (first.rsplit('/').next().unwrap(), w[1..].to_vec()),
                    None => continue,
                };
                if ppm_tests::PROGRAMS.contains(&program) {
                    out.push((
                        file.clone(),
                        t.to_string(),
                        program.to_string(),
                        args.iter().map(|a| a.to_string()).collect(),
                    ));
                }
            }
        }
    }
    out
}

#[test]
fn shell_words_split_as_a_shell_does() {
    assert_eq!(
        shell_words(r#"ppm-send --to pi:5006 '{"norm": {"thr": -1}}'   # the rover"#).unwrap(),
        ["ppm-send", "--to", "pi:5006", r#"{"norm": {"thr": -1}}"#]
    );
    assert_eq!(shell_words("a \"b c\"").unwrap(), ["a", "b c"]);
    assert_eq!(shell_words("echo x | nc -u host 5005"), None);
}

/// Every documented command line of ppm's programs parses with the
/// program's real argument parser: run with `--help` after the documented
/// arguments, the program reads them all (an unknown option or a bad value
/// fails) and stops at `--help` without doing anything.
#[test]
fn documented_command_lines_parse() {
    let commands = documented_commands();
    let mut programs: Vec<&str> = commands.iter().map(|c| c.2.as_str()).collect();
    programs.sort_unstable();
    programs.dedup();
    assert!(
        programs.len() >= 6,
        "documented commands of only {programs:?}"
    );
    for (file, line, program, args) in &commands {
        let out = std::process::Command::new(ppm_tests::bin(program))
            .args(args)
            .arg("--help")
            .output()
            .unwrap_or_else(|e| panic!("{program}: {e}"));
        assert!(
            out.status.success() && String::from_utf8_lossy(&out.stdout).contains("Usage:"),
            "{file}: `{line}` does not parse: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}
