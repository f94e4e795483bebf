//! Test helper for the real-kernel tests: drives a gpio-sim *input* line at
//! PPM timing by writing its `pull` attribute (`pull-up` for high,
//! `pull-down` for low) on its own clock, and records for every write
//! CLOCK_MONOTONIC right before and right after it: the window in which the
//! line really changed, i.e. its own measured jitter. The host compares the
//! kernel's timestamps of the edges (`ppm-capture`'s log) with that record.
//! Not part of ppm: gpio-sim exists only for tests.
//!
//! Usage: pull-timed PULL_ATTRIBUTE FRAMES US,US,... LOG
//!
//! The signal: idle low, 300 us high pulses, frames of 22.5 ms; a lead-in
//! pulse one sync before the first frame (so a reader syncs on frame 0) and
//! a closing pulse one sync after the last channel of the last frame (so
//! that frame is closed). Each write is timed with clock_nanosleep
//! (TIMER_ABSTIME) to [`SPIN_NS`] before its due time, then a spin on
//! clock_gettime; SCHED_FIFO [`PRIORITY`] and locked memory where allowed.
//!
//! LOG: a header `# channels_us A,B,.. pulse_us P frame_us F frames N`, then
//! one line per write: `LEVEL DUE_NS BEFORE_NS AFTER_NS` (LEVEL 1 for
//! pull-up, 0 for pull-down; CLOCK_MONOTONIC ns).

use nix::time::{clock_gettime, clock_nanosleep, ClockId, ClockNanosleepFlags};
use ppmd::rt::RtSetup;
use std::fs::File;
use std::io::Write;
use std::os::unix::fs::FileExt;

/// Width of every pulse, us.
const PULSE_US: u64 = 300;
/// Frame period (leading edge to leading edge of frame starts), us.
const FRAME_US: u64 = 22_500;
/// The last part of each wait spent spinning instead of sleeping, ns.
const SPIN_NS: u64 = 100_000;
/// SCHED_FIFO priority (as ppmd's timing thread).
const PRIORITY: u8 = 80;
/// The first frame starts this long after the start (after the lead-in), ns.
const START_NS: u64 = 50_000_000;

fn now() -> u64 {
    let t = clock_gettime(ClockId::CLOCK_MONOTONIC).expect("clock_gettime");
    t.tv_sec() as u64 * 1_000_000_000 + t.tv_nsec() as u64
}

/// Sleeps until `SPIN_NS` before `due`, then spins until `due`.
fn wait_until(due: u64) {
    let wake = due.saturating_sub(SPIN_NS);
    if now() < wake {
        let ts =
            nix::sys::time::TimeSpec::new((wake / 1_000_000_000) as _, (wake % 1_000_000_000) as _);
        // EINTR: the spin below covers what is left.
        let _ = clock_nanosleep(
            ClockId::CLOCK_MONOTONIC,
            ClockNanosleepFlags::TIMER_ABSTIME,
            &ts,
        );
    }
    while now() < due {
        std::hint::spin_loop();
    }
}

/// The due times and levels of every write, relative to the first frame's
/// start: lead-in pulse, `frames` frames of one pulse per channel boundary,
/// closing pulse.
fn schedule(frames: u64, channels_us: &[u64]) -> Vec<(i64, u8)> {
    let frame_ns = (FRAME_US * 1_000) as i64;
    let pulse_ns = (PULSE_US * 1_000) as i64;
    let sum_ns: i64 = channels_us.iter().map(|&c| c as i64 * 1_000).sum();
    let sync_ns = frame_ns - sum_ns;
    let mut leads = vec![-sync_ns];
    for f in 0..frames as i64 {
        let mut t = f * frame_ns;
        leads.push(t);
        for &c in channels_us {
            t += c as i64 * 1_000;
            leads.push(t);
        }
    }
    leads.push(frames as i64 * frame_ns);
    leads
        .into_iter()
        .flat_map(|t| [(t, 1), (t + pulse_ns, 0)])
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let [_, attr, frames, values, log] = &args[..] else {
        eprintln!("usage: pull-timed PULL_ATTRIBUTE FRAMES US,US,... LOG");
        std::process::exit(2);
    };
    let frames: u64 = frames.parse().expect("FRAMES");
    let channels: Vec<u64> = values
        .split(',')
        .map(|v| v.trim().parse().expect("a channel value in us"))
        .collect();
    let sum: u64 = channels.iter().sum();
    assert!(
        channels.iter().all(|c| (800..=2200).contains(c)) && FRAME_US - sum > 4_000,
        "channels {channels:?} do not fit a {FRAME_US} us frame with a sync"
    );
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(attr)
        .expect("opening the pull attribute");
    let write = |level: u8| {
        let value: &[u8] = if level == 1 { b"pull-up" } else { b"pull-down" };
        file.write_at(value, 0).expect("writing the pull attribute");
    };
    write(0);
    let rt = RtSetup {
        priority: PRIORITY,
        cpu: None,
        mlock: true,
        cpu_dma_latency: false,
        allow_degraded: true,
    };
    let got = rt.apply().expect("real-time setup");
    eprintln!("pull-timed: {}", got.summary());

    let plan = schedule(frames, &channels);
    let mut rec: Vec<(u8, u64, u64, u64)> = Vec::with_capacity(plan.len());
    let t0 = now() + START_NS;
    for &(at, level) in &plan {
        let due = (t0 as i64 + at) as u64;
        wait_until(due);
        let before = now();
        write(level);
        let after = now();
        rec.push((level, due, before, after));
    }
    drop(got);

    let mut out = std::io::BufWriter::new(File::create(log).expect("creating the log"));
    let list: Vec<String> = channels.iter().map(|c| c.to_string()).collect();
    writeln!(
        out,
        "# channels_us {} pulse_us {PULSE_US} frame_us {FRAME_US} frames {frames}",
        list.join(",")
    )
    .unwrap();
    for (level, due, before, after) in &rec {
        writeln!(out, "{level} {due} {before} {after}").unwrap();
    }
    out.flush().expect("writing the log");
    let late = rec.iter().map(|r| r.3 - r.1).max().unwrap_or(0);
    let window = rec.iter().map(|r| r.3 - r.2).max().unwrap_or(0);
    eprintln!(
        "pull-timed: {frames} frames, {} writes; latest write ended {:.1} us after its due time, longest write {:.1} us",
        rec.len(),
        late as f64 / 1e3,
        window as f64 / 1e3
    );
}
