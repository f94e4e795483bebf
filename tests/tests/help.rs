//! Every program's `--help` opens with what that program does (not the
//! tools crate's description, shared by six programs), ppmd's names both
//! protocols it speaks, and no program's help shows another's name in its
//! log format.

use ppm_tests::{bin, PROGRAMS};
use std::process::Command;

fn help(program: &str) -> String {
    let out = Command::new(bin(program)).arg("--help").output().unwrap();
    assert!(out.status.success(), "{program} --help");
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn every_program_says_what_it_does() {
    let mut firsts = Vec::new();
    for program in PROGRAMS {
        let text = help(program);
        let first = text.lines().next().unwrap_or("").to_string();
        assert!(!first.is_empty(), "{program}: {text}");
        assert!(
            !text.contains("Tools for ppm users"),
            "{program} prints the tools crate's description: {first}"
        );
        firsts.push((program, first));
    }
    for (i, (p, a)) in firsts.iter().enumerate() {
        for (q, b) in &firsts[i + 1..] {
            assert_ne!(a, b, "{p} and {q} open with the same line");
        }
    }
    let ppmd = help("ppmd");
    assert!(
        ppmd.contains("PPM") && ppmd.contains("SBUS"),
        "ppmd's help names one protocol: {ppmd}"
    );
    for program in ["ppmd", "udp-ingress"] {
        let text = help(program);
        let format = text
            .split("--log-format")
            .nth(1)
            .unwrap_or_else(|| panic!("{program}: no --log-format: {text}"));
        assert!(!format.contains("ppmd]"), "{program}: {format}");
    }
}
