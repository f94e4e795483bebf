//! Test helper for the real-kernel tests: emits a PPM signal on a gpio-sim
//! *input* line by writing its `pull` attribute (gpio-sim's way of driving a
//! line from outside), with ppmd's own timing loop, so that `jitter
//! --capture` can read kernel-timestamped edges of a line it requested as an
//! input. Not part of ppm: gpio-sim exists only for tests.
//!
//! Usage: pull-ppm PULL_ATTRIBUTE FRAMES US,US,...

use ppm_shared::config::{Config, FailsafeAction, RtSection};
use ppm_shared::frame::Level;
use ppm_shared::ipc::CommandSample;
use ppm_shared::protocol::parse;
use ppm_shared::trace::TraceEdge;
use ppmd::clock::Margin;
use ppmd::emitter::{self, EmitterConfig, LineRef, Stats};
use ppmd::line::{Line, LineError};
use ppmd::rt::RtSetup;
use ppmd::source::RepeatSource;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::Arc;

struct PullOutput(File);

impl Line for PullOutput {
    fn write(&mut self, edge: &TraceEdge) -> Result<(), LineError> {
        let value: &[u8] = match edge.level {
            Level::High => b"pull-up",
            Level::Low => b"pull-down",
        };
        self.0.write_at(value, 0).map(|_| ()).map_err(|e| {
            LineError::Write(nix::errno::Errno::from_raw(e.raw_os_error().unwrap_or(5)))
        })
    }

    fn park(&mut self, level: Level) -> Result<(), LineError> {
        self.write(&TraceEdge {
            scheduled_ns: 0,
            actual_ns: 0,
            level,
        })
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let [_, attr, frames, values] = &args[..] else {
        eprintln!("usage: pull-ppm PULL_ATTRIBUTE FRAMES US,US,...");
        std::process::exit(2);
    };
    let model = Config::default().validate().expect("default config");
    let cmd = parse(format!("[{values}]").as_bytes(), &model).expect("values");
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(attr)
        .expect("opening the pull attribute");
    let mut out = PullOutput(file);
    out.park(model.idle_level())
        .expect("setting the idle level");
    RtSetup::from_config(&RtSection {
        allow_degraded: true,
        ..RtSection::default()
    })
    .apply()
    .expect("real-time setup");
    let stop = Arc::new(AtomicBool::new(false));
    let mut source = RepeatSource {
        sample: CommandSample::new(&cmd, model.fingerprint(), 1, 0, 0),
        frames: frames.parse().expect("FRAMES"),
        stop: stop.clone(),
    };
    let margin = Margin::Auto {
        min_ns: 20_000,
        max_ns: 1_000_000,
    };
    let cfg = EmitterConfig {
        failsafe_after_ns: 1_000_000_000,
        failsafe_action: FailsafeAction::Silence,
        startup: FailsafeAction::Silence,
    };
    let stats = Stats::default();
    let (mut meter, _reader) = ppmd::meter::meter(u64::MAX);
    emitter::run(
        &model,
        &cfg,
        margin,
        &mut source,
        LineRef::Edges(&mut out),
        &stop,
        &stats,
        &mut meter,
        None,
    );
    eprintln!("pull-ppm: {} frames", stats.frames.load(Relaxed));
}
