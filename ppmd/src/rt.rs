//! Real-time setup of the timing thread: SCHED_FIFO priority, CPU pinning,
//! locked memory, a prefaulted stack, 1 ns timer slack and
//! `/dev/cpu_dma_latency` held at 0, plus a report of what the kernel gives
//! (preemption model, RT throttling).
//!
//! Each step either succeeds or yields a [`Shortfall`] that says how to fix
//! it. [`RtSetup::apply`] fails on the first shortfall unless a degraded run
//! was allowed; then it records every shortfall so the statistics can say
//! the run was degraded.

use ppm_shared::config::RtSection;
pub use ppm_shared::sched::{online_cpus, parse_cpu_list, Shortfall};
use ppm_shared::sched::{pin, resolve_rt_cpu, set_fifo};
use std::fs::File;
use std::io::Write;

/// Bytes of stack touched at start so the timing loop never page-faults on it.
const PREFAULT_STACK_BYTES: usize = 256 * 1024;
/// Stack size of the timing thread (more than what is prefaulted).
pub const RT_STACK_BYTES: usize = 1024 * 1024;

/// The requested real-time settings, resolved from `[rt]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RtSetup {
    /// SCHED_FIFO priority 1..=99, or 0 for the normal scheduler.
    pub priority: u8,
    /// CPU to pin the thread to, if any.
    pub cpu: Option<usize>,
    /// Lock all memory (mlockall) and prefault the stack.
    pub mlock: bool,
    /// Hold `/dev/cpu_dma_latency` at 0.
    pub cpu_dma_latency: bool,
    /// Run on when a step fails, marking the run degraded.
    pub allow_degraded: bool,
}

impl RtSetup {
    /// Resolves `[rt]` (the `last` CPU becomes the highest online one).
    pub fn from_config(rt: &RtSection) -> RtSetup {
        RtSetup {
            priority: rt.priority,
            cpu: resolve_rt_cpu(rt.cpu),
            mlock: rt.mlock,
            cpu_dma_latency: rt.cpu_dma_latency,
            allow_degraded: rt.allow_degraded,
        }
    }

    /// Applies the settings to the calling thread (mlockall and the DMA
    /// latency request apply to the whole process). Call it on the timing
    /// thread before its loop.
    pub fn apply(&self) -> Result<RtObtained, Shortfall> {
        let mut got = RtObtained {
            kernel: KernelInfo::read(),
            ..RtObtained::default()
        };
        let mut shortfalls = Vec::new();
        // Ok(true): obtained; Ok(false): missing but a degraded run is allowed.
        let mut obtained = |r: Result<(), Shortfall>| -> Result<bool, Shortfall> {
            match r {
                Ok(()) => Ok(true),
                Err(s) if self.allow_degraded => {
                    shortfalls.push(s);
                    Ok(false)
                }
                Err(s) => Err(s),
            }
        };
        // Timer slack: a sleeping thread's wake-up may be deferred by up to
        // this much (50 us by default) to batch timers.
        obtained(nix::sys::prctl::set_timerslack(1).map_err(|e| {
            Shortfall::new("timer slack", format!("prctl(PR_SET_TIMERSLACK): {e}"), "")
        }))?;
        if let Some(cpu) = self.cpu {
            if obtained(pin(cpu, "rt.cpu"))? {
                got.cpu = Some(cpu);
            }
        }
        if self.mlock {
            got.mlocked = obtained(lock_memory())?;
        }
        if self.cpu_dma_latency {
            match hold_dma_latency() {
                Ok(f) => got.dma_latency = Some(f),
                Err(s) => {
                    obtained(Err(s))?;
                }
            }
        }
        if self.priority > 0 && obtained(set_fifo(self.priority, "ppmd"))? {
            got.priority = self.priority;
        }
        got.shortfalls = shortfalls;
        Ok(got)
    }
}

/// What the setup obtained.
#[derive(Debug, Default)]
pub struct RtObtained {
    /// SCHED_FIFO priority obtained (0: normal scheduler).
    pub priority: u8,
    /// CPU the thread is pinned to.
    pub cpu: Option<usize>,
    /// Memory locked.
    pub mlocked: bool,
    /// The open `/dev/cpu_dma_latency` (the request lasts while it is open).
    pub dma_latency: Option<File>,
    /// Settings that could not be had (a degraded run when not empty).
    pub shortfalls: Vec<Shortfall>,
    /// The kernel's real-time facts.
    pub kernel: KernelInfo,
}

impl RtObtained {
    /// True when any requested setting is missing.
    pub fn degraded(&self) -> bool {
        !self.shortfalls.is_empty()
    }

    /// One line for the start-up log.
    pub fn summary(&self) -> String {
        format!(
            "kernel {} ({}); policy {} priority {}; cpu {}; memory {}; cpu_dma_latency {}; RT throttling {}",
            self.kernel.release,
            self.kernel.preemption,
            if self.priority > 0 { "SCHED_FIFO" } else { "SCHED_OTHER" },
            self.priority,
            self.cpu.map_or("any".to_string(), |c| c.to_string()),
            if self.mlocked { "locked" } else { "not locked" },
            if self.dma_latency.is_some() { "held at 0" } else { "not held" },
            self.kernel.rt_throttling,
        )
    }
}

/// The kernel's real-time facts, for the start-up report.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct KernelInfo {
    /// `uname -r`.
    pub release: String,
    /// Preemption model: `PREEMPT_RT`, `PREEMPT_DYNAMIC`, `PREEMPT` or `none/voluntary`.
    pub preemption: String,
    /// True on a PREEMPT_RT kernel.
    pub preempt_rt: bool,
    /// RT throttling, from /proc/sys/kernel/sched_rt_runtime_us and _period_us.
    pub rt_throttling: String,
}

