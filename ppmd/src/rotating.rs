//! The one log file type of ppmd: an append-only file rotated at a size cap
//! ([`RotatingFile`]), and the lock-free ring and writer thread that feed it
//! from the timing loop ([`spawn`]). The frame log and the simulated line's
//! trace go through both; the HdrHistogram log (written by the main thread)
//! through the file alone.
//!
//! What the file does, whoever uses it:
//! - At the cap `FILE` becomes `FILE.1`, `FILE.1` becomes `FILE.2`, ...,
//!   keeping `keep` numbered copies; the new `FILE` starts with the header,
//!   if there is one.
//! - Only a regular file is rotated: never `/dev/null`, a FIFO or a device
//!   (nor a symbolic link to one).
//! - A rotation that fails (a rename or the new file refused) is said once
//!   and the file grows on, unrotated: the writing goes on.
//! - A write that fails (a full disk, `/dev/full`) drops what was buffered
//!   and returns the error; the writer thread counts the rows lost, keeps
//!   the last error and tries again with the next rows.
//! - [`RotatingFile::finish`] flushes and, for a regular file, syncs.

use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// Bytes buffered before a write reaches the file.
const BUFFER: usize = 64 * 1024;
/// Stack of a writer thread.
const WRITER_STACK: usize = 256 * 1024;

/// An append-only file rotated at a size cap (see the module's docs).
pub struct RotatingFile {
    what: &'static str,
    path: PathBuf,
    max_bytes: u64,
    keep: usize,
    /// Written at the top of every file a rotation starts.
    header: Vec<u8>,
    regular: bool,
    file: File,
    /// Written, not yet flushed.
    buf: Vec<u8>,
    /// The file's size, what is buffered included.
    size: u64,
    /// A rotation failed: the file grows on, unrotated.
    stuck: bool,
}

impl RotatingFile {
    /// Opens `path` for appending (creating it if missing). `what` names
    /// the file in messages (`frame log`). It is rotated once a write would
    /// take it beyond `max_bytes` (`u64::MAX`: never), keeping `keep`
    /// numbered copies (at least one).
    pub fn append(
        what: &'static str,
        path: &Path,
        max_bytes: u64,
        keep: usize,
    ) -> io::Result<RotatingFile> {
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        RotatingFile::new(what, path, file, max_bytes, keep)
    }

    /// Creates (truncates) `path` and writes `header` at its top, flushed:
    /// an error here is the caller's. Every file a rotation starts begins
    /// with the same header. Otherwise as [`RotatingFile::append`].
    pub fn create(
        what: &'static str,
        path: &Path,
        header: &[u8],
        max_bytes: u64,
        keep: usize,
    ) -> io::Result<RotatingFile> {
        let mut f = RotatingFile::new(what, path, File::create(path)?, max_bytes, keep)?;
        f.set_header(header);
        f.write(header)?;
        f.flush()?;
        Ok(f)
    }

    fn new(
        what: &'static str,
        path: &Path,
        file: File,
        max_bytes: u64,
        keep: usize,
    ) -> io::Result<RotatingFile> {
        let meta = file.metadata()?;
        Ok(RotatingFile {
            what,
            path: path.to_owned(),
            max_bytes,
            keep: keep.max(1),
            header: Vec::new(),
            regular: meta.is_file(),
            size: meta.len(),
            file,
            buf: Vec::with_capacity(BUFFER),
            stuck: false,
        })
    }

    /// Sets the header every file a rotation starts from now on begins
    /// with (the current file is left as it is).
    pub fn set_header(&mut self, header: &[u8]) {
        self.header = header.to_vec();
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What the file is, for messages (`frame log`).
    pub fn what(&self) -> &'static str {
        self.what
    }

    /// Whether the file is a regular file (only those are rotated and
    /// synced).
    pub fn is_regular(&self) -> bool {
        self.regular
    }

    /// `FILE.n`.
    pub fn numbered(&self, n: usize) -> PathBuf {
        let mut p = self.path.clone().into_os_string();
        p.push(format!(".{n}"));
        PathBuf::from(p)
    }

