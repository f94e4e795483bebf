//! The verdict and the summary of a loopback run: the checks the verdict
//! is made of ([`checks`]), the text printed and written with `--summary`
//! ([`summary`]), the SVG of `--svg` ([`svg`]).

use super::analysis::{Analysis, FrameTally, EXACT_NS};
use super::sweep::Sweep;
use anyhow::Result;
use ppm_tools::analysis::Percentiles;
use std::path::Path;

/// What the verdict allows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Thresholds {
    /// The edge error's 99.9th percentile, at most, ns.
    pub max_p999_ns: u64,
    /// A value read, at most this far from the value sent, ns.
    pub max_value_error_ns: u64,
}

/// One rule of the verdict, and how the run fared.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Check {
    /// Its name in the summary (`check NAME: ...`).
    pub name: &'static str,
    /// Whether the run meets it.
    pub ok: bool,
    /// What was found.
    pub detail: String,
}

/// The loop's own counters over the run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LoopCounts {
    /// Frames emitted.
    pub frames: u64,
    /// Edges written.
    pub edges: u64,
    /// Frames moved later as a whole (their values exact).
    pub late_frames: u64,
    /// Frames cut short at a late edge.
    pub aborted_frames: u64,
    /// Frames with an edge that may have reached the line late.
    pub glitched_frames: u64,
    /// Frames skipped.
    pub overruns: u64,
    /// Writes the line refused.
    pub write_errors: u64,
}

/// The run's facts besides the edges.
#[derive(Debug, Clone, Default)]
pub struct Run {
    /// The output as given.
    pub output: String,
    /// The input, as it describes itself.
    pub input: String,
    /// A sim loopback (the input's times are the trace's actual_ns).
    pub sim: bool,
    /// Seconds the loop ran.
    pub seconds: f64,
    /// The frame, in words.
    pub frame: String,
    /// What the real-time setup obtained.
    pub realtime: String,
    /// Notes: settings not obtained, the frame lengthened, Ctrl-C.
    pub notes: Vec<String>,
    /// The loop's counters.
    pub counts: LoopCounts,
    /// Written edges the ring dropped (not in the schedule).
    pub dropped: u64,
}

/// Microseconds of `ns`, to the nanosecond, without trailing zeros.
fn us(ns: f64) -> String {
    let s = format!("{:.3}", ns / 1e3);
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.into()
    }
}

/// The rules of the verdict (see docs/real-time.md, "Self-test with a
/// jumper wire"), each with what the run showed.
pub fn checks(a: &Analysis, dropped: u64, t: &Thresholds) -> Vec<Check> {
    let m = &a.matching;
    let edges_ok = a.written > 0
        && m.lost == 0
        && m.missed == 0
        && m.unexpected == 0
        && dropped == 0
        && m.pairs.len() == a.written;
    let edges = Check {
        name: "edges",
        ok: edges_ok,
        detail: if edges_ok {
            format!(
                "every one of the {} edges written was read back, in order",
                a.written
            )
        } else if a.written == 0 {
            "no edge was written".into()
        } else {
            format!(
                "{} of {} edges written were read back; {} lost by the kernel, {} missed, {} unexpected, {} not recorded",
                m.pairs.len(),
                a.written,
                m.lost,
                m.missed,
                m.unexpected,
                dropped
            )
        },
    };
    let s = &a.sweep;
    let sweep = Check {
        name: "sweep",
        ok: s.whole > 0 && s.of_sweep == s.whole,
        detail: format!(
            "{} of {} whole frames written were steps of the sweep",
            s.of_sweep, s.whole
        ),
    };
    let max = t.max_value_error_ns;
    let mut read_all = vec![];
    let mut failed = vec![];
    let mut tallies: Vec<(&str, &FrameTally)> = a
        .receivers
        .iter()
        .filter_map(|(r, t)| t.as_ref().ok().map(|t| (r.name(), t)))
        .collect();
    tallies.push(("capture", &a.capture));
    for (name, f) in tallies {
        if f.all_read_within(max) {
            read_all.push(name);
        } else if f.sent == 0 {
            failed.push(format!(
                "{name} was sent no frame it hands on (too short a run, or frames cut short too often for it to lock on their channel count)"
            ));
        } else {
            failed.push(format!(
                "{name} read {} of {} frames sent, {} not as sent, largest value error {} us",
                f.matched,
                f.sent,
                f.not_sent(),
                us(f.max_error_ns as f64)
            ));
        }
    }
    let frames = Check {
        name: "frames",
        ok: failed.is_empty(),
        detail: if failed.is_empty() {
            format!(
                "{} read every frame sent, each value within {} us",
                read_all.join(", "),
                us(max as f64)
            )
        } else {
            format!("{} (allowed: {} us)", failed.join("; "), us(max as f64))
        },
    };
    let p = Percentiles::of_histogram(&a.line_error);
    let error = Check {
        name: "edge error",
        ok: p.count > 0 && p.p999 <= t.max_p999_ns as f64,
        detail: if p.count == 0 {
            "no edge read back to measure".into()
        } else {
            format!(
                "p99.9 {} us {} {} us",
                us(p.p999),
                if p.p999 <= t.max_p999_ns as f64 {
                    "<="
                } else {
                    ">"
                },
                us(t.max_p999_ns as f64)
            )
        },
    };
    vec![edges, sweep, frames, error]
}

