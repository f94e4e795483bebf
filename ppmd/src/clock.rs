//! CLOCK_MONOTONIC time in nanoseconds and absolute-deadline sleeps, and
//! the [`Clock`] the timing loop reads and waits on: [`SystemClock`] in
//! ppmd, a simulated one in the loop's tests (so they are exact and never
//! sleep).

use nix::sys::time::TimeSpec;
use nix::time::{clock_nanosleep, ClockId, ClockNanosleepFlags};
pub use ppm_shared::time::{now_ns, realtime_ns};
use std::os::fd::RawFd;

#[cfg(test)]
pub mod sim;

/// Most file descriptors one wait watches.
pub const MAX_WATCHED: usize = 8;

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

/// Sleeps until CLOCK_MONOTONIC reaches `deadline_ns`, or until one of `fds`
/// (at most [`MAX_WATCHED`]) is readable or in error. Returns those as a
/// [`Readable`] (all zero when the deadline came). Without fds it is
/// [`sleep_until`]. Never allocates.
pub fn sleep_until_or_readable(deadline_ns: u64, fds: &[RawFd]) -> Readable {
    let none = Readable {
        readable: 0,
        broken: 0,
    };
    if fds.is_empty() {
        sleep_until(deadline_ns);
        return none;
    }
    let n = fds.len().min(MAX_WATCHED);
    let mut polled = [nix::libc::pollfd {
        fd: -1,
        events: nix::libc::POLLIN,
        revents: 0,
    }; MAX_WATCHED];
    for (p, &fd) in polled.iter_mut().zip(&fds[..n]) {
        p.fd = fd;
    }
    loop {
        let now = now_ns();
        if now >= deadline_ns {
            return none;
        }
        let left = deadline_ns - now;
        let ts = nix::libc::timespec {
            tv_sec: (left / 1_000_000_000) as _,
            tv_nsec: (left % 1_000_000_000) as _,
        };
        // SAFETY: `polled` holds `n` initialised pollfd entries and outlives
        // the call; the timeout is a valid timespec; no signal mask is given.
        let r = unsafe {
            nix::libc::ppoll(
                polled.as_mut_ptr(),
                n as nix::libc::nfds_t,
                &ts,
                std::ptr::null(),
            )
        };
        if r > 0 {
            let mut got = none;
            for (i, p) in polled[..n].iter().enumerate() {
                if p.revents & nix::libc::POLLIN != 0 {
                    got.readable |= 1 << i;
                } else if p.revents != 0 {
                    got.broken |= 1 << i;
                }
            }
            return got;
        }
        // 0: the timeout (checked against the clock above); -1: EINTR.
    }
}

/// Which watched fds ended a sleep (bit `i`: `fds[i]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Readable {
    /// Readable ones.
    pub readable: u32,
    /// Ones in error (closed, hung up): they would end every sleep at once,
    /// so the caller stops watching them.
    pub broken: u32,
}

impl Readable {
    /// Whether any fd ended the sleep.
    pub fn any(&self) -> bool {
        self.readable | self.broken != 0
    }
}

/// The time and the waits the timing loop uses. [`SystemClock`] is the
/// machine's; a test gives a simulated one, whose time moves only when the
/// loop reads it, spins or sleeps, so the loop runs deterministically.
pub trait Clock {
    /// CLOCK_MONOTONIC, ns.
    fn now_ns(&self) -> u64;
    /// CLOCK_REALTIME, ns since the Unix epoch (for logs only).
    fn realtime_ns(&self) -> u64;
    /// Sleeps until `deadline_ns` or until one of `fds` is readable or in
    /// error, as [`sleep_until_or_readable`] does.
    fn sleep_until_or_readable(&self, deadline_ns: u64, fds: &[RawFd]) -> Readable;
    /// One turn of a busy wait.
    fn spin(&self) {
        std::hint::spin_loop();
    }
}

/// The machine's clocks: CLOCK_MONOTONIC and CLOCK_REALTIME, with absolute
/// sleeps on CLOCK_MONOTONIC.
#[derive(Debug, Clone, Copy, Default)]
pub struct SystemClock;

impl Clock for SystemClock {
    #[inline]
    fn now_ns(&self) -> u64 {
        now_ns()
    }
    #[inline]
    fn realtime_ns(&self) -> u64 {
        realtime_ns()
    }
    #[inline]
    fn sleep_until_or_readable(&self, deadline_ns: u64, fds: &[RawFd]) -> Readable {
        sleep_until_or_readable(deadline_ns, fds)
    }
}

