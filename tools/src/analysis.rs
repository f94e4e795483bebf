//! Exact statistics of a recorded waveform: edge error and the channel
//! periods a transmitter would see, from a sim trace or captured edges.

use ppm_shared::decode::DecodedFrame;
use ppm_shared::receiver::Receiver;
use ppm_shared::trace::Trace;

/// Nearest-rank percentiles of a set of values.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Percentiles {
    /// Number of values.
    pub count: usize,
    /// Smallest.
    pub min: f64,
    /// Median.
    pub p50: f64,
    /// 90th percentile.
    pub p90: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Largest.
    pub max: f64,
}

impl Percentiles {
    /// Percentiles of `values` (sorted in place).
    pub fn of(values: &mut [f64]) -> Percentiles {
        if values.is_empty() {
            return Percentiles::default();
        }
        values.sort_by(f64::total_cmp);
        let n = values.len();
        let rank = |q: f64| values[((q * n as f64).ceil() as usize).clamp(1, n) - 1];
        Percentiles {
            count: n,
            min: values[0],
            p50: rank(0.5),
            p90: rank(0.9),
            p99: rank(0.99),
            p999: rank(0.999),
            max: values[n - 1],
        }
    }

    /// Percentiles of an HDR histogram (its precision: 3 significant digits).
    pub fn of_histogram(h: &hdrhistogram::Histogram<u64>) -> Percentiles {
        if h.is_empty() {
            return Percentiles::default();
        }
        Percentiles {
            count: h.len() as usize,
            min: h.min() as f64,
            p50: h.value_at_quantile(0.5) as f64,
            p90: h.value_at_quantile(0.9) as f64,
            p99: h.value_at_quantile(0.99) as f64,
            p999: h.value_at_quantile(0.999) as f64,
            max: h.max() as f64,
        }
    }

    /// `min A p50 B p99 C p99.9 D max E`, values divided by `scale`, 3 decimals.
    pub fn line(&self, scale: f64) -> String {
        format!(
            "min {:.3} p50 {:.3} p99 {:.3} p99.9 {:.3} max {:.3}",
            self.min / scale,
            self.p50 / scale,
            self.p99 / scale,
            self.p999 / scale,
            self.max / scale
        )
    }
}

/// What `jitter --trace` reports.
#[derive(Debug, Clone, Default)]
pub struct TraceReport {
    /// Edges in the trace.
    pub edges: usize,
    /// Edge error, actual minus scheduled, ns.
    pub edge_error_ns: Percentiles,
    /// Frames decoded from scheduled times.
    pub frames_scheduled: usize,
    /// Frames decoded from actual times.
    pub frames_actual: usize,
    /// Channel period error |actual - scheduled| of frames both decodings share, ns.
    pub period_error_ns: Percentiles,
    /// Frames at the same position whose channel count differs between the two decodings.
    pub frames_differing: usize,
    /// The receiver whose reading is counted below.
    pub receiver: Option<Receiver>,
    /// Frames that receiver hands on, by actual time.
    pub frames_read: usize,
}

/// Analyses a sim trace; counts the frames `receiver` hands on.
pub fn analyse_trace(trace: &Trace, receiver: Receiver) -> TraceReport {
    let mut errors: Vec<f64> = trace.edges.iter().map(|e| e.error_ns() as f64).collect();
    let scheduled = trace.decode(false);
    let actual = trace.decode(true);
    let (mut periods, differing) = period_errors(&scheduled, &actual);
    TraceReport {
        edges: trace.edges.len(),
        edge_error_ns: Percentiles::of(&mut errors),
        frames_scheduled: scheduled.len(),
        frames_actual: actual.len(),
        period_error_ns: Percentiles::of(&mut periods),
        frames_differing: differing,
        receiver: Some(receiver),
        frames_read: trace.decode_as(receiver, true).len(),
    }
}

/// |actual - reference| of every channel period of frames matched by start
/// time (within half a frame), and the number of matched frames whose channel
/// counts differ.
pub fn period_errors(reference: &[DecodedFrame], actual: &[DecodedFrame]) -> (Vec<f64>, usize) {
    let mut out = Vec::new();
    let mut differing = 0;
    let mut j = 0;
    for r in reference {
        while j < actual.len() && actual[j].start_ns + 5_000_000 < r.start_ns {
            j += 1;
        }
        let Some(a) = actual.get(j) else { break };
        if a.start_ns > r.start_ns + 5_000_000 {
            continue;
        }
        if a.channels_ns.len() != r.channels_ns.len() {
            differing += 1;
            continue;
        }
        out.extend(
            r.channels_ns
                .iter()
                .zip(&a.channels_ns)
                .map(|(r, a)| (*a as f64 - *r as f64).abs()),
        );
    }
    (out, differing)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank() {
        let mut v: Vec<f64> = (1..=1000).map(|i| i as f64).collect();
        let p = Percentiles::of(&mut v);
        assert_eq!(
            (p.min, p.p50, p.p99, p.p999, p.max),
            (1.0, 500.0, 990.0, 999.0, 1000.0)
        );
        let mut one = vec![7.0];
        assert_eq!(Percentiles::of(&mut one).p999, 7.0);
        assert_eq!(Percentiles::of(&mut []).count, 0);
    }
}
