//! The `jitter` tool: cyclictest's formats, the trace analysis against
//! percentiles computed here directly from the trace, and the live view of a
//! running ppmd.

use nix::sys::signal::Signal;
use ppm_tests::{bin, Sandbox, Sender};
use std::process::{Command, Output, Stdio};
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
    // As cyclictest: with -q -h the histogram block is the summary, no T: line.
    assert!(!out.contains("T: 0 ("), "{out}");
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
    let attach_svg = sb.dir.join("attach.svg");
    let attach = std::thread::spawn({
        let (cfg, name) = (cfg.to_string(), sb.name.clone());
        let svg = attach_svg.to_str().unwrap().to_string();
        move || {
            let out = Command::new(bin("jitter"))
                .args([
                    "--attach", &name, "--config", &cfg, "-l", "2", "-q", "-h", "50", "--plot",
                    &svg,
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

    check_svg(&attach_svg, "edge error of");

    // --trace: percentiles equal those computed here from the raw lines.
    let trace_svg = sb.dir.join("trace.svg");
    let out = run(&[
        "--trace",
        trace.to_str().unwrap(),
        "--plot",
        trace_svg.to_str().unwrap(),
    ]);
    let mut errors: Vec<i64> = std::fs::read_to_string(&trace)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<i64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            v[1] - v[0]
        })
        .collect();
    // More than 1000, so that p99.9 is a rank of its own and not the
    // maximum (about 2400 in these 3 s; frames cut short at a late edge
    // have fewer).
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
    check_svg(&trace_svg, &format!("edge error of {} edges", errors.len()));
    // The p99 mark is the trace's p99, to the 3 digits it shows.
    let svg = std::fs::read_to_string(&trace_svg).unwrap();
    let shown: f64 = svg
        .split("p99 = ")
        .nth(1)
        .and_then(|t| t.split(" us").next())
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no p99 mark:\n{svg}"));
    let p99 = rank(&errors, 0.99) as f64 / 1e3;
    assert!(
        (shown - p99).abs() <= p99.abs() * 0.005 + 0.001,
        "p99 mark {shown} vs {p99}"
    );
}

/// A written SVG: the whole document, its title, the four marks.
fn check_svg(path: &std::path::Path, title: &str) {
    let svg = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(svg.trim_start().starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    assert!(svg.contains(title), "title `{title}`:\n{svg}");
    for mark in ["p50 = ", "p99 = ", "p99.9 = ", "max = "] {
        assert!(svg.contains(mark), "{mark}:\n{svg}");
    }
}

#[test]
fn the_latency_test_plots_its_histogram() {
    let sb = Sandbox::new("jplot");
    let svg = sb.dir.join("latency.svg");
    run(&[
        "-q",
        "-t",
        "2",
        "-l",
        "300",
        "-i",
        "500",
        "--plot",
        svg.to_str().unwrap(),
    ]);
    check_svg(&svg, "jitter: wake-up latency, 2 threads, -i 500 us");
    // A directory that does not exist: a clear error naming the file.
    let bad = Command::new(bin("jitter"))
        .args(["-q", "-l", "10", "--plot", "/nonexistent/dir/x.svg"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("/nonexistent/dir/x.svg"),
        "{bad:?}"
    );
}

/// A line's shape: every run of digits and spaces that holds a digit
/// becomes its width (`T: 0 ( 6589) P:50` and `T: 0 (15452) P:50` are the
/// same shape); the overflow cycle lists and the break lines keep only
/// their labels (which cycles overflowed differs from run to run).
fn shape(text: &str) -> Vec<String> {
    text.lines()
        .map(|l| {
            if l.starts_with("# Thread ") || l.starts_with("# Break ") {
                return l.split(':').next().unwrap().to_string();
            }
            let mut out = String::new();
            let mut run = String::new();
            let flush = |run: &mut String, out: &mut String| {
                if run.chars().any(|c| c.is_ascii_digit()) {
                    out.push_str(&format!("<{}>", run.len()));
                } else {
                    out.push_str(run);
                }
                run.clear();
            };
            for c in l.chars() {
                if c.is_ascii_digit() || c == ' ' {
                    run.push(c);
                } else {
                    flush(&mut run, &mut out);
                    out.push(c);
                }
            }
            flush(&mut run, &mut out);
            out
        })
        .collect()
}

/// Whether cyclictest is here; under CI it must be (CI installs rt-tests).
fn have_cyclictest() -> bool {
    let here = Command::new("cyclictest")
        .arg("--help")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok();
    if !here {
        assert!(
            std::env::var_os("CI").is_none(),
            "cyclictest is not installed: apt-get install rt-tests"
        );
        eprintln!("skipped: cyclictest is not installed (apt-get install rt-tests)");
    }
    here
}

fn output(program: &str, args: &[&str]) -> Output {
    let out = Command::new(program)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("running {program}: {e}"));
    assert!(
        out.status.success(),
        "{program} {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The same command lines through cyclictest 2.40 and jitter print the
/// same lines in the same formats (jitter with `--spin 0`, a plain sleep
/// as cyclictest's, so that both see latencies of the same size). rteval's
/// own call among them.
#[test]
fn jitter_prints_what_cyclictest_prints() {
    if !have_cyclictest() {
        return;
    }
    let jitter = bin("jitter");
    let cases: [&[&str]; 8] = [
        &["-q", "-h", "5", "-l", "50", "-p", "50", "-m"],
        &["-q", "-l", "30", "-t", "2", "-p", "50"],
        &["-q", "-H", "3", "-l", "20", "-t", "2", "-p", "50"],
        &["-q", "-N", "-l", "20", "-p", "50"],
        &["-q", "-b", "5", "-l", "100", "-p", "50"],
        &[
            "-i100", "-qmu", "-h", "3500", "-p95", "-t1", "-a0", "-l", "200",
        ],
        &["-S", "-q", "-l", "20", "-p", "50"],
        &["-q", "-t", "-a", "-D", "1", "-i", "10000", "-p", "50"],
    ];
    for args in cases {
        let theirs = output("cyclictest", args);
        let mut ours_args = args.to_vec();
        ours_args.extend(["--spin", "0"]);
        let ours = output(jitter.to_str().unwrap(), &ours_args);
        let (t, o) = (
            String::from_utf8_lossy(&theirs.stdout),
            String::from_utf8_lossy(&ours.stdout),
        );
        assert_eq!(
            shape(&o),
            shape(&t),
            "{args:?}\n--- cyclictest:\n{t}\n--- jitter:\n{o}"
        );
    }

    // --json: the same keys, at every level (histogram buckets aside).
    fn keys(v: &serde_json::Value, path: &str, out: &mut Vec<String>) {
        if let Some(o) = v.as_object() {
            for (k, v) in o {
                let p = format!("{path}/{k}");
                out.push(p.clone());
                if k != "histogram" {
                    keys(v, &p, out);
                }
            }
        }
    }
    let dir = Sandbox::new("ctjson");
    let mut docs = Vec::new();
    for program in ["cyclictest", jitter.to_str().unwrap()] {
        let file = dir.dir.join(format!("{}.json", docs.len()));
        let json = format!("--json={}", file.display());
        output(
            program,
            &["-q", "-h", "5", "-l", "20", "-t", "2", "-p", "50", &json],
        );
        let doc: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
        let mut k = Vec::new();
        keys(&doc, "", &mut k);
        k.sort();
        docs.push((k, doc));
    }
    assert_eq!(docs[1].0, docs[0].0);
    // Times as cyclictest writes them: `Mon, 23 Nov 2026 13:16:47 +0000`.
    let time = |d: &serde_json::Value| shape(d["start_time"].as_str().unwrap());
    assert_eq!(time(&docs[1].1), time(&docs[0].1));
}

/// SIGUSR1 prints cyclictest's status block to standard error and the test
/// runs on; SIGTERM then ends it with its summary.
#[test]
fn sigusr1_prints_a_status_block_and_the_test_goes_on() {
    let run_with_usr1 = |program: &str| -> (String, String) {
        let child = Command::new(program)
            .args(["-q", "-D", "3", "-t", "2", "-p", "50"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(1_000));
        let pid = nix::unistd::Pid::from_raw(child.id() as i32);
        nix::sys::signal::kill(pid, Signal::SIGUSR1).unwrap();
        let out = child.wait_with_output().unwrap();
        assert!(out.status.success(), "{program}: {:?}", out.status);
        (
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .filter(|l| !l.starts_with("# T:"))
                .map(|l| format!("{l}\n"))
                .collect(),
        )
    };
    let jitter = bin("jitter");
    let (out, err) = run_with_usr1(jitter.to_str().unwrap());
    let block = shape(&err);
    assert_eq!(block.len(), 5, "{err}");
    assert_eq!(block[0], "#---------------------------");
    assert_eq!(block[1], "# cyclictest current status:");
    assert!(block[2].starts_with("T:<3>(<5>) P:<3>I:<5>C:"), "{err}");
    assert!(block[3].starts_with("T:<3>(<5>) P:<3>I:<5>C:"), "{err}");
    // The test ran its 3 s after the signal: about 3000 and 2000 cycles.
    // How many is the function here: it went on to its end. A cycle a
    // loaded machine misses is skipped, not counted; these leave room for
    // a sixth of them missed.
    let cycles = |l: &str| -> u64 {
        l.split("C:")
            .nth(1)
            .unwrap()
            .split_whitespace()
            .next()
            .unwrap()
            .parse()
            .unwrap()
    };
    let t: Vec<&str> = out.lines().filter(|l| l.starts_with("T:")).collect();
    assert_eq!(t.len(), 2, "{out}");
    assert!(cycles(t[0]) > 2_500 && cycles(t[1]) > 1_600, "{out}");
    let at_signal: Vec<&str> = err.lines().filter(|l| l.starts_with("T:")).collect();
    assert!(cycles(at_signal[0]) < 2_000, "{err}");
    if have_cyclictest() {
        let (_, theirs) = run_with_usr1("cyclictest");
        assert_eq!(
            block,
            shape(&theirs),
            "--- cyclictest:\n{theirs}\n--- jitter:\n{err}"
        );
    }
}

/// cyclictest's options jitter has no use for are accepted with a note
/// (`-n`, gone from cyclictest 2.x, for older scripts), and -D takes
/// cyclictest's suffixes.
#[test]
fn cyclictest_options_are_accepted() {
    let jitter = bin("jitter");
    let out = output(
        jitter.to_str().unwrap(),
        &["-q", "-s", "-n", "-u", "-l", "5", "-D", "1m"],
    );
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("-s (--system): not applicable, ignored"),
        "{out:?}"
    );
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("C:      5"),
        "{out:?}"
    );
    let bad = Command::new(&jitter).args(["-D", "5x"]).output().unwrap();
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("s, m, h or d"),
        "{bad:?}"
    );
}

/// A CPU that is not online (docs/real-time.md's `-a 3` on a smaller
/// machine) fails with a fix in jitter's own options, not ppmd's
/// `rt.cpu` or `--allow-degraded`, which jitter does not have.
#[test]
fn an_offline_cpu_names_a_fix_jitter_has() {
    let out = Command::new(bin("jitter"))
        .args(["-a", "4095", "-l", "5", "-q"])
        .output()
        .unwrap();
    assert!(!out.status.success(), "{out:?}");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.starts_with(
            "jitter: CPU pinning: CPU 4095 does not exist or is offline (online: "
        ) && err.trim_end().ends_with(
            ". Fix: give -a (--affinity) CPUs from the online list, or leave -a out to run unpinned"
        ),
        "{err}"
    );
    assert!(
        !err.contains("allow-degraded") && !err.contains("rt.cpu"),
        "{err}"
    );
}
