//! What the main thread sets up for each output around the timing thread:
//! the emitter's settings, the meter, frame log and line the loop takes
//! ([`Output::open`] hands them over as a [`TimedOutput`]), the snapshot
//! publisher, then, once the loop runs, the output's [`Monitor`]
//! ([`Output::watch`]) and its last words at exit ([`Output::finish`]).

use crate::clock::Margin;
use crate::emitter::module::ModuleTiming;
use crate::emitter::{EmitterConfig, Stats};
use crate::framelog;
use crate::lines::{tag, OpenLine};
use crate::meter::{self, MeterReader};
use crate::monitor::{HdrLog, Monitor, Obtained, SnapshotPublisher, SNAPSHOT_EVERY_NS};
use crate::pilot::PilotSlot;
use crate::timing::TimedOutput;
use anyhow::Result;
use ppm_shared::config::{fault, FailsafeSection, OutputPlan, RtSection, Shared, SpinMargin};
use ppm_shared::logging::Chain;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
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

/// An output's loop settings: its `failsafe`.
pub fn emitter_config(failsafe: &FailsafeSection) -> EmitterConfig {
    EmitterConfig {
        failsafe_after_ns: failsafe.after_ms * 1_000_000,
        failsafe_action: failsafe.action,
        startup: failsafe.startup,
    }
}

/// One output as the main thread holds it: its plan and the pieces around
/// its loop; the timing thread has its [`TimedOutput`]. `V` is the main
/// thread's view of the loop: the meter's reading side ([`MeterReader`])
/// until the loop runs, then its [`Monitor`] ([`Output::watch`] turns the
/// one into the other), so one struct holds the output all along.
pub struct Output<V = MeterReader> {
    /// Its plan: name, frame model, line, failsafe.
    pub plan: OutputPlan,
    /// `NAME: ` before its log lines when there are several outputs.
    pub tag: String,
    /// Its counters, which the loop updates.
    pub stats: Arc<Stats>,
    /// The writing end of its frame log, when it has one.
    pub log_writer: Option<framelog::Writer>,
    /// The publisher of its timing snapshots.
    pub publisher: SnapshotPublisher,
    /// Its command source's receive errors, left by the timing thread once
    /// the loop stopped.
    pub receive_errors: Arc<AtomicU64>,
    /// What its pilot's thread tells the loop, when it has a pilot's radio
    /// (`ppmd.pilot`); the timing thread's part holds it too.
    /// The timing corrections of the transmitter module it drives
    /// (`ppm.crsf_target = "module"`): its telemetry thread leaves them,
    /// its grid follows them.
    pub module: Option<Arc<ModuleTiming>>,
    pub pilot: Option<Arc<PilotSlot>>,
    several: bool,
    /// The main thread's view of its loop.
    view: V,
}

/// An output once its loop runs: watched through its [`Monitor`].
pub type Watched = Output<Monitor>;

impl Output {
    /// Sets up output `plan`, one of `several` or not: opens its frame log,
    /// if any (and says so, rotated at the `shared` size), its meter and its
    /// snapshot publisher, and the slot of its pilot's radio, if any. The
    /// timing thread's part takes the meter's and the frame log's writing
    /// sides and the output's `line`.
    pub fn open(
        plan: OutputPlan,
        line: OpenLine,
        shared: &Shared,
        several: bool,
    ) -> Result<(Output, TimedOutput)> {
        let tag = tag(several, &plan.name);
        let (log, log_writer) = match &plan.frame_log {
            Some(path) => {
                let (p, w) = framelog::open(path, shared.frame_log_max_mb << 20).map_err(|e| {
                    fault::path_error(
                        &plan.keys.name("ppmd.frame_log"),
                        &format!("opening the frame log {}", path.display()),
                        path,
                        e,
                        "name a file ppmd may create and append to, in a directory that exists (under systemd: /var/log/ppm, the unit's LogsDirectory; elsewhere add a ReadWritePaths= line)",
                    )
                })?;
                log::info!("{tag}frame log: {}", path.display());
                (Some(p), Some(w))
            }
            None => (None, None),
        };
        let (meter, reader) = meter::meter(SNAPSHOT_EVERY_NS);
        let publisher = SnapshotPublisher::open(&shared.ipc.root, &plan.name)?;
        let stats = Arc::new(Stats::default());
        let receive_errors = Arc::new(AtomicU64::new(0));
        let pilot = plan.pilot.as_ref().map(|_| Arc::new(PilotSlot::default()));
        let module = plan
            .drives_module()
            .then(|| Arc::new(ModuleTiming::default()));
        let timed = TimedOutput {
            name: plan.name.clone(),
            model: plan.model.clone(),
            ecfg: emitter_config(&plan.failsafe),
            stats: stats.clone(),
            meter,
            log,
            line,
            receive_errors: receive_errors.clone(),
            pilot: pilot.clone(),
            module: module.clone(),
        };
        let output = Output {
            plan,
            tag,
            stats,
            log_writer,
            publisher,
            receive_errors,
            pilot,
            module,
            several,
            view: reader,
        };
        Ok((output, timed))
    }

