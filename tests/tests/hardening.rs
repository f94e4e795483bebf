//! The systemd units' sandboxes: each unit in deploy/ scores 4.0 or lower
//! ("OK") in `systemd-analyze security`, and the real programs, traced with
//! strace through a whole pipeline (follow timing, frame and HdrHistogram
//! logs, real-time settings, signed commands, a seq file, a status query),
//! do only what their unit allows: system calls (SystemCallFilter=, groups
//! expanded by `systemd-analyze syscall-filter`), socket families
//! (RestrictAddressFamilies=), writes (ProtectSystem=strict: only the
//! unit's directories and /dev/shm), devices (DevicePolicy=closed), /proc
//! (ProcSubset=pid), abstract sockets (PrivateNetwork=), and the rules of
//! MemoryDenyWriteExecute=, RestrictRealtime=, RestrictSUIDSGID= and
//! RestrictNamespaces=.
//!
//! Needs `systemd-analyze` (package systemd) and `strace` (package strace):
//! without them the tests fail under CI (the variable CI set) and are
//! skipped otherwise.

use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use ppm_tests::{bin, Sandbox};
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::fs::File;
use std::io::ErrorKind;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
const UNITS: [&str; 3] = [
    "ppmd.service",
    "udp-ingress.service",
    "udp-ingress@.service",
];
/// The highest exposure `systemd-analyze security` calls "OK".
const MAX_EXPOSURE: f64 = 4.0;
const STARTUP: Duration = Duration::from_secs(30);
const KEY_HEX: &str = "8f2a55e0c1d94b7e3a6f0b1c2d3e4f5061728394a5b6c7d8e9f0a1b2c3d4e5f6";

/// True when `tool` runs. When it is missing: under CI (the variable CI
/// set) the test fails, naming the package to install; otherwise it says
/// it is skipped.
fn have(tool: &str, package: &str) -> bool {
    match Command::new(tool)
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
    {
        Ok(_) => true,
        Err(e) if e.kind() == ErrorKind::NotFound => {
            if std::env::var_os("CI").is_some() {
                panic!("{tool} is not installed: install the package `{package}` (apt-get install {package})");
            }
            eprintln!("skipped: {tool} not installed (package `{package}`)");
            false
        }
        Err(e) => panic!("running {tool}: {e}"),
    }
}

fn unit_path(unit: &str) -> PathBuf {
    Path::new(ROOT).join("deploy").join(unit)
}

/// The `key=value` directives of a unit file, in order.
fn directives(unit: &str) -> Vec<(String, String)> {
    ppm_tests::unit_directives(unit)
}

/// Every value of `key`, in order.
fn values<'a>(d: &'a [(String, String)], key: &str) -> Vec<&'a str> {
    d.iter()
        .filter(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
        .collect()
}

/// The last value of `key`, as systemd takes it.
fn last<'a>(d: &'a [(String, String)], key: &str) -> Option<&'a str> {
    values(d, key).last().copied()
}

fn yes(d: &[(String, String)], key: &str) -> bool {
    last(d, key).is_some_and(|v| ["yes", "true", "on", "1"].contains(&v))
}

