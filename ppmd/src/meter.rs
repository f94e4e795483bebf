//! Timing measurement inside the loop without disturbing it.
//!
//! The timing thread records into HDR histograms of a preallocated
//! [`Interval`]. Once per interval (at a frame's end, in the slack before the
//! next frame) it hands the full interval to the reader through a lock-free
//! ring and takes an empty one back from a second ring: no allocation, no
//! lock, no system call. The reader (a normal thread) merges, logs and
//! publishes, resets the interval and returns it.

use hdrhistogram::Histogram;

/// Highest value the histograms hold, ns (larger values are recorded as this).
pub const HIST_MAX_NS: u64 = 10_000_000_000;
/// Significant decimal digits of the histograms.
const SIGFIG: u8 = 3;
/// Intervals in circulation: one being filled, one being read, spares.
const POOL: usize = 4;

/// New empty histogram with the meter's range.
pub fn histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, HIST_MAX_NS, SIGFIG).expect("valid histogram bounds")
}

/// Measurements of one interval, in nanoseconds.
#[derive(Debug, Clone)]
pub struct Interval {
    /// CLOCK_MONOTONIC start of the interval.
    pub start_ns: u64,
    /// CLOCK_MONOTONIC end of the interval.
    pub end_ns: u64,
    /// Edge error: time read just before the write minus scheduled time.
    pub edge_error: Histogram<u64>,
    /// Duration of the output write.
    pub write: Histogram<u64>,
    /// Wake-up lateness of the sleep before each edge.
    pub wake_late: Histogram<u64>,
    /// Time spent spinning, per frame.
    pub frame_spin: Histogram<u64>,
    /// Per aborted frame: how late the edge that aborted it was found.
    pub aborted: Histogram<u64>,
    /// Per glitched frame: how late its latest timed edge reached the line.
    pub glitched: Histogram<u64>,
    /// Total spin time in the interval.
    pub spin_total_ns: u64,
}

impl Interval {
    fn new() -> Interval {
        Interval {
            start_ns: 0,
            end_ns: 0,
            edge_error: histogram(),
            write: histogram(),
            wake_late: histogram(),
            frame_spin: histogram(),
            aborted: histogram(),
            glitched: histogram(),
            spin_total_ns: 0,
        }
    }

    fn reset(&mut self) {
        self.edge_error.reset();
        self.write.reset();
        self.wake_late.reset();
        self.frame_spin.reset();
        self.aborted.reset();
        self.glitched.reset();
        self.spin_total_ns = 0;
    }
}

/// The timing thread's side.
pub struct Meter {
    current: Box<Interval>,
    full: rtrb::Producer<Box<Interval>>,
    empty: rtrb::Consumer<Box<Interval>>,
    every_ns: u64,
    /// Intervals extended because the reader had no empty one to give back.
    pub missed_handoffs: u64,
}

/// The reader's side.
pub struct MeterReader {
    full: rtrb::Consumer<Box<Interval>>,
    empty: rtrb::Producer<Box<Interval>>,
}

/// A meter handing over an interval about every `every_ns`, and its reader.
pub fn meter(every_ns: u64) -> (Meter, MeterReader) {
    let (full_tx, full_rx) = rtrb::RingBuffer::new(POOL);
    let (mut empty_tx, empty_rx) = rtrb::RingBuffer::new(POOL);
    for _ in 1..POOL {
        empty_tx
            .push(Box::new(Interval::new()))
            .expect("pool fits the ring");
    }
    (
        Meter {
            current: Box::new(Interval::new()),
            full: full_tx,
            empty: empty_rx,
            every_ns,
            missed_handoffs: 0,
        },
        MeterReader {
            full: full_rx,
            empty: empty_tx,
        },
    )
}

impl Meter {
    /// Starts the first interval at `now_ns`.
    pub fn start(&mut self, now_ns: u64) {
        self.current.start_ns = now_ns;
    }

    /// The interval being filled (for a caller that reads it in place, such
    /// as the benchmark, instead of through a [`MeterReader`]).
    pub fn current(&self) -> &Interval {
        &self.current
    }

