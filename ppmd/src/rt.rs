//! Real-time setup of the timing thread: SCHED_FIFO priority, CPU pinning,
//! locked memory, a prefaulted stack, 1 ns timer slack and
//! `/dev/cpu_dma_latency` held at 0, plus a report of what the kernel gives
//! (preemption model, RT throttling).
//!
//! Each step either succeeds or yields a [`Shortfall`] that says how to fix
//! it. [`RtSetup::apply`] fails on the first shortfall unless a degraded run
//! was allowed; then it records every shortfall so the statistics can say
//! the run was degraded.

use ppm_shared::config::{CpuChoice, RtSection};
use std::fmt;
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
            cpu: match rt.cpu {
                CpuChoice::None => None,
                CpuChoice::Last => Some(online_cpus().last().copied().unwrap_or(0)),
                CpuChoice::Index(i) => Some(i),
            },
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
            if obtained(pin(cpu))? {
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
        if self.priority > 0 && obtained(set_fifo(self.priority))? {
            got.priority = self.priority;
        }
        got.shortfalls = shortfalls;
        Ok(got)
    }
}

/// One real-time setting that could not be had, and how to get it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Shortfall {
    /// The setting.
    pub what: &'static str,
    /// What went wrong.
    pub detail: String,
    /// How to fix it.
    pub fix: String,
}

impl Shortfall {
    fn new(what: &'static str, detail: String, fix: &str) -> Shortfall {
        Shortfall {
            what,
            detail,
            fix: fix.into(),
        }
    }
}

impl fmt::Display for Shortfall {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.what, self.detail)?;
        if !self.fix.is_empty() {
            write!(f, ". Fix: {}", self.fix)?;
        }
        write!(
            f,
            " (or set rt.allow_degraded = true / --allow-degraded to run without it)"
        )
    }
}

impl std::error::Error for Shortfall {}

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

/// The online CPUs, from sysfs (falls back to the process's affinity).
pub fn online_cpus() -> Vec<usize> {
    if let Ok(s) = std::fs::read_to_string("/sys/devices/system/cpu/online") {
        if let Some(v) = parse_cpu_list(s.trim()) {
            return v;
        }
    }
    let n = std::thread::available_parallelism().map_or(1, |n| n.get());
    (0..n).collect()
}

/// Parses a kernel CPU list such as `0-3,6,8-9`.
pub fn parse_cpu_list(s: &str) -> Option<Vec<usize>> {
    let mut out = Vec::new();
    for part in s.split(',').filter(|p| !p.is_empty()) {
        match part.split_once('-') {
            Some((a, b)) => out.extend(a.trim().parse::<usize>().ok()?..=b.trim().parse().ok()?),
            None => out.push(part.trim().parse().ok()?),
        }
    }
    Some(out)
}

fn pin(cpu: usize) -> Result<(), Shortfall> {
    use nix::sched::{sched_setaffinity, CpuSet};
    let online = online_cpus();
    let list = |v: &[usize]| {
        v.iter()
            .map(|c| c.to_string())
            .collect::<Vec<_>>()
            .join(",")
    };
    if !online.contains(&cpu) {
        return Err(Shortfall::new(
            "CPU pinning",
            format!(
                "CPU {cpu} does not exist or is offline (online: {})",
                list(&online)
            ),
            "set rt.cpu to one of the online CPUs",
        ));
    }
    let mut set = CpuSet::new();
    set.set(cpu)
        .and_then(|_| sched_setaffinity(nix::unistd::Pid::from_raw(0), &set))
        .map_err(|e| {
            Shortfall::new(
                "CPU pinning",
                format!("sched_setaffinity to CPU {cpu}: {e}"),
                "check that the CPU is not excluded by a cgroup cpuset (systemd AllowedCPUs=)",
            )
        })
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

fn set_fifo(priority: u8) -> Result<(), Shortfall> {
    use thread_priority::unix::{
        set_thread_priority_and_policy, thread_native_id, RealtimeThreadSchedulePolicy,
        ScheduleParams, ThreadSchedulePolicy,
    };
    use thread_priority::ThreadPriority;
    let p = ThreadPriority::from_posix(ScheduleParams {
        sched_priority: priority as i32,
    });
    set_thread_priority_and_policy(
        thread_native_id(),
        p,
        ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
    )
    .map_err(|e| {
        let rtprio = nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_RTPRIO)
            .map_or("unknown".to_string(), |(soft, _)| soft.to_string());
        Shortfall::new(
            "SCHED_FIFO",
            format!("priority {priority} refused ({e}; RLIMIT_RTPRIO is {rtprio})"),
            "run as root, give the binary CAP_SYS_NICE (`setcap cap_sys_nice+ep ppmd`), or raise RLIMIT_RTPRIO (systemd LimitRTPRIO=99, `ulimit -r 99`)",
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_lists() {
        assert_eq!(parse_cpu_list("0-3,6,8-9"), Some(vec![0, 1, 2, 3, 6, 8, 9]));
        assert_eq!(parse_cpu_list("0"), Some(vec![0]));
        assert_eq!(parse_cpu_list("x"), None);
        assert!(!online_cpus().is_empty());
    }

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
