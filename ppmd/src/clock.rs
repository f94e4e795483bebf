//! CLOCK_MONOTONIC time in nanoseconds and absolute-deadline sleeps.

use nix::sys::time::TimeSpec;
use nix::time::{clock_nanosleep, ClockId, ClockNanosleepFlags};
pub use ppm_shared::time::{now_ns, realtime_ns};

/// Sleeps until CLOCK_MONOTONIC reaches `deadline_ns` (an absolute deadline,
/// so a late wake-up never shifts later deadlines). Resumes after signals.
pub fn sleep_until(deadline_ns: u64) {
    let ts = TimeSpec::new(
        (deadline_ns / 1_000_000_000) as _,
        (deadline_ns % 1_000_000_000) as _,
    );
    while clock_nanosleep(
        ClockId::CLOCK_MONOTONIC,
        ClockNanosleepFlags::TIMER_ABSTIME,
        &ts,
    )
    .is_err()
    {
        if now_ns() >= deadline_ns {
            return;
        }
    }
}

/// Sleeps until `spin_ns` before `deadline_ns`, then spins on the clock until
/// the deadline. Returns the time read when the deadline was reached.
pub fn wait_until(deadline_ns: u64, spin_ns: u64) -> u64 {
    let wake = deadline_ns.saturating_sub(spin_ns);
    if now_ns() < wake {
        sleep_until(wake);
    }
    loop {
        let now = now_ns();
        if now >= deadline_ns {
            return now;
        }
        std::hint::spin_loop();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn never_returns_early() {
        for spin in [0, 200_000] {
            let deadline = now_ns() + 2_000_000;
            let t = wait_until(deadline, spin);
            assert!(t >= deadline);
            assert!(now_ns() >= deadline);
        }
    }

    #[test]
    fn past_deadline_returns_at_once() {
        let t0 = now_ns();
        let t = wait_until(t0 - 1_000_000, 0);
        assert!(t >= t0);
    }
}
