//! Opening every output's line: simulated, GPIO (lines of one chip share one
//! request, a bank), or SPI.

use crate::emitter::{self, LineRef};
use crate::line::serial::SerialLine;
use crate::line::spi::{self, SpiLine};
use crate::line::{FrameLine, Line, SimFrameLine, SimLine};
use anyhow::{Context, Result};
use ppm_shared::config::{fault, ConfigError, KeyName, OutputPlan, OutputSpec, Shared, Timing};
use ppm_shared::frame::{FrameKind, Level};
use std::path::PathBuf;

/// One output's line, as the timing thread owns it, by the way its frames
/// leave.
pub enum OpenLine {
    /// Edge by edge, on a line of its own (sim, or the only one of ours on
    /// its GPIO chip).
    Edges(Box<dyn Line>),
    /// Edge by edge, on line `bit` of bank `bank` of [`Lines::banks`].
    Banked { bank: usize, bit: u32 },
    /// Whole frames (SPI).
    Whole(Box<dyn FrameLine>),
}

impl OpenLine {
    /// The line as the loop writes it.
    pub fn line_ref(&mut self) -> LineRef<'_> {
        match self {
            OpenLine::Edges(line) => LineRef::Edges(line.as_mut()),
            OpenLine::Banked { bank, bit } => LineRef::Banked {
                bank: *bank,
                bit: *bit,
            },
            OpenLine::Whole(line) => LineRef::Whole(line.as_mut()),
        }
    }
}

/// Every output's plan with its line, and the banks (several lines of one
/// GPIO chip in one request) some of the lines are in.
pub struct Lines {
    /// Each output's plan and line, in the plan's order.
    pub each: Vec<(OutputPlan, OpenLine)>,
    /// The banks [`OpenLine::Banked`] lines point into, shared by their
    /// outputs.
    pub banks: Vec<crate::line::gpio::GpioBank>,
}

/// `NAME: ` in front of a log line when there are several outputs.
pub fn tag(several: bool, name: &str) -> String {
    if several {
        format!("{name}: ")
    } else {
        String::new()
    }
}

