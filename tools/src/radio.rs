//! A simulated radio's pieces, for the read-back's tests and benchmark:
//! following ppm's simulated line as it grows, and a radio's own PPM
//! frames as edges.

use ppm_shared::signal::Level;
use std::io::Read;
use std::path::{Path, PathBuf};

/// A radio's separator pulse, ns.
pub const PULSE_NS: u64 = 300_000;

/// Follows a growing trace file (the simulated line's format): the
/// complete lines written since the last call.
pub struct Follow {
    file: Option<std::fs::File>,
    path: PathBuf,
    partial: String,
}

impl Follow {
    /// Follows `path`, which may not exist yet.
    pub fn new(path: &Path) -> Follow {
        Follow {
            file: None,
            path: path.to_owned(),
            partial: String::new(),
        }
    }

    /// Edges `(actual_ns, level)` written since the last call (none while
    /// the file does not exist).
    pub fn edges(&mut self) -> std::io::Result<Vec<(u64, Level)>> {
        if self.file.is_none() {
            self.file = std::fs::File::open(&self.path).ok();
        }
        let Some(f) = self.file.as_mut() else {
            return Ok(vec![]);
        };
        let mut text = std::mem::take(&mut self.partial);
        f.read_to_string(&mut text)?;
        let complete = text.rfind('\n').map_or(0, |i| i + 1);
        self.partial = text[complete..].to_owned();
        Ok(text[..complete]
            .lines()
            .filter_map(|l| match ppm_shared::trace::parse_line(l) {
                Some(Ok(e)) => Some((e.actual_ns, e.level)),
                _ => None,
            })
            .collect())
    }
}

/// One PPM frame of a radio (idle low, [`PULSE_NS`] pulses) starting at
/// `start` with channels `us`: its edges `(time_ns, level after)`, the
/// pulse that ends the last channel included (the sync follows).
pub fn frame_edges(start: u64, us: &[u64]) -> Vec<(u64, u8)> {
    let mut out = Vec::new();
    let mut t = start;
    for &v in us {
        out.extend([(t, 1), (t + PULSE_NS, 0)]);
        t += v * 1_000;
    }
    out.extend([(t, 1), (t + PULSE_NS, 0)]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn a_frame_is_a_pulse_before_each_channel_and_one_after() {
        assert_eq!(
            frame_edges(1_000, &[1_000, 2_000]),
            [
                (1_000, 1),
                (301_000, 0),
                (1_001_000, 1),
                (1_301_000, 0),
                (3_001_000, 1),
                (3_301_000, 0)
            ]
        );
    }

    #[test]
    fn complete_lines_only_and_a_file_that_comes_late() {
        let path = std::env::temp_dir().join(format!("ppm-radio-{}.trace", std::process::id()));
        let _ = std::fs::remove_file(&path);
        let mut f = Follow::new(&path);
        assert!(f.edges().unwrap().is_empty());
        let mut w = std::fs::File::create(&path).unwrap();
        w.write_all(b"# idle_level 0\n5 6 1\n7 8").unwrap();
        assert_eq!(f.edges().unwrap(), [(6, Level::High)]);
        w.write_all(b" 0\n").unwrap();
        assert_eq!(f.edges().unwrap(), [(8, Level::Low)]);
        let _ = std::fs::remove_file(&path);
    }
}
