//! Faults of the files, directories and devices the configuration names,
//! met when a program opens them at start: which ones stop it as the
//! configuration's fault, and how the message names the key.
//!
//! Both programs exit with status 78 (EX_CONFIG,
//! [`EXIT_CONFIG`](crate::daemon::EXIT_CONFIG)), on which the systemd
//! units do not restart (`RestartPreventExitStatus=78`), when the path is
//! wrong and stays wrong until someone edits the configuration or the file
//! system: it or its directory does not exist, it is the wrong kind of file
//! (a directory, a FIFO, a device), it may not be used (permissions, a
//! read-only file system, the unit's sandbox) or it holds something that
//! cannot be right. What a restart may cure exits with status 1, and
//! systemd restarts it a second later: a full disk, an I/O error, too many
//! open files, a busy device. [`path_at_fault`] tells the two apart.

use super::keys::KeyName;
use super::ConfigError;
use std::io::{self, ErrorKind};
use std::path::Path;

/// Whether `e`, met opening, creating or reading a path a key names, is
/// the path's fault (exit status 78: a restart meets it again), not a
/// passing one (exit status 1).
pub fn path_at_fault(e: &io::Error) -> bool {
    use nix::errno::Errno;
    matches!(
        e.kind(),
        ErrorKind::NotFound
            | ErrorKind::PermissionDenied
            | ErrorKind::ReadOnlyFilesystem
            | ErrorKind::IsADirectory
            | ErrorKind::NotADirectory
            | ErrorKind::AlreadyExists
            | ErrorKind::InvalidInput
            | ErrorKind::InvalidData
            | ErrorKind::InvalidFilename
    ) || e.raw_os_error().is_some_and(|n| {
        [Errno::ELOOP, Errno::ENXIO, Errno::ENODEV, Errno::ENOTTY].contains(&Errno::from_raw(n))
    })
}

/// What `e` means for `path`, in words to add after it: which directory is
/// missing, that the file system is read-only, ... (empty when `e` says
/// it all).
pub fn explain(e: &io::Error, path: &Path) -> String {
    match e.kind() {
        ErrorKind::NotFound => {
            let dir = match path.parent() {
                Some(d) if d.as_os_str().is_empty() => Path::new("."),
                Some(d) => d,
                None => return String::new(),
            };
            if dir.is_dir() {
                format!("{} does not exist", path.display())
            } else {
                format!("the directory {} does not exist", dir.display())
            }
        }
        // create_dir_all where a file is.
        ErrorKind::AlreadyExists if !path.is_dir() => {
            format!("{} is there, and is not a directory", path.display())
        }
        ErrorKind::ReadOnlyFilesystem => "the file system is read-only there; under systemd \
             (ProtectSystem=strict) only the unit's own directories are writable, others need \
             a ReadWritePaths= line"
            .into(),
        ErrorKind::PermissionDenied => {
            "the user the program runs as may not use it (its mode, owner or group), \
             or the unit's sandbox hides it"
                .into()
        }
        _ => String::new(),
    }
}

/// The error a program stops with after `e`, met `doing` something with
/// `path`, which `key` names: when the path is at fault
/// ([`path_at_fault`]), a [`ConfigError`] (exit status 78) naming the key,
/// what went wrong and `fix`; otherwise `e` after `doing` (exit status 1,
/// a restart may cure it).
pub fn path_error(
    key: &KeyName,
    doing: &str,
    path: &Path,
    e: io::Error,
    fix: &str,
) -> anyhow::Error {
    if !path_at_fault(&e) {
        return anyhow::Error::new(e).context(doing.to_string());
    }
    let why = explain(&e, path);
    let why = if why.is_empty() {
        String::new()
    } else {
        format!(" ({why})")
    };
    let message = format!("{doing}: {e}{why}: {fix}");
    anyhow::Error::new(match key {
        KeyName::File(k) => ConfigError::invalid(k.clone(), message),
        KeyName::Option(o) => ConfigError::Usage(format!("{o}: {message}")),
    })
}

