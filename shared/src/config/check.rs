//! The checks of one output's configuration: every key outside `[ppm]`
//! here, `[ppm]` by [`FrameModel::build`]. Errors name the key.

use super::schema::{Config, CpuChoice, FailsafeAction, IngressSection, OutputSpec};
use super::{ConfigError, OutputPlan};
use crate::frame::FrameModel;
use crate::frame::PpmSection;
use crate::mavlink;
use crate::wire::LineKind;
use std::path::PathBuf;

impl Config {
    /// Checks every key of this configuration as one output's (an
    /// `[[outputs]]` file is checked whole by [`Plan::resolve`](super::Plan::resolve))
    /// and builds its frame model.
    pub fn validate(&self) -> Result<FrameModel, ConfigError> {
        self.lower().map(|p| p.model)
    }

    /// Checks every key of this configuration as one output's and lowers
    /// it, each value parsed once, into the output's plan: what the
    /// programs run (the frame model, the parsed line, allowlists,
    /// read-back and MAVLink settings).
    pub(crate) fn lower(&self) -> Result<OutputPlan, ConfigError> {
        validate_name(&self.name)?;
        let i = &self.ingress;
        if !(4096..=16 * 1024 * 1024).contains(&i.recv_buffer_bytes) {
            return Err(ConfigError::invalid(
                "ingress.recv_buffer_bytes",
                format!("{} is outside 4096..=16777216 bytes", i.recv_buffer_bytes),
            ));
        }
        let allow = self.allow()?;
        let status_allow = self.status_allow()?;
        if i.priority > 99 {
            return Err(ConfigError::invalid(
                "ingress.priority",
                format!("{} is outside 0..=99 (0: normal scheduler)", i.priority),
            ));
        }
        if i.priority > 0 && i.priority >= self.rt.priority {
            return Err(ConfigError::invalid(
                "ingress.priority",
                format!(
                    "{} is not below rt.priority = {}: ppmd's timing thread must be able to preempt the receive thread",
                    i.priority, self.rt.priority
                ),
            ));
        }
        // "last" is resolved by udp-ingress, which knows the online CPUs.
        busy_poll_cpu(
            i,
            match self.rt.cpu {
                CpuChoice::Index(r) => Some(r),
                _ => None,
            },
        )?;
        let output = self.output()?;
        if !(50_000..=20_000_000).contains(&self.ppmd.spi_hz) {
            return Err(ConfigError::invalid(
                "ppmd.spi_hz",
                format!(
                    "{} Hz is outside 50000..=20000000 (1000000: edges to 1 us)",
                    self.ppmd.spi_hz
                ),
            ));
        }
        let spec = self.ppm.protocol.spec();
        (spec.check_line)(line_kind(&output), self.ppm.idle_level, &self.ppmd.output)
            .map_err(|(key, message)| ConfigError::invalid(key, message))?;
        let readback = self.readback_plan()?;
        let pilot = self.pilot_plan()?;
        if self.ppm.protocol != crate::wire::Protocol::Crsf
            && self.ppm.crsf_target == crate::wire::crsf::CrsfTarget::Module
        {
            return Err(ConfigError::invalid(
                "ppm.crsf_target",
                format!(
                    "\"module\" drives an ExpressLRS module with CRSF, and ppm.protocol is \"{}\": set ppm.protocol = \"crsf\", or remove ppm.crsf_target",
                    self.ppm.protocol.name()
                ),
            ));
        }
        if self.ppm.protocol == crate::wire::Protocol::Crsf
            && self.ppm.crsf_target == crate::wire::crsf::CrsfTarget::Module
            && pilot.is_none()
        {
            return Err(ConfigError::invalid(
                "ppmd.pilot",
                "ppm.crsf_target = \"module\" drives a transmitter module directly, with no radio and no trainer switch between ppm and the link, so a person must be able to take over: read a pilot's radio (its trainer output, PPM) with ppmd.pilot = \"gpio:LINE\" and name its takeover switch with pilot.switch_channel (see docs/crsf.md)",
            ));
        }
        if pilot.is_some() && readback.is_some() {
            return Err(ConfigError::invalid(
                "ppmd.pilot",
                "an output reads either its radio back (ppmd.readback) or a pilot's radio (ppmd.pilot), not both: the takeover state each reports is the output's one state; remove one",
            ));
        }
        for (key, action) in [
            ("failsafe.action", self.failsafe.action),
            ("failsafe.startup", self.failsafe.startup),
        ] {
            if action == FailsafeAction::Flag && !spec.failsafe_flag {
                return Err(ConfigError::invalid(
                    key,
                    format!(
                        "\"flag\" sets SBUS's failsafe flag, and {} has none: use \"silence\", \"hold\" or \"default\" (or ppm.protocol = \"sbus\")",
                        spec.title
                    ),
                ));
            }
        }
        for (key, mb) in [
            ("ppmd.frame_log_max_mb", self.ppmd.frame_log_max_mb),
            ("ppmd.trace_max_mb", self.ppmd.trace_max_mb),
        ] {
            if !(1..=65_536).contains(&mb) {
                return Err(ConfigError::invalid(
                    key,
                    format!("{mb} MiB is outside 1..=65536"),
                ));
            }
        }
        let rt = &self.rt;
        if rt.priority > 99 {
            return Err(ConfigError::invalid(
                "rt.priority",
                format!("{} is outside 0..=99 (0: normal scheduler)", rt.priority),
            ));
        }
        if rt.spin_margin_max_us > 5_000 {
            return Err(ConfigError::invalid(
                "rt.spin_margin_max_us",
                format!("{} us is outside 0..=5000", rt.spin_margin_max_us),
            ));
        }
        if rt.spin_margin_min_us > rt.spin_margin_max_us {
            return Err(ConfigError::invalid(
                "rt.spin_margin_min_us",
                format!(
                    "{} us is above rt.spin_margin_max_us = {} us",
                    rt.spin_margin_min_us, rt.spin_margin_max_us
                ),
            ));
        }
        if !(1..=60_000).contains(&self.failsafe.after_ms) {
            return Err(ConfigError::invalid(
                "failsafe.after_ms",
                format!("{} ms is outside 1..=60000", self.failsafe.after_ms),
            ));
        }
        if self.failsafe.startup == FailsafeAction::Hold {
            return Err(ConfigError::invalid(
                "failsafe.startup",
                "\"hold\" has no command to hold before the first one: use \"silence\" or \"default\"",
            ));
        }
        if self.ipc.root.as_os_str().is_empty() || !self.ipc.root.is_absolute() {
            return Err(ConfigError::invalid(
                "ipc.root",
                format!(
                    "`{}` must be an absolute directory path",
                    self.ipc.root.display()
                ),
            ));
        }
        let model = FrameModel::build(&self.resolved_ppm(&output))?;
        Ok(OutputPlan {
            name: self.name.clone(),
            mavlink: self.mavlink_settings(&model)?,
            model,
            output,
            frame_log: self.ppmd.frame_log.clone(),
            readback,
            pilot,
            ingress: self.ingress.clone(),
            allow,
            status_allow,
            seq_file: self.seq_file(),
            failsafe: self.failsafe.clone(),
            keys: self.set.clone(),
        })
    }