    /// Appends one record (whole lines), rotating first when it would take
    /// the file beyond the cap; a record never straddles two files. On an
    /// error what was buffered is dropped (the caller counts it lost) and
    /// the next write tries again.
    pub fn write(&mut self, record: &[u8]) -> io::Result<()> {
        let len = record.len() as u64;
        if self.regular
            && !self.stuck
            && self.size > self.header.len() as u64
            && self.size.saturating_add(len) > self.max_bytes
        {
            self.rotate()?;
        }
        self.buf.extend_from_slice(record);
        self.size += len;
        if self.buf.len() >= BUFFER {
            self.flush()?;
        }
        Ok(())
    }

    /// Writes what is buffered. On an error it is dropped (the caller
    /// counts it lost); the file stays open and the next write tries again.
    pub fn flush(&mut self) -> io::Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let r = self.file.write_all(&self.buf);
        self.buf.clear();
        if r.is_err() {
            // What reached the file before the error is in it; the rest is not.
            if let Ok(m) = self.file.metadata() {
                self.size = m.len();
            }
        }
        r
    }

    /// Flushes and, for a regular file, syncs its data (`/dev/null` cannot
    /// be synced).
    pub fn finish(mut self) -> io::Result<()> {
        self.flush()?;
        if self.regular {
            self.file.sync_data()?;
        }
        Ok(())
    }

    /// `FILE.keep-1` -> `FILE.keep`, ..., `FILE` -> `FILE.1`, and a new
    /// `FILE` with the header. When a rename or the new file fails, says so
    /// once and writes on where it was.
    fn rotate(&mut self) -> io::Result<()> {
        self.flush()?;
        let renamed = (1..self.keep)
            .rev()
            .filter(|&n| std::fs::symlink_metadata(self.numbered(n)).is_ok())
            .try_for_each(|n| rename(&self.numbered(n), &self.numbered(n + 1)))
            .and_then(|()| rename(&self.path, &self.numbered(1)));
        if let Err(e) = renamed {
            self.stuck = true;
            log::warn!(
                "{} {}: cannot rotate it ({e}); it grows on, unrotated",
                self.what,
                self.path.display()
            );
            return Ok(());
        }
        match OpenOptions::new()
            .create(true)
            .truncate(true)
            .write(true)
            .open(&self.path)
        {
            Ok(f) => {
                self.file = f;
                self.size = 0;
                let header = std::mem::take(&mut self.header);
                let r = self.write(&header);
                self.header = header;
                r
            }
            Err(e) => {
                self.stuck = true;
                log::warn!(
                    "{} {}: cannot start a new file ({e}); it goes on in {}, unrotated",
                    self.what,
                    self.path.display(),
                    self.numbered(1).display()
                );
                Ok(())
            }
        }
    }
}

impl Drop for RotatingFile {
    fn drop(&mut self) {
        let _ = self.flush();
    }
}

fn rename(from: &Path, to: &Path) -> io::Result<()> {
    std::fs::rename(from, to).map_err(|e| {
        io::Error::new(
            e.kind(),
            format!("renaming {} to {}: {e}", from.display(), to.display()),
        )
    })
}

/// How a writer thread runs.
#[derive(Debug, Clone, Copy)]
pub struct WriterOptions {
    /// The thread's name.
    pub thread: &'static str,
    /// Rows the ring holds.
    pub capacity: usize,
    /// How often the thread drains the ring and flushes.
    pub flush_every: Duration,
    /// Whether the thread says itself (log) when writes start failing and
    /// when they work again; otherwise its owner reads
    /// [`Writer::lost`] and [`Writer::last_error`] and says it.
    pub say_write_errors: bool,
}

/// The timing loop's end of a writer's ring.
pub struct Producer<T> {
    ring: rtrb::Producer<T>,
    counts: Arc<Counts>,
}