/// Creates the directory `dir` that `key` names (with its parents) if it
/// is missing and checks that this user may create files in it; the error
/// is [`path_error`]'s, with `fix`.
pub fn ensure_dir(key: &KeyName, what: &str, dir: &Path, fix: &str) -> anyhow::Result<()> {
    use nix::unistd::{access, AccessFlags};
    let doing = format!("{what} {}", dir.display());
    std::fs::create_dir_all(dir).map_err(|e| path_error(key, &doing, dir, e, fix))?;
    if !dir.is_dir() {
        let e = io::Error::new(ErrorKind::NotADirectory, "it is not a directory");
        return Err(path_error(key, &doing, dir, e, fix));
    }
    access(dir, AccessFlags::W_OK | AccessFlags::X_OK)
        .map_err(|errno| path_error(key, &doing, dir, io::Error::from(errno), fix))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(e: &anyhow::Error) -> i32 {
        crate::daemon::exit_status(e, |_| false)
    }

    #[test]
    fn a_wrong_path_is_the_configurations_fault_a_full_disk_is_not() {
        for kind in [
            ErrorKind::NotFound,
            ErrorKind::PermissionDenied,
            ErrorKind::ReadOnlyFilesystem,
            ErrorKind::IsADirectory,
            ErrorKind::InvalidInput,
            ErrorKind::InvalidData,
        ] {
            assert!(path_at_fault(&io::Error::from(kind)), "{kind:?}");
        }
        for errno in [nix::errno::Errno::ENXIO, nix::errno::Errno::ELOOP] {
            assert!(path_at_fault(&io::Error::from(errno)), "{errno}");
        }
        for errno in [
            nix::errno::Errno::ENOSPC,
            nix::errno::Errno::EIO,
            nix::errno::Errno::EMFILE,
            nix::errno::Errno::EBUSY,
            nix::errno::Errno::EAGAIN,
        ] {
            assert!(!path_at_fault(&io::Error::from(errno)), "{errno}");
        }
    }

    #[test]
    fn path_errors_name_the_key_or_the_option() {
        let dir = std::env::temp_dir().join(format!("ppm-fault-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let path = dir.join("missing").join("f.jsonl");
        let e = std::fs::File::create(&path).unwrap_err();
        let key = KeyName::File("ppmd.frame_log".into());
        let err = path_error(&key, "opening the frame log", &path, e, "create it");
        assert_eq!(status(&err), crate::daemon::EXIT_CONFIG);
        assert_eq!(
            err.to_string(),
            format!(
                "config key `ppmd.frame_log`: opening the frame log: No such file or directory (os error 2) (the directory {} does not exist): create it",
                path.parent().unwrap().display()
            )
        );
        let opt = KeyName::Option("--frame-log");
        let e = io::Error::from(ErrorKind::IsADirectory);
        let err = path_error(&opt, "opening the frame log", &dir, e, "name a file");
        assert_eq!(status(&err), crate::daemon::EXIT_CONFIG);
        assert!(err.to_string().starts_with("--frame-log: opening"), "{err}");
        // A full disk: exit status 1, the cause kept whole.
        let e = io::Error::from(nix::errno::Errno::ENOSPC);
        let err = path_error(&key, "opening the frame log", &path, e, "create it");
        assert_eq!(status(&err), crate::daemon::EXIT_FAILURE);
        assert!(err.downcast_ref::<io::Error>().is_some());
    }

    #[test]
    fn a_directory_that_cannot_be_one_is_refused() {
        let dir = std::env::temp_dir().join(format!("ppm-fault-dir-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let key = KeyName::File("ipc.root".into());
        ensure_dir(&key, "the ipc root", &dir.join("a/b"), "fix").unwrap();
        assert!(dir.join("a/b").is_dir());
        let file = dir.join("file");
        std::fs::write(&file, "").unwrap();
        for bad in [file.clone(), file.join("sub")] {
            let e = ensure_dir(&key, "the ipc root", &bad, "set ipc.root").unwrap_err();
            assert_eq!(status(&e), crate::daemon::EXIT_CONFIG, "{e}");
            assert!(e.to_string().starts_with("config key `ipc.root`"), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
