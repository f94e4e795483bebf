//! Running ppm's programs as separate processes, for `ppm-bench` and the
//! whole-system tests (which re-export it): a [`Scratch`] directory and
//! port for one run, and a [`Proc`] that owns one child, knows its log,
//! reads its memory and CPU time, and kills it when dropped.

use std::fs::File;
use std::net::UdpSocket;
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus};
use std::time::{Duration, Instant};

/// A port on 127.0.0.1 that was free a moment ago.
pub fn free_udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("binding an ephemeral port")
        .port()
}

/// A fresh directory for one run (its configuration, logs, traces and
/// shared-memory root) and a free UDP port on 127.0.0.1 for its udp-ingress.
/// The directory is removed when dropped, unless the thread is panicking
/// (then it is kept for a look).
pub struct Scratch {
    /// The directory.
    pub dir: PathBuf,
    /// A UDP port on 127.0.0.1 that was free when the scratch was made.
    pub port: u16,
}

impl Scratch {
    /// The directory `name` in the system's temporary directory, emptied
    /// if it was there.
    pub fn new(name: &str) -> std::io::Result<Scratch> {
        let dir = std::env::temp_dir().join(name);
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir)?;
        Ok(Scratch {
            dir,
            port: free_udp_port(),
        })
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// A running process whose stderr goes to a log file, killed when dropped.
pub struct Proc {
    child: Option<Child>,
    /// Its stderr log.
    pub log: PathBuf,
}

impl Proc {
    /// Starts `cmd` (its arguments, environment and other streams as the
    /// caller set them) with its stderr written to `log`.
    pub fn start(mut cmd: Command, log: PathBuf) -> std::io::Result<Proc> {
        let child = cmd.stderr(File::create(&log)?).spawn()?;
        Ok(Proc {
            child: Some(child),
            log,
        })
    }

    /// Sends `signal` and waits up to `timeout` for the exit.
    ///
    /// Panics when the process was already reaped or does not exit in time.
    pub fn signal_and_wait(
        &mut self,
        signal: nix::sys::signal::Signal,
        timeout: Duration,
    ) -> ExitStatus {
        let child = self.child.as_mut().expect("process already reaped");
        let pid = nix::unistd::Pid::from_raw(child.id() as i32);
        nix::sys::signal::kill(pid, signal).expect("sending a signal");
        self.wait(timeout)
    }

