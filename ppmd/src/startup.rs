//! What the main thread sets up for each output around the timing thread:
//! the emitter's settings, the meter and frame log the loop takes
//! ([`Output::lane`]), the output's [`Monitor`] once the loop runs, and its
//! last words at exit ([`Output::finish`]).

use crate::clock::Margin;
use crate::emitter::{EmitterConfig, Stats};
use crate::framelog;
use crate::lines::tag;
use crate::meter::{self, Meter, MeterReader};
use crate::monitor::{HdrLog, Monitor, Obtained, SNAPSHOT_EVERY_NS};
use crate::timing::LanePart;
use anyhow::{Context, Result};
use ppm_shared::config::{Config, RtSection, SpinMargin};
use ppm_shared::frame::FrameModel;
use std::sync::Arc;

/// The spin margin `[rt]` asks for: fixed, or automatic within its bounds.
pub fn spin_margin(rt: &RtSection) -> Margin {
    match rt.spin_margin_us {
        SpinMargin::Fixed(us) => Margin::Fixed(us as u64 * 1_000),
        SpinMargin::Auto => Margin::Auto {
            min_ns: rt.spin_margin_min_us as u64 * 1_000,
            max_ns: rt.spin_margin_max_us as u64 * 1_000,
        },
    }
}

/// Output `c`'s loop settings: its `[failsafe]` and the spin `margin`.
pub fn emitter_config(c: &Config, margin: Margin) -> EmitterConfig {
    EmitterConfig {
        margin,
        failsafe_after_ns: c.failsafe.after_ms * 1_000_000,
        failsafe_action: c.failsafe.action,
        startup: c.failsafe.startup,
    }
}

/// One output as the main thread sets it up: the timing thread takes its
/// [`Output::lane`], the main thread keeps the rest and reads the loop
/// through [`Output::monitor`].
pub struct Output {
    /// Its configuration.
    pub cfg: Config,
    /// Its frame model.
    pub model: FrameModel,
    /// `NAME: ` before its log lines when there are several outputs.
    pub tag: String,
    /// Its counters, which the loop updates.
    pub stats: Arc<Stats>,
    /// The writing end of its frame log, when it has one.
    pub log_writer: Option<framelog::Writer>,
    ecfg: EmitterConfig,
    several: bool,
    /// Taken by [`Output::lane`].
    meter: Option<Meter>,
    log: Option<framelog::Producer>,
    /// Taken by [`Output::monitor`].
    reader: Option<MeterReader>,
}

impl Output {
    /// Sets up output `cfg`, one of `several` or not, with the spin
    /// `margin`: opens its frame log, if any (and says so), and its meter.
    pub fn open(cfg: Config, model: FrameModel, margin: Margin, several: bool) -> Result<Output> {
        let tag = tag(several, &cfg.name);
        let (log, log_writer) = match &cfg.ppmd.frame_log {
            Some(path) => {
                let (p, w) = framelog::open(path, cfg.ppmd.frame_log_max_mb << 20)
                    .with_context(|| format!("opening the frame log {}", path.display()))?;
                log::info!("{tag}frame log: {}", path.display());
                (Some(p), Some(w))
            }
            None => (None, None),
        };
        let (meter, reader) = meter::meter(SNAPSHOT_EVERY_NS);
        Ok(Output {
            ecfg: emitter_config(&cfg, margin),
            cfg,
            model,
            tag,
            stats: Arc::new(Stats::default()),
            log_writer,
            several,
            meter: Some(meter),
            log,
            reader: Some(reader),
        })
    }

    /// What the timing thread takes to run this output: its settings, its
    /// counters, the meter's and the frame log's writing sides. Panics when
    /// taken twice.
    pub fn lane(&mut self) -> LanePart {
        LanePart {
            name: self.cfg.name.clone(),
            model: self.model.clone(),
            ecfg: self.ecfg,
            stats: self.stats.clone(),
            meter: self.meter.take().expect("an output's lane is taken once"),
            log: self.log.take(),
        }
    }

    /// The main thread's view of this output's loop, once the timing thread
    /// said what it `obtained`. Panics when made twice.
    pub fn monitor(&mut self, obtained: &Obtained) -> Monitor {
        let reader = self.reader.take().expect("an output has one monitor");
        let prefix = if self.several {
            format!("{}.", self.cfg.name)
        } else {
            String::new()
        };
        Monitor::new(
            (&self.model, self.cfg.failsafe.after_ms),
            obtained,
            reader,
            self.stats.clone(),
            prefix,
        )
    }

