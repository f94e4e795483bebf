//! Bounded reads of the small files ppm is given: the configuration, the
//! auth key and the seq file.
//!
//! A path may name anything: a FIFO (reading it waits for a writer that may
//! never come), `/dev/zero` (endless), a directory, or a file far larger than
//! its content could sensibly be. Each is opened without blocking, checked
//! on the opened descriptor (no race with a rename), refused unless it is a
//! regular file no larger than its limit, and read no further than the limit.

use std::fs::{File, OpenOptions};
use std::io::{self, Read};
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::Path;

/// The largest configuration file read: 1 MiB (the example, every key with
/// its comment, is about 10 KiB).
pub const CONFIG_MAX_BYTES: u64 = 1 << 20;
/// The largest key file read: 64 hex characters and some whitespace.
pub const KEY_MAX_BYTES: u64 = 4096;
/// The largest seq file read: one number of at most 20 digits.
pub const SEQ_MAX_BYTES: u64 = 4096;

/// What kind of file `meta` is, in words, for an error.
fn kind(meta: &std::fs::Metadata) -> &'static str {
    let t = meta.file_type();
    if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a regular file"
    }
}

fn too_large(len: u64, max: u64) -> io::Error {
    io::Error::new(
        io::ErrorKind::InvalidData,
        format!("it holds {len} bytes or more, and this file is never larger than {max}"),
    )
}

/// Opens `path` with `options` without blocking (a FIFO would otherwise
/// wait for a writer), and refuses it unless it is a regular file of at most
/// `max` bytes. The errors say what the file is instead.
pub fn open_regular(options: &mut OpenOptions, path: &Path, max: u64) -> io::Result<File> {
    let file = options
        .custom_flags(nix::fcntl::OFlag::O_NONBLOCK.bits() | nix::fcntl::OFlag::O_NOCTTY.bits())
        .open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("it is {}, not a regular file", kind(&meta)),
        ));
    }
    if meta.len() > max {
        return Err(too_large(meta.len(), max));
    }
    Ok(file)
}

/// Reads an opened file as UTF-8, at most `max` bytes: a file that grew past
/// its limit after [`open_regular`] looked is refused, not read on.
pub fn read_bounded(mut file: &File, max: u64) -> io::Result<String> {
    let mut text = String::new();
    (&mut file).take(max + 1).read_to_string(&mut text)?;
    if text.len() as u64 > max {
        return Err(too_large(text.len() as u64, max));
    }
    Ok(text)
}

/// [`open_regular`] for reading, then [`read_bounded`].
pub fn read_small(path: &Path, max: u64) -> io::Result<String> {
    let file = open_regular(OpenOptions::new().read(true), path, max)?;
    read_bounded(&file, max)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::sync::mpsc;
    use std::time::Duration;

    /// Runs `f` on its own thread and fails the test when it takes longer
    /// than 10 s (a read that hangs), instead of hanging the suite.
    pub(crate) fn within_10s<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(f());
        });
        rx.recv_timeout(Duration::from_secs(10))
            .expect("the read returned (it hung for 10 s)")
    }

    fn dir(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("ppm-files-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn a_small_regular_file_is_read_whole() {
        let d = dir("small");
        let p = d.join("f");
        std::fs::write(&p, "abc\n").unwrap();
        assert_eq!(read_small(&p, 4).unwrap(), "abc\n");
        let e = read_small(&p, 3).unwrap_err().to_string();
        assert!(
            e.contains("4 bytes or more") && e.contains("never larger than 3"),
            "{e}"
        );
    }

    #[test]
    fn a_fifo_is_refused_at_once() {
        let d = dir("fifo");
        let p = d.join("fifo");
        nix::unistd::mkfifo(&p, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
        let e = within_10s(move || read_small(&p, 4096)).unwrap_err();
        assert!(
            e.to_string()
                .contains("a FIFO (named pipe), not a regular file"),
            "{e}"
        );
    }

    #[test]
    fn devices_and_directories_are_refused() {
        for (p, what) in [
            ("/dev/zero", "a character device"),
            ("/dev/null", "a character device"),
            ("/", "a directory"),
        ] {
            let e = within_10s(move || read_small(Path::new(p), 4096)).unwrap_err();
            assert!(e.to_string().contains(what), "{p}: {e}");
        }
    }
}
