//! A simulated [`Clock`] for the timing loop's tests. Its time moves only
//! when the loop reads it (by [`Sim::set_read_ns`] a reading), spins (by
//! [`Sim::set_spin_ns`] a turn) or sleeps (to the deadline, plus
//! [`Sim::set_wake_late_ns`]); stalls of the loop, wake-ups of command
//! sources and the stop are scripted at set times. So a test of the loop
//! never sleeps, takes milliseconds for seconds of frames, and gets the same
//! edges on every machine. Single-threaded: the loop, its test sources and
//! outputs share one [`Sim`] (a cheap handle).

use super::{Clock, Readable};
use std::os::fd::RawFd;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::{Arc, Mutex, MutexGuard};

/// Where simulated CLOCK_MONOTONIC starts: far enough from 0 that nothing
/// in the loop saturates at 0.
pub const START_NS: u64 = 1_000_000_000_000;
/// CLOCK_REALTIME minus CLOCK_MONOTONIC in the simulation.
pub const REALTIME_OFFSET_NS: u64 = 1_700_000_000_000_000_000;
/// The first fd number [`Sim::wake_fd`] hands out.
const FIRST_FD: RawFd = 10_000;

/// A simulated clock; clones share it.
#[derive(Clone)]
pub struct Sim(Arc<Mutex<State>>);

struct State {
    now: u64,
    read_ns: u64,
    spin_ns: u64,
    wake_late_ns: u64,
    /// (from, for): the first reading at or after `from` finds the loop
    /// held up `for` ns. Sorted by `from`.
    stalls: Vec<(u64, u64)>,
    stop: Option<(u64, Arc<AtomicBool>)>,
    fds: Vec<WakeFd>,
    sleeps: u64,
    /// Sleeps in a row that ended at once, on a readable fd.
    at_once: u64,
}

/// Sleeps in a row that end at once, on a readable fd, before the
/// simulation calls it a livelock (a loop that never clears a wake-up spins
/// without time moving; the test would hang).
const LIVELOCK: u64 = 100_000;

/// A wake fd: readable from each wake-up time on until cleared.
struct WakeFd {
    wakes: Vec<u64>,
    /// Wake-ups at or before this were cleared.
    cleared_at: Option<u64>,
}

impl WakeFd {
    /// The first time at or after `t` that it is readable.
    fn ready_from(&self, t: u64) -> Option<u64> {
        self.wakes
            .iter()
            .find(|&&w| self.cleared_at.is_none_or(|c| w > c))
            .map(|&w| w.max(t))
    }
}

impl State {
    /// Moves the time to `now`; the stop comes when the time reaches it,
    /// as another thread's would.
    fn set_now(&mut self, now: u64) {
        self.now = now;
        if let Some((at, flag)) = self.stop.as_ref() {
            if now >= *at {
                flag.store(true, Relaxed);
            }
        }
    }

    fn fd_index(&self, fd: RawFd) -> Option<usize> {
        let i = usize::try_from(fd.checked_sub(FIRST_FD)?).ok()?;
        (i < self.fds.len()).then_some(i)
    }
}

impl Default for Sim {
    fn default() -> Self {
        Sim::new()
    }
}

impl Sim {
    /// A clock at [`START_NS`]: readings take 100 ns, a spin turn 100 ns,
    /// and sleeps end exactly at their deadline.
    pub fn new() -> Sim {
        Sim(Arc::new(Mutex::new(State {
            now: START_NS,
            read_ns: 100,
            spin_ns: 100,
            wake_late_ns: 0,
            stalls: Vec::new(),
            stop: None,
            fds: Vec::new(),
            sleeps: 0,
            at_once: 0,
        })))
    }

