//! The last accepted signed `seq` (and, with MAVLink signing, the newest
//! signing timestamp accepted), kept in a small file so that a restarted
//! udp-ingress still refuses replays of commands accepted before.
//!
//! The file holds one decimal number and a newline. It is rewritten in place
//! at most once per interval while new commands arrive, and at exit (then
//! also flushed to the disk). A crash (SIGKILL, a panic) loses at most the
//! `seq`s accepted in the last interval: a datagram from that window, replayed
//! after the restart, would be accepted once. The written number survives the
//! crash of the process but, until the kernel writes it back (seconds), not a
//! power loss. A file on a tmpfs (`/run`, `/tmp`) is gone after a reboot.

use anyhow::Result;
use ppm_shared::config::{fault, ConfigError, KeyName};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Width of the written number; every write has the same length, so an
/// in-place rewrite never leaves a tail of an older, longer one.
const WIDTH: usize = 20;

/// What a state file keeps, for its messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Kind {
    /// Its name ("seq file").
    pub what: &'static str,
    /// The key that sets it.
    pub key: &'static str,
    /// The number it holds.
    pub number: &'static str,
    /// Where to put it instead, when it cannot be had where it is.
    pub fix: &'static str,
}

/// The last accepted signed `seq` (`ingress.seq_file`).
pub const SEQ: Kind = Kind {
    what: "seq file",
    key: "ingress.seq_file",
    number: "the last accepted seq",
    fix: "set ingress.seq_file to a regular file udp-ingress may create and rewrite, in a directory it may write (under systemd /var/lib/ppm/NAME.last_seq: the unit's StateDirectory, which also survives a reboot)",
};

/// The newest MAVLink signing timestamp accepted (`mavlink.timestamp_file`).
pub const MAVLINK_TIMESTAMP: Kind = Kind {
    what: "MAVLink timestamp file",
    key: "mavlink.timestamp_file",
    number: "the newest signing timestamp accepted",
    fix: "set mavlink.timestamp_file to a regular file udp-ingress may create and rewrite, in a directory it may write (under systemd /var/lib/ppm/NAME.mavlink_timestamp: the unit's StateDirectory, which also survives a reboot)",
};

/// The state file, open for the life of the ingress.
#[derive(Debug)]
pub struct SeqFile {
    kind: Kind,
    path: PathBuf,
    file: File,
    every: Duration,
    written: Option<u64>,
    last_write: Option<Instant>,
    sized: bool,
}

impl SeqFile {
    /// Opens (or creates, mode 600, with its directory) the seq file;
    /// returns it with the `seq` it holds (`None` when new or empty). A file
    /// holding anything but a number is refused: a wrong floor would let
    /// replays in.
    pub fn open(path: &Path, every: Duration) -> Result<(SeqFile, Option<u64>)> {
        SeqFile::open_as(SEQ, path, every)
    }

    /// [`SeqFile::open`] for a file of `kind`, named in messages by its
    /// key.
    pub fn open_as(kind: Kind, path: &Path, every: Duration) -> Result<(SeqFile, Option<u64>)> {
        SeqFile::open_named(kind, &KeyName::File(kind.key.into()), path, every)
    }