impl<T> Producer<T> {
    /// Queues a row; when the ring is full the row is dropped, counted in
    /// [`Writer::dropped`], and `false` returned. Never allocates or blocks.
    #[inline]
    pub fn push(&mut self, row: T) -> bool {
        let queued = self.ring.push(row).is_ok();
        if !queued {
            self.counts.dropped.fetch_add(1, Ordering::Relaxed);
        }
        queued
    }
}

#[derive(Default)]
struct Counts {
    stop: AtomicBool,
    dropped: AtomicU64,
    written: AtomicU64,
    lost: AtomicU64,
    last_error: Mutex<Option<String>>,
}

impl Counts {
    fn set_error(&self, e: String) {
        if let Ok(mut last) = self.last_error.lock() {
            *last = Some(e);
        }
    }
}

/// A writer thread and its counters (the owner's end).
pub struct Writer {
    counts: Arc<Counts>,
    what: &'static str,
    thread: Option<JoinHandle<()>>,
}

/// Starts a thread that drains a ring of `T` into `file`, one line a row
/// (`format` writes the row, without the newline, into an empty string),
/// flushing every `options.flush_every`. Rows written are counted when
/// their flush succeeds; when a write fails the rows since the last flush
/// are counted lost, the error is kept and the next rows try again.
pub fn spawn<T, F>(
    mut file: RotatingFile,
    options: WriterOptions,
    mut format: F,
) -> io::Result<(Producer<T>, Writer)>
where
    T: Send + 'static,
    F: FnMut(&T, &mut String) + Send + 'static,
{
    let (producer, mut consumer) = rtrb::RingBuffer::<T>::new(options.capacity);
    let counts = Arc::new(Counts::default());
    let what = file.what();
    let c = counts.clone();
    let thread = std::thread::Builder::new()
        .name(options.thread.into())
        .stack_size(WRITER_STACK)
        .spawn(move || {
            let mut line = String::with_capacity(256);
            let mut failing = false;
            loop {
                let stopping = c.stop.load(Ordering::Acquire);
                let (mut batch, mut failed) = (0u64, None);
                while let Ok(row) = consumer.pop() {
                    batch += 1;
                    if failed.is_none() {
                        line.clear();
                        format(&row, &mut line);
                        line.push('\n');
                        failed = file.write(line.as_bytes()).err();
                    }
                }
                if failed.is_none() {
                    failed = file.flush().err();
                }
                match failed {
                    None => {
                        c.written.fetch_add(batch, Ordering::Relaxed);
                        if failing && batch > 0 {
                            failing = false;
                            if options.say_write_errors {
                                log::info!(
                                    "{what} {}: writing again ({} rows lost)",
                                    file.path().display(),
                                    c.lost.load(Ordering::Relaxed)
                                );
                            }
                        }
                    }
                    Some(e) => {
                        c.lost.fetch_add(batch, Ordering::Relaxed);
                        if !failing && options.say_write_errors {
                            log::warn!(
                                "{what} {}: cannot write ({e}); rows are lost (counted) until it can",
                                file.path().display()
                            );
                        }
                        failing = true;
                        c.set_error(e.to_string());
                    }
                }
                if stopping {
                    if let Err(e) = file.finish() {
                        c.set_error(e.to_string());
                    }
                    return;
                }
                std::thread::park_timeout(options.flush_every);
            }
        })?;
    Ok((
        Producer {
            ring: producer,
            counts: counts.clone(),
        },
        Writer {
            counts,
            what,
            thread: Some(thread),
        },
    ))
}

impl Writer {
    /// Rows dropped because the ring was full (the writer fell behind).
    pub fn dropped(&self) -> u64 {
        self.counts.dropped.load(Ordering::Relaxed)
    }

    /// Rows written (and flushed).
    pub fn written(&self) -> u64 {
        self.counts.written.load(Ordering::Relaxed)
    }

    /// Rows lost because the file could not be written (a full disk, a
    /// device that refuses writes); the writer goes on with the next rows.
    pub fn lost(&self) -> u64 {
        self.counts.lost.load(Ordering::Relaxed)
    }

