//! The `jitter` tool: cyclictest's formats, the trace analysis against
//! percentiles computed here directly from the trace, and the live view of a
//! running ppmd.

use nix::sys::signal::Signal;
use ppm_tests::{bin, Sandbox, Sender};
use std::process::Command;
use std::time::Duration;

fn run(args: &[&str]) -> String {
    let out = Command::new(bin("jitter"))
        .args(args)
        .output()
        .expect("running jitter");
    assert!(
        out.status.success(),
        "jitter {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn cyclictest_summary_block_and_json() {
    let dir = Sandbox::new("cyclic");
    let json = dir.dir.join("out.json");
    let out = run(&[
        "-q",
        "-h",
        "100",
        "-l",
        "2000",
        "-i",
        "200",
        &format!("--json={}", json.display()),
    ]);
    let lines: Vec<&str> = out.lines().collect();
    let h = lines
        .iter()
        .position(|l| *l == "# Histogram")
        .expect("# Histogram");
    for (i, row) in lines[h + 1..h + 101].iter().enumerate() {
        let (bucket, count) = row.split_once(' ').unwrap();
        assert_eq!(bucket, format!("{i:06}"));
        assert_eq!(count.len(), 6, "{row}");
    }
    let footer = &lines[h + 101..];
    assert!(footer[0].starts_with("# Total: "), "{footer:?}");
    let total: u64 = footer[0][9..].parse().unwrap();
    let overflows: u64 = footer[4]["# Histogram Overflows: ".len()..]
        .parse()
        .unwrap();
    assert_eq!(total + overflows, 2000);
    assert!(footer[1].starts_with("# Min Latencies: "));
    assert!(footer[2].starts_with("# Avg Latencies: "));
    assert!(footer[3].starts_with("# Max Latencies: "));
    assert_eq!(footer[5], "# Histogram Overflow at cycle number:");
    assert!(footer[6].starts_with("# Thread 0:"));
    let t = footer
        .iter()
        .find(|l| l.starts_with("T: 0 ("))
        .expect("T: line");
    assert!(t.contains("I:200 C:   2000 Min:"), "{t}");
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    assert_eq!(doc["thread"]["0"]["cycles"], 2000);
    let in_hist: u64 = doc["thread"]["0"]["histogram"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(in_hist, total);
}

/// Nearest-rank percentile of sorted values.
fn rank(sorted: &[i64], q: f64) -> i64 {
    let n = sorted.len();
    sorted[((q * n as f64).ceil() as usize).clamp(1, n) - 1]
}

#[test]
fn trace_analysis_matches_the_trace_and_attach_shows_the_daemon() {
    let sb = Sandbox::new("jtrace");
    let cfg = sb.config("");
    let cfg = cfg.to_str().unwrap();
    let trace = sb.dir.join("line.trace");
    let mut ppmd = sb.spawn(
        "ppmd",
        &[
            "--config",
            cfg,
            "--output",
            &format!("sim:{}", trace.display()),
        ],
        "ppmd",
    );
    let _ingress = sb.spawn("udp-ingress", &["--config", cfg], "ingress");
    ppmd.wait_for_log("commands from", Duration::from_secs(30));
    let attach = std::thread::spawn({
        let (cfg, name) = (cfg.to_string(), sb.name.clone());
        move || {
            let out = Command::new(bin("jitter"))
                .args([
                    "--attach", &name, "--config", &cfg, "-l", "2", "-q", "-h", "50",
                ])
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            String::from_utf8(out.stdout).unwrap()
        }
    });
    let s = Sender::new(sb.addr());
    for _ in 0..150 {
        s.send(b"[1100, 1900]");
        std::thread::sleep(Duration::from_millis(20));
    }
    let live = attach.join().unwrap();
    assert!(ppmd
        .signal_and_wait(Signal::SIGTERM, Duration::from_secs(10))
        .success());

    // --attach: cyclictest's block from ppmd's snapshot.
    assert!(live.contains("# Histogram\n000000 "), "{live}");
    let t = live
        .lines()
        .find(|l| l.starts_with("T: 0 ("))
        .expect("T: line");
    assert!(t.contains("I:22500 C:"), "{t}");
    assert!(live.contains("edge error p50"), "{live}");

    // --trace: percentiles equal those computed here from the raw lines.
    let out = run(&["--trace", trace.to_str().unwrap()]);
    let mut errors: Vec<i64> = std::fs::read_to_string(&trace)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<i64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            v[1] - v[0]
        })
        .collect();
    assert!(errors.len() > 1000, "{} edges", errors.len());
    errors.sort_unstable();
    let us = |ns: i64| format!("{:.3}", ns as f64 / 1e3);
    let want = format!(
        "edge error us: min {} p50 {} p99 {} p99.9 {} max {}",
        us(errors[0]),
        us(rank(&errors, 0.5)),
        us(rank(&errors, 0.99)),
        us(rank(&errors, 0.999)),
        us(*errors.last().unwrap())
    );
    assert!(out.contains(&want), "expected `{want}` in:\n{out}");
    assert!(
        out.contains(&format!("edges {} frames", errors.len())),
        "{out}"
    );
    assert!(out.contains("channel period error us: min "), "{out}");
}