#[test]
fn every_unit_scores_ok_in_systemd_analyze_security() {
    if !have("systemd-analyze", "systemd") {
        return;
    }
    for unit in UNITS {
        let out = Command::new("systemd-analyze")
            .args(["security", "--offline=yes", "--no-pager"])
            .arg(unit_path(unit))
            .output()
            .expect("running systemd-analyze security");
        let table = String::from_utf8_lossy(&out.stdout);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{unit}: {stderr}\n{table}");
        // A misspelt or invalid directive is ignored with a warning, and
        // the score does not show it.
        assert!(
            stderr.trim().is_empty(),
            "{unit}: systemd ignores part of it:\n{stderr}"
        );
        let score: f64 = table
            .lines()
            .find_map(|l| l.split_once("Overall exposure level for "))
            .and_then(|(_, rest)| rest.split_once(": "))
            .and_then(|(_, rest)| rest.split_whitespace().next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{unit}: no overall exposure level in\n{table}"));
        assert!(
            score <= MAX_EXPOSURE,
            "{unit}: exposure {score} is above {MAX_EXPOSURE}:\n{table}"
        );
        eprintln!("{unit}: exposure {score}");
    }
}

/// systemd's system call groups (`@name`), each with its members, some of
/// them groups.
fn syscall_groups() -> HashMap<String, Vec<String>> {
    let out = Command::new("systemd-analyze")
        .arg("syscall-filter")
        .arg("--no-pager")
        .output()
        .expect("running systemd-analyze syscall-filter");
    assert!(
        out.status.success(),
        "systemd-analyze syscall-filter failed"
    );
    let mut groups: HashMap<String, Vec<String>> = HashMap::new();
    let mut current: Option<String> = None;
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        if line.starts_with('@') {
            let name = line.trim().to_string();
            groups.entry(name.clone()).or_default();
            current = Some(name);
        } else if !line.starts_with(' ') {
            current = None;
        } else if let Some(group) = &current {
            let item = line.trim();
            if !item.is_empty() && !item.starts_with('#') {
                groups.get_mut(group).unwrap().push(item.to_string());
            }
        }
    }
    assert!(
        groups.contains_key("@system-service") && groups.contains_key("@default"),
        "systemd-analyze syscall-filter lists no @system-service"
    );
    groups
}

fn expand(groups: &HashMap<String, Vec<String>>, item: &str, into: &mut HashSet<String>) {
    if item.starts_with('@') {
        let members = groups
            .get(item)
            .unwrap_or_else(|| panic!("unknown system call group {item}"));
        for m in members {
            expand(groups, m, into);
        }
    } else {
        into.insert(item.to_string());
    }
}

/// A list directive as systemd reads it: the first assignment decides
/// whether it allows (no `~`) or denies (`~`), later ones add or remove,
/// and an empty one resets it.
#[derive(Debug, Default)]
struct ListFilter {
    /// None: no filter.
    allow_list: Option<bool>,
    set: HashSet<String>,
}

impl ListFilter {
    fn parse(
        assignments: &[&str],
        mut expand_item: impl FnMut(&str, &mut HashSet<String>),
    ) -> Self {
        let mut f = ListFilter::default();
        for a in assignments {
            if a.is_empty() {
                f = ListFilter::default();
                continue;
            }
            let (invert, list) = match a.strip_prefix('~') {
                Some(rest) => (true, rest),
                None => (false, *a),
            };
            let allow_list = *f.allow_list.get_or_insert(!invert);
            let mut items = HashSet::new();
            for item in list.split_whitespace() {
                // `name:errno` sets a name's error number.
                expand_item(item.split(':').next().unwrap(), &mut items);
            }
            if invert != allow_list {
                f.set.extend(items);
            } else {
                f.set.retain(|s| !items.contains(s));
            }
        }
        f
    }

    fn allows(&self, name: &str) -> bool {
        match self.allow_list {
            None => true,
            Some(allow_list) => self.set.contains(name) == allow_list,
        }
    }
}

fn syscall_filter(d: &[(String, String)], groups: &HashMap<String, Vec<String>>) -> ListFilter {
    let assignments = values(d, "SystemCallFilter");
    let mut f = ListFilter::parse(&assignments, |item, into| expand(groups, item, into));
    if f.allow_list == Some(true) {
        // An allow list always lets @default through.
        let mut default = HashSet::new();
        expand(groups, "@default", &mut default);
        f.set.extend(default);
    }
    f
}

fn address_families(d: &[(String, String)]) -> ListFilter {
    let assignments: Vec<&str> = values(d, "RestrictAddressFamilies")
        .into_iter()
        .map(|v| if v == "none" { "" } else { v })
        .collect();
    let none = values(d, "RestrictAddressFamilies").last() == Some(&"none");
    let mut f = ListFilter::parse(&assignments, |item, into| {
        into.insert(item.to_string());
    });
    if none {
        f.allow_list = Some(true);
        f.set.clear();
    }
    f
}

