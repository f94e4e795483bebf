//! A trace of the simulated line (`ppm_shared::trace`) read as an input,
//! followed while it grows, as `tail -F` follows a file:
//!
//! - The trace may not exist yet: it is looked for at every poll.
//! - Only complete lines are taken; a line still being written is kept
//!   until its newline arrives.
//! - `#` comments are skipped, but `# idle_level N` is kept
//!   ([`EdgeSource::idle_level`]).
//! - Each edge becomes an [`EdgeEvent`] at its written (actual) time,
//!   numbered 1, 2, ... across files, as the kernel numbers a line's edges.
//! - Rotation (ppmd renames `FILE` to `FILE.1` and starts `FILE` again,
//!   see [`crate::rotating`]): once `FILE` names another file, the old
//!   one is read to its end, then the new one from its start. A file that
//!   shrank (truncated, as a restarted ppmd does) is read again from its
//!   start.
//! - With no data it polls every [`POLL`]: this runs on the read-back
//!   thread, not in the timing loop.
//!
//! What it cannot see: a second rotation before it noticed the first (the
//! file in between is gone, `FILE.1` replaced), and a truncated file that
//! grew past where it was read before it looked.

use super::{EdgeSource, InputError};
use ppm_shared::capture::EdgeEvent;
use ppm_shared::signal::Level;
use ppm_shared::trace;
use std::fs::File;
use std::io::{ErrorKind, Read, Seek, SeekFrom};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// How often the trace is looked at when there is nothing new.
pub const POLL: Duration = Duration::from_millis(1);

/// Bytes read at a time; also the longest line taken (an edge is about
/// 40 bytes).
const BUFFER: usize = 64 * 1024;

/// How much of a malformed line its error shows.
const SHOWN: usize = 80;

/// The trace being read.
struct Followed {
    file: File,
    /// Which file it is: `FILE` naming another one is a rotation.
    dev: u64,
    ino: u64,
    /// Bytes read from it.
    pos: u64,
    /// `FILE` names another file now: this one is read to its end once
    /// more (what was written before the rename), then left.
    replaced: bool,
}

/// A sim trace followed as it grows (see the module's docs).
pub struct SimInput {
    path: PathBuf,
    description: String,
    file: Option<Followed>,
    /// Read, not yet taken: `buf[start..end]`.
    buf: Box<[u8]>,
    start: usize,
    end: usize,
    /// Lines taken from the current file.
    line: usize,
    /// The last edge's number.
    seq: u64,
    idle: Option<Level>,
}

impl std::fmt::Debug for SimInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimInput")
            .field("path", &self.path)
            .field("seq", &self.seq)
            .finish_non_exhaustive()
    }
}

/// What one complete line is.
enum Parsed {
    /// A comment or a blank line; `Some` for `# idle_level N`.
    Comment(Option<Level>),
    Edge(trace::TraceEdge),
    Malformed,
}

fn parse(line: &[u8]) -> Parsed {
    let Ok(text) = std::str::from_utf8(line) else {
        return Parsed::Malformed;
    };
    // As `Trace::read` reads it: 1 is high, anything else low.
    if let Some(v) = text.trim().strip_prefix("# idle_level ") {
        return Parsed::Comment(Some(Level::from_bit(v.trim() == "1")));
    }
    match trace::parse_line(text) {
        None => Parsed::Comment(None),
        Some(Ok(e)) => Parsed::Edge(e),
        Some(Err(())) => Parsed::Malformed,
    }
}

/// At most [`SHOWN`] characters of `line`, for a message.
fn shown(line: &[u8]) -> String {
    let text = String::from_utf8_lossy(line);
    match text.char_indices().nth(SHOWN) {
        Some((cut, _)) => format!("{}...", &text[..cut]),
        None => text.into_owned(),
    }
}

impl SimInput {
    /// Follows the trace at `path`, which need not exist yet. Nothing is
    /// opened until the first [`EdgeSource::read`].
    pub fn open(path: &Path) -> SimInput {
        SimInput {
            path: path.to_owned(),
            description: format!("sim:{}", path.display()),
            file: None,
            buf: vec![0; BUFFER].into_boxed_slice(),
            start: 0,
            end: 0,
            line: 0,
            seq: 0,
            idle: None,
        }
    }

    fn malformed(&self, line: &[u8], number: usize) -> InputError {
        InputError::Malformed {
            path: self.path.clone(),
            line: number,
            text: shown(line),
        }
    }

