//! `ppmd --hdr-log`: an HdrHistogram interval log that the readers people
//! use read unchanged: this crate's own parser, Python's `hdrh` (in the
//! suite: CI installs it), and the Java HistogramLogProcessor with no
//! options (when `java` and the HdrHistogram jar are installed).

use hdrhistogram::serialization::interval_log::{IntervalLogIterator, LogEntry};
use hdrhistogram::serialization::Deserializer;
use nix::sys::signal::Signal;
use ppm_shared::framelog::{self, Status};
use ppm_tests::{at_50hz, Sandbox, Sender};
use std::process::Command;
use std::time::Duration;

const SECOND: Duration = Duration::from_secs(1);

/// What the log holds: per interval, the untagged histogram's count and
/// the `edge_error` tagged one's (0 when absent); the count of every
/// histogram in the file's order; and the `aborted` and `glitched`
/// histograms' counts over all intervals.
struct Intervals {
    edges: Vec<(u64, u64)>,
    /// Each interval's tags, in the file's order.
    tags: Vec<Vec<String>>,
    all: Vec<u64>,
    aborted: u64,
    glitched: u64,
}

fn intervals(text: &str) -> Intervals {
    let mut d = Deserializer::new();
    let mut out: Vec<(u64, u64)> = Vec::new();
    let mut tags: Vec<Vec<String>> = Vec::new();
    let mut all = Vec::new();
    let (mut aborted, mut glitched) = (0, 0);
    let mut start = None;
    for e in IntervalLogIterator::new(text.as_bytes()) {
        match e.expect("the log parses") {
            LogEntry::Interval(iv) => {
                let h: hdrhistogram::Histogram<u64> = d
                    .deserialize(&mut base64_decode(iv.encoded_histogram()).as_slice())
                    .unwrap();
                let count = h.len();
                all.push(count);
                if let Some(t) = iv.tag() {
                    tags.last_mut()
                        .expect("untagged first")
                        .push(t.as_str().to_string());
                }
                match iv.tag().map(|t| t.as_str().to_string()) {
                    None => {
                        out.push((count, 0));
                        tags.push(Vec::new());
                        start = Some(iv.start_timestamp());
                    }
                    Some(t) if t == "edge_error" => {
                        assert_eq!(Some(iv.start_timestamp()), start, "same interval");
                        out.last_mut().expect("untagged first").1 = count;
                    }
                    // Frames aborted or glitched at a late edge (this
                    // ppmd runs without real-time priority), when any.
                    Some(t) if t == "aborted" => aborted += count,
                    Some(t) if t == "glitched" => glitched += count,
                    Some(t) => assert_eq!(t, "write"),
                }
            }
            LogEntry::StartTime(_) | LogEntry::BaseTime(_) => {}
        }
    }
    Intervals {
        edges: out,
        tags,
        all,
        aborted,
        glitched,
    }
}

fn base64_decode(s: &str) -> Vec<u8> {
    // Standard alphabet with padding, as the log writes it.
    const A: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = Vec::new();
    let (mut acc, mut bits) = (0u32, 0);
    for c in s.bytes().filter(|c| *c != b'=') {
        acc = (acc << 6) | A.iter().position(|a| *a == c).expect("base64") as u32;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
        }
    }
    out
}