/// Opens every output's line, with the `shared` settings, and hands each
/// back with its output. GPIO lines on one chip (however the chip is named)
/// share one request, a bank, so their simultaneous edges are written in one
/// call; a chip with one of our lines gets a request of its own.
pub fn open_lines(shared: &Shared, outputs: Vec<OutputPlan>) -> Result<Lines> {
    let mut each: Vec<Option<OpenLine>> = outputs.iter().map(|_| None).collect();
    /// A chip's path, its CHIP as first given, and its outputs (index, LINE).
    type Chip = (PathBuf, String, Vec<(usize, String)>);
    let mut chips: Vec<Chip> = Vec::new();
    for (i, cfg) in outputs.iter().enumerate() {
        let model = &cfg.model;
        // Frames of bytes always go whole.
        let bytes = model.wire().kind() == FrameKind::Bytes;
        match cfg.output.clone() {
            OutputSpec::Sim { path, .. } if bytes => {
                let sim = create_sim(cfg, shared.trace_max_mb, path)?;
                let line = SimFrameLine::new(
                    sim,
                    model.idle_level(),
                    model.wire().uart(),
                    ppm_shared::time::now_ns,
                );
                each[i] = Some(OpenLine::Whole(Box::new(line)));
            }
            OutputSpec::Sim { path, whole: true } => {
                let sim = create_sim(cfg, shared.trace_max_mb, path)?;
                log::info!(
                    "output `{}`: each frame handed to the simulated line whole at its start, timed by the line's own clock, as an spi: output sends it",
                    cfg.name
                );
                let line =
                    SimFrameLine::new(sim, model.idle_level(), None, ppm_shared::time::now_ns);
                each[i] = Some(OpenLine::Whole(Box::new(line)));
            }
            OutputSpec::Sim { path, .. } => {
                each[i] = Some(OpenLine::Edges(open_sim(cfg, shared.trace_max_mb, path)?));
            }
            OutputSpec::Spi { device } if bytes => {
                // Only SBUS's bytes go through SPI (the configuration
                // refuses others).
                let out = SpiLine::open(&device, spi::SBUS_HZ, model.wire().frame_wire_ns())
                    .map_err(|e| line_error(cfg, e, format!("output `{}`", cfg.name)))?;
                log::info!(
                    "output `{}`: spi {} (true SBUS, each frame one transfer, bits to 10 us)",
                    cfg.name,
                    out.description()
                );
                each[i] = Some(OpenLine::Whole(Box::new(out)));
            }
            OutputSpec::Serial { device } => {
                // The configuration pairs serial: only with a protocol of
                // bytes, which has a UART format.
                let wire = model.wire();
                let format = wire.uart().ok_or_else(|| {
                    anyhow::anyhow!(
                        "output `{}`: {} has no UART format for serial:{}",
                        cfg.name,
                        wire.spec().title,
                        device.display()
                    )
                })?;
                let out = SerialLine::open(&device, format).map_err(|e| {
                    let at = format!("output `{}`: serial:{}", cfg.name, device.display());
                    line_error(cfg, e, at)
                })?;
                if let Some(real) = out.rate_off(format.baud) {
                    let message = format!(
                        "output `{}`: the UART of {} runs at {real} baud, not the {} asked (its clock cannot make that rate, and the kernel keeps another without an error): receivers would misread every frame; on a Raspberry Pi use a PL011 UART (ttyAMA*), whose clock makes it, or a USB adaptor that does{}",
                        cfg.name,
                        device.display(),
                        format.baud,
                        if model.protocol() == ppm_shared::wire::Protocol::Crsf {
                            ", or set ppm.crsf_baud to a rate it makes"
                        } else {
                            ""
                        }
                    );
                    if !shared.rt.allow_degraded {
                        return Err(match cfg.keys.name("ppmd.output") {
                            KeyName::File(key) => ConfigError::Invalid { key, message },
                            KeyName::Option(o) => ConfigError::Usage(format!("{o}: {message}")),
                        }
                        .into());
                    }
                    log::warn!("DEGRADED RUN (rt.allow_degraded): {message}");
                }
                log::info!(
                    "output `{}`: serial {} ({}, {}, each frame one write)",
                    cfg.name,
                    device.display(),
                    wire.spec().title,
                    format.describe()
                );
                each[i] = Some(OpenLine::Whole(Box::new(out)));
            }
            OutputSpec::Spi { device } => {
                // The longest frame: the lead-in pulse after silence, every
                // channel at its maximum, the last pulse.
                let longest = emitter::LEAD_IN_MAX_NS
                    + (0..model.channels())
                        .map(|c| model.max_ns(c) as u64)
                        .sum::<u64>()
                    + model.pulse_ns();
                let out = SpiLine::open(&device, shared.spi_hz, longest)
                    .map_err(|e| line_error(cfg, e, format!("output `{}`", cfg.name)))?;
                log::info!(
                    "output `{}`: spi {} (each frame one transfer, edges to {} ns)",
                    cfg.name,
                    out.description(),
                    1_000_000_000 / shared.spi_hz as u64
                );
                each[i] = Some(OpenLine::Whole(Box::new(out)));
            }
            OutputSpec::Gpio { chip, line } => {
                let spec = if chip.is_empty() {
                    format!("gpio:{line}")
                } else {
                    format!("gpio:{chip}:{line}")
                };
                let (_, summary, _) = crate::line::gpio::resolve_line(&chip, &line)
                    .map_err(|e| line_error(cfg, e, format!("output `{}`: {spec}", cfg.name)))?;
                // `gpio:LINE`: the chip that has it, by its path.
                let chip = if chip.is_empty() {
                    summary.path.to_string_lossy().into_owned()
                } else {
                    chip
                };
                match chips.iter_mut().find(|c| c.0 == summary.path) {
                    Some(c) => c.2.push((i, line)),
                    None => chips.push((summary.path, chip, vec![(i, line)])),
                }
            }
        }
    }
    let mut banks = Vec::new();
    for (path, chip, members) in chips {
        if let [(i, line)] = members.as_slice() {
            let cfg = &outputs[*i];
            let out =
                crate::line::gpio::open(&chip, line, cfg.model.idle_level()).map_err(|e| {
                    line_error(cfg, e, format!("output `{}`: gpio:{chip}:{line}", cfg.name))
                })?;
            log::info!("output `{}`: gpio {}", cfg.name, out.description());
            each[*i] = Some(OpenLine::Edges(Box::new(out)));
            continue;
        }
        let lines: Vec<(String, Level)> = members
            .iter()
            .map(|(i, line)| (line.clone(), outputs[*i].model.idle_level()))
            .collect();
        let names: Vec<&str> = members
            .iter()
            .map(|(i, _)| outputs[*i].name.as_str())
            .collect();
        let bank = crate::line::gpio::open_bank(&path.to_string_lossy(), &lines)
            .with_context(|| format!("outputs {}: GPIO chip {chip}", names.join(", ")))?;
        for (bit, ((i, _), d)) in members.iter().zip(bank.descriptions()).enumerate() {
            log::info!(
                "output `{}`: gpio {d} (one request with {})",
                outputs[*i].name,
                names.join(", ")
            );
            each[*i] = Some(OpenLine::Banked {
                bank: banks.len(),
                bit: bit as u32,
            });
        }
        banks.push(bank);
    }
    let each = outputs
        .into_iter()
        .zip(each)
        .map(|(o, l)| (o, l.expect("every output got a line above")))
        .collect();
    Ok(Lines { each, banks })
}