    /// The last error (a write, the final sync, a panic of the thread), if
    /// any.
    pub fn last_error(&self) -> Option<String> {
        self.counts
            .last_error
            .lock()
            .map(|e| e.clone())
            .unwrap_or(None)
    }

    /// Writes what is queued, flushes, syncs a regular file and stops the
    /// thread (at once, not at its next round). What could not be written
    /// is counted in [`Writer::lost`] and [`Writer::last_error`], never an
    /// error here: a log is not worth the line. Does nothing a second time.
    pub fn finish(&mut self) {
        self.counts.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            t.thread().unpark();
            if t.join().is_err() {
                self.counts
                    .set_error(format!("the {} writer panicked", self.what));
            }
        }
    }

    /// Whether everything was written: an error when a write, the final
    /// sync or the thread failed (rows dropped from a full ring are not
    /// counted here).
    pub fn check(&self) -> io::Result<()> {
        match self.last_error() {
            None => Ok(()),
            Some(e) => Err(io::Error::other(format!(
                "{}: {} rows could not be written ({e})",
                self.what,
                self.lost()
            ))),
        }
    }
}

impl Drop for Writer {
    fn drop(&mut self) {
        self.finish();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh directory for one test.
    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("ppmd-rotating-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn lines(p: &Path) -> Vec<String> {
        std::fs::read_to_string(p)
            .unwrap_or_default()
            .lines()
            .map(str::to_owned)
            .collect()
    }

    fn options() -> WriterOptions {
        WriterOptions {
            thread: "test-writer",
            capacity: 1024,
            flush_every: Duration::from_millis(10),
            say_write_errors: true,
        }
    }

    /// A writer of `row N` lines.
    fn rows(file: RotatingFile) -> (Producer<u32>, Writer) {
        spawn(file, options(), |n: &u32, s: &mut String| {
            use std::fmt::Write as _;
            let _ = write!(s, "row {n:04}");
        })
        .unwrap()
    }

    #[test]
    fn rotates_at_the_cap_keeping_n_copies_each_with_the_header() {
        let d = dir("cap");
        let path = d.join("f.log");
        // A 6-byte header and 9-byte rows: 4 rows a file (42 bytes <= 45).
        let f = RotatingFile::create("test log", &path, b"# hdr\n", 45, 2).unwrap();
        let (mut p, mut w) = rows(f);
        for n in 0..18 {
            assert!(p.push(n));
        }
        w.finish();
        assert_eq!((w.written(), w.lost(), w.dropped()), (18, 0, 0));
        w.check().unwrap();
        let row = |n: u32| format!("row {n:04}");
        let want = |ns: std::ops::Range<u32>| {
            std::iter::once("# hdr".to_string())
                .chain(ns.map(row))
                .collect::<Vec<_>>()
        };
        // 18 rows, 4 a file: 0-3, 4-7, 8-11 (gone), 12-15 (.1), 16-17.
        assert_eq!(lines(&path), want(16..18));
        assert_eq!(lines(&d.join("f.log.1")), want(12..16));
        assert_eq!(lines(&d.join("f.log.2")), want(8..12));
        assert!(!d.join("f.log.3").exists(), "two copies kept");
        let _ = std::fs::remove_dir_all(d);
    }

    #[test]
    fn appends_and_rotates_a_file_without_a_header() {
        let d = dir("append");
        let path = d.join("f.log");
        std::fs::write(&path, "old\n").unwrap();
        let mut f = RotatingFile::append("test log", &path, 20, 3).unwrap();
        for n in 0..5 {
            f.write(format!("row {n:04}\n").as_bytes()).unwrap();
        }
        f.finish().unwrap();
        assert_eq!(lines(&d.join("f.log.2")), ["old", "row 0000"]);
        assert_eq!(lines(&d.join("f.log.1")), ["row 0001", "row 0002"]);
        assert_eq!(lines(&path), ["row 0003", "row 0004"]);
        let _ = std::fs::remove_dir_all(d);
    }

    #[test]
    fn never_rotates_what_is_not_a_regular_file() {
        // /dev/null, and a link to it: were it rotated, the link would move.
        let d = dir("null");
        let link = d.join("null.log");
        std::os::unix::fs::symlink("/dev/null", &link).unwrap();
        for path in [Path::new("/dev/null"), &link] {
            let f = RotatingFile::create("test log", path, b"# hdr\n", 10, 3).unwrap();
            assert!(!f.is_regular());
            let (mut p, mut w) = rows(f);
            for n in 0..100 {
                p.push(n);
            }
            w.finish();
            assert_eq!((w.written(), w.lost()), (100, 0));
            w.check().unwrap();
        }
        assert!(Path::new("/dev/null").exists());
        assert!(std::fs::symlink_metadata(&link).unwrap().is_symlink());
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 1, "no copies");
        assert!(!Path::new("/dev/null.1").exists());
        let _ = std::fs::remove_dir_all(d);
    }

