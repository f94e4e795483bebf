//! Latency statistics in cyclictest's formats: the live `T:` line, the `-h`
//! histogram block and the `--json` file, so scripts and plots written for
//! cyclictest read jitter's output unchanged.

use serde_json::{json, Map, Value};
use std::time::Duration;

/// Latencies of one thread, in whole units (us, or ns with `-N`).
#[derive(Debug, Clone)]
pub struct LatencyStats {
    hist: Vec<u64>,
    overflow: u64,
    outliers: Vec<u64>,
    /// Samples recorded.
    pub cycles: u64,
    /// Smallest latency.
    pub min: u64,
    /// Largest latency.
    pub max: u64,
    /// Most recent latency.
    pub act: u64,
    sum: u128,
}

impl LatencyStats {
    /// Statistics with a histogram of `buckets` buckets of one unit (0 for none).
    pub fn new(buckets: usize) -> LatencyStats {
        LatencyStats {
            hist: vec![0; buckets],
            overflow: 0,
            outliers: Vec::new(),
            cycles: 0,
            min: u64::MAX,
            max: 0,
            act: 0,
            sum: 0,
        }
    }

    /// Records one latency of sample number `cycle`.
    pub fn record(&mut self, v: u64, cycle: u64) {
        self.record_n(v, 1);
        // As many overflow cycle numbers as the histogram has buckets, as
        // cyclictest keeps.
        if v as usize >= self.hist.len()
            && !self.hist.is_empty()
            && self.outliers.len() < self.hist.len()
        {
            self.outliers.push(cycle);
        }
    }

    /// Records `n` samples of latency `v` (from a histogram).
    pub fn record_n(&mut self, v: u64, n: u64) {
        if n == 0 {
            return;
        }
        self.cycles += n;
        self.min = self.min.min(v);
        self.max = self.max.max(v);
        self.act = v;
        self.sum += v as u128 * n as u128;
        let with_histogram = !self.hist.is_empty();
        match self.hist.get_mut(v as usize) {
            Some(b) => *b += n,
            None if with_histogram => self.overflow += n,
            None => {}
        }
    }

    /// Replaces the summary figures (for statistics known only as a summary,
    /// such as a running ppmd's snapshot); `sum` is the sum of all latencies.
    pub fn with_summary(mut self, cycles: u64, min: u64, max: u64, act: u64, sum: u128) -> Self {
        self.cycles = cycles;
        self.min = min;
        self.max = max;
        self.act = act;
        self.sum = sum;
        self
    }

    /// Mean latency (integer, as cyclictest prints it).
    pub fn avg(&self) -> u64 {
        if self.cycles == 0 {
            0
        } else {
            (self.sum / self.cycles as u128) as u64
        }
    }

    fn min_or_zero(&self) -> u64 {
        if self.cycles == 0 {
            0
        } else {
            self.min
        }
    }

    /// cyclictest's status line: `T: 0 ( 1234) P:80 I:1000 C:   1000 Min: ...`
    /// (`Act` and `Avg` wider with `-N`, as cyclictest prints them).
    pub fn t_line(&self, thread: usize, tid: u32, prio: u32, interval: u64, nsecs: bool) -> String {
        let w = if nsecs { 8 } else { 5 };
        format!(
            "T:{thread:2} ({tid:5}) P:{prio:2} I:{interval} C:{:7} Min:{:7} Act:{:w$} Avg:{:w$} Max:{:8}",
            self.cycles,
            self.min_or_zero(),
            self.act,
            self.avg(),
            self.max
        )
    }

    /// cyclictest's `-h` block for this one thread.
    pub fn histogram_block(&self) -> String {
        histogram_block(&[self], false)
    }
}

