//! One ppmd per output name: each output's lock file under the ipc root,
//! `<ipc.root>/ppmd-NAME.lock`, held with `flock` for as long as ppmd runs
//! and holding its pid. The kernel drops the lock when the process ends,
//! however it ends (SIGKILL, a crash), so a stale file of a dead ppmd never
//! blocks a restart: only a running ppmd holds the lock.

use anyhow::{bail, Context, Result};
use nix::errno::Errno;
use nix::fcntl::{Flock, FlockArg};
use ppm_shared::config::{fault, KeyName};
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

/// The lock file of output `name` under the ipc root.
pub fn lock_path(root: &Path, name: &str) -> PathBuf {
    root.join(format!("ppmd-{name}.lock"))
}

/// The claim on one output name; dropping it releases the name.
#[derive(Debug)]
pub struct Claim {
    _lock: Flock<File>,
}

/// What to do about an ipc root ppmd cannot use.
const IPC_ROOT_FIX: &str = "set ipc.root to a directory ppmd and udp-ingress (the same user) may create files in; under systemd /run/ppm, the units' RuntimeDirectory";

/// Claims output `name` for this process, or says which ppmd drives it.
/// An ipc root (`ipc.root`) that cannot be made or written is the
/// configuration's fault (exit status 78); another ppmd on the name is not
/// (exit status 1: restarted, this one starts once that one is gone).
pub fn claim(root: &Path, name: &str) -> Result<Claim> {
    let key = KeyName::File("ipc.root".into());
    fault::ensure_dir(&key, "the ipc root", root, IPC_ROOT_FIX)?;
    let path = lock_path(root, name);
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .mode(0o644)
        .open(&path)
        .map_err(|e| {
            fault::path_error(
                &key,
                &format!("opening the lock file {}", path.display()),
                &path,
                e,
                IPC_ROOT_FIX,
            )
        })?;
    let mut lock = match Flock::lock(file, FlockArg::LockExclusiveNonblock) {
        Ok(lock) => lock,
        Err((mut file, Errno::EWOULDBLOCK)) => {
            let mut text = String::new();
            let _ = file.read_to_string(&mut text);
            let other = match text.trim().parse::<u32>() {
                Ok(pid) => format!("ppmd pid {pid}"),
                Err(_) => "another ppmd (starting: its pid is not written yet)".into(),
            };
            bail!(
                "output `{name}` is driven by {other}, which holds {}: two ppmd on one name would drive two lines with the same commands. Stop that one first, or start this one with another --name (and its udp-ingress with the same --name)",
                path.display()
            );
        }
        Err((_, e)) => {
            return Err(e).with_context(|| format!("locking {}", path.display()));
        }
    };
    lock.set_len(0)
        .and_then(|_| lock.rewind())
        .and_then(|_| writeln!(lock, "{}", std::process::id()))
        .with_context(|| format!("writing the pid to {}", path.display()))?;
    Ok(Claim { _lock: lock })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_name_is_claimed_once_and_free_again_when_released() {
        let root = std::env::temp_dir().join(format!("ppmd-instance-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let first = claim(&root, "plane").unwrap();
        let path = lock_path(&root, "plane");
        assert_eq!(
            std::fs::read_to_string(&path).unwrap().trim(),
            std::process::id().to_string()
        );
        // A second claim (flock is per open file, so even from this process).
        let e = format!("{:#}", claim(&root, "plane").unwrap_err());
        assert_eq!(
            e,
            format!(
                "output `plane` is driven by ppmd pid {}, which holds {}: two ppmd on one name would drive two lines with the same commands. Stop that one first, or start this one with another --name (and its udp-ingress with the same --name)",
                std::process::id(),
                path.display()
            )
        );
        // Another name is free.
        let _rover = claim(&root, "rover").unwrap();
        // Released (as when the process ends): the file stays, the name is free.
        drop(first);
        assert!(path.exists());
        let _again = claim(&root, "plane").unwrap();
        std::fs::remove_dir_all(&root).unwrap();
    }
}
