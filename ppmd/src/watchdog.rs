//! systemd's watchdog, petted only while the timing loop makes progress.
//!
//! Under `Type=notify` with `WatchdogSec=`, systemd gives ppmd
//! `WATCHDOG_USEC` and restarts it when no `WATCHDOG=1` came for that long.
//! A process that merely lives is not enough: the pets come from the main
//! thread, which checks first that the timing thread's decision counter
//! ([`Stats::decisions`](crate::emitter::Stats::decisions), at least once a
//! frame) moved since the last pet. A timing loop that hangs (a stuck
//! output write, a deadlock, a thread stopped by a debugger) stops the
//! petting, and systemd restarts ppmd.

use std::time::{Duration, Instant};

/// What [`Watchdog::tick`] asks the caller to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Send `WATCHDOG=1`.
    Pet,
    /// Nothing to send now.
    Wait,
    /// The loop made no progress for this long (said once per stall):
    /// no pet is sent, say so in the log.
    Stalled(Duration),
    /// The loop moves again after a stall; pet.
    Resumed,
}

/// The petting decision, apart from the sending (tested without systemd).
#[derive(Debug)]
pub struct Watchdog {
    timeout: Duration,
    progress: u64,
    progress_at: Instant,
    moved_since_pet: bool,
    last_pet: Option<Instant>,
    stalled: bool,
}

impl Watchdog {
    /// A watchdog systemd expects a pet from within `timeout`; it is petted
    /// every `timeout / 4` while the loop moves, and a stall is said after
    /// `timeout / 2` without progress (systemd acts at `timeout`).
    pub fn new(timeout: Duration, progress: u64, now: Instant) -> Watchdog {
        Watchdog {
            timeout,
            progress,
            progress_at: now,
            moved_since_pet: false,
            last_pet: None,
            stalled: false,
        }
    }

    /// The watchdog systemd asked for, or `None`: `WATCHDOG_USEC`, when
    /// `WATCHDOG_PID` is unset or names this process (as
    /// `sd_watchdog_enabled(3)` reads them).
    pub fn from_env(progress: u64, now: Instant) -> Option<Watchdog> {
        let var = |k| std::env::var(k).ok();
        let usec: u64 = var("WATCHDOG_USEC")?.trim().parse().ok()?;
        let ours = var("WATCHDOG_PID")
            .is_none_or(|p| p.trim().parse::<u32>().ok() == Some(std::process::id()));
        (usec > 0 && ours).then(|| Watchdog::new(Duration::from_micros(usec), progress, now))
    }

    /// systemd's timeout.
    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// Takes the loop's progress counter at `now` (called every 100 ms or
    /// so) and says whether to pet.
    pub fn tick(&mut self, progress: u64, now: Instant) -> Verdict {
        if progress != self.progress {
            self.progress = progress;
            self.progress_at = now;
            self.moved_since_pet = true;
            if std::mem::take(&mut self.stalled) {
                self.last_pet = Some(now);
                self.moved_since_pet = false;
                return Verdict::Resumed;
            }
        }
        let quiet = now.saturating_duration_since(self.progress_at);
        if !self.stalled && quiet >= self.timeout / 2 {
            self.stalled = true;
            return Verdict::Stalled(quiet);
        }
        let due = self
            .last_pet
            .is_none_or(|t| now.saturating_duration_since(t) >= self.timeout / 4);
        if due && self.moved_since_pet {
            self.last_pet = Some(now);
            self.moved_since_pet = false;
            Verdict::Pet
        } else {
            Verdict::Wait
        }
    }
}

/// ppmd's side of `Type=notify`: READY=1 at start, the watchdog petted
/// while the loop moves (stalls and recoveries said in the log), STOPPING=1
/// at the end. Without `NOTIFY_SOCKET` every message is a no-op.
#[derive(Debug)]
pub struct Systemd {
    watchdog: Option<Watchdog>,
    notify_failed: bool,
}