    /// At exit, the loop stopped: finishes the frame log, reads what the
    /// loop handed over last, and says what went wrong with the frame log
    /// and the summary (with the command source's `receive_errors`).
    pub fn finish(&mut self, monitor: &mut Monitor, hdr: Option<&mut HdrLog>, receive_errors: u64) {
        if let Some(w) = self.log_writer.as_mut() {
            w.finish();
        }
        monitor.tick(hdr, self.log_writer.as_ref());
        for line in monitor.final_report(self.log_writer.as_ref()) {
            log::warn!("{}{line}", self.tag);
        }
        log::info!("{}{}", self.tag, monitor.summary(receive_errors));
    }
}

/// The monitors of every output, in order; the first one's edge error also
/// goes untagged into the HdrHistogram log (what its tools read by default).
pub fn monitors(outputs: &mut [Output], obtained: &Obtained) -> Vec<Monitor> {
    let mut monitors: Vec<Monitor> = outputs.iter_mut().map(|o| o.monitor(obtained)).collect();
    if let Some(first) = monitors.first_mut() {
        first.hdr_untagged = true;
    }
    monitors
}

#[cfg(test)]
mod tests {
    use super::*;
    use ppm_shared::config::FailsafeAction;
    use std::panic::{catch_unwind, AssertUnwindSafe};

    #[test]
    fn the_loop_settings_come_from_the_configuration() {
        let c = Config::parse(
            "[rt]\nspin_margin_us = 150\n[failsafe]\nafter_ms = 250\naction = \"hold\"\nstartup = \"default\"",
        )
        .unwrap();
        assert_eq!(spin_margin(&c.rt), Margin::Fixed(150_000));
        let auto =
            Config::parse("[rt]\nspin_margin_min_us = 30\nspin_margin_max_us = 400").unwrap();
        assert_eq!(
            spin_margin(&auto.rt),
            Margin::Auto {
                min_ns: 30_000,
                max_ns: 400_000
            }
        );
        let e = emitter_config(&c, Margin::Fixed(7));
        assert_eq!(e.margin, Margin::Fixed(7));
        assert_eq!(e.failsafe_after_ns, 250_000_000);
        assert_eq!(e.failsafe_action, FailsafeAction::Hold);
        assert_eq!(e.startup, FailsafeAction::Default);
    }

    /// An output named `name` with its frame log in `dir`.
    fn output(dir: &std::path::Path, name: &str, several: bool) -> Output {
        let log = dir.join(format!("{name}.jsonl"));
        let cfg = Config::parse(&format!(
            "name = \"{name}\"\n[ppmd]\nframe_log = {:?}\n[failsafe]\nafter_ms = 300",
            log.to_str().unwrap()
        ))
        .unwrap();
        let model = cfg.validate().unwrap();
        Output::open(cfg, model, Margin::Fixed(5_000), several).unwrap()
    }

    #[test]
    fn an_output_hands_its_lane_and_monitor_over_once() {
        let dir = std::env::temp_dir().join(format!("ppm-startup-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let obtained = Obtained {
            summary: String::new(),
            shortfalls: vec![],
            priority: 0,
            cpu: None,
            preempt_rt: false,
        };

        let mut one = output(&dir, "solo", false);
        assert_eq!(one.tag, "");
        assert!(dir.join("solo.jsonl").exists(), "the frame log is opened");
        let lane = one.lane();
        assert_eq!(lane.name, "solo");
        assert_eq!(lane.ecfg.margin, Margin::Fixed(5_000));
        assert_eq!(lane.ecfg.failsafe_after_ns, 300_000_000);
        assert!(lane.log.is_some());
        assert!(Arc::ptr_eq(&lane.stats, &one.stats));
        assert!(catch_unwind(AssertUnwindSafe(|| one.lane())).is_err());
        let m = one.monitor(&obtained);
        assert_eq!((m.tag_prefix.as_str(), m.failsafe_after_ms), ("", 300));
        assert!(catch_unwind(AssertUnwindSafe(|| one.monitor(&obtained))).is_err());

        let mut two = [output(&dir, "a", true), output(&dir, "b", true)];
        assert_eq!((two[0].tag.as_str(), two[1].tag.as_str()), ("a: ", "b: "));
        let ms = monitors(&mut two, &obtained);
        let tags: Vec<(&str, bool)> = ms
            .iter()
            .map(|m| (m.tag_prefix.as_str(), m.hdr_untagged))
            .collect();
        assert_eq!(tags, [("a.", true), ("b.", false)]);

        for o in std::iter::once(&mut one).chain(two.iter_mut()) {
            o.log_writer.as_mut().unwrap().finish();
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