    #[test]
    fn a_failed_rotation_keeps_writing_to_the_current_file() {
        // The copy the last rename would replace is a directory with
        // something in it: the rename fails (as root too).
        for keep in [1, 3] {
            let d = dir(&format!("stuck{keep}"));
            let path = d.join("f.log");
            let blocker = d.join(format!("f.log.{keep}"));
            std::fs::create_dir_all(&blocker).unwrap();
            std::fs::write(blocker.join("keep"), "x").unwrap();
            let f = RotatingFile::create("test log", &path, b"# hdr\n", 45, keep).unwrap();
            let (mut p, mut w) = rows(f);
            for n in 0..100 {
                p.push(n);
                if n % 10 == 9 {
                    std::thread::sleep(Duration::from_millis(5));
                }
            }
            w.finish();
            assert_eq!((w.written(), w.lost()), (100, 0), "keep {keep}");
            w.check().unwrap();
            assert!(blocker.join("keep").exists());
            // The rows before the failed rotation are in the copies, four
            // a file; every later row is in the current file, in order.
            let mut all = vec![];
            for n in (1..keep).rev() {
                let copy = lines(&d.join(format!("f.log.{n}")));
                assert_eq!(copy.len(), 5, "keep {keep}: header and 4 rows");
                all.extend(copy.into_iter().skip(1));
            }
            let current = lines(&path);
            assert_eq!(current[0], "# hdr");
            all.extend(current.into_iter().skip(1));
            let want: Vec<String> = (0..100).map(|n| format!("row {n:04}")).collect();
            assert_eq!(&all[all.len() - 100..], &want[..], "keep {keep}");
            let _ = std::fs::remove_dir_all(d);
        }
    }

    #[test]
    fn write_errors_are_counted_and_the_writer_goes_on() {
        // /dev/full takes the open and refuses every write (ENOSPC).
        let f = RotatingFile::append("test log", Path::new("/dev/full"), 10, 3).unwrap();
        let (mut p, mut w) = rows(f);
        for n in 0..50 {
            p.push(n);
        }
        std::thread::sleep(Duration::from_millis(100));
        assert_eq!((w.lost(), w.written()), (50, 0), "counted while running");
        assert!(w.last_error().is_some_and(|e| e.contains("space")));
        for n in 50..60 {
            p.push(n);
        }
        w.finish();
        assert_eq!((w.lost(), w.written()), (60, 0));
        assert!(w.check().unwrap_err().to_string().contains("60 rows"));
        assert!(Path::new("/dev/full").exists(), "not rotated");
    }

    #[test]
    fn a_full_ring_drops_and_counts() {
        let (mut p, mut w) = spawn(
            RotatingFile::append("test log", Path::new("/dev/null"), u64::MAX, 1).unwrap(),
            WriterOptions {
                capacity: 8,
                flush_every: Duration::from_secs(10),
                ..options()
            },
            |_: &u32, _: &mut String| {},
        )
        .unwrap();
        let queued = (0..100).filter(|&n| p.push(n)).count() as u64;
        w.finish();
        assert!(w.dropped() > 0);
        assert_eq!(w.dropped() + queued, 100);
        assert_eq!(w.written(), queued);
    }
}
