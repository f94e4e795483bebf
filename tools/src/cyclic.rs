//! Latency statistics in cyclictest's formats: the live `T:` line, the `-h`
//! histogram block and the `--json` file, so scripts and plots written for
//! cyclictest read jitter's output unchanged.

use serde_json::{json, Map, Value};

/// Overflow cycle numbers kept for the `# Thread 0:` line (as cyclictest).
const MAX_OUTLIERS: usize = 1_000;

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
        if v as usize >= self.hist.len()
            && !self.hist.is_empty()
            && self.outliers.len() < MAX_OUTLIERS
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

    /// cyclictest's status line: `T: 0 ( 1234) P:80 I:1000 C:   1000 Min: ...`.
    pub fn t_line(&self, thread: usize, tid: u32, prio: u32, interval: u64) -> String {
        format!(
            "T:{thread:2} ({tid:5}) P:{prio:2} I:{interval} C:{:7} Min:{:7} Act:{:8} Avg:{:8} Max:{:8}",
            self.cycles,
            self.min_or_zero(),
            self.act,
            self.avg(),
            self.max
        )
    }

    /// cyclictest's `-h` block, from `# Histogram` to the overflow cycle list.
    pub fn histogram_block(&self) -> String {
        let mut s = String::from("# Histogram\n");
        for (i, c) in self.hist.iter().enumerate() {
            s += &format!("{i:06} {c:06}\n");
        }
        let total: u64 = self.hist.iter().sum();
        s += &format!("# Total: {total:09}\n");
        s += &format!("# Min Latencies: {:05}\n", self.min_or_zero());
        s += &format!("# Avg Latencies: {:05}\n", self.avg());
        s += &format!("# Max Latencies: {:05}\n", self.max);
        s += &format!("# Histogram Overflows: {:05}\n", self.overflow);
        s += "# Histogram Overflow at cycle number:\n# Thread 0:";
        for c in &self.outliers {
            s += &format!(" {c:05}");
        }
        if self.overflow > self.outliers.len() as u64 {
            s += &format!(
                " # {:05} others",
                self.overflow - self.outliers.len() as u64
            );
        }
        s += "\n";
        s
    }

    /// cyclictest's `--json` document for one thread.
    pub fn json(
        &self,
        cmdline: &str,
        start: &str,
        end: &str,
        cpu: i64,
        resolution_in_ns: u64,
    ) -> Value {
        let mut hist = Map::new();
        for (i, c) in self.hist.iter().enumerate().filter(|(_, c)| **c > 0) {
            hist.insert(i.to_string(), json!(c));
        }
        let uts = nix::sys::utsname::uname().ok();
        let field = |f: fn(&nix::sys::utsname::UtsName) -> &std::ffi::OsStr| {
            uts.as_ref()
                .map(|u| f(u).to_string_lossy().into_owned())
                .unwrap_or_default()
        };
        let version = field(|u| u.version());
        json!({
            "file_version": 1,
            "cmdline": cmdline,
            "rt_test_version": concat!("ppm-jitter ", env!("CARGO_PKG_VERSION")),
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
            "num_threads": 1,
            "resolution_in_ns": resolution_in_ns,
            "thread": {
                "0": {
                    "histogram": hist,
                    "cycles": self.cycles,
                    "min": self.min_or_zero(),
                    "max": self.max,
                    "avg": if self.cycles == 0 { 0.0 } else { self.sum as f64 / self.cycles as f64 },
                    "cpu": cpu,
                    "node": 0,
                }
            }
        })
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
        assert_eq!(lines[0], "# Histogram");
        assert_eq!(
            &lines[1..5],
            [
                "000000 000000",
                "000001 000002",
                "000002 000001",
                "000003 000001"
            ]
        );
        assert_eq!(lines[5], "# Total: 000000004");
        assert_eq!(lines[6], "# Min Latencies: 00001");
        assert_eq!(lines[7], "# Avg Latencies: 00004");
        assert_eq!(lines[8], "# Max Latencies: 00012");
        assert_eq!(lines[9], "# Histogram Overflows: 00002");
        assert_eq!(lines[10], "# Histogram Overflow at cycle number:");
        assert_eq!(lines[11], "# Thread 0: 00004 00005");
        assert_eq!(
            s.t_line(0, 42, 80, 1000),
            "T: 0 (   42) P:80 I:1000 C:      6 Min:      1 Act:      12 Avg:       4 Max:      12"
        );
    }

    #[test]
    fn json_has_cyclictests_shape() {
        let mut s = LatencyStats::new(10);
        s.record_n(3, 5);
        let j = s.json("jitter -l 5", "a", "b", 1, 0);
        assert_eq!(j["thread"]["0"]["histogram"]["3"], 5);
        assert_eq!(j["thread"]["0"]["cycles"], 5);
        assert_eq!(j["num_threads"], 1);
        assert_eq!(j["file_version"], 1);
    }
}