/// cyclictest's `-h` block (`-H`: `histofall`, a sum column when there are
/// several threads), from `# Histogram` to the blank line after the
/// overflow cycle lists.
pub fn histogram_block(threads: &[&LatencyStats], histofall: bool) -> String {
    let sum_column = histofall && threads.len() > 1;
    let buckets = threads.iter().map(|t| t.hist.len()).max().unwrap_or(0);
    let mut s = String::from("# Histogram\n");
    for i in 0..buckets {
        let counts: Vec<u64> = threads
            .iter()
            .map(|t| t.hist.get(i).copied().unwrap_or(0))
            .collect();
        let cols: Vec<String> = counts.iter().map(|c| format!("{c:06}")).collect();
        s += &format!("{i:06} {}", cols.join("\t"));
        if sum_column {
            s += &format!("\t{:06}", counts.iter().sum::<u64>());
        }
        s += "\n";
    }
    let totals: Vec<u64> = threads.iter().map(|t| t.hist.iter().sum()).collect();
    let row = |label: &str, vals: &[u64], width: usize, sum: Option<u64>| {
        let mut r = format!("# {label}:");
        for v in vals {
            r += &format!(" {v:0width$}");
        }
        if let Some(x) = sum {
            r += &format!(" {x:0width$}");
        }
        r + "\n"
    };
    let all = |f: fn(&[u64]) -> u64, v: &[u64]| sum_column.then(|| f(v));
    let mins: Vec<u64> = threads.iter().map(|t| t.min_or_zero()).collect();
    let avgs: Vec<u64> = threads.iter().map(|t| t.avg()).collect();
    let maxs: Vec<u64> = threads.iter().map(|t| t.max).collect();
    let oflows: Vec<u64> = threads.iter().map(|t| t.overflow).collect();
    s += &row("Total", &totals, 9, all(|v| v.iter().sum(), &totals));
    s += &row("Min Latencies", &mins, 5, None);
    s += &row("Avg Latencies", &avgs, 5, None);
    s += &row(
        "Max Latencies",
        &maxs,
        5,
        all(|v| v.iter().copied().max().unwrap_or(0), &maxs),
    );
    s += &row(
        "Histogram Overflows",
        &oflows,
        5,
        all(|v| v.iter().sum(), &oflows),
    );
    s += "# Histogram Overflow at cycle number:\n";
    for (i, t) in threads.iter().enumerate() {
        s += &format!("# Thread {i}:");
        for c in &t.outliers {
            s += &format!(" {c:05}");
        }
        if t.overflow > t.outliers.len() as u64 {
            s += &format!(" # {:05} others", t.overflow - t.outliers.len() as u64);
        }
        s += "\n";
    }
    s += "\n";
    s
}

/// One measuring thread's part of the `--json` document.
#[derive(Debug, Clone)]
pub struct JsonThread<'a> {
    /// Its statistics.
    pub stats: &'a LatencyStats,
    /// The CPU it ran on (pinned, or where it ended), -1 if unknown.
    pub cpu: i64,
}