    /// `[mavlink]` against the output's channels (`model`, from
    /// [`Config::validate`]).
    pub fn mavlink_settings(&self, model: &FrameModel) -> Result<mavlink::Settings, ConfigError> {
        let m = &self.mavlink;
        for (key, id) in [
            ("mavlink.system_id", m.system_id),
            ("mavlink.component_id", m.component_id),
        ] {
            if id == 0 {
                return Err(ConfigError::invalid(
                    key,
                    "0 is outside 1..=255 (0 addresses every system or component)",
                ));
            }
        }
        let channel = |key: &str, name: &str| {
            model.index_of(name).ok_or_else(|| {
                ConfigError::invalid(
                    key,
                    format!(
                        "no channel `{name}`; channels are {}",
                        model.names().join(", ")
                    ),
                )
            })
        };
        let axes = match &m.axes {
            None => mavlink::Settings::defaults_for(model).axes,
            Some(names) => {
                let [x, y, z, r] = &names[..] else {
                    return Err(ConfigError::invalid(
                        "mavlink.axes",
                        format!(
                            "{} names, 4 wanted: the channels of x, y, z and r, or \"none\"",
                            names.len()
                        ),
                    ));
                };
                let mut axes = [None; 4];
                for (a, name) in axes.iter_mut().zip([x, y, z, r]) {
                    if name != "none" {
                        *a = Some(channel("mavlink.axes", name)?);
                    }
                }
                axes
            }
        };
        if m.buttons.len() > 32 {
            return Err(ConfigError::invalid(
                "mavlink.buttons",
                format!("{} names, MANUAL_CONTROL has 32 buttons", m.buttons.len()),
            ));
        }
        let buttons = m
            .buttons
            .iter()
            .map(|name| channel("mavlink.buttons", name))
            .collect::<Result<Vec<_>, _>>()?;
        if m.rc_channels_hz > mavlink::RC_CHANNELS_MAX_HZ {
            return Err(ConfigError::invalid(
                "mavlink.rc_channels_hz",
                format!(
                    "{} is above {}: ppmd reports its line ten times a second",
                    m.rc_channels_hz,
                    mavlink::RC_CHANNELS_MAX_HZ
                ),
            ));
        }
        Ok(mavlink::Settings {
            system_id: m.system_id,
            component_id: m.component_id,
            axes,
            thrust: m.thrust,
            buttons,
            key_file: m.key_file.clone(),
            timestamp_file: Some(self.mavlink_timestamp_file()),
            rc_channels_hz: m.rc_channels_hz,
            vehicle_type: m.vehicle_type,
        })
    }