/// How far before an edge the timer stops sleeping and spins.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Margin {
    /// Always this many nanoseconds.
    Fixed(u64),
    /// Follows the observed wake-up lateness, between `min_ns` and `max_ns`
    /// (starting at `max_ns` until the first sleep is observed). Keep
    /// `max_ns` below the shortest gap the loop sleeps through, or it spins
    /// without a break.
    Auto { min_ns: u64, max_ns: u64 },
}

/// Wake-ups the automatic margin looks back over (about 5 s of frames).
const WINDOW: usize = 4096;
/// Resolution of the lateness window.
const BUCKET_NS: u64 = 5_000;
/// Lateness buckets (the last one holds everything from 2 ms up).
const BUCKETS: usize = 400;
/// Wake-ups of the window the automatic margin may leave uncovered: it
/// covers the 99.5th percentile of the observed lateness, so rare spikes do
/// not keep the loop spinning (an edge after such a spike is late, and
/// counted).
const UNCOVERED: usize = WINDOW / 200;
/// Headroom the automatic margin keeps above that percentile.
const AUTO_HEADROOM_NS: u64 = 10_000;

/// The last [`WINDOW`] wake-up latenesses, as bucket counts. Fixed size:
/// observing never allocates.
#[derive(Debug, Clone)]
struct Window {
    ring: [u16; WINDOW],
    counts: [u32; BUCKETS],
    pos: usize,
    filled: usize,
}

impl Window {
    fn observe(&mut self, late_ns: u64) {
        let b = ((late_ns / BUCKET_NS) as usize).min(BUCKETS - 1);
        if self.filled == WINDOW {
            self.counts[self.ring[self.pos] as usize] -= 1;
        } else {
            self.filled += 1;
        }
        self.ring[self.pos] = b as u16;
        self.counts[b] += 1;
        self.pos = (self.pos + 1) % WINDOW;
    }

    /// Upper bound of the lateness all but [`UNCOVERED`] of the window stay under.
    fn covered_ns(&self) -> u64 {
        let allowed = self.filled * UNCOVERED / WINDOW;
        let mut above = 0;
        for b in (0..BUCKETS).rev() {
            above += self.counts[b] as usize;
            if above > allowed {
                return (b as u64 + 1) * BUCKET_NS;
            }
        }
        0
    }
}

/// What one wait measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Waited {
    /// CLOCK_MONOTONIC read when the deadline was reached (never before it).
    pub now_ns: u64,
    /// How late the sleep woke after its wake-up time, if it slept.
    pub woke_late_ns: Option<u64>,
    /// Time spent spinning.
    pub spun_ns: u64,
}

/// How a wait with watched file descriptors ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wake {
    /// The deadline was reached.
    Due(Waited),
    /// Some watched fds became readable (or broke) before the sleep ended;
    /// the wait did not spin.
    Readable(Readable),
}

/// Sleep-then-spin waits: an absolute sleep until a margin before the
/// deadline, then a spin on CLOCK_MONOTONIC. The sleep's wake-up lateness is
/// what the margin has to cover; with [`Margin::Auto`] the margin covers the
/// 99.5th percentile of the lateness of the last 4096 sleeps, plus 10 us.
#[derive(Debug, Clone)]
pub struct EdgeTimer {
    margin: Margin,
    margin_ns: u64,
    window: Option<Window>,
}

impl EdgeTimer {
    /// A timer with this margin policy.
    pub fn new(margin: Margin) -> EdgeTimer {
        let margin_ns = match margin {
            Margin::Fixed(ns) => ns,
            Margin::Auto { max_ns, .. } => max_ns,
        };
        // Inline, not boxed: the timer lives on the timing thread's stack and
        // nothing is freed when the loop ends.
        let window = matches!(margin, Margin::Auto { .. }).then_some(Window {
            ring: [0; WINDOW],
            counts: [0; BUCKETS],
            pos: 0,
            filled: 0,
        });
        EdgeTimer {
            margin,
            margin_ns,
            window,
        }
    }

    /// The current margin in nanoseconds.
    pub fn margin_ns(&self) -> u64 {
        self.margin_ns
    }

    /// Waits on `clock` until `deadline_ns`. Never returns early.
    pub fn wait<C: Clock + ?Sized>(&mut self, clock: &C, deadline_ns: u64) -> Waited {
        match self.wait_or_readable(clock, deadline_ns, &[]) {
            Wake::Due(w) => w,
            Wake::Readable(_) => unreachable!("no fds watched"),
        }
    }

