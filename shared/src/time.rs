//! Clock reads in nanoseconds, as both processes stamp them.

use nix::time::{clock_gettime, ClockId};

/// CLOCK_MONOTONIC now, in nanoseconds (a vDSO read: no system call).
pub fn now_ns() -> u64 {
    read(ClockId::CLOCK_MONOTONIC)
}

/// CLOCK_REALTIME now, in nanoseconds since the Unix epoch.
pub fn realtime_ns() -> u64 {
    read(ClockId::CLOCK_REALTIME)
}

fn read(clock: ClockId) -> u64 {
    // Both clocks always exist on Linux; the read cannot fail.
    let t = clock_gettime(clock).expect("clock_gettime");
    t.tv_sec() as u64 * 1_000_000_000 + t.tv_nsec() as u64
}