    fn state(&self) -> MutexGuard<'_, State> {
        self.0.lock().expect("the simulation")
    }

    /// The time now, without reading the clock (it does not move).
    pub fn at(&self) -> u64 {
        self.state().now
    }

    /// How long a reading takes.
    pub fn set_read_ns(&self, ns: u64) {
        self.state().read_ns = ns;
    }

    /// How long one spin turn takes.
    pub fn set_spin_ns(&self, ns: u64) {
        self.state().spin_ns = ns;
    }

    /// How late every sleep ends after its deadline (or wake-up).
    pub fn set_wake_late_ns(&self, ns: u64) {
        self.state().wake_late_ns = ns;
    }

    /// Holds the caller (the loop, inside an output's write) up for `ns`.
    pub fn advance(&self, ns: u64) {
        let mut s = self.state();
        let now = s.now + ns;
        s.set_now(now);
    }

    /// The first reading at or after `from` finds the loop held up for `ns`
    /// (as a preempted thread finds it).
    pub fn stall_at(&self, from: u64, ns: u64) {
        let mut s = self.state();
        s.stalls.push((from, ns));
        s.stalls.sort_unstable();
    }

    /// Holds the caller up for every stall due by now (as the next reading
    /// would); returns how long. A test output calls it in a write: the
    /// hold-up then comes before the edge reaches the line.
    pub fn hold_due_stalls(&self) -> u64 {
        let mut s = self.state();
        let mut held = 0;
        while let Some(&(from, ns)) = s.stalls.first() {
            if from > s.now + held {
                break;
            }
            s.stalls.remove(0);
            held += ns;
        }
        let now = s.now + held;
        s.set_now(now);
        held
    }

    /// Sets `flag` when the time reaches `at`.
    pub fn stop_at(&self, at: u64, flag: Arc<AtomicBool>) {
        self.state().stop = Some((at, flag));
    }

    /// A new wake fd, readable from each of `wakes` on until
    /// [`Sim::clear`]ed. Fd numbers it did not hand out are in error when
    /// watched (as a closed fd is).
    pub fn wake_fd(&self, mut wakes: Vec<u64>) -> RawFd {
        wakes.sort_unstable();
        let mut s = self.state();
        s.fds.push(WakeFd {
            wakes,
            cleared_at: None,
        });
        FIRST_FD + s.fds.len() as RawFd - 1
    }

    /// Clears the wake-ups of `fd` up to now.
    pub fn clear(&self, fd: RawFd) {
        let mut s = self.state();
        let now = s.now;
        if let Some(i) = s.fd_index(fd) {
            s.fds[i].cleared_at = Some(now);
        }
    }

    /// Sleeps the loop has made.
    pub fn sleeps(&self) -> u64 {
        self.state().sleeps
    }
}

impl Clock for Sim {
    fn now_ns(&self) -> u64 {
        let mut s = self.state();
        let mut now = s.now;
        while let Some(&(from, ns)) = s.stalls.first() {
            if from > now {
                break;
            }
            s.stalls.remove(0);
            now += ns;
        }
        s.set_now(now);
        let read_ns = s.read_ns;
        s.set_now(now + read_ns);
        now
    }

    fn realtime_ns(&self) -> u64 {
        self.at() + REALTIME_OFFSET_NS
    }

    fn sleep_until_or_readable(&self, deadline_ns: u64, fds: &[RawFd]) -> Readable {
        let mut got = Readable {
            readable: 0,
            broken: 0,
        };
        let mut s = self.state();
        let now = s.now;
        if now >= deadline_ns {
            return got;
        }
        s.sleeps += 1;
        for (i, &fd) in fds.iter().enumerate() {
            if s.fd_index(fd).is_none() {
                got.broken |= 1 << i;
            }
        }
        if got.any() {
            return got;
        }
        let ready =
            |s: &State, fd: RawFd, t: u64| s.fds[s.fd_index(fd).expect("known")].ready_from(t);
        let first = fds.iter().filter_map(|&fd| ready(&s, fd, now)).min();
        match first.filter(|&t| t < deadline_ns) {
            Some(t) => {
                s.at_once = if t == now { s.at_once + 1 } else { 0 };
                assert!(
                    s.at_once < LIVELOCK,
                    "livelock: {LIVELOCK} sleeps in a row ended at once on a readable fd"
                );
                let woke = if t == now { now } else { t + s.wake_late_ns };
                s.set_now(woke);
                for (i, &fd) in fds.iter().enumerate() {
                    if ready(&s, fd, woke).is_some_and(|r| r <= woke) {
                        got.readable |= 1 << i;
                    }
                }
            }
            None => {
                s.at_once = 0;
                let woke = deadline_ns + s.wake_late_ns;
                s.set_now(woke);
            }
        }
        got
    }