    /// [`SeqFile::open_as`], the key named `key` in messages (as the
    /// file wrote it: `outputs[1].ingress.seq_file`). What stays wrong
    /// until someone fixes the path or the file (a missing or unwritable
    /// directory, a FIFO, a directory, a device, a file far too large, or
    /// one holding anything but a number) is the configuration's fault,
    /// exit status 78 ([`fault::path_error`]); a full disk or an I/O
    /// error is not.
    pub fn open_named(
        kind: Kind,
        key: &KeyName,
        path: &Path,
        every: Duration,
    ) -> Result<(SeqFile, Option<u64>)> {
        let what = kind.what;
        use std::os::unix::fs::OpenOptionsExt;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| {
                let doing = format!("creating {} for the {what}", dir.display());
                fault::path_error(key, &doing, dir, e, kind.fix)
            })?;
        }
        let max = ppm_shared::files::SEQ_MAX_BYTES;
        let file = ppm_shared::files::open_regular(
            std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .mode(0o600),
            path,
            max,
        )
        .map_err(|e| {
            let doing = format!(
                "opening the {what} {} for reading and writing",
                path.display()
            );
            fault::path_error(key, &doing, path, e, kind.fix)
        })?;
        let text = ppm_shared::files::read_bounded(&file, max).map_err(|e| {
            let doing = format!("reading the {what} {}", path.display());
            fault::path_error(key, &doing, path, e, kind.fix)
        })?;
        let t = text.trim();
        let floor = if t.is_empty() {
            None
        } else {
            match t.parse::<u64>() {
                Ok(n) => Some(n),
                Err(_) => {
                    let message = format!(
                        "the {what} {} holds `{}`, not {}: fix it, or delete it if no signed datagram recorded so far can be replayed",
                        path.display(),
                        t.chars().take(40).collect::<String>(),
                        kind.number
                    );
                    return Err(match key {
                        KeyName::File(k) => ConfigError::Invalid {
                            key: k.clone(),
                            message,
                        },
                        KeyName::Option(o) => ConfigError::Usage(format!("{o}: {message}")),
                    }
                    .into());
                }
            }
        };
        let sized = text.len() == WIDTH + 1;
        Ok((
            SeqFile {
                kind,
                path: path.to_owned(),
                file,
                every,
                written: floor,
                last_write: None,
                sized,
            },
            floor,
        ))
    }

    /// Its path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What it keeps.
    pub fn kind(&self) -> Kind {
        self.kind
    }

    /// Writes `seq` if it changed and the last write is at least the
    /// interval old (call it on every wake-up). True when it wrote.
    pub fn note(&mut self, seq: Option<u64>, now: Instant) -> std::io::Result<bool> {
        let due = self
            .last_write
            .is_none_or(|t| now.duration_since(t) >= self.every);
        match seq {
            Some(s) if due && self.written != Some(s) => {
                self.write(s)?;
                self.last_write = Some(now);
                Ok(true)
            }
            _ => Ok(false),
        }
    }

    /// Writes `seq` if it changed and flushes the file to the disk (at exit).
    pub fn flush(&mut self, seq: Option<u64>) -> std::io::Result<()> {
        if let Some(s) = seq.filter(|s| self.written != Some(*s)) {
            self.write(s)?;
        }
        self.file.sync_data()
    }

    fn write(&mut self, seq: u64) -> std::io::Result<()> {
        self.file
            .write_all_at(format!("{seq:0WIDTH$}\n").as_bytes(), 0)?;
        if !self.sized {
            self.file.set_len(WIDTH as u64 + 1)?;
            self.sized = true;
        }
        self.written = Some(seq);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(label: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("ppm-seqfile-{label}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn keeps_the_last_seq_across_opens() {
        let d = dir("keep");
        let path = d.join("sub/ppm.last_seq");
        let every = Duration::from_millis(100);
        let (mut f, floor) = SeqFile::open(&path, every).unwrap();
        assert_eq!(floor, None);
        let t = Instant::now();
        assert!(f.note(Some(5), t).unwrap());
        assert!(
            !f.note(Some(6), t + Duration::from_millis(50)).unwrap(),
            "too soon"
        );
        assert!(!f.note(None, t + Duration::from_millis(150)).unwrap());
        assert!(f.note(Some(6), t + Duration::from_millis(150)).unwrap());
        assert!(
            !f.note(Some(6), t + Duration::from_millis(300)).unwrap(),
            "unchanged"
        );
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "00000000000000000006\n"
        );
        f.note(Some(7), t + Duration::from_millis(160)).unwrap();
        f.flush(Some(u64::MAX)).unwrap();
        drop(f);
        let (_, floor) = SeqFile::open(&path, every).unwrap();
        assert_eq!(floor, Some(u64::MAX));
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&path).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600);

        // Written by hand, shorter: read, and rewritten at full width.
        std::fs::write(&path, " 42\n").unwrap();
        let (mut f, floor) = SeqFile::open(&path, every).unwrap();
        assert_eq!(floor, Some(42));
        f.flush(Some(43)).unwrap();
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "00000000000000000043\n"
        );
        std::fs::remove_dir_all(&d).unwrap();
    }

    /// A seq file that is a FIFO, a device or a huge file is refused at
    /// once (`/dev/zero` used to be read until memory ran out).
    #[test]
    fn a_seq_file_that_is_not_a_small_regular_file_is_refused_at_once() {
        let d = dir("odd");
        std::fs::create_dir_all(&d).unwrap();
        let fifo = d.join("fifo");
        nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
        let big = d.join("big");
        std::fs::File::create(&big)
            .unwrap()
            .set_len(1 << 20)
            .unwrap();
        for (path, what) in [
            (fifo, "a FIFO (named pipe), not a regular file"),
            (PathBuf::from("/dev/zero"), "a character device"),
            (
                big,
                "1048576 bytes or more, and this file is never larger than 4096",
            ),
        ] {
            let shown = path.display().to_string();
            let (tx, rx) = std::sync::mpsc::channel();
            std::thread::spawn(move || {
                let _ = tx.send(SeqFile::open(&path, Duration::ZERO).map(|_| ()));
            });
            let err = rx
                .recv_timeout(Duration::from_secs(10))
                .expect("the open returned (it hung for 10 s)")
                .unwrap_err();
            let e = format!("{err:#}");
            assert!(e.contains(&shown) && e.contains(what), "{e}");
            assert!(e.starts_with("config key `ingress.seq_file`"), "{e}");
            let status = ppm_shared::daemon::exit_status(&err, |_| false);
            assert_eq!(status, ppm_shared::daemon::EXIT_CONFIG, "{e}");
        }
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn garbage_is_refused_with_the_path() {
        let d = dir("garbage");
        std::fs::create_dir_all(&d).unwrap();
        let path = d.join("x.last_seq");
        std::fs::write(&path, "twelve").unwrap();
        let err = SeqFile::open(&path, Duration::ZERO).unwrap_err();
        let e = format!("{err:#}");
        assert!(
            e.starts_with("config key `ingress.seq_file`: the seq file")
                && e.contains(&path.display().to_string())
                && e.contains("twelve"),
            "{e}"
        );
        let status = ppm_shared::daemon::exit_status(&err, |_| false);
        assert_eq!(status, ppm_shared::daemon::EXIT_CONFIG);
        std::fs::remove_dir_all(&d).unwrap();
    }
}