    /// Records one edge's error and write duration.
    #[inline]
    pub fn edge(&mut self, error_ns: u64, write_ns: u64) {
        self.current.edge_error.saturating_record(error_ns);
        self.current.write.saturating_record(write_ns);
    }

    /// Records one aborted frame: how late its edge was found.
    #[inline]
    pub fn aborted(&mut self, late_ns: u64) {
        self.current.aborted.saturating_record(late_ns);
    }

    /// Records one glitched frame: how late its latest timed edge was.
    #[inline]
    pub fn glitched(&mut self, late_ns: u64) {
        self.current.glitched.saturating_record(late_ns);
    }

    /// Records one sleep's wake-up lateness.
    #[inline]
    pub fn wake(&mut self, late_ns: u64) {
        self.current.wake_late.saturating_record(late_ns);
    }

    /// Records one frame's spin time.
    #[inline]
    pub fn frame(&mut self, spin_ns: u64) {
        self.current.frame_spin.saturating_record(spin_ns);
        self.current.spin_total_ns += spin_ns;
    }

    /// Hands the interval over when it is due (call between frames).
    pub fn maybe_hand_over(&mut self, now_ns: u64) {
        if now_ns < self.current.start_ns.saturating_add(self.every_ns) {
            return;
        }
        self.hand_over(now_ns);
    }

    /// Hands the interval over now, due or not: when the loop ends, so the
    /// reader gets what was measured since the last hand-over.
    pub fn hand_over(&mut self, now_ns: u64) {
        match self.empty.pop() {
            Ok(mut next) => {
                next.start_ns = now_ns;
                std::mem::swap(&mut self.current, &mut next);
                next.end_ns = now_ns;
                // The ring holds POOL boxes and POOL boxes exist: never full.
                let _ = self.full.push(next);
            }
            Err(_) => self.missed_handoffs += 1,
        }
    }
}

impl MeterReader {
    /// Calls `f` with every interval handed over since the last call, then
    /// resets and returns it to the meter.
    pub fn drain(&mut self, mut f: impl FnMut(&Interval)) {
        while let Ok(mut iv) = self.full.pop() {
            f(&iv);
            iv.reset();
            let _ = self.empty.push(iv);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_last_interval_is_handed_over_when_the_loop_ends() {
        let (mut m, mut r) = meter(1_000);
        m.start(0);
        m.aborted(5_000);
        m.maybe_hand_over(999);
        m.hand_over(999);
        let mut aborted = vec![];
        r.drain(|iv| aborted.push((iv.start_ns, iv.end_ns, iv.aborted.len())));
        assert_eq!(aborted, [(0, 999, 1)]);
    }

    #[test]
    fn intervals_circulate() {
        let (mut m, mut r) = meter(1_000);
        m.start(0);
        m.edge(500, 40);
        m.frame(100);
        m.maybe_hand_over(999);
        let mut n = 0;
        r.drain(|_| n += 1);
        assert_eq!(n, 0, "not due yet");
        let mut seen = vec![];
        m.maybe_hand_over(1_000);
        m.edge(700, 40);
        m.maybe_hand_over(2_000);
        r.drain(|iv| {
            seen.push((
                iv.start_ns,
                iv.end_ns,
                iv.edge_error.max(),
                iv.spin_total_ns,
            ))
        });
        assert_eq!(seen, [(0, 1_000, 500, 100), (1_000, 2_000, 700, 0)]);
        // Many more rounds: the pool never runs dry when the reader keeps up.
        for k in 3..1000 {
            m.edge(k, 1);
            m.maybe_hand_over(k * 1_000);
            r.drain(|_| {});
        }
        assert_eq!(m.missed_handoffs, 0);
    }

    #[test]
    fn a_slow_reader_extends_the_interval() {
        let (mut m, mut r) = meter(1);
        m.start(0);
        for k in 1..=10 {
            m.edge(k, 1);
            m.maybe_hand_over(k);
        }
        assert_eq!(m.missed_handoffs, 10 - (POOL as u64 - 1));
        let mut total = 0;
        r.drain(|iv| total += iv.edge_error.len());
        assert_eq!(total, POOL as u64 - 1);
    }
}