    /// Waits until `deadline_ns` as [`EdgeTimer::wait`] does, but returns
    /// early, before spinning, when one of `fds` becomes readable during the
    /// sleep. The spin itself is not interrupted: it is at most the margin.
    pub fn wait_or_readable<C: Clock + ?Sized>(
        &mut self,
        clock: &C,
        deadline_ns: u64,
        fds: &[RawFd],
    ) -> Wake {
        let wake = deadline_ns.saturating_sub(self.margin_ns);
        let mut woke_late_ns = None;
        let mut spin_start = clock.now_ns();
        if spin_start < wake {
            let readable = clock.sleep_until_or_readable(wake, fds);
            if readable.any() {
                return Wake::Readable(readable);
            }
            spin_start = clock.now_ns();
            let late = spin_start - wake;
            woke_late_ns = Some(late);
            self.observe(late);
        } else if let Margin::Auto { min_ns, .. } = self.margin {
            // Waits that never sleep teach nothing about lateness; without a
            // first observation the starting (largest) margin would never
            // shrink, and a loop whose deadlines are closer than it would spin
            // forever (and meet RT throttling). Halved at each such wait, it
            // reaches the least in a few, while the first sleeps keep a
            // margin that a late wake-up does not overrun (dropped to the
            // least at once, a first sleep woken 40 us late aborted the
            // first frame).
            if self.window.as_ref().is_some_and(|w| w.filled == 0) {
                self.margin_ns = (self.margin_ns / 2).max(min_ns.max(AUTO_HEADROOM_NS));
            }
        }
        loop {
            let now = clock.now_ns();
            if now >= deadline_ns {
                return Wake::Due(Waited {
                    now_ns: now,
                    woke_late_ns,
                    spun_ns: now.saturating_sub(spin_start),
                });
            }
            clock.spin();
        }
    }

    fn observe(&mut self, late_ns: u64) {
        if let (Margin::Auto { min_ns, max_ns }, Some(w)) = (self.margin, self.window.as_mut()) {
            w.observe(late_ns);
            self.margin_ns = (w.covered_ns() + AUTO_HEADROOM_NS).clamp(min_ns, max_ns);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn never_returns_early() {
        for margin in [
            Margin::Fixed(0),
            Margin::Fixed(200_000),
            Margin::Auto {
                min_ns: 20_000,
                max_ns: 500_000,
            },
        ] {
            let mut t = EdgeTimer::new(margin);
            for _ in 0..20 {
                // Far enough past the largest margin that even a machine
                // stalled for a few ms (qemu-user in CI) still sleeps.
                let deadline = now_ns() + 10_000_000;
                let w = t.wait(&SystemClock, deadline);
                assert!(w.now_ns >= deadline);
                assert!(w.woke_late_ns.is_some(), "it slept");
            }
        }
    }

    #[test]
    fn past_deadline_returns_at_once() {
        let mut t = EdgeTimer::new(Margin::Fixed(0));
        let t0 = now_ns();
        let w = t.wait(&SystemClock, t0 - 1_000_000);
        assert!(w.now_ns >= t0);
        assert_eq!(w.woke_late_ns, None, "no sleep");
        assert!(w.spun_ns < 1_000_000);
    }

    #[test]
    fn auto_margin_follows_lateness_within_bounds() {
        let mut t = EdgeTimer::new(Margin::Auto {
            min_ns: 20_000,
            max_ns: 1_000_000,
        });
        assert_eq!(t.margin_ns(), 1_000_000, "starts at the maximum");
        t.observe(40_000);
        assert_eq!(t.margin_ns(), 45_000 + 10_000, "covers the bucket of 40 us");
        t.observe(5_000_000);
        assert_eq!(t.margin_ns(), 1_000_000, "capped");
        for _ in 0..WINDOW {
            t.observe(1_000);
        }
        assert_eq!(
            t.margin_ns(),
            20_000,
            "the spike left the window: the minimum"
        );
        // A few spikes in the window stay uncovered; more than 0.1% are covered.
        for _ in 0..UNCOVERED {
            t.observe(300_000);
        }
        assert_eq!(t.margin_ns(), 20_000);
        t.observe(300_000);
        assert_eq!(t.margin_ns(), 305_000 + 10_000);
        let mut first = EdgeTimer::new(Margin::Auto {
            min_ns: 20_000,
            max_ns: 1_000_000,
        });
        let sim = sim::Sim::new();
        let w = first.wait(&sim, sim.at() + 100_000);
        assert_eq!(w.woke_late_ns, None, "inside the starting margin: no sleep");
        assert_eq!(first.margin_ns(), 500_000, "but the margin halved");
        for _ in 0..4 {
            first.wait(&sim, sim.at() + 10_000);
        }
        assert_eq!(
            first.margin_ns(),
            31_250,
            "halved at each wait without a sleep"
        );
        first.wait(&sim, sim.at() + 10_000);
        assert_eq!(first.margin_ns(), 20_000, "down to the least");
        let mut f = EdgeTimer::new(Margin::Fixed(300_000));
        f.observe(900_000);
        assert_eq!(f.margin_ns(), 300_000);
    }
}