/// cyclictest's `--json` document, with cyclictest's keys, colons included
/// (`"cmdline:"`, `"rt_test_version:"`: so cyclictest 2.40 writes them).
/// `histogram`: whether `-h` was given (the key is there only then).
pub fn json(
    threads: &[JsonThread],
    cmdline: &str,
    start: &str,
    end: &str,
    nsecs: bool,
    histogram: bool,
) -> Value {
    let uts = nix::sys::utsname::uname().ok();
    let field = |f: fn(&nix::sys::utsname::UtsName) -> &std::ffi::OsStr| {
        uts.as_ref()
            .map(|u| f(u).to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let version = field(|u| u.version());
    let mut per = Map::new();
    for (i, t) in threads.iter().enumerate() {
        let s = t.stats;
        let mut o = Map::new();
        if histogram {
            let mut hist = Map::new();
            for (b, c) in s.hist.iter().enumerate().filter(|(_, c)| **c > 0) {
                hist.insert(b.to_string(), json!(c));
            }
            o.insert("histogram".into(), Value::Object(hist));
        }
        let avg = if s.cycles == 0 {
            0.0
        } else {
            (s.sum as f64 / s.cycles as f64 * 100.0).round() / 100.0
        };
        o.insert("cycles".into(), json!(s.cycles));
        o.insert("min".into(), json!(s.min_or_zero()));
        o.insert("max".into(), json!(s.max));
        o.insert("avg".into(), json!(avg));
        o.insert("cpu".into(), json!(t.cpu));
        o.insert("node".into(), json!(0));
        per.insert(i.to_string(), Value::Object(o));
    }
    json!({
        "file_version": 1,
        "cmdline:": cmdline,
        "rt_test_version:": concat!("ppm-jitter ", env!("CARGO_PKG_VERSION")),
        "start_time": start,
        "end_time": end,
        "return_code": 0,
        "sysinfo": {
            "sysname": field(|u| u.sysname()),
            "nodename": field(|u| u.nodename()),
            "release": field(|u| u.release()),
            "version": version,
            "machine": field(|u| u.machine()),
            "realtime": version.contains("PREEMPT_RT") as u8,
        },
        "num_threads": threads.len(),
        "resolution_in_ns": nsecs as u8,
        "thread": per,
    })
}

/// cyclictest's `-D`: a number of seconds, or with a suffix `s`, `m`
/// (minutes), `h`, `d`; `ms` (milliseconds) is jitter's own addition.
pub fn parse_cyclictest_duration(s: &str) -> Result<Duration, String> {
    let t = s.trim();
    let (num, scale) = if let Some(n) = t.strip_suffix("ms") {
        (n, 1e-3)
    } else {
        match t.char_indices().last() {
            Some((i, c)) if c.is_ascii_alphabetic() => {
                let scale = match c.to_ascii_lowercase() {
                    's' => 1.0,
                    'm' => 60.0,
                    'h' => 3_600.0,
                    'd' => 86_400.0,
                    _ => return Err(format!("`{s}`: the suffix must be s, m, h or d (or ms)")),
                };
                (&t[..i], scale)
            }
            _ => (t, 1.0),
        }
    };
    match num.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(Duration::from_secs_f64(v * scale)),
        _ => Err(format!(
            "`{s}` is not a duration: seconds, or a number with s, m, h or d (10, 30s, 5m, 1h, 1d)"
        )),
    }
}

/// cyclictest's `-a CPUSET`: `2`, `0-3`, `3-5,0`; the CPUs in order given.
pub fn parse_cpuset(s: &str) -> Result<Vec<usize>, String> {
    let bad = || format!("`{s}` is not a CPU set (e.g. 2, 0-3, 3-5,0)");
    let mut cpus = Vec::new();
    for part in s.split(',') {
        let part = part.trim();
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b): (usize, usize) = (
                    a.trim().parse().map_err(|_| bad())?,
                    b.trim().parse().map_err(|_| bad())?,
                );
                if a > b {
                    return Err(bad());
                }
                cpus.extend(a..=b);
            }
            None => cpus.push(part.parse().map_err(|_| bad())?),
        }
    }
    if cpus.is_empty() || cpus.len() > 4096 {
        return Err(bad());
    }
    Ok(cpus)
}