/// `e`, met opening output `cfg`'s line, with `context` (`output `NAME``,
/// and the line), as ppmd stops with. When the line cannot be had as
/// configured ([`crate::output_fault`]) and the file's key named it, a
/// configuration error naming the key (`ppmd.output`,
/// `outputs[1].output`), with a fix where the line's own message has
/// none; given with `--output`, the message is the line's own (exit status
/// 78 all the same, by [`crate::output_fault`]).
fn line_error<E>(cfg: &OutputPlan, e: E, context: String) -> anyhow::Error
where
    E: std::error::Error + Send + Sync + 'static,
{
    let chain = || {
        std::iter::successors(Some(&e as &(dyn std::error::Error + 'static)), |c| {
            c.source()
        })
    };
    let fault = chain().any(crate::output_fault);
    let errno = chain()
        .find_map(|c| c.downcast_ref::<std::io::Error>())
        .and_then(|io| io.raw_os_error());
    let spi = chain().any(|c| c.is::<crate::line::spi::SpiError>());
    let fix = match (spi, errno) {
        (true, Some(libc::EPERM)) => ": the unit's device policy refuses it (DevicePolicy=closed): uncomment DeviceAllow=char-spi rw in ppmd.service (`sudo systemctl edit ppmd`)",
        (true, Some(libc::ENOENT)) => ": name a spidev device this machine has (/dev/spidevB.C; on a Raspberry Pi enable SPI with dtparam=spi=on in config.txt)",
        _ => "",
    };
    let err = anyhow::Error::new(e).context(context);
    match cfg.keys.name("ppmd.output") {
        KeyName::File(key) if fault => {
            // The chain, each cause once (a line's error may say its
            // source in its own words already).
            let mut message = String::new();
            for cause in err.chain().map(|c| c.to_string()) {
                if !message.contains(&cause) {
                    if !message.is_empty() {
                        message += ": ";
                    }
                    message += &cause;
                }
            }
            anyhow::Error::new(ConfigError::Invalid {
                key,
                message: message + fix,
            })
        }
        _ => err,
    }
}

/// Opens output `cfg`'s simulated line: its trace at `path` (by default
/// `ppm-NAME.trace`, with a header saying the model), rotated at
/// `trace_max_mb` MiB.
pub fn open_sim(
    cfg: &OutputPlan,
    trace_max_mb: u64,
    path: Option<PathBuf>,
) -> Result<Box<dyn Line>> {
    Ok(Box::new(create_sim(cfg, trace_max_mb, path)?))
}

/// The simulated line of [`open_sim`], for either protocol (an SBUS
/// output's header says `protocol sbus`).
fn create_sim(cfg: &OutputPlan, trace_max_mb: u64, path: Option<PathBuf>) -> Result<SimLine> {
    let model = &cfg.model;
    let path = path.unwrap_or_else(|| PathBuf::from(format!("ppm-{}.trace", cfg.name)));
    let header: Vec<String> = [
        "ppm simulated line: <scheduled_ns> <actual_ns> <level>, CLOCK_MONOTONIC".to_string(),
        format!("name {}", cfg.name),
        format!("idle_level {}", model.idle_level().as_u8()),
        format!("channels {}", model.names().join(",")),
        format!("frame_ns {}", model.frame_ns()),
        format!("pulse_ns {}", model.pulse_ns()),
        format!("receiver {}", model.receiver().name()),
        format!("protocol {}", model.protocol().name()),
    ]
    .into_iter()
    .chain(model.wire().uart().map(|u| format!("baud {}", u.baud)))
    .collect::<Vec<_>>();
    let sim = SimLine::create(&path, &header, trace_max_mb << 20).map_err(|e| {
        fault::path_error(
            &cfg.keys.name("ppmd.output"),
            &format!("creating sim trace {}", path.display()),
            &path,
            e,
            "give the trace a path ppmd may create, in a directory that exists (sim:PATH; plain sim writes ppm-NAME.trace in ppmd's working directory, / under systemd, which is read-only)",
        )
    })?;
    log::info!("output `{}`: sim, trace in {}", cfg.name, path.display());
    Ok(sim)
}

/// One output's signal and settings, for the start-up log: channels,
/// timing, pulse, idle level, where its commands come from, failsafe and
/// the spin margin.
pub fn describe(shared: &Shared, c: &OutputPlan) -> String {
    let model = &c.model;
    let timing = match model.timing() {
        Timing::Grid => format!("grid timing, frame {} us", model.frame_ns() as f64 / 1e3),
        Timing::Follow => {
            let (min, max) = model.follow_sync_ns();
            format!(
                "follow timing, {} {}..{} us",
                model.wire().spec().gap,
                min as f64 / 1e3,
                max as f64 / 1e3
            )
        }
    };
    let wire = model.wire().describe();
    format!(
        "{} channels ({}), {timing}, {wire}, idle {:?}; commands from `{}` (ipc root {}); failsafe {:?} after {} ms; spin margin {:?}",
        model.channels(),
        model.names().join(" "),
        model.idle_level(),
        ppm_shared::ipc::command_service_name(&c.name),
        shared.ipc.root.display(),
        c.failsafe.action,
        c.failsafe.after_ms,
        shared.rt.spin_margin_us,
    )
}