/// The verdict line: PASS when every check is met, else FAIL and the
/// checks not met.
pub fn verdict(checks: &[Check]) -> String {
    let failed: Vec<&str> = checks.iter().filter(|c| !c.ok).map(|c| c.name).collect();
    if failed.is_empty() {
        "verdict: PASS".into()
    } else {
        format!("verdict: FAIL ({})", failed.join(", "))
    }
}

/// `sent N read N exact N (within 1 us), not as sent N, largest value error X us`.
fn tally_line(f: &FrameTally) -> String {
    format!(
        "sent {} read {} exact {} (within {} us), not as sent {}, largest value error {} us",
        f.sent,
        f.read,
        f.exact,
        us(EXACT_NS as f64),
        f.not_sent(),
        us(f.max_error_ns as f64)
    )
}

/// The summary: what was sent, read and found, the checks and the verdict.
pub fn summary(run: &Run, sweep: &Sweep, a: &Analysis, checks: &[Check]) -> String {
    let mut s = String::new();
    let mut line = |text: String| {
        s += &text;
        s.push('\n');
    };
    line(format!(
        "# jitter loopback: output {}, input {}, {:.1} s",
        run.output, run.input, run.seconds
    ));
    line(format!("sweep: {}", sweep.describe()));
    line(format!("frame: {}", run.frame));
    line(format!("real-time: {}", run.realtime));
    for n in &run.notes {
        line(format!("note: {n}"));
    }
    if run.sim {
        line("note: sim loopback: the input reads the trace's actual_ns, the time ppmd's loop read just before each write, so the edge error below is what ppmd measures of its own writes, not a wire's; on a Pi, wire the output to an input pin".into());
    }
    let c = &run.counts;
    line(format!(
        "loop: {} frames, {} edges written; {} late frames, {} aborted, {} glitched, {} overruns, {} write errors",
        c.frames, c.edges, c.late_frames, c.aborted_frames, c.glitched_frames, c.overruns, c.write_errors
    ));
    let m = &a.matching;
    line(format!(
        "edges: {} written, {} read, {} paired; {} lost by the kernel, {} missed, {} unexpected, {} before the first frame, {} not recorded",
        a.written,
        a.read,
        m.pairs.len(),
        m.lost,
        m.missed,
        m.unexpected,
        m.before,
        run.dropped
    ));
    let p = Percentiles::of_histogram(&a.line_error);
    line(format!(
        "edge error us, as the line carries it (read time minus scheduled time, {} edges): {}",
        p.count,
        p.line(1e3)
    ));
    if a.early > 0 {
        line(format!(
            "early edges: {} read before their scheduled time (counted at 0 above), the earliest {} us",
            a.early,
            us(a.min_error_ns as f64)
        ));
    }
    let own = Percentiles::of_histogram(&a.own_error);
    line(format!(
        "edge error us, as ppmd measured it (its clock just before the write minus scheduled time, {} edges): {}",
        own.count,
        own.line(1e3)
    ));
    let w = &a.sweep;
    line(format!(
        "sweep frames: {} whole frames written, {} of them steps of the sweep; {} cut short at a late edge",
        w.whole, w.of_sweep, w.cut
    ));
    for (r, t) in &a.receivers {
        line(match t {
            Ok(t) => format!("{}: {}", r.name(), tally_line(t)),
            Err(rule) => format!("{}: not applicable: {rule}", r.name()),
        });
    }
    let refused: Vec<String> = a
        .capture_counts
        .reasons()
        .iter()
        .map(|(k, v)| format!("{k} {v}"))
        .collect();
    line(format!(
        "capture: {}; refused: {}",
        tally_line(&a.capture),
        refused.join(", ")
    ));
    for c in checks {
        line(format!(
            "check {}: {}: {}",
            c.name,
            if c.ok { "ok" } else { "FAIL" },
            c.detail
        ));
    }
    line(verdict(checks));
    s
}

/// The edge error as the line carries it, as an SVG histogram (log count
/// axis), p50, p99, p99.9 and the maximum marked.
pub fn svg(path: &Path, run: &Run, a: &Analysis) -> Result<()> {
    let p = Percentiles::of_histogram(&a.line_error);
    let title = if run.sim {
        format!(
            "jitter loopback (sim): edge error of {} edges, as ppmd measured them",
            p.count
        )
    } else {
        format!(
            "jitter loopback: edge error of {} edges, kernel timestamps of {}",
            p.count, run.input
        )
    };
    ppm_tools::plot::histogram_svg(
        path,
        &title,
        "us",
        &a.line_error,
        1e3,
        &[
            ("p50", p.p50 / 1e3),
            ("p99", p.p99 / 1e3),
            ("p99.9", p.p999 / 1e3),
            ("max", p.max / 1e3),
        ],
    )
}