/// One program run under `strace -f`, killed when dropped.
struct Traced {
    child: Option<Child>,
    /// The strace output.
    trace: PathBuf,
    /// The program's (and strace's) stderr.
    log: PathBuf,
}

impl Traced {
    /// Starts `binary` with `args` and the environment variables `env`.
    fn start(
        sb: &Sandbox,
        binary: &str,
        args: &[&str],
        env: &[(&str, &str)],
        label: &str,
    ) -> Traced {
        let trace = sb.dir.join(format!("{label}.strace"));
        let log = sb.dir.join(format!("{label}.log"));
        let child = Command::new("strace")
            .args(["-f", "-qq", "-y", "-o"])
            .arg(&trace)
            .arg("--")
            .arg(bin(binary))
            .args(args)
            .current_dir(&sb.dir)
            .env("RUST_LOG", "info")
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(File::create(sb.dir.join(format!("{label}.out"))).unwrap())
            .stderr(File::create(&log).unwrap())
            .spawn()
            .expect("starting strace");
        Traced {
            child: Some(child),
            trace,
            log,
        }
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn wait_for_log(&mut self, needle: &str) {
        let end = Instant::now() + STARTUP;
        while !self.log_text().contains(needle) {
            let exited = self.child.as_mut().unwrap().try_wait().unwrap();
            assert!(
                exited.is_none() && Instant::now() < end,
                "`{needle}` did not appear in {} (exit {exited:?}):\n{}",
                self.log.display(),
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// The traced program's pid: the first line of the trace is its execve.
    fn program_pid(&self) -> Pid {
        let text = std::fs::read_to_string(&self.trace).unwrap_or_default();
        let pid = text
            .split_whitespace()
            .next()
            .and_then(|p| p.parse().ok())
            .unwrap_or_else(|| panic!("no pid in {}", self.trace.display()));
        Pid::from_raw(pid)
    }

    /// Sends `signal` to the program and waits for it (and strace) to exit.
    fn stop(&mut self, signal: Signal) -> ExitStatus {
        kill(self.program_pid(), signal).expect("signalling the program");
        let child = self.child.as_mut().unwrap();
        let end = Instant::now() + Duration::from_secs(20);
        loop {
            if let Some(status) = child.try_wait().unwrap() {
                self.child = None;
                return status;
            }
            assert!(
                Instant::now() < end,
                "no exit after {signal}:\n{}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Traced {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = kill(self.program_pid(), Signal::SIGKILL);
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// What one traced program did.
#[derive(Debug, Default)]
struct Usage {
    /// System call -> the first line that made it.
    syscalls: BTreeMap<String, String>,
    /// Socket families (`AF_UNIX`, ...).
    families: BTreeSet<String>,
    /// Paths written: opened for writing, created, removed, renamed, ...
    writes: BTreeSet<String>,
    /// Paths opened, for reading or writing.
    opened: BTreeSet<String>,
    /// Lines that break a rule of the unit, each with the rule.
    lines: Vec<String>,
}

/// The quoted strings among a system call's arguments (strace's escapes
/// left as they are: the paths here are plain).
fn quoted(args: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut chars = args.chars();
    while let Some(c) = chars.next() {
        if c != '"' {
            continue;
        }
        let mut s = String::new();
        while let Some(c) = chars.next() {
            match c {
                '\\' => {
                    s.push(c);
                    if let Some(n) = chars.next() {
                        s.push(n);
                    }
                }
                '"' => break,
                _ => s.push(c),
            }
        }
        out.push(s);
    }
    out
}

/// The directory strace's `-y` gives for the first argument
/// (`AT_FDCWD</dir>` or `3</dir>`), if any.
fn dirfd_path(args: &str) -> Option<PathBuf> {
    let first = args.split(", ").next()?;
    let (_, rest) = first.split_once('<')?;
    Some(PathBuf::from(rest.strip_suffix('>')?))
}

fn absolute(path: &str, dir: Option<&Path>, cwd: &Path) -> String {
    let p = Path::new(path);
    if p.is_absolute() {
        path.to_string()
    } else {
        dir.unwrap_or(cwd).join(p).display().to_string()
    }
}

/// Reads an strace output (`-f -y`).
fn usage(trace: &Path, cwd: &Path) -> Usage {
    let text = std::fs::read_to_string(trace)
        .unwrap_or_else(|e| panic!("reading {}: {e}", trace.display()));
    let mut u = Usage::default();
    for line in text.lines() {
        // `PID name(args) = result`, or `PID name(args <unfinished ...>`;
        // `<... name resumed>`, signals and exits are not calls.
        let Some((_, call)) = line.split_once(' ') else {
            continue;
        };
        let call = call.trim_start();
        let Some((name, args)) = call.split_once('(') else {
            continue;
        };
        if name.is_empty()
            || !name
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
        {
            continue;
        }
        u.syscalls
            .entry(name.to_string())
            .or_insert_with(|| line.to_string());
        let strings = quoted(args);
        let dir = dirfd_path(args);
        match name {
            "socket" | "socketpair" => {
                if let Some(family) = args.split(',').next() {
                    u.families.insert(family.trim().to_string());
                }
            }
            "open" | "openat" | "openat2" | "creat" => {
                if let Some(p) = strings.first() {
                    let dir = if name == "openat" || name == "openat2" {
                        dir.as_deref()
                    } else {
                        None
                    };
                    let p = absolute(p, dir, cwd);
                    let writing = name == "creat"
                        || ["O_WRONLY", "O_RDWR", "O_CREAT", "O_TRUNC"]
                            .iter()
                            .any(|f| args.contains(f));
                    if writing {
                        u.writes.insert(p.clone());
                    }
                    u.opened.insert(p);
                }
            }
            "mkdir" | "rmdir" | "unlink" | "rename" | "link" | "symlink" | "chmod" | "truncate"
            | "mknod" | "chown" | "lchown" => {
                // The last path is the one made or changed (symlink and
                // link: the new name; rename: both).
                let skip = usize::from(matches!(name, "link" | "symlink"));
                for p in strings.iter().skip(skip) {
                    u.writes.insert(absolute(p, None, cwd));
                }
            }
            "mkdirat" | "unlinkat" | "renameat" | "renameat2" | "linkat" | "symlinkat"
            | "fchmodat" | "mknodat" | "fchownat" | "utimensat" => {
                // Their directory arguments: strace's -y shows each.
                let dirs: Vec<Option<PathBuf>> = args
                    .split(", ")
                    .filter(|a| a.starts_with("AT_FDCWD") || a.contains('<'))
                    .filter(|a| !a.starts_with('"'))
                    .map(|a| {
                        a.split_once('<')
                            .and_then(|(_, r)| r.strip_suffix('>'))
                            .map(PathBuf::from)
                    })
                    .collect();
                let skip = usize::from(matches!(name, "linkat" | "symlinkat"));
                for (i, p) in strings.iter().enumerate().skip(skip) {
                    let d = dirs.get(i).cloned().flatten().or_else(|| dir.clone());
                    u.writes.insert(absolute(p, d.as_deref(), cwd));
                }
            }
            _ => {}
        }
        // Rules that are about arguments.
        let rule = match name {
            "mprotect" | "pkey_mprotect" if args.contains("PROT_EXEC") => {
                Some("MemoryDenyWriteExecute=yes (executable mprotect)")
            }
            "mmap" | "mmap2" if args.contains("PROT_EXEC") && args.contains("PROT_WRITE") => {
                Some("MemoryDenyWriteExecute=yes (writable and executable mapping)")
            }
            "sched_setscheduler" | "sched_setattr"
                if ["SCHED_FIFO", "SCHED_RR", "SCHED_DEADLINE"]
                    .iter()
                    .any(|p| args.contains(p)) =>
            {
                Some("RestrictRealtime=yes")
            }
            "chmod" | "fchmod" | "fchmodat" | "mknod" | "mknodat" | "open" | "openat" | "creat"
            | "mkdir" | "mkdirat"
                if args.contains("S_ISUID") || args.contains("S_ISGID") =>
            {
                Some("RestrictSUIDSGID=yes")
            }
            "clone" | "clone3" | "unshare" | "setns" if args.contains("CLONE_NEW") => {
                Some("RestrictNamespaces=yes")
            }
            "bind" | "connect" | "sendto" | "sendmsg" if args.contains("sun_path=@") => {
                Some("PrivateNetwork=yes (an abstract socket is private to it)")
            }
            _ => None,
        };
        if let Some(rule) = rule {
            u.lines.push(format!("{rule}: {line}"));
        }
    }
    assert!(
        u.syscalls.contains_key("execve"),
        "{} records no program",
        trace.display()
    );
    u
}

/// What a unit lets a program do, and the sandbox directories that stand
/// for the unit's directories.
struct Allowed<'a> {
    unit: &'a str,
    d: Vec<(String, String)>,
    syscalls: ListFilter,
    families: ListFilter,
    /// Directories it may write: /dev/shm and the stand-ins for the
    /// unit's directories (RuntimeDirectory=, ...) it has.
    writable: Vec<PathBuf>,
}

/// Devices every DevicePolicy=closed unit may open.
const CLOSED_DEVICES: [&str; 8] = [
    "/dev/null",
    "/dev/zero",
    "/dev/full",
    "/dev/random",
    "/dev/urandom",
    "/dev/tty",
    "/dev/ptmx",
    "/dev/pts/",
];

impl Allowed<'_> {
    fn new<'a>(
        unit: &'a str,
        groups: &HashMap<String, Vec<String>>,
        dirs: &[(&str, PathBuf)],
        extra: &[PathBuf],
    ) -> Allowed<'a> {
        let d = directives(unit);
        assert_eq!(
            last(&d, "ProtectSystem"),
            Some("strict"),
            "{unit}: the write check assumes ProtectSystem=strict"
        );
        let mut writable = vec![PathBuf::from("/dev/shm/")];
        // A stand-in is writable only if the unit has the directory.
        for (key, dir) in dirs {
            if last(&d, key).is_some() {
                writable.push(dir.clone());
            }
        }
        writable.extend(extra.iter().cloned());
        Allowed {
            unit,
            syscalls: syscall_filter(&d, groups),
            families: address_families(&d),
            d,
            writable,
        }
    }

    fn device_allowed(&self, path: &str) -> bool {
        if path.starts_with("/dev/shm/") {
            return true;
        }
        match last(&self.d, "DevicePolicy") {
            Some("closed") => {}
            Some("strict") => return false,
            _ => return true,
        }
        if CLOSED_DEVICES.iter().any(|dev| path.starts_with(dev)) {
            return true;
        }
        values(&self.d, "DeviceAllow").iter().any(|v| {
            let spec = v.split_whitespace().next().unwrap_or("");
            match spec.strip_prefix("char-") {
                // char-gpiochip: /dev/gpiochipN; char-spi: /dev/spidevB.C.
                Some("spi") => path.starts_with("/dev/spidev"),
                Some(group) => path.starts_with(&format!("/dev/{group}")),
                None => path == spec,
            }
        })
    }

    /// Every rule of the unit the program broke, one per line.
    fn check(&self, u: &Usage) -> Vec<String> {
        let unit = self.unit;
        let mut bad = Vec::new();
        for (name, line) in &u.syscalls {
            if !self.syscalls.allows(name) {
                bad.push(format!(
                    "{unit}: SystemCallFilter= refuses `{name}`, used: {line}"
                ));
            }
        }
        for family in &u.families {
            if !self.families.allows(family) {
                bad.push(format!("{unit}: RestrictAddressFamilies= refuses {family}"));
            }
        }
        for path in &u.writes {
            if path.starts_with("/dev/") && !path.starts_with("/dev/shm/") {
                continue; // a device: checked below
            }
            if !self.writable.iter().any(|w| Path::new(path).starts_with(w)) {
                bad.push(format!(
                    "{unit}: writes {path}, which ProtectSystem=strict makes read-only (or PrivateTmp=yes private): only {:?}",
                    self.writable
                ));
            }
        }
        for path in u.opened.iter().filter(|p| p.starts_with("/dev/")) {
            if !self.device_allowed(path) {
                bad.push(format!("{unit}: DevicePolicy=/DeviceAllow= refuse {path}"));
            }
        }
        if last(&self.d, "ProcSubset") == Some("pid") {
            for path in u.opened.iter().filter(|p| p.starts_with("/proc/")) {
                let first = path["/proc/".len()..].split('/').next().unwrap_or("");
                let per_process = first == "self"
                    || first == "thread-self"
                    || first.chars().all(|c| c.is_ascii_digit());
                if !per_process {
                    bad.push(format!("{unit}: ProcSubset=pid hides {path}"));
                }
            }
        }
        for line in &u.lines {
            let rule = line.split('=').next().unwrap_or("");
            if yes(&self.d, rule) {
                bad.push(format!("{unit}: {line}"));
            }
        }
        bad
    }
}

fn run_tool(binary: &str, args: &[&str]) -> String {
    let out = Command::new(bin(binary))
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("running {binary}: {e}"));
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{binary} {args:?}: {}\n{text}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

#[test]
fn the_programs_do_only_what_their_units_allow() {
    if !have("strace", "strace") || !have("systemd-analyze", "systemd") {
        return;
    }
    let sb = Sandbox::new("hardening");
    // The sandbox's stand-ins for the units' directories, made beforehand
    // as systemd makes them: ipc.root for /run/ppm (RuntimeDirectory=),
    // log/ for /var/log/ppm (LogsDirectory=), state/ for /var/lib/ppm
    // (StateDirectory=). sim/ holds the simulated line, which a real
    // deployment does not have.
    let (ipc, logs, state, sim) = (
        sb.dir.join("ipc"),
        sb.dir.join("log"),
        sb.dir.join("state"),
        sb.dir.join("sim"),
    );
    for d in [&ipc, &logs, &state, &sim] {
        std::fs::create_dir_all(d).unwrap();
    }
    let key = sb.dir.join("auth.key");
    std::fs::write(&key, KEY_HEX).unwrap();
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
    // The production settings: real time (which fails gracefully without
    // root), the timing thread pinned, /dev/cpu_dma_latency held; the
    // ingress pinned; follow timing, so ppmd waits on iceoryx2's sockets.
    let cfg = sb.config_with_ingress(
        &format!(
            "auth_key = \"{}\"\nseq_file = \"{}\"\ncpu = 0",
            key.display(),
            state.join("ppm.last_seq").display()
        ),
        &format!(
            "[ppm]\ntiming = \"follow\"\n[ppmd]\nframe_log = \"{}\"\n\
             [rt]\npriority = 80\nmlock = true\ncpu_dma_latency = true\nallow_degraded = true\n",
            logs.join("frames.jsonl").display()
        ),
    );
    let cfg = cfg.to_str().unwrap();
    let trace = format!("sim:{}", sim.join("line.trace").display());
    let hdr = logs.join("hdr.log");
    let hdr = hdr.to_str().unwrap();

    // ppmd's messages to systemd (Type=notify, WatchdogSec=) come here,
    // so the trace has them too.
    let notify_path = sb.dir.join("notify.sock");
    let notify = UnixDatagram::bind(&notify_path).expect("binding the notify socket");
    notify.set_nonblocking(true).unwrap();
    let mut ppmd = Traced::start(
        &sb,
        "ppmd",
        &["--config", cfg, "--output", &trace, "--hdr-log", hdr],
        &[
            ("NOTIFY_SOCKET", notify_path.to_str().unwrap()),
            ("WATCHDOG_USEC", "2000000"),
        ],
        "ppmd",
    );
    ppmd.wait_for_log("commands from");
    let mut ingress = Traced::start(&sb, "udp-ingress", &["--config", cfg], &[], "ingress");
    ingress.wait_for_log("listening on");

    let to = sb.addr().to_string();
    let key_s = key.to_str().unwrap();
    run_tool(
        "ppm-send",
        &[
            "--to",
            &to,
            "--auth-key",
            key_s,
            "--name",
            &sb.name,
            "--count",
            "75",
            "[1500, 1500, 1000, 1500]",
        ],
    );
    let status = run_tool("ppm-status", &["--to", &to]);
    // One HdrHistogram interval a second.
    std::thread::sleep(Duration::from_millis(1200));
    let reply = ppm_tests::status(sb.addr());
    // Every command came and was accepted (signed); under strace some may
    // be superseded by the next before they are handed on.
    let datagrams = &reply.datagrams;
    assert!(
        datagrams.received == 75
            && datagrams.applied > 0
            && datagrams.rejected.0.values().all(|n| *n == 0),
        "the signed commands flew: {reply}"
    );
    assert!(
        reply.ppmd.as_ref().map(|p| p.frames) > Some(0),
        "ppmd emitted frames: {reply}\n{status}"
    );

    assert!(
        ingress.stop(Signal::SIGINT).success(),
        "{}",
        ingress.log_text()
    );
    assert!(ppmd.stop(Signal::SIGTERM).success(), "{}", ppmd.log_text());
    let mut buf = [0u8; 4096];
    let mut notified = Vec::new();
    while let Ok(n) = notify.recv(&mut buf) {
        notified.push(String::from_utf8_lossy(&buf[..n]).replace('\n', " "));
    }
    eprintln!("ppmd told systemd: {notified:?}");
    let d = directives("ppmd.service");
    let told = |what: &str| notified.iter().any(|m| m.split(' ').any(|w| w == what));
    if last(&d, "Type") == Some("notify") {
        assert!(told("READY=1"), "Type=notify needs READY=1: {notified:?}");
    }
    if last(&d, "WatchdogSec").is_some() {
        assert!(
            told("WATCHDOG=1"),
            "WatchdogSec= needs WATCHDOG=1: {notified:?}"
        );
    }
    for (file, what) in [
        (logs.join("frames.jsonl"), "the frame log"),
        (logs.join("hdr.log"), "the HdrHistogram log"),
        (state.join("ppm.last_seq"), "the seq file"),
        (sim.join("line.trace"), "the line"),
    ] {
        let len = std::fs::metadata(&file).map(|m| m.len()).unwrap_or(0);
        assert!(len > 0, "{what} ({}) is empty", file.display());
    }

    let groups = syscall_groups();
    let ppmd_unit = Allowed::new(
        "ppmd.service",
        &groups,
        &[("RuntimeDirectory", ipc.clone()), ("LogsDirectory", logs)],
        &[sim],
    );
    let ppmd_usage = usage(&ppmd.trace, &sb.dir);
    let ingress_usage = usage(&ingress.trace, &sb.dir);
    let mut bad = ppmd_unit.check(&ppmd_usage);
    for unit in ["udp-ingress.service", "udp-ingress@.service"] {
        let allowed = Allowed::new(
            unit,
            &groups,
            &[
                ("RuntimeDirectory", ipc.clone()),
                ("StateDirectory", state.clone()),
            ],
            &[],
        );
        bad.extend(allowed.check(&ingress_usage));
    }
    for (program, u) in [("ppmd", &ppmd_usage), ("udp-ingress", &ingress_usage)] {
        eprintln!(
            "{program}: families {:?}\n  system calls {:?}",
            u.families,
            u.syscalls.keys().collect::<Vec<_>>()
        );
    }
    // The pipeline used what the units are tuned to.
    for (u, needed) in [
        (&ppmd_usage, &["AF_UNIX"][..]),
        (&ingress_usage, &["AF_UNIX", "AF_INET"][..]),
    ] {
        for family in needed {
            assert!(u.families.contains(*family), "{family} was not used");
        }
    }
    assert!(
        bad.is_empty(),
        "the units would stop what the programs do (traces in {}):\n{}",
        sb.dir.display(),
        bad.join("\n")
    );
}