#[test]
fn the_hdr_log_is_read_by_rust_python_and_java_readers() {
    let sb = Sandbox::new("hdrlog");
    let cfg = sb.config("");
    let log = sb.dir.join("edge.hlog");
    let frames = sb.dir.join("frames.jsonl");
    let output = format!("sim:{}", sb.dir.join("line.trace").display());
    let mut ppmd = sb.spawn(
        "ppmd",
        &[
            "--config",
            cfg.to_str().unwrap(),
            "--output",
            &output,
            "--hdr-log",
            log.to_str().unwrap(),
            "--frame-log",
            frames.to_str().unwrap(),
        ],
        "ppmd",
    );
    ppmd.wait_for_log("commands from", 30 * SECOND);
    let _ingress = sb.start_ingress(&cfg, &[]);
    let s = Sender::new(sb.addr());
    at_50hz(150, |_| s.send(b"[1100, 1900, 1500, 1500]"));
    // A silent line for over an interval: its histograms are empty, and
    // there all the same.
    std::thread::sleep(5 * SECOND / 2);
    assert!(ppmd.signal_and_wait(Signal::SIGTERM, 10 * SECOND).success());
    let text = std::fs::read_to_string(&log).unwrap();

    // The headers Java's reader looks for.
    let lines: Vec<&str> = text.lines().collect();
    assert!(
        lines.contains(&"#[Histogram log format version 1.3]"),
        "{text}"
    );
    assert!(lines.iter().any(|l| l.starts_with("#[StartTime: ")));
    assert!(lines.contains(
        &r#""StartTimestamp","Interval_Length","Interval_Max","Interval_Compressed_Histogram""#
    ));

    // Every interval has an untagged histogram, the same as its edge_error.
    let Intervals {
        edges: iv,
        tags,
        all,
        aborted,
        glitched,
    } = intervals(&text);
    assert!(iv.len() >= 2, "{iv:?}");
    assert!(iv.iter().all(|(u, t)| u == t), "{iv:?}");
    // And every tag, in every interval, the silent ones (no edge) too.
    for t in &tags {
        assert_eq!(
            t,
            &["edge_error", "write", "aborted", "glitched"],
            "{tags:?}"
        );
    }
    assert!(
        iv.iter().any(|(u, _)| *u == 0),
        "no silent interval: {iv:?}"
    );
    // About 150 frames of 9 edges; fewer on a loaded machine, which cuts
    // frames short at a late edge. The readers below must agree on the
    // counts, whatever they are: one edge is what they need to read.
    let total: u64 = iv.iter().map(|(u, _)| u).sum();
    assert!(total >= 1, "no edge in the log: {iv:?}");

    // The aborted and glitched histograms count the frames the frame log
    // calls so, and ppmd's exit summary says the same.
    let rows = framelog::read_frames(&frames).unwrap_or_else(|e| panic!("{e}"));
    let aborted_rows = rows.iter().filter(|r| r.status == Status::Aborted).count() as u64;
    let glitched_rows = rows.iter().filter(|r| r.glitched).count() as u64;
    assert_eq!(
        (aborted, glitched),
        (aborted_rows, glitched_rows),
        "{rows:?}"
    );
    let summary = ppmd.log_text();
    assert!(
        summary.contains(&format!(
            " {aborted} aborted frames, {glitched} glitched frames,"
        )),
        "{summary}"
    );
    eprintln!("{aborted} aborted and {glitched} glitched frames, in all three");

    // Python's hdrh, unchanged.
    let script = format!(
        "from hdrh.log import HistogramLogReader\n\
         from hdrh.histogram import HdrHistogram\n\
         r = HistogramLogReader({:?}, HdrHistogram(1, 60 * 10**9, 3))\n\
         counts = []\n\
         while True:\n\
         \x20   h = r.get_next_interval_histogram()\n\
         \x20   if h is None: break\n\
         \x20   counts.append(str(h.get_total_count()))\n\
         print(' '.join(counts))\n",
        log.to_str().unwrap()
    );
    let py = Command::new("python3")
        .args(["-c", &script])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&py.stderr);
    if err.contains("No module named 'hdrh'") {
        assert!(
            std::env::var_os("CI").is_none(),
            "Python's hdrh is not installed: python3 -m pip install hdrhistogram"
        );
        eprintln!("skipped the Python reader: python3 -m pip install hdrhistogram");
    } else {
        assert!(py.status.success(), "{err}");
        // hdrh reads every histogram, tagged or not (it has no tags).
        let want: Vec<String> = all.iter().map(|c| c.to_string()).collect();
        assert_eq!(String::from_utf8_lossy(&py.stdout).trim(), want.join(" "));
    }

    // Java's HistogramLogProcessor with no options (Debian's
    // libhdrhistogram-java 2.1.11), when installed.
    let jar = "/usr/share/java/hdrhistogram.jar";
    let java = Command::new("java")
        .args(["-cp", jar, "org.HdrHistogram.HistogramLogProcessor", "-i"])
        .arg(&log)
        .output();
    match java {
        Ok(out) if std::path::Path::new(jar).exists() => {
            let text = String::from_utf8_lossy(&out.stdout);
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            let count: u64 = text
                .lines()
                .find_map(|l| l.split("Total count    =").nth(1))
                .and_then(|v| v.trim().trim_end_matches(']').trim().parse().ok())
                .unwrap_or_else(|| panic!("no total count:\n{text}"));
            assert_eq!(count, total, "{text}");
        }
        _ => eprintln!(
            "skipped the Java reader: apt-get install libhdrhistogram-java default-jre-headless"
        ),
    }
}