    fn spin(&self) {
        let mut s = self.state();
        let now = s.now + s.spin_ns;
        s.set_now(now);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::{EdgeTimer, Margin, Wake};

    #[test]
    fn readings_spins_and_sleeps_move_the_time() {
        let sim = Sim::new();
        assert_eq!(sim.now_ns(), START_NS);
        assert_eq!(sim.now_ns(), START_NS + 100, "a reading takes 100 ns");
        sim.spin();
        assert_eq!(sim.at(), START_NS + 300);
        let none = sim.sleep_until_or_readable(START_NS + 5_000, &[]);
        assert!(!none.any());
        assert_eq!(sim.at(), START_NS + 5_000);
        sim.set_wake_late_ns(700);
        sim.sleep_until_or_readable(START_NS + 6_000, &[]);
        assert_eq!(sim.at(), START_NS + 6_700);
        // A deadline passed: no sleep, no time.
        sim.sleep_until_or_readable(START_NS, &[]);
        assert_eq!(sim.at(), START_NS + 6_700);
        assert_eq!(sim.sleeps(), 2);
        assert_eq!(sim.realtime_ns(), START_NS + 6_700 + REALTIME_OFFSET_NS);
    }

    #[test]
    fn stalls_come_at_the_first_reading_after_their_time_the_stop_at_it() {
        let sim = Sim::new();
        let flag = Arc::new(AtomicBool::new(false));
        sim.stall_at(START_NS + 1_000, 50_000);
        sim.stop_at(START_NS + 40_000, flag.clone());
        sim.advance(999);
        assert_eq!(sim.now_ns(), START_NS + 999, "before the stall");
        assert!(!flag.load(Relaxed));
        assert_eq!(sim.now_ns(), START_NS + 1_099 + 50_000, "held up");
        assert!(flag.load(Relaxed), "the stall carried it past the stop");
        assert_eq!(sim.now_ns(), START_NS + 51_199, "once");
        let flag = Arc::new(AtomicBool::new(false));
        sim.stop_at(START_NS + 60_000, flag.clone());
        sim.sleep_until_or_readable(START_NS + 70_000, &[]);
        assert!(flag.load(Relaxed), "a sleep past the stop time");
    }

    #[test]
    fn wake_fds_end_sleeps_until_cleared() {
        let sim = Sim::new();
        let a = sim.wake_fd(vec![START_NS + 3_000, START_NS + 9_000]);
        let b = sim.wake_fd(vec![START_NS + 4_000]);
        let r = sim.sleep_until_or_readable(START_NS + 10_000, &[b, a]);
        assert_eq!((r.readable, r.broken), (0b10, 0));
        assert_eq!(sim.at(), START_NS + 3_000);
        // Still readable: the next sleep ends at once.
        let r = sim.sleep_until_or_readable(START_NS + 10_000, &[b, a]);
        assert_eq!(r.readable, 0b10);
        assert_eq!(sim.at(), START_NS + 3_000);
        sim.clear(a);
        let r = sim.sleep_until_or_readable(START_NS + 10_000, &[b, a]);
        assert_eq!(r.readable, 0b01);
        assert_eq!(sim.at(), START_NS + 4_000);
        sim.clear(b);
        // The deadline comes before a's next wake-up.
        let r = sim.sleep_until_or_readable(START_NS + 8_000, &[b, a]);
        assert!(!r.any());
        assert_eq!(sim.at(), START_NS + 8_000);
        // An fd it did not hand out is in error at once.
        let r = sim.sleep_until_or_readable(START_NS + 20_000, &[a, 7]);
        assert_eq!((r.readable, r.broken), (0, 0b10));
        assert_eq!(sim.at(), START_NS + 8_000);
    }

    #[test]
    #[should_panic(expected = "livelock")]
    fn a_wake_up_never_cleared_is_a_livelock() {
        let sim = Sim::new();
        let fd = sim.wake_fd(vec![START_NS]);
        loop {
            sim.sleep_until_or_readable(START_NS + 1_000, &[fd]);
        }
    }

    #[test]
    fn the_edge_timer_sleeps_then_spins_to_the_deadline() {
        let sim = Sim::new();
        sim.set_wake_late_ns(30_000);
        let mut t = EdgeTimer::new(Margin::Fixed(100_000));
        let deadline = START_NS + 1_000_000;
        let w = t.wait(&sim, deadline);
        // Slept to 100 us before it, woke 30 us late, spun the rest in
        // 100 ns turns (and readings).
        assert_eq!(w.woke_late_ns, Some(30_000));
        assert!(w.now_ns >= deadline && w.now_ns < deadline + 200, "{w:?}");
        assert_eq!(w.spun_ns, w.now_ns - (deadline - 100_000 + 30_000));
        // A wake fd ends the sleep before the spin.
        let fd = sim.wake_fd(vec![START_NS + 1_500_000]);
        match t.wait_or_readable(&sim, START_NS + 3_000_000, &[fd]) {
            Wake::Readable(r) => assert_eq!(r.readable, 1),
            Wake::Due(w) => panic!("not woken: {w:?}"),
        }
        assert_eq!(sim.at(), START_NS + 1_530_000);
    }
}