    /// Takes the complete lines read, until `out` is full; returns how
    /// many edges it put there. A malformed line is an error when it comes
    /// first, else left for the next call (the edges before it are
    /// returned first); either way it is passed when its error is returned.
    fn take_lines(&mut self, out: &mut [EdgeEvent]) -> Result<usize, InputError> {
        let mut n = 0;
        while n < out.len() {
            let rest = &self.buf[self.start..self.end];
            let Some(nl) = rest.iter().position(|&b| b == b'\n') else {
                break;
            };
            let line = &rest[..nl];
            match parse(line) {
                Parsed::Comment(idle) => self.idle = idle.or(self.idle),
                Parsed::Edge(e) => {
                    self.seq += 1;
                    out[n] = EdgeEvent {
                        at_ns: e.actual_ns,
                        level: e.level,
                        seq: self.seq,
                    };
                    n += 1;
                }
                Parsed::Malformed if n > 0 => break,
                Parsed::Malformed => {
                    let e = self.malformed(line, self.line + 1);
                    self.start += nl + 1;
                    self.line += 1;
                    return Err(e);
                }
            }
            self.start += nl + 1;
            self.line += 1;
        }
        Ok(n)
    }

    /// Reads more of the current file; false at its end (or with no file).
    fn fill(&mut self) -> Result<bool, InputError> {
        if self.file.is_none() {
            return Ok(false);
        }
        if self.start == self.end {
            (self.start, self.end) = (0, 0);
        } else if self.end == self.buf.len() {
            if self.start == 0 {
                // One line fills the buffer: no trace line is that long.
                let e = self.malformed(&self.buf[..SHOWN], self.line + 1);
                (self.start, self.end) = (0, 0);
                return Err(e);
            }
            self.buf.copy_within(self.start..self.end, 0);
            (self.start, self.end) = (0, self.end - self.start);
        }
        let Some(f) = &mut self.file else {
            return Ok(false);
        };
        loop {
            match f.file.read(&mut self.buf[self.end..]) {
                Ok(0) => return Ok(false),
                Ok(k) => {
                    self.end += k;
                    f.pos += k as u64;
                    return Ok(true);
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(error) => {
                    return Err(InputError::SimRead {
                        path: self.path.clone(),
                        error,
                    })
                }
            }
        }
    }

    /// At the end of what is open: opens the trace when it appears,
    /// follows a rotation, rereads a truncated file. True when there may
    /// be more to read now.
    fn follow(&mut self) -> Result<bool, InputError> {
        let Some(f) = &mut self.file else {
            return self.reopen();
        };
        let named = match std::fs::metadata(&self.path) {
            Ok(m) => m,
            // Between the rename and the new file, or deleted: what is open
            // is read on, and the name looked for again.
            Err(e) if e.kind() == ErrorKind::NotFound => return Ok(false),
            Err(error) => {
                return Err(InputError::SimOpen {
                    path: self.path.clone(),
                    error,
                })
            }
        };
        if (named.dev(), named.ino()) != (f.dev, f.ino) {
            if !f.replaced {
                f.replaced = true;
                return Ok(true);
            }
            return self.reopen();
        }
        if named.is_file() && named.len() < f.pos {
            f.file
                .seek(SeekFrom::Start(0))
                .map_err(|error| InputError::SimRead {
                    path: self.path.clone(),
                    error,
                })?;
            f.pos = 0;
            self.restart();
            return Ok(true);
        }
        Ok(false)
    }

    /// Opens the file `path` names now, from its start; false when there
    /// is none.
    fn reopen(&mut self) -> Result<bool, InputError> {
        let opened = File::open(&self.path).and_then(|file| {
            let m = file.metadata()?;
            Ok(Followed {
                file,
                dev: m.dev(),
                ino: m.ino(),
                pos: 0,
                replaced: false,
            })
        });
        match opened {
            Ok(f) => {
                self.file = Some(f);
                self.restart();
                Ok(true)
            }
            Err(e) if e.kind() == ErrorKind::NotFound => {
                self.file = None;
                Ok(false)
            }
            Err(error) => Err(InputError::SimOpen {
                path: self.path.clone(),
                error,
            }),
        }
    }

    /// A new file, or the file again from its start: a line left
    /// incomplete in the one before never ends.
    fn restart(&mut self) {
        (self.start, self.end, self.line) = (0, 0, 0);
    }
}

impl EdgeSource for SimInput {
    fn read(&mut self, out: &mut [EdgeEvent], timeout: Duration) -> Result<usize, InputError> {
        if out.is_empty() {
            return Ok(0);
        }
        let deadline = Instant::now().checked_add(timeout);
        loop {
            let n = self.take_lines(out)?;
            if n > 0 {
                return Ok(n);
            }
            if self.fill()? || self.follow()? {
                continue;
            }
            let left = match deadline {
                Some(d) => d.saturating_duration_since(Instant::now()),
                None => POLL,
            };
            if left.is_zero() {
                return Ok(0);
            }
            std::thread::sleep(left.min(POLL));
        }
    }

    fn description(&self) -> &str {
        &self.description
    }

    fn idle_level(&self) -> Option<Level> {
        self.idle
    }
}

#[cfg(test)]
mod tests;