    /// This output once the timing thread said what it `obtained`: the
    /// main thread's view of its loop.
    pub fn watch(self, obtained: &Obtained) -> Watched {
        let prefix = if self.several {
            format!("{}.", self.plan.name)
        } else {
            String::new()
        };
        let monitor = Monitor::new(
            (&self.plan.model, self.plan.failsafe.after_ms),
            obtained,
            self.view,
            self.stats.clone(),
            prefix,
        );
        Output {
            plan: self.plan,
            tag: self.tag,
            stats: self.stats,
            log_writer: self.log_writer,
            publisher: self.publisher,
            receive_errors: self.receive_errors,
            pilot: self.pilot,
            module: self.module,
            several: self.several,
            view: monitor,
        }
    }
}

impl Watched {
    /// Reads the loop's measurements; publishes a snapshot when one is due,
    /// else offers the last one to new subscribers; and publishes the
    /// newest frame the line carried, when a new one went out.
    pub fn tick(&mut self, hdr: Option<&mut HdrLog>) {
        if let Some(sample) = self.stats.last_frame.load() {
            if let Err(e) = self.publisher.publish_line(sample) {
                log::debug!("publishing the line sample: {}", Chain(&e));
            }
        }
        match self.view.tick(hdr, self.log_writer.as_ref()) {
            Some(snapshot) => {
                if let Err(e) = self.publisher.publish(snapshot) {
                    log::debug!("publishing timing snapshot: {}", Chain(&e));
                }
            }
            None => self.publisher.serve_new_subscribers(),
        }
    }

    /// At exit, the loop stopped: finishes the frame log, reads what the
    /// loop handed over last, and says what went wrong with the frame log
    /// and the summary (with the command source's receive errors).
    pub fn finish(&mut self, hdr: Option<&mut HdrLog>) {
        if let Some(w) = self.log_writer.as_mut() {
            w.finish();
        }
        self.view.tick(hdr, self.log_writer.as_ref());
        for line in self.view.final_report(self.log_writer.as_ref()) {
            log::warn!("{}{line}", self.tag);
        }
        let receive_errors = self.receive_errors.load(Relaxed);
        log::info!("{}{}", self.tag, self.view.summary(receive_errors));
    }
}

/// Every output once the timing thread said what it `obtained`, in order;
/// the first one's edge error also goes untagged into the HdrHistogram log
/// (what its tools read by default).
pub fn watch_all(outputs: Vec<Output>, obtained: &Obtained) -> Vec<Watched> {
    let mut watched: Vec<Watched> = outputs.into_iter().map(|o| o.watch(obtained)).collect();
    if let Some(first) = watched.first_mut() {
        first.view.hdr_untagged = true;
    }
    watched
}