    /// `[ppm]` with the idle level the protocol takes on `output` when the
    /// key is not given ([`crate::wire::Spec::line_idle_level`]).
    fn resolved_ppm(&self, output: &OutputSpec) -> PpmSection {
        let mut ppm = self.ppm.clone();
        if ppm.idle_level.is_none() {
            ppm.idle_level = (ppm.protocol.spec().line_idle_level)(line_kind(output));
        }
        ppm
    }

    /// The address blocks of `ingress.allow` (a bare address is a block of one).
    pub fn allow(&self) -> Result<Vec<ipnet::IpNet>, ConfigError> {
        self.ingress
            .allow
            .iter()
            .map(|s| parse_net(s).map_err(|m| ConfigError::invalid("ingress.allow", m)))
            .collect()
    }

    /// The address blocks of `ingress.status_allow`.
    pub fn status_allow(&self) -> Result<Vec<ipnet::IpNet>, ConfigError> {
        self.ingress
            .status_allow
            .iter()
            .map(|s| parse_net(s).map_err(|m| ConfigError::invalid("ingress.status_allow", m)))
            .collect()
    }

    /// The file udp-ingress keeps the last accepted signed `seq` in:
    /// `ingress.seq_file`, by default `<ipc.root>/<name>.last_seq`.
    pub fn seq_file(&self) -> PathBuf {
        self.ingress
            .seq_file
            .clone()
            .unwrap_or_else(|| self.ipc.root.join(format!("{}.last_seq", self.name)))
    }

    /// The file udp-ingress keeps the newest MAVLink signing timestamp in:
    /// `mavlink.timestamp_file`, by default
    /// `<ipc.root>/<name>.mavlink_timestamp`.
    pub fn mavlink_timestamp_file(&self) -> PathBuf {
        self.mavlink.timestamp_file.clone().unwrap_or_else(|| {
            self.ipc
                .root
                .join(format!("{}.mavlink_timestamp", self.name))
        })
    }

    /// The read-back `ppmd.readback` and `[readback]` describe, checked:
    /// errors name the key.
    pub fn readback_plan(&self) -> Result<Option<super::ReadbackPlan>, ConfigError> {
        let Some(input) = &self.ppmd.readback else {
            return Ok(None);
        };
        let input: crate::capture::InputSpec = input
            .parse()
            .map_err(|m| ConfigError::invalid("ppmd.readback", m))?;
        if !self.ppm.protocol.spec().reads_back {
            return Err(ConfigError::invalid(
                "ppmd.readback",
                "a read-back reads PPM (a radio's module bay set to PPM), and compares it with a PPM output's frames: set ppm.protocol = \"ppm\", or remove ppmd.readback",
            ));
        }
        let r = &self.readback;
        for (key, v, lo, hi, unit) in [
            ("readback.tolerance_us", r.tolerance_us, 1, 500, " us"),
            ("readback.window_ms", r.window_ms, 10, 2_000, " ms"),
            ("readback.frames", r.frames as u32, 1, 10, ""),
            (
                "readback.channels",
                r.channels.unwrap_or(1) as u32,
                1,
                16,
                "",
            ),
        ] {
            if !(lo..=hi).contains(&v) {
                return Err(ConfigError::invalid(
                    key,
                    format!("{v}{unit} is outside {lo}..={hi}"),
                ));
            }
        }
        Ok(Some(super::ReadbackPlan {
            input,
            log: self.ppmd.readback_log.clone(),
            capture: crate::capture::CaptureSettings {
                idle: r.idle_level,
                channels: r.channels,
            },
            matching: crate::capture::MatchSettings {
                tolerance_ns: r.tolerance_us * 1_000,
                window_ns: r.window_ms as u64 * 1_000_000,
                frames: r.frames,
            },
        }))
    }