impl KernelInfo {
    /// Reads the facts from uname, /sys and /proc.
    pub fn read() -> KernelInfo {
        let uts = nix::sys::utsname::uname().ok();
        let release = uts
            .as_ref()
            .map(|u| u.release().to_string_lossy().into_owned())
            .unwrap_or_default();
        let version = uts
            .as_ref()
            .map(|u| u.version().to_string_lossy().into_owned())
            .unwrap_or_default();
        let realtime =
            std::fs::read_to_string("/sys/kernel/realtime").is_ok_and(|s| s.trim() == "1");
        let preemption = preemption_model(&version, realtime);
        let read = |p: &str| {
            std::fs::read_to_string(p)
                .ok()
                .and_then(|s| s.trim().parse::<i64>().ok())
        };
        let rt_throttling = describe_throttling(
            read("/proc/sys/kernel/sched_rt_runtime_us"),
            read("/proc/sys/kernel/sched_rt_period_us"),
        );
        KernelInfo {
            release,
            preempt_rt: preemption == "PREEMPT_RT",
            preemption,
            rt_throttling,
        }
    }
}

/// The preemption model from `uname -v` (and /sys/kernel/realtime).
pub fn preemption_model(version: &str, realtime: bool) -> String {
    let words: Vec<&str> = version.split_whitespace().collect();
    let m = if realtime || words.contains(&"PREEMPT_RT") {
        "PREEMPT_RT"
    } else if words.contains(&"PREEMPT_DYNAMIC") {
        "PREEMPT_DYNAMIC"
    } else if words.contains(&"PREEMPT") {
        "PREEMPT"
    } else {
        "none/voluntary"
    };
    m.to_string()
}

/// Describes RT throttling: real-time threads may use `runtime` of every
/// `period` microseconds (-1: unlimited).
pub fn describe_throttling(runtime_us: Option<i64>, period_us: Option<i64>) -> String {
    match (runtime_us, period_us) {
        (Some(-1), _) => "off (sched_rt_runtime_us = -1)".into(),
        (Some(r), Some(p)) if p > 0 => format!(
            "on: RT threads get {r} of every {p} us ({:.0}%), a spinning loop past that is stalled",
            r as f64 * 100.0 / p as f64
        ),
        _ => "unknown".into(),
    }
}

fn lock_memory() -> Result<(), Shortfall> {
    use nix::sys::mman::{mlockall, MlockAllFlags};
    mlockall(MlockAllFlags::MCL_CURRENT | MlockAllFlags::MCL_FUTURE).map_err(|e| {
        Shortfall::new(
            "mlockall",
            format!("locking memory: {e}"),
            "run as root, or raise RLIMIT_MEMLOCK (systemd LimitMEMLOCK=infinity, `ulimit -l unlimited`)",
        )
    })?;
    prefault_stack();
    Ok(())
}

/// Touches the stack so its pages are mapped (and, after mlockall, locked).
#[inline(never)]
fn prefault_stack() {
    let mut buf = [0u8; PREFAULT_STACK_BYTES];
    for i in (0..buf.len()).step_by(4096) {
        buf[i] = 1;
    }
    std::hint::black_box(&buf);
}

fn hold_dma_latency() -> Result<File, Shortfall> {
    let path = "/dev/cpu_dma_latency";
    let fix = "run as root, or give the user write access to /dev/cpu_dma_latency (udev rule)";
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .open(path)
        .map_err(|e| Shortfall::new("cpu_dma_latency", format!("opening {path}: {e}"), fix))?;
    f.write_all(&0i32.to_ne_bytes())
        .map_err(|e| Shortfall::new("cpu_dma_latency", format!("writing {path}: {e}"), fix))?;
    Ok(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn preemption_models() {
        assert_eq!(
            preemption_model("#1 SMP PREEMPT_RT Debian 6.1.0", false),
            "PREEMPT_RT"
        );
        assert_eq!(
            preemption_model("#1 SMP PREEMPT_DYNAMIC @0", false),
            "PREEMPT_DYNAMIC"
        );
        assert_eq!(preemption_model("#1 SMP PREEMPT Debian", false), "PREEMPT");
        assert_eq!(preemption_model("#1 SMP Debian", false), "none/voluntary");
        assert_eq!(preemption_model("#1 SMP", true), "PREEMPT_RT");
    }

    #[test]
    fn throttling() {
        assert!(describe_throttling(Some(950_000), Some(1_000_000)).contains("95%"));
        assert!(describe_throttling(Some(-1), Some(1_000_000)).starts_with("off"));
        assert_eq!(describe_throttling(None, None), "unknown");
    }

    #[test]
    fn missing_cpu_fails_unless_degraded_allowed() {
        let mut s = RtSetup {
            priority: 0,
            cpu: Some(4096),
            mlock: false,
            cpu_dma_latency: false,
            allow_degraded: false,
        };
        let e = std::thread::spawn({
            let s = s.clone();
            move || s.apply().map(|_| ()).unwrap_err()
        })
        .join()
        .unwrap();
        assert_eq!(e.what, "CPU pinning");
        assert!(
            e.to_string().contains("CPU 4096") && e.to_string().contains("rt.cpu"),
            "{e}"
        );
        s.allow_degraded = true;
        let got = std::thread::spawn(move || s.apply().unwrap())
            .join()
            .unwrap();
        assert!(got.degraded());
        assert_eq!(got.shortfalls[0].what, "CPU pinning");
    }
}