#[cfg(test)]
mod tests {
    use super::*;
    use ppm_shared::config::{Config, FailsafeAction, Plan};

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
        let e = emitter_config(&c.failsafe);
        assert_eq!(e.failsafe_after_ns, 250_000_000);
        assert_eq!(e.failsafe_action, FailsafeAction::Hold);
        assert_eq!(e.startup, FailsafeAction::Default);
    }

    /// An output named `name` on `line`, with its frame log and ipc root in
    /// `dir`.
    fn output(
        dir: &std::path::Path,
        name: &str,
        line: OpenLine,
        several: bool,
    ) -> (Output, TimedOutput) {
        let log = dir.join(format!("{name}.jsonl"));
        let cfg = Config::parse(&format!(
            "name = \"{name}\"\n[ppmd]\nframe_log = {:?}\n[failsafe]\nafter_ms = 300\n[ipc]\nroot = {:?}",
            log.to_str().unwrap(),
            dir.join("ipc").to_str().unwrap(),
        ))
        .unwrap();
        let (shared, plan) = Plan::resolve_one(&cfg).unwrap();
        Output::open(plan, line, &shared, several).unwrap()
    }

    #[test]
    fn an_output_with_a_pilots_radio_shares_its_slot_with_the_timing_thread() {
        let dir = std::env::temp_dir().join(format!("ppm-startup-pilot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cfg = Config::parse(&format!(
            "name = \"flown\"\n[ppmd]\npilot = \"sim:{}\"\n[pilot]\nswitch_channel = 5\n[ipc]\nroot = {:?}",
            dir.join("radio.trace").display(),
            dir.join("ipc").to_str().unwrap(),
        ))
        .unwrap();
        let (shared, plan) = Plan::resolve_one(&cfg).unwrap();
        assert_eq!(plan.pilot.as_ref().unwrap().switch_channel, 4);
        let line = OpenLine::Banked { bank: 0, bit: 0 };
        let (one, timed) = Output::open(plan, line, &shared, false).unwrap();
        let (main, loop_) = (one.pilot.as_ref().unwrap(), timed.pilot.as_ref().unwrap());
        assert!(Arc::ptr_eq(main, loop_));
        assert_eq!(main.state(), crate::pilot::PilotState::NoInput);
        drop((one, timed));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_output_hands_its_timed_part_over_and_is_watched() {
        let dir = std::env::temp_dir().join(format!("ppm-startup-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let obtained = Obtained {
            summary: String::new(),
            shortfalls: vec![],
            priority: 0,
            cpu: None,
            preempt_rt: false,
        };

        let (one, timed) = output(&dir, "solo", OpenLine::Banked { bank: 2, bit: 3 }, false);
        assert_eq!(one.tag, "");
        assert!(dir.join("solo.jsonl").exists(), "the frame log is opened");
        assert_eq!(timed.name, "solo");
        assert_eq!(timed.ecfg.failsafe_after_ns, 300_000_000);
        assert!(timed.log.is_some());
        assert!(matches!(timed.line, OpenLine::Banked { bank: 2, bit: 3 }));
        assert!(Arc::ptr_eq(&timed.stats, &one.stats));
        assert!(
            timed.pilot.is_none() && one.pilot.is_none(),
            "no ppmd.pilot"
        );
        timed.receive_errors.store(7, Relaxed);
        let mut one = one.watch(&obtained);
        assert_eq!(one.receive_errors.load(Relaxed), 7);
        let m = &one.view;
        assert_eq!((m.tag_prefix.as_str(), m.failsafe_after_ms), ("", 300));
        assert!(Arc::ptr_eq(&m.stats, &one.stats));

        let two = ["a", "b"].map(|n| output(&dir, n, OpenLine::Banked { bank: 0, bit: 0 }, true).0);
        assert_eq!((two[0].tag.as_str(), two[1].tag.as_str()), ("a: ", "b: "));
        let mut two = watch_all(two.into(), &obtained);
        let tags: Vec<(&str, bool)> = two
            .iter()
            .map(|w| (w.view.tag_prefix.as_str(), w.view.hdr_untagged))
            .collect();
        assert_eq!(tags, [("a.", true), ("b.", false)]);

        for w in std::iter::once(&mut one).chain(two.iter_mut()) {
            w.log_writer.as_mut().unwrap().finish();
        }
        // Their publishers' files go before the directory.
        drop((one, two));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