    /// The pilot's radio `ppmd.pilot` and `[pilot]` describe, checked:
    /// errors name the key.
    pub fn pilot_plan(&self) -> Result<Option<super::PilotPlan>, ConfigError> {
        let Some(input) = &self.ppmd.pilot else {
            return Ok(None);
        };
        let input: crate::capture::InputSpec = input
            .parse()
            .map_err(|m| ConfigError::invalid("ppmd.pilot", m))?;
        let p = &self.pilot;
        let Some(switch) = p.switch_channel else {
            return Err(ConfigError::invalid(
                "pilot.switch_channel",
                "ppmd.pilot needs the channel of the pilot's radio that carries the takeover switch (1..=16, as the radio numbers its trainer output's channels): set pilot.switch_channel",
            ));
        };
        let channels = p.channels.unwrap_or(16);
        for (key, v, lo, hi, unit) in [
            ("pilot.channels", u32::from(channels), 1, 16, ""),
            (
                "pilot.switch_channel",
                u32::from(switch),
                1,
                u32::from(channels.clamp(1, 16)),
                "",
            ),
            (
                "pilot.switch_above_us",
                p.switch_above_us,
                900,
                2_100,
                " us",
            ),
        ] {
            if !(lo..=hi).contains(&v) {
                return Err(ConfigError::invalid(
                    key,
                    format!("{v}{unit} is outside {lo}..={hi}"),
                ));
            }
        }
        Ok(Some(super::PilotPlan {
            input,
            capture: crate::capture::CaptureSettings {
                idle: p.idle_level,
                channels: p.channels,
            },
            switch_channel: usize::from(switch) - 1,
            switch_above_ns: u64::from(p.switch_above_us) * 1_000,
        }))
    }

    /// `ppmd.output`, parsed.
    pub fn output(&self) -> Result<OutputSpec, ConfigError> {
        self.ppmd
            .output
            .parse()
            .map_err(|m| ConfigError::invalid("ppmd.output", m))
    }
}

/// What kind of line `output` is, as a protocol's line check sees it.
fn line_kind(output: &OutputSpec) -> LineKind {
    match output {
        OutputSpec::Gpio { .. } => LineKind::Gpio,
        OutputSpec::Spi { .. } => LineKind::Spi,
        OutputSpec::Sim { whole: true, .. } => LineKind::SimWhole,
        OutputSpec::Sim { .. } => LineKind::Sim,
        OutputSpec::Serial { .. } => LineKind::Serial,
    }
}

/// Refuses a busy-polling receive thread pinned to the CPU of ppmd's
/// timing thread: `rt_cpu` is `rt.cpu` resolved on this machine.
pub(crate) fn busy_poll_cpu(
    ingress: &IngressSection,
    rt_cpu: Option<usize>,
) -> Result<(), ConfigError> {
    match (ingress.busy_poll, ingress.cpu.index(), rt_cpu) {
        (true, Some(c), Some(r)) if c == r => Err(ConfigError::invalid(
            "ingress.cpu",
            format!(
                "busy_poll would spin on CPU {c}, the CPU ppmd's timing thread is pinned to (rt.cpu): pick another CPU"
            ),
        )),
        _ => Ok(()),
    }
}

/// Parses an address block, `10.0.0.0/24` or `::1/128`; a bare address is a
/// block of one.
pub fn parse_net(s: &str) -> Result<ipnet::IpNet, String> {
    let s = s.trim();
    s.parse::<ipnet::IpNet>()
        .or_else(|e| {
            s.parse::<std::net::IpAddr>()
                .map(ipnet::IpNet::from)
                .map_err(|_| e)
        })
        .map_err(|e| {
            format!(
                "`{s}` is not an address block such as 10.0.0.0/24, 127.0.0.1/32 or ::1/128 ({e})"
            )
        })
}

/// Checks an output name (used in shared-memory service names and file names).
pub fn validate_name(name: &str) -> Result<(), ConfigError> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
    if ok {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            "name",
            format!("`{name}` must be 1..=64 letters, digits, `-` or `_`"),
        ))
    }
}