    /// Waits up to `timeout` for the process to exit by itself.
    ///
    /// Panics (after killing it) when it does not, with its log.
    pub fn wait(&mut self, timeout: Duration) -> ExitStatus {
        let mut child = self.child.take().expect("process already reaped");
        let end = Instant::now() + timeout;
        loop {
            if let Some(status) = child.try_wait().expect("waiting") {
                return status;
            }
            if Instant::now() > end {
                let _ = child.kill();
                let _ = child.wait();
                panic!(
                    "process did not exit within {timeout:?}; log:\n{}",
                    self.log_text()
                );
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Asks the process to stop (SIGTERM) and waits for it, however long
    /// it takes; errors are ignored (it may have exited already).
    pub fn terminate(mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(child.id() as i32),
                nix::sys::signal::Signal::SIGTERM,
            );
            let _ = child.wait();
        }
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("process already reaped").id()
    }

    /// Its resident memory (VmRSS) in KiB, if /proc tells it.
    pub fn try_rss_kib(&self) -> Option<u64> {
        std::fs::read_to_string(format!("/proc/{}/status", self.pid()))
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("VmRSS:"))
                    .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
            })
    }

    /// Its resident memory (VmRSS) in KiB.
    ///
    /// Panics when /proc does not tell it (the process is gone).
    pub fn rss_kib(&self) -> u64 {
        self.try_rss_kib().expect("VmRSS of a running process")
    }

    /// CPU time used so far (user + system), seconds; 0 when /proc does
    /// not tell it.
    pub fn cpu_s(&self) -> f64 {
        let stat =
            std::fs::read_to_string(format!("/proc/{}/stat", self.pid())).unwrap_or_default();
        let ticks = nix::unistd::sysconf(nix::unistd::SysconfVar::CLK_TCK)
            .ok()
            .flatten()
            .unwrap_or(100) as f64;
        cpu_ticks(&stat) as f64 / ticks
    }

    /// Kills the process with SIGKILL (as a crash would).
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Its stderr so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Waits up to `timeout`, polling every 20 ms, until its log contains
    /// `needle`; false when it did not appear in time.
    pub fn log_shows(&self, needle: &str, timeout: Duration) -> bool {
        let end = Instant::now() + timeout;
        while !self.log_text().contains(needle) {
            if Instant::now() > end {
                return false;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        true
    }

    /// Waits until its log contains `needle`.
    ///
    /// Panics, with the log, when it does not appear within `timeout`.
    pub fn wait_for_log(&self, needle: &str, timeout: Duration) {
        assert!(
            self.log_shows(needle, timeout),
            "`{needle}` did not appear in {} within {timeout:?}:\n{}",
            self.log.display(),
            self.log_text()
        );
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// What a [`Pty`] read: each chunk with when it arrived (CLOCK_MONOTONIC
/// ns).
pub type Chunks = Vec<(u64, Vec<u8>)>;

/// A pseudo-terminal pair, for a program's `serial:` output: the slave's
/// path to hand it, and a thread reading the master end, which stamps every
/// chunk with CLOCK_MONOTONIC as it arrives.
pub struct Pty {
    /// The slave end's path (`/dev/pts/N`).
    pub slave: PathBuf,
    /// The master end, to write what the device at the other end sends
    /// (a flight controller's telemetry).
    master: File,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    reader: Option<std::thread::JoinHandle<Chunks>>,
}

impl Pty {
    /// Opens a pair and starts reading its master end.
    pub fn open() -> std::io::Result<Pty> {
        Pty::open_answering(|_, _| Vec::new())
    }

    /// [`Pty::open`], with a device at the master end that answers:
    /// `answer` gets every chunk read with when it arrived, and what it
    /// returns is written back at once (a module's answers after each of
    /// a handset's frames).
    pub fn open_answering(
        mut answer: impl FnMut(u64, &[u8]) -> Vec<u8> + Send + 'static,
    ) -> std::io::Result<Pty> {
        use nix::libc;
        use std::io::{Read, Write};
        use std::os::fd::{AsRawFd, FromRawFd};
        use std::sync::atomic::Ordering;
        // SAFETY: plain libc calls on a descriptor this function owns; the
        // name buffer outlives ptsname_r, which NUL-terminates within it.
        let (mut master, slave) = unsafe {
            let fd = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC);
            if fd < 0 {
                return Err(std::io::Error::last_os_error());
            }
            let master = File::from_raw_fd(fd);
            if libc::grantpt(fd) != 0 || libc::unlockpt(fd) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            let mut name = [0 as libc::c_char; 128];
            if libc::ptsname_r(fd, name.as_mut_ptr(), name.len()) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            let path = std::ffi::CStr::from_ptr(name.as_ptr());
            (master, PathBuf::from(path.to_string_lossy().into_owned()))
        };
        let writer = master.try_clone()?;
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let stopping = stop.clone();
        let reader = std::thread::spawn(move || {
            let mut got = Vec::new();
            let mut buf = [0u8; 4096];
            while !stopping.load(Ordering::Relaxed) {
                let mut pfd = libc::pollfd {
                    fd: master.as_raw_fd(),
                    events: libc::POLLIN,
                    revents: 0,
                };
                // SAFETY: one live pollfd for the whole call.
                let ready = unsafe { libc::poll(&mut pfd, 1, 50) };
                if ready == 1 {
                    match master.read(&mut buf) {
                        Ok(n) if n > 0 => {
                            let now = ppm_shared::time::now_ns();
                            let reply = answer(now, &buf[..n]);
                            if !reply.is_empty() {
                                let _ = master.write_all(&reply);
                            }
                            got.push((now, buf[..n].to_vec()));
                        }
                        // No slave open (EIO) yet or any more: wait.
                        _ => std::thread::sleep(Duration::from_millis(5)),
                    }
                }
            }
            got
        });
        Ok(Pty {
            slave,
            master: writer,
            stop,
            reader: Some(reader),
        })
    }

    /// Writes `bytes` to the master end: the program at the slave end
    /// reads them, as from the device's TX line.
    pub fn send(&self, bytes: &[u8]) -> std::io::Result<()> {
        use std::io::Write;
        (&self.master).write_all(bytes)
    }

    /// Stops reading; every chunk read, with when it arrived.
    pub fn finish(mut self) -> Chunks {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        self.reader
            .take()
            .map(|r| r.join().expect("the pty reader"))
            .unwrap_or_default()
    }
}

impl Drop for Pty {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// User plus system time in a `/proc/PID/stat` line, in clock ticks:
/// fields 14 and 15, counted by position after the command name's closing
/// parenthesis (the fields before them hold non-numbers, such as the state,
/// and -1, such as `tpgid` without a terminal); 0 when the line says none.
pub fn cpu_ticks(stat: &str) -> u64 {
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    // After the ')': state is field 3, so utime (14) and stime (15) are 11 and 12.
    let field = |i: usize| f.get(i).and_then(|x| x.parse::<u64>().ok()).unwrap_or(0);
    field(11) + field(12)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_is_read_by_field_position() {
        // A process without a terminal (tpgid -1), a name with spaces and
        // a parenthesis: utime 2100, stime 35.
        let stat = "4242 (ppmd (x) y) S 1 4242 4242 0 -1 4194560 100 0 0 0 2100 35 7 8 20 0 3 0";
        assert_eq!(cpu_ticks(stat), 2135);
        assert_eq!(cpu_ticks(""), 0);
    }

    #[test]
    fn a_scratch_is_fresh_and_removed_after() {
        let name = format!("ppm-harness-scratch-{}", std::process::id());
        let first = Scratch::new(&name).unwrap();
        std::fs::write(first.dir.join("left.txt"), "x").unwrap();
        std::mem::forget(first);
        let s = Scratch::new(&name).unwrap();
        assert!(!s.dir.join("left.txt").exists(), "emptied");
        assert!(
            UdpSocket::bind(("127.0.0.1", s.port)).is_ok(),
            "a free port"
        );
        let dir = s.dir.clone();
        drop(s);
        assert!(!dir.exists());
    }

    #[test]
    fn a_process_is_watched_through_its_log_and_proc() {
        let scratch = Scratch::new(&format!("ppm-harness-{}", std::process::id())).unwrap();
        let dir = &scratch.dir;
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo ready >&2; exec sleep 30"]);
        let p = Proc::start(cmd, dir.join("sh.log")).unwrap();
        assert!(
            p.log_shows("ready", Duration::from_secs(10)),
            "{}",
            p.log_text()
        );
        assert!(!p.log_shows("never", Duration::from_millis(50)));
        assert!(p.rss_kib() > 0);
        assert!(p.cpu_s() >= 0.0);
        let pid = p.pid();
        p.terminate();
        // Reaped: the pid names no process (not even a zombie) any more.
        let gone = nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid as i32), None);
        assert_eq!(gone, Err(nix::errno::Errno::ESRCH));
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "exit 3"]);
        let mut p = Proc::start(cmd, dir.join("exit.log")).unwrap();
        assert_eq!(p.wait(Duration::from_secs(10)).code(), Some(3));
    }
}