impl Systemd {
    /// Says READY=1 (the outputs are open and the loop runs) and takes the
    /// watchdog systemd asked for, if any.
    pub fn start(progress: u64, now: Instant) -> Systemd {
        let watchdog = Watchdog::from_env(progress, now);
        if let Some(w) = &watchdog {
            log::info!(
                "systemd watchdog: {:?}, petted while the timing loop makes progress",
                w.timeout()
            );
        }
        if let Err(e) = notify(sd_notify::NotifyState::Ready) {
            log::warn!("cannot tell systemd ppmd is ready: {e}");
        }
        Systemd {
            watchdog,
            notify_failed: false,
        }
    }

    /// Takes the loop's progress counter (every 100 ms or so) and pets the
    /// watchdog when [`Watchdog::tick`] says so.
    pub fn tick(&mut self, progress: u64, now: Instant) {
        let Some(w) = self.watchdog.as_mut() else {
            return;
        };
        let pet = match w.tick(progress, now) {
            Verdict::Pet => true,
            Verdict::Resumed => {
                log::warn!("the timing loop makes progress again: petting systemd's watchdog");
                true
            }
            Verdict::Stalled(quiet) => {
                log::error!(
                    "the timing loop has made no progress for {quiet:?}: systemd's watchdog is no longer petted and restarts ppmd {:?} after the last pet",
                    w.timeout()
                );
                false
            }
            Verdict::Wait => false,
        };
        if pet {
            match notify(sd_notify::NotifyState::Watchdog) {
                Ok(()) => self.notify_failed = false,
                Err(e) if !self.notify_failed => {
                    self.notify_failed = true;
                    log::warn!("cannot pet systemd's watchdog: {e}");
                }
                Err(_) => {}
            }
        }
    }

    /// Says STOPPING=1.
    pub fn stopping(&self) {
        let _ = notify(sd_notify::NotifyState::Stopping);
    }
}

/// Tells systemd (when `NOTIFY_SOCKET` is set) one state; failures are
/// returned for the caller to count or log, never fatal.
pub fn notify(state: sd_notify::NotifyState) -> std::io::Result<()> {
    sd_notify::notify(false, &[state])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Ticks every 100 ms with `progress(i)`; returns the verdicts.
    fn run(ticks: u64, progress: impl Fn(u64) -> u64) -> Vec<Verdict> {
        let t0 = Instant::now();
        let mut w = Watchdog::new(Duration::from_secs(2), progress(0), t0);
        (1..=ticks)
            .map(|i| w.tick(progress(i), t0 + Duration::from_millis(100 * i)))
            .collect()
    }

    fn pets(v: &[Verdict]) -> usize {
        v.iter()
            .filter(|v| matches!(v, Verdict::Pet | Verdict::Resumed))
            .count()
    }

    #[test]
    fn a_moving_loop_is_petted_every_quarter_timeout() {
        let v = run(40, |i| i * 5);
        assert_eq!(pets(&v), 8, "{v:?}");
        assert_eq!(v[0], Verdict::Pet);
        assert_eq!(&v[1..5], [Verdict::Wait; 4]);
        assert_eq!(v[5], Verdict::Pet);
    }

    #[test]
    fn a_stalled_loop_stops_the_petting_until_it_moves() {
        // Moves for 1 s, stalls for 3 s (systemd's 2 s pass), moves again.
        let v = run(60, |i| {
            if i <= 10 {
                i
            } else if i <= 40 {
                10
            } else {
                i
            }
        });
        let pets_at: Vec<usize> = v
            .iter()
            .enumerate()
            .filter(|(_, v)| matches!(v, Verdict::Pet | Verdict::Resumed))
            .map(|(i, _)| i + 1)
            .collect();
        assert_eq!(pets_at, [1, 6, 11, 41, 46, 51, 56], "{v:?}");
        // No pet between the last progress (tick 10) and tick 41: 3 s.
        assert_eq!(v[19], Verdict::Stalled(Duration::from_secs(1)));
        assert_eq!(
            v.iter()
                .filter(|v| matches!(v, Verdict::Stalled(_)))
                .count(),
            1
        );
        assert_eq!(v[40], Verdict::Resumed);
    }

    #[test]
    fn a_loop_that_never_moves_is_never_petted() {
        let v = run(50, |_| 7);
        assert_eq!(pets(&v), 0, "{v:?}");
        assert_eq!(v[9], Verdict::Stalled(Duration::from_secs(1)));
    }
}
