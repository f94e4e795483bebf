//! An interferer for testing the timing loop on a real kernel: a thread of
//! higher SCHED_FIFO priority than ppmd's, pinned to ppmd's CPU, that holds
//! the CPU busy for a few hundred microseconds at random times, so the loop
//! is held up right before its edges as an interrupt storm or a runaway
//! real-time task would hold it up. `ppm-interfere` runs it from the command
//! line; `ppm-bench` and the real-kernel tests run that.

use std::time::Duration;

/// What to hold up, how long and how often.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plan {
    /// Each burst lasts from `burst_ns.0` to `burst_ns.1` (inclusive).
    pub burst_ns: (u64, u64),
    /// From the end of one burst to the start of the next.
    pub gap_ns: (u64, u64),
    /// Seed of the pseudo-random times (the same seed, the same bursts).
    pub seed: u64,
}

/// A small deterministic generator (xorshift64*): enough for spreading
/// bursts, with no dependency.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    /// A generator from `seed` (0 is taken as 1).
    pub fn new(seed: u64) -> Rng {
        Rng(seed.max(1))
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// A value in `lo..=hi`.
    pub fn in_range(&mut self, (lo, hi): (u64, u64)) -> u64 {
        lo + self.next_u64() % (hi - lo + 1)
    }
}

/// Starts a thread that pins itself to `cpu`, takes SCHED_FIFO `priority`
/// and runs the bursts of `plan` until `stop` is set; returns once the
/// thread has its settings (or the reason it could not have them). The
/// thread's result is the bursts it made.
pub fn spawn(
    cpu: usize,
    priority: u8,
    plan: Plan,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> Result<std::thread::JoinHandle<Vec<Burst>>, ppm_shared::sched::Shortfall> {
    let (tx, rx) = std::sync::mpsc::channel();
    let handle = std::thread::spawn(move || {
        let set = ppm_shared::sched::pin(cpu, "the interfering thread's CPU")
            .and_then(|_| ppm_shared::sched::set_fifo(priority, "ppm-interfere"));
        let ok = set.is_ok();
        let _ = tx.send(set);
        if !ok {
            return Vec::new();
        }
        run_while(&plan, |_| !stop.load(std::sync::atomic::Ordering::Relaxed))
    });
    rx.recv()
        .expect("the interfering thread says how it started")?;
    Ok(handle)
}

/// One burst: when it started (CLOCK_MONOTONIC) and how long the CPU was
/// held.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Burst {
    /// Start, ns.
    pub start_ns: u64,
    /// Length, ns.
    pub len_ns: u64,
}

/// Parses `A..B` or a single `A` (both ends inclusive) of whole numbers in
/// the unit `unit` (`us` or `ms`), given in nanoseconds.
pub fn parse_range(s: &str, unit: &str) -> Result<(u64, u64), String> {
    let scale = match unit {
        "us" => 1_000,
        "ms" => 1_000_000,
        _ => unreachable!("a unit of this module"),
    };
    let num = |t: &str| {
        t.trim()
            .parse::<u64>()
            .map_err(|_| format!("`{s}` is not a range of whole {unit} (e.g. 100..500)"))
    };
    let (lo, hi) = match s.split_once("..") {
        Some((a, b)) => (num(a)?, num(b)?),
        None => (num(s)?, num(s)?),
    };
    if lo == 0 || lo > hi {
        return Err(format!(
            "`{s}`: the range must go from at least 1 {unit} up (e.g. 100..500)"
        ));
    }
    Ok((lo * scale, hi * scale))
}

/// Runs the bursts of `plan` on the calling thread (which the caller has
/// pinned and made SCHED_FIFO) for `duration`, busy-spinning on
/// CLOCK_MONOTONIC through each burst and sleeping between them; returns
/// the bursts made.
pub fn run(plan: &Plan, duration: Duration) -> Vec<Burst> {
    let end = ppm_shared::time::now_ns() + duration.as_nanos() as u64;
    run_while(plan, |next| next < end)
}

/// [`run`] while `go_on(start of the next burst)` says so.
pub fn run_while(plan: &Plan, mut go_on: impl FnMut(u64) -> bool) -> Vec<Burst> {
    use ppm_shared::time::now_ns;
    let mut rng = Rng::new(plan.seed);
    let mut bursts = Vec::new();
    let mut next = now_ns() + rng.in_range(plan.gap_ns);
    while go_on(next) {
        ppmd::clock::sleep_until(next);
        let start = now_ns();
        let until = start + rng.in_range(plan.burst_ns);
        let mut now = start;
        while now < until {
            std::hint::spin_loop();
            now = now_ns();
        }
        bursts.push(Burst {
            start_ns: start,
            len_ns: now - start,
        });
        next = now + rng.in_range(plan.gap_ns);
    }
    bursts
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_parse_in_their_unit_and_refuse_nonsense() {
        assert_eq!(parse_range("100..500", "us"), Ok((100_000, 500_000)));
        assert_eq!(parse_range("300", "us"), Ok((300_000, 300_000)));
        assert_eq!(parse_range("5..50", "ms"), Ok((5_000_000, 50_000_000)));
        for bad in ["", "0..5", "9..3", "a..b", "1.5..2", "-1..3"] {
            let e = parse_range(bad, "us").unwrap_err();
            assert!(e.contains(&format!("`{bad}`")), "{e}");
        }
    }

    #[test]
    fn the_generator_stays_in_range_and_repeats_with_its_seed() {
        let mut a = Rng::new(7);
        let mut b = Rng::new(7);
        let xs: Vec<u64> = (0..1000).map(|_| a.in_range((100, 120))).collect();
        assert!(xs.iter().all(|x| (100..=120).contains(x)));
        assert!((100..=120).all(|v| xs.contains(&v)), "every value comes");
        let ys: Vec<u64> = (0..1000).map(|_| b.in_range((100, 120))).collect();
        assert_eq!(xs, ys);
        assert_ne!(Rng::new(8).next_u64(), Rng::new(7).next_u64());
    }

    #[test]
    fn bursts_hold_the_cpu_for_their_length_at_their_gaps() {
        let plan = Plan {
            burst_ns: (200_000, 300_000),
            gap_ns: (2_000_000, 3_000_000),
            seed: 3,
        };
        let bursts = run(&plan, Duration::from_millis(50));
        // The gaps and lengths are at least what was drawn (a busy machine
        // only makes them longer): at most 50 / 2.2 bursts, and each at
        // least 200 us.
        assert!(!bursts.is_empty() && bursts.len() <= 22, "{bursts:?}");
        for w in bursts.windows(2) {
            assert!(w[1].start_ns >= w[0].start_ns + w[0].len_ns + 2_000_000);
        }
        assert!(bursts.iter().all(|b| b.len_ns >= 200_000), "{bursts:?}");
    }
}
