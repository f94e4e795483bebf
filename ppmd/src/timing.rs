//! The timing thread: it opens each output's command source, applies the
//! real-time setup, says what it obtained, then runs the outputs
//! ([`crate::emitter::run_outputs`]) until told to stop, and leaves the
//! lines idle.

use crate::clock::Margin;
use crate::emitter::{self, EmitterConfig, Output, Recording, Stats};
use crate::line::gpio::GpioBank;
use crate::line::Bank;
use crate::lines::OpenLine;
use crate::meter::Meter;
use crate::monitor::Obtained;
use crate::pilot::{PilotMux, PilotSlot};
use crate::rt::{RtSetup, Shortfall, RT_STACK_BYTES};
use crate::source::{CommandSource, IpcSource};
use anyhow::Result;
use ppm_shared::config::Timing;
use ppm_shared::frame::FrameModel;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::mpsc::Sender;
use std::sync::Arc;
use std::thread::JoinHandle;

/// One output as the timing thread owns it (the main thread keeps the
/// rest, see [`crate::startup::Output`]).
pub struct TimedOutput {
    /// The output's name (its command service's).
    pub name: String,
    /// Its frame model.
    pub model: FrameModel,
    /// Its failsafe settings.
    pub ecfg: EmitterConfig,
    /// Its counters, also read by the main thread.
    pub stats: Arc<Stats>,
    /// Its histograms' writing side.
    pub meter: Meter,
    /// Its frame log, if any.
    pub log: Option<crate::framelog::Producer>,
    /// Its line (or its place in a bank of the ones given to [`spawn`]).
    pub line: OpenLine,
    /// Where its command source's receive errors are left once the loop
    /// stopped, for the main thread's summary.
    pub receive_errors: Arc<AtomicU64>,
    /// Its pilot's radio, when it has one (`ppmd.pilot`): its commands then
    /// go through a [`PilotMux`].
    pub pilot: Option<Arc<PilotSlot>>,
    /// The timing corrections of the transmitter module it drives, which
    /// its grid follows.
    pub module: Option<Arc<crate::emitter::module::ModuleTiming>>,
}

/// One output on the timing thread once its command source is open.
struct Subscribed {
    part: TimedOutput,
    source: Box<dyn CommandSource>,
}

impl TimedOutput {
    /// Opens its command source under the shared-memory `root`: the
    /// groundstation's, through its pilot's radio when it has one.
    fn subscribe(self, root: &Path) -> Result<Subscribed> {
        let follow = self.model.timing() == Timing::Follow;
        let ground = Box::new(IpcSource::open(root, &self.name, follow)?);
        let source: Box<dyn CommandSource> = match &self.pilot {
            Some(slot) => Box::new(PilotMux::new(ground, slot.clone(), &self.model)),
            None => ground,
        };
        Ok(Subscribed { part: self, source })
    }
}

impl Subscribed {
    /// This output as the loop drives it.
    fn emitter(&mut self) -> Output<'_> {
        let p = &mut self.part;
        Output {
            model: &p.model,
            cfg: p.ecfg,
            source: &mut *self.source,
            line: p.line.line_ref(),
            rec: Recording {
                stats: &p.stats,
                meter: &mut p.meter,
                log: p.log.as_mut(),
            },
            sync: p.module.as_deref(),
        }
    }
}

/// A real-time setting the timing thread could not have (and
/// `rt.allow_degraded` did not let it run without), naming the key that
/// asked for it: the configuration's fault, exit status 78 (the shortfall
/// says how to get it, or to allow a degraded run).
fn rt_error(s: Shortfall) -> anyhow::Error {
    let key = match s.what {
        "CPU pinning" => Some("rt.cpu"),
        "SCHED_FIFO" => Some("rt.priority"),
        "mlockall" => Some("rt.mlock"),
        "cpu_dma_latency" => Some("rt.cpu_dma_latency"),
        _ => None,
    };
    match key {
        Some(k) => anyhow::Error::new(s).context(format!("config key `{k}`")),
        None => anyhow::Error::new(s),
    }
}

/// Starts the timing thread with the `outputs` and the `banks` their lines
/// may be in. It sends what its real-time setup obtained on `ready` (`None`
/// when the sources or the setup failed: the thread then returns the
/// error), runs with the spin `margin` until `stop`, and leaves each
/// source's receive errors in its output's [`TimedOutput::receive_errors`].
pub fn spawn(
    outputs: Vec<TimedOutput>,
    mut banks: Vec<GpioBank>,
    root: PathBuf,
    setup: RtSetup,
    margin: Margin,
    stop: Arc<AtomicBool>,
    ready_tx: Sender<Option<Obtained>>,
) -> std::io::Result<JoinHandle<Result<()>>> {
    std::thread::Builder::new()
        .name("ppmd-timing".into())
        .stack_size(RT_STACK_BYTES)
        .spawn(move || -> Result<()> {
            let started = outputs
                .into_iter()
                .map(|o| o.subscribe(&root))
                .collect::<Result<Vec<_>>>()
                .and_then(|subscribed| Ok((subscribed, setup.apply().map_err(rt_error)?)));
            let (mut subscribed, obtained) = match started {
                Ok(v) => v,
                Err(e) => {
                    let _ = ready_tx.send(None);
                    return Err(e);
                }
            };
            let _ = ready_tx.send(Some(Obtained::from(&obtained)));
            {
                let mut outputs: Vec<Output> =
                    subscribed.iter_mut().map(Subscribed::emitter).collect();
                let mut bank_refs: Vec<&mut dyn Bank> =
                    banks.iter_mut().map(|b| b as &mut dyn Bank).collect();
                emitter::run_outputs(
                    &crate::clock::SystemClock,
                    margin,
                    &mut outputs,
                    &mut bank_refs,
                    &stop,
                );
            }
            for s in &subscribed {
                s.part.receive_errors.store(s.source.errors(), Relaxed);
            }
            // Sets the lines idle and flushes the sim traces.
            drop(subscribed);
            drop(banks);
            drop(obtained); // releases /dev/cpu_dma_latency
            Ok(())
        })
}
