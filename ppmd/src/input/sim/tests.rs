use super::*;
use crate::line::{Line, SimLine};
use ppm_shared::trace::TraceEdge;
use std::io::Write;

/// A fresh directory for one test.
fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("ppmd-input-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Edge `i`'s trace line: scheduled at `i` us, written 7 ns later, high
/// for odd `i`.
fn line(i: u64) -> String {
    format!("{} {} {}\n", i * 1000, i * 1000 + 7, i % 2)
}

/// Edge `i` as read, numbered `seq`.
fn edge(i: u64, seq: u64) -> EdgeEvent {
    EdgeEvent {
        at_ns: i * 1000 + 7,
        level: Level::from_bit(i % 2 == 1),
        seq,
    }
}

fn append(path: &Path, text: &str) {
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .unwrap();
    f.write_all(text.as_bytes()).unwrap();
}

const NO_EDGE: EdgeEvent = EdgeEvent {
    at_ns: 0,
    level: Level::Low,
    seq: 0,
};

/// Everything there is to read now (reads without waiting until one
/// gives nothing).
fn drain(src: &mut SimInput) -> Vec<EdgeEvent> {
    let mut all = vec![];
    let mut out = [NO_EDGE; 64];
    loop {
        let n = src.read(&mut out, Duration::ZERO).unwrap();
        if n == 0 {
            return all;
        }
        all.extend_from_slice(&out[..n]);
    }
}

#[test]
fn a_line_written_in_pieces_is_taken_once_complete() {
    let d = dir("pieces");
    let path = d.join("t.trace");
    append(&path, "# idle_l");
    let mut src = SimInput::open(&path);
    assert_eq!(drain(&mut src), []);
    append(&path, "evel 1\n");
    append(&path, &line(1));
    append(&path, "2000 20");
    assert_eq!(drain(&mut src), [edge(1, 1)]);
    assert_eq!(src.idle_level(), Some(Level::High));
    append(&path, "07 ");
    assert_eq!(drain(&mut src), []);
    append(&path, "0\n");
    append(&path, &line(3));
    assert_eq!(drain(&mut src), [edge(2, 2), edge(3, 3)]);
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn the_header_gives_the_idle_level() {
    let d = dir("header");
    let path = d.join("t.trace");
    std::fs::write(
        &path,
        format!("# idle_level 0\n# frame_ns 22500000\n\n{}", line(1)),
    )
    .unwrap();
    let mut src = SimInput::open(&path);
    assert_eq!(src.idle_level(), None, "nothing read yet");
    assert_eq!(drain(&mut src), [edge(1, 1)]);
    assert_eq!(src.idle_level(), Some(Level::Low));
    // Without the header, the level stays unknown.
    let bare = d.join("bare.trace");
    std::fs::write(&bare, line(1)).unwrap();
    let mut src = SimInput::open(&bare);
    assert_eq!(drain(&mut src), [edge(1, 1)]);
    assert_eq!(src.idle_level(), None);
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn a_trace_that_appears_late_is_read_from_its_start() {
    let d = dir("late");
    let path = d.join("t.trace");
    let mut src = SimInput::open(&path);
    let mut out = [NO_EDGE; 8];
    let t = Instant::now();
    assert_eq!(src.read(&mut out, Duration::from_millis(5)).unwrap(), 0);
    assert!(
        t.elapsed() >= Duration::from_millis(5),
        "waited the timeout"
    );
    std::fs::write(&path, format!("# idle_level 1\n{}{}", line(1), line(2))).unwrap();
    assert_eq!(src.read(&mut out, Duration::from_secs(10)).unwrap(), 2);
    assert_eq!(out[..2], [edge(1, 1), edge(2, 2)]);
    assert_eq!(src.idle_level(), Some(Level::High));
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn a_rotation_loses_and_repeats_no_edge() {
    let d = dir("rotation");
    let path = d.join("t.trace");
    let old = d.join("t.trace.1");
    let header = "# idle_level 1\n";
    std::fs::write(&path, format!("{header}{}{}", line(1), line(2))).unwrap();
    let mut src = SimInput::open(&path);
    assert_eq!(drain(&mut src), [edge(1, 1), edge(2, 2)]);
    // Written after the last look, then renamed away: still read.
    append(&path, &line(3));
    append(&path, &line(4));
    std::fs::rename(&path, &old).unwrap();
    // No FILE yet (between the rename and the new file).
    assert_eq!(drain(&mut src), [edge(3, 3), edge(4, 4)]);
    assert_eq!(drain(&mut src), []);
    std::fs::write(&path, format!("{header}{}", line(5))).unwrap();
    assert_eq!(drain(&mut src), [edge(5, 5)]);
    // A rotation seen at once: the rest of the old file, then the new one.
    append(&path, &line(6));
    std::fs::rename(&path, &old).unwrap();
    std::fs::write(&path, format!("{header}{}{}", line(7), line(8))).unwrap();
    assert_eq!(drain(&mut src), [edge(6, 6), edge(7, 7), edge(8, 8)]);
    append(&path, &line(9));
    assert_eq!(drain(&mut src), [edge(9, 9)]);
    assert_eq!(src.idle_level(), Some(Level::High));
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn a_truncated_trace_is_read_again_from_its_start() {
    let d = dir("truncated");
    let path = d.join("t.trace");
    std::fs::write(
        &path,
        format!("# idle_level 1\n{}{}{}", line(1), line(2), line(3)),
    )
    .unwrap();
    let mut src = SimInput::open(&path);
    assert_eq!(drain(&mut src), [edge(1, 1), edge(2, 2), edge(3, 3)]);
    // A partial line, then the file is started again (same inode, as a
    // restarted ppmd's `File::create` does): the partial line is dropped.
    append(&path, "4000 40");
    assert_eq!(drain(&mut src), []);
    std::fs::write(&path, format!("# idle_level 0\n{}", line(4))).unwrap();
    assert_eq!(drain(&mut src), [edge(4, 4)]);
    assert_eq!(src.idle_level(), Some(Level::Low));
    append(&path, &line(5));
    assert_eq!(drain(&mut src), [edge(5, 5)]);
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn a_malformed_line_is_an_error_naming_the_path_and_line() {
    let d = dir("malformed");
    let path = d.join("t.trace");
    std::fs::write(
        &path,
        format!("# idle_level 1\n{}1000 1007 2\n{}", line(1), line(2)),
    )
    .unwrap();
    let mut src = SimInput::open(&path);
    let mut out = [NO_EDGE; 8];
    // The edge before it first, then the error, then the edges after it.
    assert_eq!(src.read(&mut out, Duration::ZERO).unwrap(), 1);
    assert_eq!(out[0], edge(1, 1));
    let e = src.read(&mut out, Duration::ZERO).unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "input sim:{} line 3: `1000 1007 2` is not an edge (`<scheduled_ns> <actual_ns> <0|1>`) nor a `#` comment",
            path.display()
        )
    );
    assert!(matches!(e, InputError::Malformed { line: 3, .. }));
    assert_eq!(drain(&mut src), [edge(2, 2)]);
    // A long line shows its start only.
    let long = d.join("long.trace");
    std::fs::write(&long, format!("{}\n", "x".repeat(200))).unwrap();
    let e = SimInput::open(&long)
        .read(&mut out, Duration::ZERO)
        .unwrap_err();
    assert!(
        e.to_string()
            .contains(&format!(" line 1: `{}...` is not an edge", "x".repeat(80))),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(d);
}

#[test]
fn edges_beyond_the_slice_wait_for_the_next_read() {
    let d = dir("slice");
    let path = d.join("t.trace");
    let text: String = (1..=5).map(line).collect();
    std::fs::write(&path, text).unwrap();
    let mut src = SimInput::open(&path);
    let mut out = [NO_EDGE; 2];
    let mut got = vec![];
    for want in [2, 2, 1, 0] {
        let n = src.read(&mut out, Duration::ZERO).unwrap();
        assert_eq!(n, want);
        got.extend_from_slice(&out[..n]);
    }
    assert_eq!(got, (1..=5).map(|i| edge(i, i)).collect::<Vec<_>>());
    assert_eq!(src.read(&mut [], Duration::ZERO).unwrap(), 0);
    let _ = std::fs::remove_dir_all(d);
}

/// ppmd's own simulated line, rotating every few dozen edges: read while
/// it writes, every edge comes back once, in order. Written a batch at a
/// time, less than a file's worth, each read back before the next, so at
/// most one rotation happens between two looks.
#[test]
fn follows_ppmds_sim_line_across_its_rotations() {
    let d = dir("simline");
    let path = d.join("t.trace");
    let mut sim = SimLine::create(&path, &["idle_level 1".into()], 2_000).unwrap();
    let mut src = SimInput::open(&path);
    let mut out = [NO_EDGE; 16];
    let mut got = vec![];
    for batch in 0..20u64 {
        for i in batch * 30 + 1..=batch * 30 + 30 {
            let e = edge(i, 0);
            sim.write(&TraceEdge {
                scheduled_ns: i * 1000,
                actual_ns: e.at_ns,
                level: e.level,
            })
            .unwrap();
        }
        let deadline = Instant::now() + Duration::from_secs(20);
        while (got.len() as u64) < batch * 30 + 30 && Instant::now() < deadline {
            let n = src.read(&mut out, Duration::from_millis(20)).unwrap();
            got.extend_from_slice(&out[..n]);
        }
    }
    sim.finish().unwrap();
    got.extend(drain(&mut src));
    assert!(d.join("t.trace.1").exists(), "it rotated");
    assert_eq!(got, (1..=600).map(|i| edge(i, i)).collect::<Vec<_>>());
    assert_eq!(src.idle_level(), Some(Level::High));
    let _ = std::fs::remove_dir_all(d);
}
