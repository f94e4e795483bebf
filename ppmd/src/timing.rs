//! The timing thread: it opens each output's command source, applies the
//! real-time setup, says what it obtained, then runs the lanes
//! ([`crate::emitter::run_lanes`]) until told to stop, and leaves the lines
//! idle.

use crate::emitter::{self, EmitterConfig, Lane, Sink, Stats};
use crate::lines::{Line, Lines};
use crate::meter::Meter;
use crate::monitor::Obtained;
use crate::output::Bank;
use crate::rt::{RtSetup, RT_STACK_BYTES};
use crate::source::{CommandSource, IpcSource};
use anyhow::Result;
use ppm_shared::config::Timing;
use ppm_shared::frame::FrameModel;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::Sender;
use std::sync::Arc;
use std::thread::JoinHandle;

/// What the timing thread takes of one output to build its lane.
pub struct LanePart {
    /// The output's name (its command service's).
    pub name: String,
    /// Its frame model.
    pub model: FrameModel,
    /// Its failsafe settings and the loop's spin margin.
    pub ecfg: EmitterConfig,
    /// Its counters, also read by the main thread.
    pub stats: Arc<Stats>,
    /// Its histograms' writing side.
    pub meter: Meter,
    /// Its frame log, if any.
    pub log: Option<crate::framelog::Producer>,
}

/// Starts the timing thread. It sends what its real-time setup obtained on
/// `ready` (`None` when the sources or the setup failed: the thread then
/// returns the error), runs until `stop`, and returns each source's
/// receive errors.
pub fn spawn(
    mut parts: Vec<LanePart>,
    mut lines: Lines,
    root: PathBuf,
    setup: RtSetup,
    stop: Arc<AtomicBool>,
    ready_tx: Sender<Option<Obtained>>,
) -> std::io::Result<JoinHandle<Result<Vec<u64>>>> {
    std::thread::Builder::new()
        .name("ppmd-timing".into())
        .stack_size(RT_STACK_BYTES)
        .spawn(move || -> Result<Vec<u64>> {
            let started = parts
                .iter()
                .map(|p| IpcSource::open(&root, &p.name, p.model.timing() == Timing::Follow))
                .collect::<Result<Vec<_>, _>>()
                .map_err(anyhow::Error::from)
                .and_then(|sources| Ok((sources, setup.apply()?)));
            let (mut sources, obtained) = match started {
                Ok(v) => v,
                Err(e) => {
                    let _ = ready_tx.send(None);
                    return Err(e);
                }
            };
            let _ = ready_tx.send(Some(Obtained::from(&obtained)));
            {
                let Lines { each, banks } = &mut lines;
                let mut lanes: Vec<Lane> = parts
                    .iter_mut()
                    .zip(sources.iter_mut())
                    .zip(each.iter_mut())
                    .map(|((p, source), line)| Lane {
                        model: &p.model,
                        cfg: p.ecfg,
                        source,
                        sink: match line {
                            Line::Own(out) => Sink::Line(out.as_mut()),
                            Line::Banked { bank, bit } => Sink::Bank {
                                bank: *bank,
                                bit: *bit,
                            },
                        },
                        stats: &p.stats,
                        meter: &mut p.meter,
                        log: p.log.as_mut(),
                    })
                    .collect();
                let mut bank_refs: Vec<&mut dyn Bank> =
                    banks.iter_mut().map(|b| b as &mut dyn Bank).collect();
                emitter::run_lanes(
                    &crate::clock::SystemClock,
                    &mut lanes,
                    &mut bank_refs,
                    &stop,
                );
            }
            drop(lines); // sets the lines idle, flushes the sim traces
            drop(obtained); // releases /dev/cpu_dma_latency
            Ok(sources.iter().map(|s| s.errors()).collect())
        })
}
