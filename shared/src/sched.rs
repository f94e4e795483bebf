//! Scheduling of the calling thread, shared by ppmd's timing thread and
//! udp-ingress's receive thread: CPU pinning and SCHED_FIFO, the online CPU
//! list, and [`Shortfall`], a setting that could not be had and how to get
//! it.

use crate::config::{ConfigError, CpuChoice, KeyName};
use std::fmt;

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
    /// A shortfall of `what`: `detail` says what went wrong, `fix` how to
    /// get it (may be empty).
    pub fn new(what: &'static str, detail: String, fix: &str) -> Shortfall {
        Shortfall {
            what,
            detail,
            fix: fix.into(),
        }
    }
}

impl Shortfall {
    /// The shortfall as a degraded run (one that was allowed) logs it: what
    /// and how to fix it, without the way to run without it, which was
    /// taken.
    pub fn degraded(&self) -> impl fmt::Display + '_ {
        Degraded(self)
    }

    /// Whether a restart meets it again, so it is the configuration's
    /// (exit status 78): SCHED_FIFO or a CPU refused (the user's rights and
    /// limits, the unit's settings). Locked memory (refused under memory
    /// pressure too), `/dev/cpu_dma_latency` (whose group udev gives it at
    /// boot, maybe after ppmd started) and the timer slack may be had on a
    /// restart: exit status 1.
    pub fn is_config(&self) -> bool {
        !matches!(self.what, "mlockall" | "cpu_dma_latency" | "timer slack")
    }

    fn what_and_fix(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.what, self.detail)?;
        if !self.fix.is_empty() {
            write!(f, ". Fix: {}", self.fix)?;
        }
        Ok(())
    }
}

/// A shortfall as [`Shortfall::degraded`] shows it.
struct Degraded<'a>(&'a Shortfall);

impl fmt::Display for Degraded<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.what_and_fix(f)
    }
}

/// The shortfall as an error (a degraded run was not allowed): what, how to
/// fix it, and how to run without it.
impl fmt::Display for Shortfall {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.what_and_fix(f)?;
        write!(
            f,
            " (or set rt.allow_degraded = true / --allow-degraded to run without it)"
        )
    }
}

impl std::error::Error for Shortfall {}

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

/// The CPU `rt.cpu` names on this machine (`"last"` is the highest online one).
pub fn resolve_rt_cpu(choice: CpuChoice) -> Option<usize> {
    match choice {
        CpuChoice::None => None,
        CpuChoice::Last => Some(online_cpus().last().copied().unwrap_or(0)),
        CpuChoice::Index(i) => Some(i),
    }
}

/// Checks at start, before anything is opened, that `cpu`, which `key`
/// names (`rt.cpu`, `ingress.cpu`, or the option `--cpu`), is online on
/// this machine: a CPU it does not have is the configuration's fault (exit
/// status 78), not a passing one. (With `rt.allow_degraded` the program
/// runs unpinned instead: [`pin`] says so.)
pub fn check_online(cpu: usize, key: &KeyName) -> Result<(), ConfigError> {
    let online = online_cpus();
    if online.contains(&cpu) {
        return Ok(());
    }
    let list = online
        .iter()
        .map(|c| c.to_string())
        .collect::<Vec<_>>()
        .join(",");
    let what = format!("CPU {cpu} does not exist or is offline on this machine (online: {list})");
    Err(match key {
        KeyName::File(k) => ConfigError::Invalid {
            key: k.clone(),
            message: format!(
                "{what}: set {k} to one of them{}, or rt.allow_degraded = true to run unpinned, marked degraded",
                if k.starts_with("rt.") {
                    ", \"last\" (the highest online) or \"none\""
                } else {
                    " or \"none\""
                }
            ),
        },
        KeyName::Option(o) => ConfigError::Usage(format!(
            "{o} {cpu}: {what}: give one of them or none, or add --allow-degraded to run unpinned, marked degraded"
        )),
    })
}

/// Pins the calling thread to `cpu`; `key` is the configuration key that
/// asked for it (named in the fix).
pub fn pin(cpu: usize, key: &str) -> Result<(), Shortfall> {
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
            &format!("set {key} to one of the online CPUs"),
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

/// Gives the calling thread SCHED_FIFO `priority` (1..=99); `program` is
/// named in the fix.
pub fn set_fifo(priority: u8, program: &str) -> Result<(), Shortfall> {
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
            &format!("run as root, give the binary CAP_SYS_NICE (`setcap cap_sys_nice+ep {program}`), or raise RLIMIT_RTPRIO (systemd LimitRTPRIO=99, `ulimit -r 99`)"),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_degraded_run_is_not_told_to_allow_itself() {
        let s = Shortfall::new("SCHED_FIFO", "refused".into(), "run as root");
        let error = s.to_string();
        assert_eq!(
            error,
            "SCHED_FIFO: refused. Fix: run as root (or set rt.allow_degraded = true / --allow-degraded to run without it)"
        );
        assert_eq!(
            s.degraded().to_string(),
            "SCHED_FIFO: refused. Fix: run as root"
        );
        let bare = Shortfall::new("timer slack", "EPERM".into(), "");
        assert_eq!(bare.degraded().to_string(), "timer slack: EPERM");
    }

    #[test]
    fn cpu_lists() {
        assert_eq!(parse_cpu_list("0-3,6,8-9"), Some(vec![0, 1, 2, 3, 6, 8, 9]));
        assert_eq!(parse_cpu_list("0"), Some(vec![0]));
        assert_eq!(parse_cpu_list("x"), None);
        assert!(!online_cpus().is_empty());
    }

    #[test]
    fn rt_cpu_resolves() {
        assert_eq!(resolve_rt_cpu(CpuChoice::None), None);
        assert_eq!(resolve_rt_cpu(CpuChoice::Index(2)), Some(2));
        assert_eq!(
            resolve_rt_cpu(CpuChoice::Last),
            online_cpus().last().copied()
        );
    }

    #[test]
    fn a_cpu_this_machine_lacks_is_a_configuration_error() {
        let first = online_cpus()[0];
        check_online(first, &KeyName::File("rt.cpu".into())).unwrap();
        let e = check_online(4095, &KeyName::File("rt.cpu".into())).unwrap_err();
        assert_eq!(e.key(), Some("rt.cpu"));
        let text = e.to_string();
        assert!(
            text.starts_with("config key `rt.cpu`: CPU 4095 does not exist or is offline")
                && text.contains("\"last\"")
                && text.contains("rt.allow_degraded"),
            "{text}"
        );
        let e = check_online(4095, &KeyName::Option("--cpu")).unwrap_err();
        assert!(e.to_string().starts_with("--cpu 4095: CPU 4095"), "{e}");
    }

    #[test]
    fn missing_cpu_names_the_key() {
        let e = std::thread::spawn(|| pin(4096, "ingress.cpu").unwrap_err())
            .join()
            .unwrap();
        assert_eq!(e.what, "CPU pinning");
        let text = e.to_string();
        assert!(
            text.contains("CPU 4096") && text.contains("set ingress.cpu to one of"),
            "{text}"
        );
    }
}