/// The CPU cyclictest pins thread `i` to: with a CPU set, its CPUs in
/// round-robin order (cyclictest sorts the set); with `-a` alone (or `-S`),
/// CPU `i` modulo the CPU count.
pub fn cpu_for_thread(i: usize, set: Option<&[usize]>, cpus: usize) -> usize {
    match set {
        Some(set) => {
            let mut sorted = set.to_vec();
            sorted.sort_unstable();
            sorted.dedup();
            sorted[i % sorted.len()]
        }
        None => i % cpus.max(1),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn block_has_cyclictests_rows_and_footer() {
        let mut s = LatencyStats::new(4);
        for (cycle, v) in [1u64, 1, 2, 3, 9, 12].iter().enumerate() {
            s.record(*v, cycle as u64);
        }
        let b = s.histogram_block();
        let lines: Vec<&str> = b.lines().collect();
        assert_eq!(
            lines,
            [
                "# Histogram",
                "000000 000000",
                "000001 000002",
                "000002 000001",
                "000003 000001",
                "# Total: 000000004",
                "# Min Latencies: 00001",
                "# Avg Latencies: 00004",
                "# Max Latencies: 00012",
                "# Histogram Overflows: 00002",
                "# Histogram Overflow at cycle number:",
                "# Thread 0: 00004 00005",
                "",
            ]
        );
        // The widths of cyclictest 2.40 (Act and Avg wider with -N).
        assert_eq!(
            s.t_line(0, 42, 80, 1000, false),
            "T: 0 (   42) P:80 I:1000 C:      6 Min:      1 Act:   12 Avg:    4 Max:      12"
        );
        assert_eq!(
            s.t_line(1, 6792, 50, 1500, true),
            "T: 1 ( 6792) P:50 I:1500 C:      6 Min:      1 Act:      12 Avg:       4 Max:      12"
        );
    }

    /// Two threads with -H: tab-separated columns, a sum column, and the
    /// sum only where cyclictest prints one (not for Min and Avg); the
    /// overflow list holds as many cycles as there are buckets.
    #[test]
    fn histofall_block_of_two_threads_is_cyclictests() {
        let mut a = LatencyStats::new(3);
        let mut b = LatencyStats::new(3);
        for (c, v) in [0u64, 1, 7, 8, 9, 10].iter().enumerate() {
            a.record(*v, c as u64);
        }
        for (c, v) in [2u64, 2, 1].iter().enumerate() {
            b.record(*v, c as u64);
        }
        let block = histogram_block(&[&a, &b], true);
        assert_eq!(
            block,
            "# Histogram\n\
             000000 000001\t000000\t000001\n\
             000001 000001\t000001\t000002\n\
             000002 000000\t000002\t000002\n\
             # Total: 000000002 000000003 000000005\n\
             # Min Latencies: 00000 00001\n\
             # Avg Latencies: 00005 00001\n\
             # Max Latencies: 00010 00002 00010\n\
             # Histogram Overflows: 00004 00000 00004\n\
             # Histogram Overflow at cycle number:\n\
             # Thread 0: 00002 00003 00004 # 00001 others\n\
             # Thread 1:\n\
             \n"
        );
        // -h (no sum column) of the same.
        let plain = histogram_block(&[&a, &b], false);
        assert!(plain.contains("000000 000001\t000000\n"), "{plain}");
        assert!(plain.contains("# Max Latencies: 00010 00002\n"), "{plain}");
    }

    #[test]
    fn json_has_cyclictests_keys() {
        let mut s = LatencyStats::new(10);
        s.record_n(3, 5);
        s.record_n(4, 1);
        let t = [
            JsonThread { stats: &s, cpu: 1 },
            JsonThread { stats: &s, cpu: -1 },
        ];
        let j = json(&t, "jitter -l 6", "a", "b", false, true);
        let keys: Vec<&str> = j.as_object().unwrap().keys().map(|k| k.as_str()).collect();
        let mut want = [
            "file_version",
            "cmdline:",
            "rt_test_version:",
            "start_time",
            "end_time",
            "return_code",
            "sysinfo",
            "num_threads",
            "resolution_in_ns",
            "thread",
        ];
        want.sort();
        let mut keys = keys;
        keys.sort();
        assert_eq!(keys, want);
        assert_eq!(j["thread"]["0"]["histogram"]["3"], 5);
        assert_eq!(j["thread"]["1"]["cpu"], -1);
        assert_eq!(j["thread"]["0"]["avg"], 3.17);
        assert_eq!(j["num_threads"], 2);
        let j = json(&t[..1], "x", "a", "b", true, false);
        assert!(j["thread"]["0"].get("histogram").is_none());
        assert_eq!(j["resolution_in_ns"], 1);
    }

    #[test]
    fn durations_as_cyclictest_reads_them() {
        let d = |s| parse_cyclictest_duration(s).unwrap();
        assert_eq!(d("10"), Duration::from_secs(10));
        assert_eq!(d("30s"), Duration::from_secs(30));
        assert_eq!(d("1m"), Duration::from_secs(60));
        assert_eq!(d("2h"), Duration::from_secs(7_200));
        assert_eq!(d("1d"), Duration::from_secs(86_400));
        assert_eq!(d("1.5"), Duration::from_millis(1_500));
        assert_eq!(d("500ms"), Duration::from_millis(500));
        for bad in ["", "m", "-1", "0", "5x", "1w"] {
            assert!(parse_cyclictest_duration(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn cpusets_and_round_robin() {
        assert_eq!(parse_cpuset("2").unwrap(), [2]);
        assert_eq!(parse_cpuset("3-5,0").unwrap(), [3, 4, 5, 0]);
        assert!(parse_cpuset("5-3").is_err());
        assert!(parse_cpuset("a").is_err());
        let set = parse_cpuset("3-5,0").unwrap();
        let cpus: Vec<usize> = (0..5).map(|i| cpu_for_thread(i, Some(&set), 8)).collect();
        assert_eq!(cpus, [0, 3, 4, 5, 0]);
        let all: Vec<usize> = (0..3).map(|i| cpu_for_thread(i, None, 2)).collect();
        assert_eq!(all, [0, 1, 0]);
    }
}
