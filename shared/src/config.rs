//! The configuration file (TOML) read by both `ppmd` and `udp-ingress`.
//!
//! Every key is optional; a missing key takes the default documented on its
//! field. Unknown keys are errors, so a typo cannot silently fall back to a
//! default. [`Config::load`] parses, [`Config::validate`] validates the PPM
//! settings against what real transmitters accept; both errors name the key.

use crate::frame::{
    us_to_ns, ChannelSpec, FrameModel, Level, ModelSpec, UnitMapping, MAX_CHANNELS, PULSE_MIN_US,
};
use crate::receiver::ReceiverChoice;
use crate::receiver::{Rules, CHANNEL_MARGIN_US, SYNC_MARGIN_US};
pub use crate::signal::Timing;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

pub use crate::signal::{CHANNEL_MAX_US, CHANNEL_MIN_US, SYNC_MAX_US, SYNC_MIN_US};
/// The longest sync `follow` timing leaves, for every receiver: EdgeTX's
/// 19 ms less [`crate::receiver::SYNC_MARGIN_US`]. A `follow` frame that
/// comes late is moved later only while its sync stays under this.
pub const FOLLOW_SYNC_CEILING_US: f64 = SYNC_MAX_US - crate::receiver::SYNC_MARGIN_US;

/// Why a configuration was refused. Every variant names the file or the key.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read (why: its source).
    #[error("cannot read config file {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is not valid TOML, has an unknown key or a value of the wrong type.
    #[error("config file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    /// A key has a value a transmitter would reject or misread.
    #[error("config key `{key}`: {message}")]
    Invalid { key: String, message: String },
    /// A command-line choice does not fit the configuration.
    #[error("{0}")]
    Usage(String),
}

impl ConfigError {
    fn invalid(key: impl Into<String>, message: impl Into<String>) -> Self {
        ConfigError::Invalid {
            key: key.into(),
            message: message.into(),
        }
    }

    /// The key this error is about, when it is about one key.
    pub fn key(&self) -> Option<&str> {
        match self {
            ConfigError::Invalid { key, .. } => Some(key),
            _ => None,
        }
    }
}

/// The whole configuration file.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Name of the output; `udp-ingress` and `ppmd` with the same name find
    /// each other. Letters, digits, `-` and `_`. Default `"ppm"`.
    pub name: String,
    /// The PPM signal.
    pub ppm: PpmSection,
    /// The UDP receiver.
    pub ingress: IngressSection,
    /// The PPM daemon.
    pub ppmd: PpmdSection,
    /// Real-time setup of ppmd's timing thread.
    pub rt: RtSection,
    /// What ppmd does when commands stop.
    pub failsafe: FailsafeSection,
    /// Shared memory between the two processes.
    pub ipc: IpcSection,
    /// `[[outputs]]`: several outputs driven by one ppmd, each a full
    /// configuration: the top-level sections with the entry's keys laid over
    /// them (see [`Config::outputs`]). Empty when the file has no
    /// `[[outputs]]`: the file then describes one output.
    #[serde(skip)]
    pub outputs: Vec<Config>,
    /// For each entry of `outputs`, the keys the entry sets itself (dotted,
    /// as in error messages), to name the right key when one is refused.
    #[serde(skip)]
    entry_keys: Vec<Vec<String>>,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            name: "ppm".into(),
            ppm: PpmSection::default(),
            ingress: IngressSection::default(),
            ppmd: PpmdSection::default(),
            rt: RtSection::default(),
            failsafe: FailsafeSection::default(),
            ipc: IpcSection::default(),
            outputs: Vec::new(),
            entry_keys: Vec::new(),
        }
    }
}

/// `[ppm]`: the signal a transmitter's trainer port receives.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PpmSection {
    /// Number of channels in a frame, 1..=16. Default 8.
    pub channels: u32,
    /// Frame length in microseconds (frame start to next frame start). Default 22500.
    pub frame_us: f64,
    /// Width of the separator pulse before every channel, in microseconds. Default 300.
    pub pulse_us: f64,
    /// Line level between pulses and while silent: `"low"` or `"high"`. Default `"low"`.
    pub idle_level: Level,
    /// Channel order of the transmitter, a permutation of the letters A (aileron),
    /// E (elevator), T (throttle), R (rudder): `"AETR"` (default), `"TAER"`,
    /// `"ATER"`, ... Channels after the fourth are `aux1`, `aux2`, ...
    pub order: String,
    /// Default value of every channel, in microseconds. Default 1500; the
    /// throttle channel defaults to its minimum instead (zero actuation).
    pub default_us: f64,
    /// Lowest value of every channel; commands below it are clamped. Default 1000.
    pub min_us: f64,
    /// Highest value of every channel; commands above it are clamped. Default 2000.
    pub max_us: f64,
    /// Per-channel overrides, keyed by channel name: `[ppm.channel.thr]`.
    pub channel: BTreeMap<String, ChannelOverride>,
    /// The receiver the signal is for: `"any"` (default: what EdgeTX,
    /// OpenTX, Betaflight and ArduPilot all read), `"edgetx"` (2.10 and
    /// later), `"opentx"` (and EdgeTX before 2.10), `"betaflight"` or
    /// `"ardupilot"`. Settings it would misread are refused at start.
    pub receiver: ReceiverChoice,
    /// When frames start: `"grid"` (default: every `frame_us`, whenever
    /// commands come) or `"follow"` (a fresh command starts its frame as soon
    /// as the previous frame's sync allows; see [`Timing`]).
    pub timing: Timing,
    /// `follow`: the shortest sync gap left before a frame, in microseconds,
    /// at least 4500 (EdgeTX's 4000 us plus a margin; 3200 for Betaflight or
    /// ArduPilot alone). Default 5000.
    pub follow_sync_min_us: f64,
    /// `follow`: the longest sync gap; when no fresh command has come by
    /// then, the last frame is repeated (or the failsafe acts). At most
    /// 18500 (EdgeTX's 19000 us less a margin), and not below
    /// `follow_sync_min_us`. Default 18000.
    pub follow_sync_max_us: f64,
}

impl Default for PpmSection {
    fn default() -> Self {
        PpmSection {
            channels: 8,
            frame_us: 22_500.0,
            pulse_us: 300.0,
            idle_level: Level::Low,
            order: "AETR".into(),
            default_us: 1_500.0,
            min_us: 1_000.0,
            max_us: 2_000.0,
            channel: BTreeMap::new(),
            receiver: ReceiverChoice::Any,
            timing: Timing::Grid,
            follow_sync_min_us: 5_000.0,
            follow_sync_max_us: 18_000.0,
        }
    }
}

/// `[ppm.channel.NAME]`: limits of one channel; an absent key takes the
/// `[ppm]` value.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelOverride {
    /// This channel's default in microseconds.
    pub default_us: Option<f64>,
    /// This channel's minimum in microseconds.
    pub min_us: Option<f64>,
    /// This channel's maximum in microseconds.
    pub max_us: Option<f64>,
    /// Lower end of the channel's engineering-unit range (e.g. -15.0 degrees);
    /// `unit_min` and `unit_max` are given both or neither. With them,
    /// commands may use the `units` form for this channel.
    pub unit_min: Option<f64>,
    /// Upper end of the engineering-unit range, above `unit_min`.
    pub unit_max: Option<f64>,
    /// Microseconds `unit_min` (and `norm` -1) maps to, 800..=2200. Default `min_us`.
    pub unit_us_min: Option<f64>,
    /// Microseconds `unit_max` (and `norm` +1) maps to, 800..=2200, above
    /// `unit_us_min`. Default `max_us`.
    pub unit_us_max: Option<f64>,
    /// Swaps the direction of the `units` and `norm` mappings. Default false.
    #[serde(default)]
    pub reverse: bool,
    /// Added to a `units` or `norm` value after the mapping, in microseconds,
    /// -500..=500. Default 0.
    #[serde(default)]
    pub trim_us: f64,
    /// A label for the unit (`"deg"`, `"m/s"`, ...), for people reading the
    /// configuration; needs a unit range.
    pub unit: Option<String>,
}

/// `[ingress]`: the UDP side.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IngressSection {
    /// Address and port to receive commands on. Default `"127.0.0.1:5005"`
    /// (this machine only); use `"0.0.0.0:5005"` to accept a groundstation's.
    pub listen: SocketAddr,
    /// Socket receive buffer (SO_RCVBUF) in bytes, 4096..=16777216. Default
    /// 262144: the kernel drops the newest datagrams when it is full, so it
    /// must not be tiny.
    pub recv_buffer_bytes: u32,
    /// Shortest interval between two log lines about rejected datagrams of one
    /// reason, in milliseconds. Default 1000.
    pub reject_log_interval_ms: u64,
    /// Key file for authenticated commands (64 hex characters, mode 600).
    /// When set, only signed commands are applied. Default: none (also
    /// `udp-ingress --auth-key FILE`).
    pub auth_key: Option<PathBuf>,
    /// Where the last accepted signed `seq` is kept across restarts, so a
    /// replayed command stays refused. Default `<ipc.root>/<name>.last_seq`.
    pub seq_file: Option<PathBuf>,
    /// Sources allowed to send, as address blocks (`"10.0.0.0/24"`,
    /// `"::1/128"`, or a bare address). Default empty: any source.
    pub allow: Vec<String>,
    /// Sources that get the full status reply to any status query, as
    /// address blocks. Others get it only for a query padded to at least a
    /// third of the reply's size (whitespace after the JSON), and otherwise
    /// `{"pad_to": N}`: no reply is more than 3 times its query, so a spoofed
    /// query cannot make the ingress an amplifier. Default: the loopback
    /// blocks (`127.0.0.0/8`, `::1/128`), which no remote sender can spoof.
    pub status_allow: Vec<String>,
    /// SCHED_FIFO priority of the receive thread, 1..=99 and below
    /// `rt.priority` (ppmd's timing thread must preempt it), or 0 for the
    /// normal scheduler (default).
    pub priority: u8,
    /// CPU the receive thread is pinned to: a number, or `"none"` (default).
    pub cpu: IngressCpu,
    /// Spin on the socket instead of sleeping until a datagram arrives: the
    /// receive thread never sleeps and takes one whole CPU, which must not be
    /// ppmd's (`rt.cpu`). Default false.
    pub busy_poll: bool,
}

impl Default for IngressSection {
    fn default() -> Self {
        IngressSection {
            listen: SocketAddr::from(([127, 0, 0, 1], 5005)),
            recv_buffer_bytes: 256 * 1024,
            reject_log_interval_ms: 1_000,
            auth_key: None,
            seq_file: None,
            allow: Vec::new(),
            status_allow: vec!["127.0.0.0/8".into(), "::1/128".into()],
            priority: 0,
            cpu: IngressCpu::None,
            busy_poll: false,
        }
    }
}

/// `[ppmd]`: the daemon that emits the signal.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PpmdSection {
    /// Where the signal goes: `"sim"` (simulated line, trace in
    /// `ppm-NAME.trace`), `"sim:PATH"`, `"gpio:CHIP:LINE"`, or
    /// `"spi:DEVICE"` (a spidev device, e.g. `/dev/spidev0.0`: each frame
    /// one transfer on MOSI, its edges exact to the bit clock). Default `"sim"`.
    pub output: String,
    /// Frame log: one JSON line per emitted frame and per line-state change,
    /// appended to this file. Default: none (also `ppmd --frame-log FILE`).
    pub frame_log: Option<PathBuf>,
    /// Size at which the frame log is rotated (FILE.1, FILE.2, FILE.3 are
    /// kept), in MiB, 1..=65536. Default 64.
    pub frame_log_max_mb: u64,
    /// Size at which a sim trace is rotated (FILE.1 is kept), in MiB,
    /// 1..=65536. Default 256 (about 2.5 h of 8 channels at 50 Hz).
    pub trace_max_mb: u64,
    /// Bit rate of an `spi:` output, Hz, 50000..=20000000: one bit is the
    /// resolution of every edge inside a frame (1 us at the default
    /// 1000000, 0.5 us at 2000000, EdgeTX's capture tick).
    pub spi_hz: u32,
}

impl Default for PpmdSection {
    fn default() -> Self {
        PpmdSection {
            output: "sim".into(),
            frame_log: None,
            frame_log_max_mb: 64,
            trace_max_mb: 256,
            spi_hz: 1_000_000,
        }
    }
}

/// `[rt]`: real-time setup of ppmd's timing thread. When a setting cannot be
/// had, ppmd stops at start with a message saying how to fix it, unless
/// `allow_degraded` is set.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RtSection {
    /// SCHED_FIFO priority 1..=99, or 0 for the normal scheduler. Default 80.
    pub priority: u8,
    /// CPU the timing thread is pinned to: a number (an isolated CPU is
    /// fine), `"last"` (the highest-numbered online CPU, default) or `"none"`.
    pub cpu: CpuChoice,
    /// Lock all memory (mlockall) and prefault the stack. Default true.
    pub mlock: bool,
    /// Hold /dev/cpu_dma_latency at 0 (no deep CPU idle states). Default true.
    pub cpu_dma_latency: bool,
    /// Run on, marked degraded, when a setting cannot be had. Default false.
    pub allow_degraded: bool,
    /// How long before each edge ppmd stops sleeping and spins on the clock:
    /// microseconds 0..=5000, or `"auto"` (default) to follow the wake-up
    /// lateness actually observed, within the two bounds below.
    pub spin_margin_us: SpinMargin,
    /// Smallest automatic margin, microseconds. Default 20.
    pub spin_margin_min_us: u32,
    /// Largest automatic margin (and the starting one), microseconds. Default 1000.
    pub spin_margin_max_us: u32,
}

impl Default for RtSection {
    fn default() -> Self {
        RtSection {
            priority: 80,
            cpu: CpuChoice::Last,
            mlock: true,
            cpu_dma_latency: true,
            allow_degraded: false,
            spin_margin_us: SpinMargin::Auto,
            spin_margin_min_us: 20,
            spin_margin_max_us: 1_000,
        }
    }
}

/// Which CPU the timing thread runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "NumberOrWord")]
pub enum CpuChoice {
    /// Not pinned.
    None,
    /// The highest-numbered online CPU.
    Last,
    /// This CPU.
    Index(usize),
}

/// Which CPU udp-ingress's receive thread runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "NumberOrWord")]
pub enum IngressCpu {
    /// Not pinned.
    None,
    /// This CPU.
    Index(usize),
}

impl IngressCpu {
    /// The CPU, when pinned.
    pub fn index(self) -> Option<usize> {
        match self {
            IngressCpu::None => None,
            IngressCpu::Index(i) => Some(i),
        }
    }
}

impl std::str::FromStr for IngressCpu {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let v = match s.trim().parse::<i64>() {
            Ok(n) => NumberOrWord::Number(n),
            Err(_) => NumberOrWord::Word(s.trim().to_string()),
        };
        IngressCpu::try_from(v)
    }
}

/// The spin margin before each edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "NumberOrWord")]
pub enum SpinMargin {
    /// Follows the observed wake-up lateness.
    Auto,
    /// Fixed, in microseconds.
    Fixed(u32),
}

/// A TOML value that is either a whole number or a word.
#[derive(Deserialize)]
#[serde(untagged)]
enum NumberOrWord {
    Number(i64),
    Word(String),
}

impl TryFrom<NumberOrWord> for CpuChoice {
    type Error = String;
    fn try_from(v: NumberOrWord) -> Result<Self, String> {
        match v {
            NumberOrWord::Number(n) if (0..4096).contains(&n) => Ok(CpuChoice::Index(n as usize)),
            NumberOrWord::Word(w) if w == "last" => Ok(CpuChoice::Last),
            NumberOrWord::Word(w) if w == "none" => Ok(CpuChoice::None),
            _ => Err("rt.cpu must be a CPU number, \"last\" or \"none\"".into()),
        }
    }
}

impl TryFrom<NumberOrWord> for IngressCpu {
    type Error = String;
    fn try_from(v: NumberOrWord) -> Result<Self, String> {
        match v {
            NumberOrWord::Number(n) if (0..4096).contains(&n) => Ok(IngressCpu::Index(n as usize)),
            NumberOrWord::Word(w) if w == "none" => Ok(IngressCpu::None),
            _ => Err("ingress.cpu must be a CPU number or \"none\"".into()),
        }
    }
}

impl TryFrom<NumberOrWord> for SpinMargin {
    type Error = String;
    fn try_from(v: NumberOrWord) -> Result<Self, String> {
        match v {
            NumberOrWord::Number(n) if (0..=5_000).contains(&n) => Ok(SpinMargin::Fixed(n as u32)),
            NumberOrWord::Word(w) if w == "auto" => Ok(SpinMargin::Auto),
            _ => Err("rt.spin_margin_us must be \"auto\" or 0..=5000 microseconds".into()),
        }
    }
}

/// `[failsafe]`: what happens when commands stop arriving.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FailsafeSection {
    /// A command older than this (by its ingress receive time) is no longer
    /// fresh, in milliseconds, 1..=60000. Default 200.
    pub after_ms: u64,
    /// What ppmd emits then: `"silence"` (no pulses, the transmitter falls back
    /// to its own sticks; default), `"hold"` (repeat the last command) or
    /// `"default"` (the configured default of every channel).
    pub action: FailsafeAction,
    /// What ppmd emits from start until the first command: `"silence"`
    /// (default) or `"default"` (`"hold"` has nothing to hold yet).
    pub startup: FailsafeAction,
}

impl Default for FailsafeSection {
    fn default() -> Self {
        FailsafeSection {
            after_ms: 200,
            action: FailsafeAction::Silence,
            startup: FailsafeAction::Silence,
        }
    }
}

/// What ppmd emits when commands stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FailsafeAction {
    /// Stop the pulses; the line rests at its idle level.
    Silence,
    /// Repeat the last command.
    Hold,
    /// Emit every channel's default.
    Default,
}

/// `[ipc]`: the shared memory between udp-ingress and ppmd.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IpcSection {
    /// Directory for the shared-memory bookkeeping files of both processes.
    /// Both must see the same directory: under systemd with `PrivateTmp=yes`
    /// pick one outside /tmp (for example `/run/ppm`). Default `/tmp/ppm`.
    pub root: PathBuf,
}

impl Default for IpcSection {
    fn default() -> Self {
        IpcSection {
            root: PathBuf::from("/tmp/ppm"),
        }
    }
}

/// Where ppmd sends the signal.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum OutputSpec {
    /// The simulated line: every edge is written to a trace file.
    Sim { path: Option<PathBuf> },
    /// A GPIO line through the GPIO character device.
    Gpio { chip: String, line: String },
    /// A spidev device: each frame is one SPI transfer on MOSI.
    Spi { device: PathBuf },
}

impl std::str::FromStr for OutputSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.split_once(':') {
            None if s == "sim" => Ok(OutputSpec::Sim { path: None }),
            Some(("sim", path)) if !path.is_empty() => Ok(OutputSpec::Sim {
                path: Some(PathBuf::from(path)),
            }),
            Some(("spi", device)) if !device.is_empty() => Ok(OutputSpec::Spi {
                device: PathBuf::from(device),
            }),
            Some(("spi", _)) => Err(format!(
                "`{s}`: an spi output is spi:DEVICE, e.g. spi:/dev/spidev0.0"
            )),
            Some(("gpio", rest)) => match rest.rsplit_once(':') {
                Some((chip, line)) if !chip.is_empty() && !line.is_empty() => {
                    Ok(OutputSpec::Gpio {
                        chip: chip.into(),
                        line: line.into(),
                    })
                }
                _ => Err(format!(
                    "`{s}`: a gpio output is gpio:CHIP:LINE, e.g. gpio:gpiochip0:18"
                )),
            },
            _ => Err(format!(
                "`{s}` is not an output: use sim, sim:PATH, gpio:CHIP:LINE or spi:DEVICE"
            )),
        }
    }
}

impl Config {
    /// Reads (a regular file of at most
    /// [`CONFIG_MAX_BYTES`](crate::files::CONFIG_MAX_BYTES)) and parses a
    /// configuration file. The PPM settings are checked by
    /// [`Config::validate`].
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text =
            crate::files::read_small(path, crate::files::CONFIG_MAX_BYTES).map_err(|source| {
                ConfigError::Read {
                    path: path.to_owned(),
                    source,
                }
            })?;
        Config::parse(&text).map_err(|e| match e {
            ConfigError::Parse { message, .. } => ConfigError::Parse {
                path: path.to_owned(),
                message,
            },
            other => other,
        })
    }

    /// Reads `path` when given, else the defaults (every key has one).
    pub fn load_or_default(path: Option<&Path>) -> Result<Config, ConfigError> {
        path.map_or_else(|| Ok(Config::default()), Config::load)
    }

    /// Parses configuration text (see [`Config::load`]).
    pub fn parse(text: &str) -> Result<Config, ConfigError> {
        let parse_error = |message: String| ConfigError::Parse {
            path: PathBuf::from("<text>"),
            message: message.trim_end().replace('\n', " | "),
        };
        let mut table: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| parse_error(e.to_string()))?;
        let entries = match table.remove("outputs") {
            None => Vec::new(),
            Some(toml::Value::Array(a)) => a,
            Some(_) => {
                return Err(parse_error(
                    "`outputs` must be an array of tables: write each output as [[outputs]]".into(),
                ))
            }
        };
        let mut cfg: Config = toml::Value::Table(table.clone())
            .try_into()
            .map_err(|e: toml::de::Error| parse_error(e.to_string()))?;
        if entries.is_empty() {
            return Ok(cfg);
        }
        for key in ["name", "ppmd.output", "ppmd.frame_log"] {
            if lookup(&table, key).is_some() {
                return Err(ConfigError::invalid(
                    key,
                    "with [[outputs]] every output sets its own `name`, `output` and `frame_log` in its entry; remove the top-level key",
                ));
            }
        }
        for (i, entry) in entries.into_iter().enumerate() {
            let toml::Value::Table(entry) = entry else {
                return Err(parse_error(format!("outputs[{i}] must be a table")));
            };
            let mut merged = table.clone();
            let mut keys = Vec::new();
            for (k, v) in entry {
                match k.as_str() {
                    "name" => {
                        keys.push("name".into());
                        merged.insert(k, v);
                    }
                    "output" | "frame_log" => {
                        keys.push(format!("ppmd.{k}"));
                        let ppmd = merged
                            .entry("ppmd")
                            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                        if let toml::Value::Table(t) = ppmd {
                            t.insert(k, v);
                        }
                    }
                    "ppm" | "ingress" | "failsafe" => {
                        collect_keys(&k, &v, &mut keys);
                        let base = merged
                            .entry(k.as_str())
                            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                        overlay(base, v);
                    }
                    _ => {
                        return Err(parse_error(format!(
                            "outputs[{i}]: unknown key `{k}`; an output entry takes name, output, frame_log and the sections [outputs.ppm], [outputs.ingress] and [outputs.failsafe] (rt, ipc, frame_log_max_mb, trace_max_mb and spi_hz are shared: set them at the top level)"
                        )))
                    }
                }
            }
            if !keys.iter().any(|k| k == "name") {
                return Err(ConfigError::invalid(
                    format!("outputs[{i}].name"),
                    "every output needs a name (udp-ingress --name NAME picks it)",
                ));
            }
            let out: Config = toml::Value::Table(merged)
                .try_into()
                .map_err(|e: toml::de::Error| parse_error(format!("outputs[{i}]: {e}")))?;
            cfg.outputs.push(out);
            cfg.entry_keys.push(keys);
        }
        Ok(cfg)
    }

    /// Checks every key and builds the PPM frame model.
    pub fn validate(&self) -> Result<FrameModel, ConfigError> {
        validate_name(&self.name)?;
        let i = &self.ingress;
        if !(4096..=16 * 1024 * 1024).contains(&i.recv_buffer_bytes) {
            return Err(ConfigError::invalid(
                "ingress.recv_buffer_bytes",
                format!("{} is outside 4096..=16777216 bytes", i.recv_buffer_bytes),
            ));
        }
        self.allow()?;
        self.status_allow()?;
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
        self.check_busy_poll_cpu(match self.rt.cpu {
            CpuChoice::Index(r) => Some(r),
            _ => None,
        })?;
        let spi = matches!(self.output()?, OutputSpec::Spi { .. });
        if !(50_000..=20_000_000).contains(&self.ppmd.spi_hz) {
            return Err(ConfigError::invalid(
                "ppmd.spi_hz",
                format!(
                    "{} Hz is outside 50000..=20000000 (1000000: edges to 1 us)",
                    self.ppmd.spi_hz
                ),
            ));
        }
        if spi && self.ppm.idle_level == Level::High {
            return Err(ConfigError::invalid(
                "ppm.idle_level",
                format!(
                    "\"high\" cannot be sent through `{}`: between transfers an SPI controller leaves MOSI low (or at the last bit), which would add an edge to every sync; use idle_level = \"low\" (an inverter in the cable gives a transmitter that wants high), or a gpio: output",
                    self.ppmd.output
                ),
            ));
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
        frame_model(&self.ppm)
    }

    /// The outputs this configuration describes: its `[[outputs]]` entries,
    /// or the configuration itself when it has none.
    pub fn output_list(&self) -> Vec<Config> {
        if self.outputs.is_empty() {
            vec![self.clone()]
        } else {
            self.outputs.clone()
        }
    }

    /// The names of the outputs, for messages.
    pub fn output_names(&self) -> Vec<String> {
        self.output_list().into_iter().map(|c| c.name).collect()
    }

    /// The one output a single-output program (udp-ingress, a tool) works
    /// with: `name` picks an `[[outputs]]` entry (required when there are
    /// several); without entries, `name` renames the file's one output.
    pub fn select(&self, name: Option<&str>) -> Result<Config, ConfigError> {
        if self.outputs.is_empty() {
            let mut c = self.clone();
            if let Some(n) = name {
                c.name = n.to_string();
            }
            return Ok(c);
        }
        match name {
            None if self.outputs.len() == 1 => Ok(self.outputs[0].clone()),
            None => Err(ConfigError::Usage(format!(
                "the configuration has {} outputs ({}): pick one with --name NAME",
                self.outputs.len(),
                self.output_names().join(", ")
            ))),
            Some(n) => self
                .outputs
                .iter()
                .find(|c| c.name == n)
                .cloned()
                .ok_or_else(|| {
                    ConfigError::Usage(format!(
                        "no output `{n}` in the configuration's [[outputs]]; its outputs: {}",
                        self.output_names().join(", ")
                    ))
                }),
        }
    }

    /// Adds an output made on ppmd's command line (`--output NAME=SPEC`):
    /// it has no keys of its own in the file, so its errors name the
    /// command-line argument.
    pub fn push_cli_output(&mut self, output: Config) {
        self.outputs.push(output);
        self.entry_keys.push(Vec::new());
    }

    /// Validates every output (see [`Config::validate`]) and what outputs
    /// must not share: names, listen addresses, lines, trace, frame-log and
    /// seq files. Errors name the key (`outputs[1].ppm.channels`, or the
    /// top-level key an output inherits).
    pub fn validate_outputs(&self) -> Result<Vec<(Config, FrameModel)>, ConfigError> {
        let list = self.output_list();
        if list.len() > MAX_OUTPUTS {
            return Err(ConfigError::invalid(
                "outputs",
                format!(
                    "{} outputs; one ppmd drives at most {MAX_OUTPUTS}",
                    list.len()
                ),
            ));
        }
        let several = list.len() > 1;
        let mut done: Vec<(Config, FrameModel)> = Vec::new();
        for (i, c) in list.into_iter().enumerate() {
            let model = c.validate().map_err(|e| self.locate(i, e))?;
            if several && matches!(c.output(), Ok(OutputSpec::Spi { .. })) {
                return Err(self.locate(
                    i,
                    ConfigError::invalid(
                        "ppmd.output",
                        format!(
                            "`{}` with other outputs: an spi output's transfer holds the timing thread for the frame, so it runs alone (start one ppmd per spi output)",
                            c.ppmd.output
                        ),
                    ),
                ));
            }
            for (j, (other, _)) in done.iter().enumerate() {
                let clash = |key: &str, what: String| {
                    Err(self.locate(
                        i,
                        ConfigError::invalid(
                            key,
                            format!("{what}, as output `{}` (outputs[{j}])", other.name),
                        ),
                    ))
                };
                if other.name == c.name {
                    return clash("name", format!("`{}` is used twice", c.name));
                }
                // Outputs made on ppmd's command line have no udp-ingress
                // settings of their own; their ingresses are started apart.
                let from_file = |k: usize| self.entry_keys.get(k).is_some_and(|k| !k.is_empty());
                if other.ingress.listen == c.ingress.listen && from_file(i) && from_file(j) {
                    return clash(
                        "ingress.listen",
                        format!(
                            "{} is the same address (each output has its own udp-ingress and port)",
                            c.ingress.listen
                        ),
                    );
                }
                if c.output_target() == other.output_target() {
                    return clash(
                        "ppmd.output",
                        format!("`{}` is the same line", c.ppmd.output),
                    );
                }
                if c.ppmd.frame_log.is_some() && c.ppmd.frame_log == other.ppmd.frame_log {
                    return clash("ppmd.frame_log", "the same frame log file".into());
                }
                if c.seq_file() == other.seq_file() {
                    return clash(
                        "ingress.seq_file",
                        format!("{} is the same seq file", c.seq_file().display()),
                    );
                }
            }
            done.push((c, model));
        }
        Ok(done)
    }

    /// What the output writes to, to find two outputs on one line or file.
    fn output_target(&self) -> Option<OutputSpec> {
        match self.output().ok()? {
            OutputSpec::Sim { path: None } => Some(OutputSpec::Sim {
                path: Some(PathBuf::from(format!("ppm-{}.trace", self.name))),
            }),
            spec => Some(spec),
        }
    }

    /// `e` as met while validating output `i`: a key the entry sets is
    /// named `outputs[i].KEY`; an inherited one keeps its top-level name and
    /// says which output it failed for.
    fn locate(&self, i: usize, e: ConfigError) -> ConfigError {
        let Some(keys) = self.entry_keys.get(i) else {
            return e;
        };
        match e {
            // An output made by ppmd's --output NAME=SPEC.
            ConfigError::Invalid { key, message } if keys.is_empty() && key == "ppmd.output" => {
                let c = &self.outputs[i];
                ConfigError::Usage(format!("--output {}={}: {message}", c.name, c.ppmd.output))
            }
            ConfigError::Invalid { key, message } => {
                let own = keys.iter().any(|k| {
                    k == &key
                        || k.starts_with(&format!("{key}."))
                        || key.starts_with(&format!("{k}."))
                });
                if own {
                    let shown = key
                        .strip_prefix("ppmd.")
                        .filter(|k| *k == "output" || *k == "frame_log")
                        .unwrap_or(&key);
                    ConfigError::Invalid {
                        key: format!("outputs[{i}].{shown}"),
                        message,
                    }
                } else if !["ppm.", "ingress.", "failsafe."]
                    .iter()
                    .any(|p| key.starts_with(p))
                {
                    ConfigError::Invalid { key, message }
                } else {
                    let name = &self.outputs[i].name;
                    ConfigError::Invalid {
                        key,
                        message: format!("{message} (inherited by output `{name}`, outputs[{i}])"),
                    }
                }
            }
            other => other,
        }
    }

    /// Refuses a busy-polling receive thread pinned to the CPU of ppmd's
    /// timing thread: `rt_cpu` is `rt.cpu` resolved on this machine.
    pub fn check_busy_poll_cpu(&self, rt_cpu: Option<usize>) -> Result<(), ConfigError> {
        match (self.ingress.busy_poll, self.ingress.cpu.index(), rt_cpu) {
            (true, Some(c), Some(r)) if c == r => Err(ConfigError::invalid(
                "ingress.cpu",
                format!(
                    "busy_poll would spin on CPU {c}, the CPU ppmd's timing thread is pinned to (rt.cpu): pick another CPU"
                ),
            )),
            _ => Ok(()),
        }
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

    /// The output named by `ppmd.output`.
    pub fn output(&self) -> Result<OutputSpec, ConfigError> {
        self.ppmd
            .output
            .parse()
            .map_err(|m| ConfigError::invalid("ppmd.output", m))
    }
}

/// Checks `[ppm]` against what transmitters accept (the receivers of
/// `ppm.receiver`) and builds the frame model; errors name the key.
pub fn frame_model(ppm: &PpmSection) -> Result<FrameModel, ConfigError> {
    let (names, limits) = resolve_channels(ppm)?;
    let mut m = ModelSpec {
        names,
        channels: Vec::new(),
        frame_ns: 0,
        pulse_ns: 0,
        idle: ppm.idle_level,
        timing: ppm.timing,
        follow_sync_ns: (0, 0),
        receiver: ppm.receiver,
    };
    let rules = ppm.receiver.rules();
    let (fewest, most) = (rules.min_channels, rules.max_channels);
    if !(fewest.0..=most.0).contains(&limits.len()) {
        let rule = if limits.len() < fewest.0 {
            fewest.1
        } else {
            most.1
        };
        return Err(invalid(
            "ppm.channels",
            format!(
                "{} channels: {rule}; under {}: use {}..={} channels, or set ppm.receiver to the one receiver you use",
                limits.len(),
                receiver_key(ppm.receiver),
                fewest.0,
                most.0
            ),
        ));
    }
    for l in &limits {
        let (lo, hi) = (rules.channel_min_us, rules.channel_max_us);
        let (key, v, bound, rule, nearest) = if l.min_us < lo.0 {
            (&l.min_key, l.min_us, lo, "raise", lo.0)
        } else if l.max_us > hi.0 {
            (&l.max_key, l.max_us, hi, "lower", hi.0)
        } else {
            continue;
        };
        return Err(invalid(
            key,
            format!(
                "{v} us: {}, less {} us for edge error, so {}..={} us under {}: {rule} {key} to {nearest} us",
                bound.1,
                CHANNEL_MARGIN_US,
                lo.0,
                hi.0,
                receiver_key(ppm.receiver),
            ),
        ));
    }
    m.channels = limits
        .iter()
        .map(|l| ChannelSpec {
            default_ns: us_to_ns(l.default_us) as u32,
            min_ns: us_to_ns(l.min_us) as u32,
            max_ns: us_to_ns(l.max_us) as u32,
            mapping: l.mapping,
        })
        .collect();
    let smallest_min = m.channels.iter().map(|c| c.min_ns).min().unwrap_or(0) as u64;
    if !ppm.pulse_us.is_finite()
        || ppm.pulse_us < PULSE_MIN_US
        || us_to_ns(ppm.pulse_us) >= smallest_min
    {
        return Err(invalid(
            "ppm.pulse_us",
            format!(
                "{} us must be at least {PULSE_MIN_US} us and shorter than the smallest channel minimum, {} us",
                ppm.pulse_us,
                smallest_min as f64 / 1e3
            ),
        ));
    }
    m.pulse_ns = us_to_ns(ppm.pulse_us);
    if !ppm.frame_us.is_finite() || ppm.frame_us <= 0.0 {
        return Err(invalid(
            "ppm.frame_us",
            format!("{} us is not a frame length", ppm.frame_us),
        ));
    }
    let frame_ns = us_to_ns(ppm.frame_us);
    m.follow_sync_ns = follow_sync(ppm, &rules)?;
    m.frame_ns = frame_ns;
    if ppm.timing == Timing::Follow {
        // Frames follow the commands: the sync gaps are the follow
        // limits, whatever the channel values; frame_us is not used.
        return Ok(FrameModel::new(m));
    }
    let sum_max: u64 = m.channels.iter().map(|c| c.max_ns as u64).sum();
    let sum_min: u64 = m.channels.iter().map(|c| c.min_ns as u64).sum();
    let n = m.channels.len();
    let (sync_min, sync_max) = (rules.sync_min_us, rules.sync_max_us);
    let sync_min_ns = us_to_ns(sync_min.0);
    if frame_ns < sum_max + sync_min_ns {
        return Err(invalid(
            "ppm.frame_us",
            format!(
                "{} us leaves a sync gap of {} us when all {} channels are at their maximum (sum {} us); {}, and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: the gap must be at least {} us under {}: raise ppm.frame_us to at least {} us or lower the channel maximums",
                ppm.frame_us,
                (frame_ns as f64 - sum_max as f64) / 1e3,
                n,
                sum_max as f64 / 1e3,
                sync_min.1,
                sync_min.0,
                receiver_key(ppm.receiver),
                (sum_max + sync_min_ns) as f64 / 1e3
            ),
        ));
    }
    if frame_ns > sum_min + us_to_ns(sync_max.0) {
        let sync_max_ns = us_to_ns(sync_max.0);
        return Err(invalid(
            "ppm.frame_us",
            format!(
                "{} us leaves a sync gap of {} us when all {} channels are at their minimum (sum {} us); {} (a longer gap is signal loss), and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: the gap must be at most {} us under {}: lower ppm.frame_us to at most {} us or add channels",
                ppm.frame_us,
                (frame_ns - sum_min) as f64 / 1e3,
                n,
                sum_min as f64 / 1e3,
                sync_max.1,
                sync_max.0,
                receiver_key(ppm.receiver),
                (sum_min + sync_max_ns) as f64 / 1e3
            ),
        ));
    }
    Ok(FrameModel::new(m))
}

/// `ppm.receiver = "NAME"`, for messages.
fn receiver_key(r: ReceiverChoice) -> String {
    match r {
        ReceiverChoice::Any => "ppm.receiver = \"any\" (every supported receiver)".into(),
        ReceiverChoice::One(r) => format!("ppm.receiver = \"{}\"", r.name()),
    }
}

/// `ppm.follow_sync_min_us` and `ppm.follow_sync_max_us` in ns, checked
/// against the sync window of the receiver (checked in either timing, so a
/// file stays valid when its timing is switched).
fn follow_sync(ppm: &PpmSection, rules: &Rules) -> Result<(u64, u64), ConfigError> {
    let (min, max) = (ppm.follow_sync_min_us, ppm.follow_sync_max_us);
    let floor = rules.sync_min_us;
    let ceiling = rules.sync_max_us.0.min(FOLLOW_SYNC_CEILING_US);
    if !min.is_finite() || min < floor.0 {
        return Err(invalid(
            "ppm.follow_sync_min_us",
            format!(
                "{min} us: {}, and ppm keeps {SYNC_MARGIN_US} us inside that for a late edge: at least {} us under {}",
                floor.1,
                floor.0,
                receiver_key(ppm.receiver)
            ),
        ));
    }
    if !max.is_finite() || max > ceiling {
        return Err(invalid(
            "ppm.follow_sync_max_us",
            format!(
                "{max} us is above {ceiling} us: EdgeTX and OpenTX read a sync only below 19000 us, and a late frame must not take it there ({SYNC_MARGIN_US} us kept; the most for every receiver)"
            ),
        ));
    }
    if max < min {
        return Err(invalid(
            "ppm.follow_sync_max_us",
            format!("{max} us is below ppm.follow_sync_min_us = {min} us"),
        ));
    }
    Ok((us_to_ns(min), us_to_ns(max)))
}

fn invalid(key: &str, message: String) -> ConfigError {
    ConfigError::Invalid {
        key: key.into(),
        message,
    }
}

/// Most outputs one ppmd drives.
pub const MAX_OUTPUTS: usize = 8;

/// The value at a dotted key path in a TOML table.
fn lookup<'a>(table: &'a toml::Table, dotted: &str) -> Option<&'a toml::Value> {
    let mut parts = dotted.split('.');
    let mut v = table.get(parts.next()?)?;
    for p in parts {
        v = v.as_table()?.get(p)?;
    }
    Some(v)
}

/// Every leaf key under `prefix` in `v`, dotted.
fn collect_keys(prefix: &str, v: &toml::Value, out: &mut Vec<String>) {
    match v {
        toml::Value::Table(t) => {
            for (k, v) in t {
                collect_keys(&format!("{prefix}.{k}"), v, out);
            }
        }
        _ => out.push(prefix.to_string()),
    }
}

/// Lays `top` over `base`: tables merge key by key, anything else replaces.
fn overlay(base: &mut toml::Value, top: toml::Value) {
    match (base, top) {
        (toml::Value::Table(b), toml::Value::Table(t)) => {
            for (k, v) in t {
                match b.get_mut(&k) {
                    Some(slot) => overlay(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
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

/// Validated per-channel limits, in microseconds.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ChannelLimits {
    pub default_us: f64,
    pub min_us: f64,
    pub max_us: f64,
    pub mapping: UnitMapping,
    /// The keys `min_us` and `max_us` come from, for messages.
    pub min_key: String,
    pub max_key: String,
}

/// Resolves names and limits of every channel and checks them; used by
/// [`frame_model`].
pub(crate) fn resolve_channels(
    ppm: &PpmSection,
) -> Result<(Vec<String>, Vec<ChannelLimits>), ConfigError> {
    let n = ppm.channels as usize;
    if !(1..=MAX_CHANNELS).contains(&n) {
        return Err(ConfigError::invalid(
            "ppm.channels",
            format!("{} is outside 1..={MAX_CHANNELS}", ppm.channels),
        ));
    }
    let names = channel_names(&ppm.order, n)?;
    for key in ppm.channel.keys() {
        if !names.iter().any(|n| n == key) {
            return Err(ConfigError::invalid(
                format!("ppm.channel.{key}"),
                format!(
                    "no channel is named `{key}`; channels are {}",
                    names.join(", ")
                ),
            ));
        }
    }
    let mut limits = Vec::with_capacity(n);
    for name in &names {
        let o = ppm.channel.get(name).cloned().unwrap_or_default();
        let key = |field: &str, overridden: bool| {
            if overridden {
                format!("ppm.channel.{name}.{field}")
            } else {
                format!("ppm.{field}")
            }
        };
        let min_us = o.min_us.unwrap_or(ppm.min_us);
        let max_us = o.max_us.unwrap_or(ppm.max_us);
        let min_key = key("min_us", o.min_us.is_some());
        let max_key = key("max_us", o.max_us.is_some());
        check_range(&min_key, min_us)?;
        check_range(&max_key, max_us)?;
        if min_us > max_us {
            return Err(ConfigError::invalid(
                min_key,
                format!("{min_us} us is above {max_key} = {max_us} us"),
            ));
        }
        // Throttle's zero actuation is its minimum: a command that leaves
        // throttle out must not spin motors up.
        let default_us = match o.default_us {
            Some(v) => v,
            None if name == "thr" => min_us,
            None => ppm.default_us,
        };
        let default_key = key("default_us", o.default_us.is_some());
        if !default_us.is_finite() || default_us < min_us || default_us > max_us {
            return Err(ConfigError::invalid(
                default_key,
                format!("{default_us} us is outside this channel's {min_us}..={max_us} us"),
            ));
        }
        limits.push(ChannelLimits {
            default_us,
            min_us,
            max_us,
            mapping: resolve_mapping(name, &o, min_us, max_us)?,
            min_key,
            max_key,
        });
    }
    Ok((names, limits))
}

/// Largest `trim_us` either way, in microseconds.
pub const TRIM_MAX_US: f64 = 500.0;

/// Checks and resolves the `units`/`norm` mapping keys of channel `name`,
/// whose limits are `min_us..=max_us`.
fn resolve_mapping(
    name: &str,
    o: &ChannelOverride,
    min_us: f64,
    max_us: f64,
) -> Result<UnitMapping, ConfigError> {
    let key = |field: &str| format!("ppm.channel.{name}.{field}");
    let units = match (o.unit_min, o.unit_max) {
        (None, None) => None,
        (Some(_), None) | (None, Some(_)) => {
            let (given, missing) = if o.unit_min.is_some() {
                ("unit_min", "unit_max")
            } else {
                ("unit_max", "unit_min")
            };
            return Err(ConfigError::invalid(
                key(missing),
                format!("{given} is set but {missing} is not: a unit range needs both ends"),
            ));
        }
        (Some(lo), Some(hi)) => {
            for (field, v) in [("unit_min", lo), ("unit_max", hi)] {
                if !v.is_finite() {
                    return Err(ConfigError::invalid(
                        key(field),
                        format!("{v} is not a finite number"),
                    ));
                }
            }
            if lo >= hi {
                return Err(ConfigError::invalid(
                    key("unit_min"),
                    format!("{lo} is not below unit_max = {hi} (use reverse = true to swap the direction)"),
                ));
            }
            // The mapping divides by the width: an infinite one gives NaN.
            if !(hi - lo).is_finite() {
                return Err(ConfigError::invalid(
                    key("unit_max"),
                    format!("the range {lo}..{hi} is too wide: unit_max - unit_min must be a finite number"),
                ));
            }
            Some((lo, hi))
        }
    };
    if units.is_none() {
        let needs_range = [
            ("unit_us_min", o.unit_us_min.is_some()),
            ("unit_us_max", o.unit_us_max.is_some()),
            ("unit", o.unit.is_some()),
        ];
        if let Some((field, _)) = needs_range.iter().find(|(_, set)| *set) {
            return Err(ConfigError::invalid(
                key(field),
                format!("needs a unit range: set ppm.channel.{name}.unit_min and unit_max too"),
            ));
        }
    }
    let us_lo = o.unit_us_min.unwrap_or(min_us);
    let us_hi = o.unit_us_max.unwrap_or(max_us);
    if let Some(v) = o.unit_us_min {
        check_range(&key("unit_us_min"), v)?;
    }
    if let Some(v) = o.unit_us_max {
        check_range(&key("unit_us_max"), v)?;
    }
    if units.is_some() && us_lo >= us_hi {
        return Err(ConfigError::invalid(
            key("unit_us_min"),
            format!(
                "{us_lo} us is not below unit_us_max = {us_hi} us (they default to the channel's min_us and max_us; use reverse = true to swap the direction)"
            ),
        ));
    }
    if !o.trim_us.is_finite() || o.trim_us.abs() > TRIM_MAX_US {
        return Err(ConfigError::invalid(
            key("trim_us"),
            format!(
                "{} us is outside -{TRIM_MAX_US}..={TRIM_MAX_US} us",
                o.trim_us
            ),
        ));
    }
    Ok(UnitMapping {
        units,
        us_lo,
        us_hi,
        reverse: o.reverse,
        trim_us: o.trim_us,
    })
}

fn check_range(key: &str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && (CHANNEL_MIN_US..=CHANNEL_MAX_US).contains(&v) {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            key,
            format!(
                "{v} us is outside {CHANNEL_MIN_US}..={CHANNEL_MAX_US} us, the channel periods transmitters accept"
            ),
        ))
    }
}

/// Channel names in transmitter order: the four stick channels as `order`
/// places them, then `aux1`, `aux2`, ...
pub fn channel_names(order: &str, channels: usize) -> Result<Vec<String>, ConfigError> {
    let letters: Vec<char> = order.chars().map(|c| c.to_ascii_uppercase()).collect();
    let mut sorted = letters.clone();
    sorted.sort_unstable();
    if sorted != ['A', 'E', 'R', 'T'] {
        return Err(ConfigError::invalid(
            "ppm.order",
            format!(
                "`{order}` must hold each of the letters A, E, T, R once (e.g. AETR, TAER, ATER)"
            ),
        ));
    }
    Ok((0..channels)
        .map(|i| match letters.get(i) {
            Some('A') => "ail".to_string(),
            Some('E') => "ele".to_string(),
            Some('T') => "thr".to_string(),
            Some(_) => "rud".to_string(),
            None => format!("aux{}", i - 3),
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_validate() {
        let c = Config::default();
        let m = c.validate().unwrap();
        assert_eq!(m.channels(), 8);
        assert_eq!(
            m.names(),
            ["ail", "ele", "thr", "rud", "aux1", "aux2", "aux3", "aux4"]
        );
        assert_eq!(
            m.default_ns(2),
            1_000_000,
            "throttle defaults to its minimum"
        );
        assert_eq!(m.default_ns(0), 1_500_000);
    }

    #[test]
    fn example_file_lists_the_defaults() {
        let text = include_str!("../../ppm.example.toml");
        assert_eq!(Config::parse(text).unwrap(), Config::default());
    }

    /// A config path naming a FIFO, a device or a huge file is refused at
    /// once with what it is (a FIFO used to hang ppmd and udp-ingress at start).
    #[test]
    fn config_files_that_are_not_small_regular_files_are_refused_at_once() {
        let dir = std::env::temp_dir().join(format!("ppm-config-odd-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let fifo = dir.join("ppm.toml");
        nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
        let big = dir.join("big.toml");
        std::fs::File::create(&big)
            .unwrap()
            .set_len(crate::files::CONFIG_MAX_BYTES + 1)
            .unwrap();
        for (path, what) in [
            (fifo, "a FIFO (named pipe), not a regular file"),
            (PathBuf::from("/dev/zero"), "a character device"),
            (
                big,
                "1048577 bytes or more, and this file is never larger than 1048576",
            ),
        ] {
            let shown = path.display().to_string();
            let e = crate::files::tests::within_10s(move || Config::load(&path)).unwrap_err();
            let e = crate::logging::Chain(&e).to_string();
            assert!(
                e.contains("cannot read config file") && e.contains(&shown) && e.contains(what),
                "{e}"
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn empty_file_is_the_default() {
        assert_eq!(Config::parse("").unwrap(), Config::default());
    }

    #[test]
    fn unknown_key_is_named() {
        let e = Config::parse("[ppm]\nframe_len = 20000\n").unwrap_err();
        assert!(e.to_string().contains("frame_len"), "{e}");
    }

    #[test]
    fn rt_words_and_numbers() {
        let c = Config::parse("[rt]\ncpu = 3\nspin_margin_us = 150").unwrap();
        assert_eq!(
            (c.rt.cpu, c.rt.spin_margin_us),
            (CpuChoice::Index(3), SpinMargin::Fixed(150))
        );
        let c = Config::parse("[rt]\ncpu = 'none'\nspin_margin_us = 'auto'").unwrap();
        assert_eq!(
            (c.rt.cpu, c.rt.spin_margin_us),
            (CpuChoice::None, SpinMargin::Auto)
        );
        for (text, key) in [
            ("[rt]\ncpu = 'first'", "rt.cpu"),
            ("[rt]\ncpu = -1", "rt.cpu"),
            ("[rt]\nspin_margin_us = 'fast'", "rt.spin_margin_us"),
            ("[rt]\nspin_margin_us = 9000", "rt.spin_margin_us"),
        ] {
            let e = Config::parse(text).unwrap_err().to_string();
            assert!(e.contains(key), "{text}: {e}");
        }
    }

    /// Validates `[ppm]` lines under `receiver`: Ok, or the key refused.
    fn under(receiver: &str, ppm: &str) -> Result<(), String> {
        let text = format!("[ppm]\nreceiver = '{receiver}'\n{ppm}");
        let c = Config::parse(&text).map_err(|e| e.to_string())?;
        c.validate()
            .map(|_| ())
            .map_err(|e| e.key().unwrap_or("?").to_string())
    }

    #[test]
    fn receivers_bound_the_channel_count() {
        let ch = "channels";
        for (receiver, fewest, most) in [
            ("any", 5, 12),
            ("edgetx", 1, 16),
            ("opentx", 1, 16),
            ("betaflight", 4, 12),
            ("ardupilot", 5, 16),
        ] {
            // A frame long enough for 16 channels at 2000 us, short enough
            // for 1 at 1000 us under the 18.5 ms longest sync: follow timing.
            let t = "timing = 'follow'\n";
            assert_eq!(under(receiver, &format!("{t}{ch} = {fewest}")), Ok(()));
            assert_eq!(under(receiver, &format!("{t}{ch} = {most}")), Ok(()));
            let want = Err("ppm.channels".to_string());
            if fewest > 1 {
                assert_eq!(under(receiver, &format!("{t}{ch} = {}", fewest - 1)), want);
            }
            assert_eq!(under(receiver, &format!("{t}{ch} = {}", most + 1)), want);
        }
        let e = Config::parse("[ppm]\nchannels = 4")
            .unwrap()
            .validate()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ArduPilot") && e.contains("MIN_RCIN_CHANNELS"),
            "{e}"
        );
        assert!(e.contains("5..=12"), "{e}");
    }

    #[test]
    fn receivers_bound_the_channel_values() {
        for (receiver, lo, hi) in [
            ("any", 905.0, 2_095.0),
            ("edgetx", 820.0, 2_180.0),
            ("opentx", 821.0, 2_179.0),
            ("betaflight", 905.0, 2_095.0),
            ("ardupilot", 800.0, 2_200.0),
        ] {
            let limits = |min: f64, max: f64| {
                format!("min_us = {min}\nmax_us = {max}\ndefault_us = {min}\ntiming = 'follow'")
            };
            assert_eq!(under(receiver, &limits(lo, hi)), Ok(()), "{receiver}");
            assert_eq!(
                under(receiver, &limits(lo - 0.1, hi)),
                Err("ppm.min_us".into()),
                "{receiver}"
            );
            assert_eq!(
                under(receiver, &limits(lo, hi + 0.1)),
                Err("ppm.max_us".into()),
                "{receiver}"
            );
        }
        let e = Config::parse("[ppm.channel.ail]\nmin_us = 850.0")
            .unwrap()
            .validate()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ppm.channel.ail.min_us")
                && e.contains("Betaflight")
                && e.contains("raise ppm.channel.ail.min_us to 905 us"),
            "{e}"
        );
    }

    #[test]
    fn receivers_bound_the_grid_sync() {
        // 8 channels of 1000..=2000 us: 16 ms at the most, 8 at the least.
        for (receiver, shortest, longest) in [
            ("any", 4_500.0, 18_500.0),
            ("edgetx", 4_500.0, 18_500.0),
            ("opentx", 4_500.0, 18_500.0),
            // A 16-bit capture at 1 MHz, less the margin.
            ("betaflight", 3_200.0, 65_036.0),
            ("ardupilot", 3_200.0, 65_036.0),
        ] {
            let frame = |us: f64| format!("frame_us = {us}");
            assert_eq!(under(receiver, &frame(16_000.0 + shortest)), Ok(()));
            assert_eq!(
                under(receiver, &frame(16_000.0 + shortest - 1.0)),
                Err("ppm.frame_us".into()),
                "{receiver}"
            );
            assert_eq!(under(receiver, &frame(8_000.0 + longest)), Ok(()));
            assert_eq!(
                under(receiver, &frame(8_000.0 + longest + 1.0)),
                Err("ppm.frame_us".into())
            );
            // Follow timing's shortest sync, likewise.
            let follow = |us: f64| format!("timing = 'follow'\nfollow_sync_min_us = {us}");
            assert_eq!(under(receiver, &follow(shortest)), Ok(()));
            assert_eq!(
                under(receiver, &follow(shortest - 1.0)),
                Err("ppm.follow_sync_min_us".into())
            );
            // Either polarity: the receivers time the edges that leave idle.
            assert_eq!(under(receiver, "idle_level = 'high'"), Ok(()));
        }
        assert!(under("spektrum", "").unwrap_err().contains("spektrum"));
        // No receiver takes an endless frame (the fuzzer's 1e300).
        for r in ["any", "edgetx", "opentx", "betaflight", "ardupilot"] {
            assert_eq!(
                under(r, "frame_us = 1e300"),
                Err("ppm.frame_us".into()),
                "{r}"
            );
        }
    }

    #[test]
    fn follow_timing_keys() {
        let c = Config::parse(
            "[ppm]\ntiming = 'follow'\nfollow_sync_min_us = 4500.0\nfollow_sync_max_us = 18500.0",
        )
        .unwrap();
        assert_eq!(c.ppm.timing, Timing::Follow);
        let m = c.validate().unwrap();
        assert_eq!(m.timing(), Timing::Follow);
        assert_eq!(m.follow_sync_ns(), (4_500_000, 18_500_000));
        assert_eq!(Config::default().ppm.timing, Timing::Grid);
        assert_eq!(
            Config::default().validate().unwrap().follow_sync_ns(),
            (5_000_000, 18_000_000)
        );
        // Follow timing does not use frame_us: 12 channels of up to 2000 us
        // need no longer frame (grid would refuse it).
        let twelve = "[ppm]\nchannels = 12\ntiming = 'follow'";
        Config::parse(twelve).unwrap().validate().unwrap();
        let e = Config::parse(&twelve.replace("follow", "grid"))
            .unwrap()
            .validate()
            .unwrap_err();
        assert_eq!(e.key(), Some("ppm.frame_us"));
        for (text, key) in [
            ("timing = 'fast'", "timing"),
            ("follow_sync_min_us = 4499.0", "ppm.follow_sync_min_us"),
            ("follow_sync_min_us = 4000.0", "ppm.follow_sync_min_us"),
            ("follow_sync_min_us = nan", "ppm.follow_sync_min_us"),
            ("follow_sync_max_us = 18501.0", "ppm.follow_sync_max_us"),
            ("follow_sync_max_us = 19000.0", "ppm.follow_sync_max_us"),
            ("follow_sync_max_us = inf", "ppm.follow_sync_max_us"),
            (
                "follow_sync_min_us = 9000.0\nfollow_sync_max_us = 8000.0",
                "ppm.follow_sync_max_us",
            ),
        ] {
            // Checked in either timing.
            for timing in ["grid", "follow"] {
                let text = format!("[ppm]\ntiming = '{timing}'\n{text}");
                let e = match Config::parse(&text) {
                    Err(e) => e.to_string(),
                    Ok(c) => c.validate().unwrap_err().to_string(),
                };
                assert!(e.contains(key), "{text}: {e}");
            }
        }
        assert_eq!("follow".parse(), Ok(Timing::Follow));
        assert_eq!("grid".parse(), Ok(Timing::Grid));
        assert!("Follow".parse::<Timing>().is_err());
        // Per output, and named there.
        let c = Config::parse(
            "[[outputs]]\nname = 'a'\noutput = 'sim:a'\n[[outputs]]\nname = 'b'\noutput = 'sim:b'\nppm.timing = 'follow'\nppm.follow_sync_min_us = 100.0",
        )
        .unwrap();
        let e = c.validate_outputs().unwrap_err();
        assert_eq!(e.key(), Some("outputs[1].ppm.follow_sync_min_us"));
        let c = Config::parse(
            "[[outputs]]\nname = 'a'\noutput = 'sim:a'\n[[outputs]]\nname = 'b'\noutput = 'sim:b'\nppm.timing = 'follow'\ningress.listen = '127.0.0.1:5006'",
        )
        .unwrap();
        let outs = c.validate_outputs().unwrap();
        assert_eq!(outs[0].1.timing(), Timing::Grid);
        assert_eq!(outs[1].1.timing(), Timing::Follow);
    }

    #[test]
    fn ingress_scheduling_keys() {
        let c = Config::parse("[ingress]\npriority = 79\ncpu = 0\nbusy_poll = true").unwrap();
        c.validate().unwrap();
        assert_eq!(
            (c.ingress.priority, c.ingress.cpu, c.ingress.busy_poll),
            (79, IngressCpu::Index(0), true)
        );
        let c = Config::parse("[ingress]\ncpu = 'none'").unwrap();
        assert_eq!(c.ingress.cpu, IngressCpu::None);
        // Pinned to ppmd's CPU without busy_poll is allowed (the thread sleeps).
        Config::parse("[ingress]\ncpu = 1\n[rt]\ncpu = 1")
            .unwrap()
            .validate()
            .unwrap();
        // Values of the wrong kind are refused while parsing, naming the key.
        for (text, key) in [
            ("[ingress]\ncpu = 'last'", "ingress.cpu"),
            ("[ingress]\ncpu = -1", "ingress.cpu"),
            ("[ingress]\ncpu = 4096", "ingress.cpu"),
            ("[ingress]\nbusy_poll = 'yes'", "busy_poll"),
            ("[ingress]\nbusy_poll = 1", "busy_poll"),
            ("[ingress]\npriority = -1", "priority"),
            ("[ingress]\npriority = 'high'", "priority"),
        ] {
            let e = Config::parse(text).unwrap_err().to_string();
            assert!(e.contains(key), "{text}: {e}");
        }
        // `rt.cpu = "last"` is resolved on the machine: the caller gives it.
        let c = Config::parse("[ingress]\nbusy_poll = true\ncpu = 1").unwrap();
        c.validate().unwrap();
        assert_eq!(
            c.check_busy_poll_cpu(Some(1)).unwrap_err().key(),
            Some("ingress.cpu")
        );
        c.check_busy_poll_cpu(Some(0)).unwrap();
        c.check_busy_poll_cpu(None).unwrap();
        assert_eq!("3".parse(), Ok(IngressCpu::Index(3)));
        assert_eq!("none".parse(), Ok(IngressCpu::None));
        assert!("last".parse::<IngressCpu>().is_err());
    }

    #[test]
    fn wrong_type_is_named() {
        let e = Config::parse("[ppm]\nchannels = \"eight\"\n").unwrap_err();
        assert!(e.to_string().contains("channels"), "{e}");
    }

    #[test]
    fn orders() {
        assert_eq!(
            channel_names("taer", 5).unwrap(),
            ["thr", "ail", "ele", "rud", "aux1"]
        );
        assert_eq!(channel_names("ATER", 2).unwrap(), ["ail", "thr"]);
        for bad in ["AETX", "AET", "AETRR", "AAER", ""] {
            let e = channel_names(bad, 4).unwrap_err();
            assert_eq!(e.key(), Some("ppm.order"), "{bad}");
        }
    }

    #[test]
    fn output_specs() {
        assert_eq!("sim".parse(), Ok(OutputSpec::Sim { path: None }));
        assert_eq!(
            "sim:/tmp/x.trace".parse(),
            Ok(OutputSpec::Sim {
                path: Some("/tmp/x.trace".into())
            })
        );
        assert_eq!(
            "gpio:/dev/gpiochip0:GPIO18".parse(),
            Ok(OutputSpec::Gpio {
                chip: "/dev/gpiochip0".into(),
                line: "GPIO18".into()
            })
        );
        assert_eq!(
            "spi:/dev/spidev0.0".parse(),
            Ok(OutputSpec::Spi {
                device: "/dev/spidev0.0".into()
            })
        );
        for bad in ["", "sim:", "gpio:", "gpio:chip", "gpio::3", "pwm:1", "spi:"] {
            assert!(bad.parse::<OutputSpec>().is_err(), "{bad}");
        }
    }

    /// An spi output: its rate within bounds, only with idle_level low (the
    /// gap between transfers is low), and alone on its ppmd.
    #[test]
    fn spi_outputs_are_checked() {
        let spi = "[ppmd]\noutput = 'spi:/dev/spidev0.0'\n";
        assert!(Config::parse(spi).unwrap().validate().is_ok());
        let key = |text: &str| {
            let c = Config::parse(text).unwrap();
            let e = c.validate_outputs().unwrap_err();
            (e.key().map(str::to_string), e.to_string())
        };
        for (hz, ok) in [
            (49_999, false),
            (50_000, true),
            (20_000_000, true),
            (20_000_001, false),
        ] {
            let c = Config::parse(&format!("{spi}spi_hz = {hz}")).unwrap();
            assert_eq!(c.validate().is_ok(), ok, "{hz}");
            if !ok {
                assert_eq!(c.validate().unwrap_err().key(), Some("ppmd.spi_hz"));
            }
        }
        let (k, e) = key(&format!("[ppm]\nidle_level = 'high'\n{spi}"));
        assert_eq!(k.as_deref(), Some("ppm.idle_level"));
        assert!(
            e.contains("idle_level = \"low\"") && e.contains("inverter"),
            "{e}"
        );
        // The same is fine on a gpio line.
        assert!(
            Config::parse("[ppm]\nidle_level = 'high'\n[ppmd]\noutput = 'gpio:0:18'")
                .unwrap()
                .validate()
                .is_ok()
        );
        let two = "[[outputs]]\nname = 'a'\noutput = 'spi:/dev/spidev0.0'\n[outputs.ingress]\nlisten = '127.0.0.1:5005'\n[[outputs]]\nname = 'b'\noutput = 'sim'\n[outputs.ingress]\nlisten = '127.0.0.1:5006'\n";
        let (k, e) = key(two);
        assert_eq!(k.as_deref(), Some("outputs[0].output"), "{e}");
        assert!(e.contains("runs alone"), "{e}");
    }

    #[test]
    fn invalid_keys_are_named() {
        let cases: &[(&str, &str)] = &[
            ("name = 'a b'", "name"),
            ("[ppm]\nchannels = 0", "ppm.channels"),
            ("[ppm]\nchannels = 17", "ppm.channels"),
            ("[ppm]\nmin_us = 700", "ppm.min_us"),
            ("[ppm]\nmax_us = 2300", "ppm.max_us"),
            (
                "[ppm]\nmin_us = 1600\ndefault_us = 1500\nmax_us = 2000",
                "ppm.default_us",
            ),
            ("[ppm]\npulse_us = 1000", "ppm.pulse_us"),
            ("[ppm]\npulse_us = 0", "ppm.pulse_us"),
            ("[ppm]\nframe_us = 19000", "ppm.frame_us"),
            ("[ppm]\nchannels = 3\nreceiver = 'edgetx'", "ppm.frame_us"),
            ("[ppm]\nchannels = 3", "ppm.channels"),
            ("[ppm.channel.aux9]\nmin_us = 900", "ppm.channel.aux9"),
            ("[ppm.channel.ail]\nmax_us = 2250", "ppm.channel.ail.max_us"),
            (
                "[ppm.channel.ail]\nmin_us = 1900\nmax_us = 1800",
                "ppm.channel.ail.min_us",
            ),
            (
                "[ingress]\nrecv_buffer_bytes = 100",
                "ingress.recv_buffer_bytes",
            ),
            ("[ppmd]\noutput = 'pwm'", "ppmd.output"),
            ("[rt]\npriority = 100", "rt.priority"),
            ("[ppmd]\nframe_log_max_mb = 0", "ppmd.frame_log_max_mb"),
            ("[ppmd]\ntrace_max_mb = 0", "ppmd.trace_max_mb"),
            ("[ppmd]\ntrace_max_mb = 65537", "ppmd.trace_max_mb"),
            ("[rt]\nspin_margin_max_us = 6000", "rt.spin_margin_max_us"),
            (
                "[rt]\nspin_margin_min_us = 600\nspin_margin_max_us = 500",
                "rt.spin_margin_min_us",
            ),
            ("[failsafe]\nafter_ms = 0", "failsafe.after_ms"),
            ("[failsafe]\nstartup = 'hold'", "failsafe.startup"),
            ("[ipc]\nroot = 'relative'", "ipc.root"),
            (
                "[ingress]\nallow = ['10.0.0.0/24', '10.0.0.300/32']",
                "ingress.allow",
            ),
            ("[ingress]\nallow = ['10.0.0.0/33']", "ingress.allow"),
            (
                "[ingress]\nstatus_allow = ['::1/129']",
                "ingress.status_allow",
            ),
            ("[ingress]\nallow = ['localhost']", "ingress.allow"),
            ("[ingress]\npriority = 100", "ingress.priority"),
            ("[ingress]\npriority = 80", "ingress.priority"),
            (
                "[ingress]\npriority = 70\n[rt]\npriority = 60",
                "ingress.priority",
            ),
            (
                "[ingress]\npriority = 1\n[rt]\npriority = 0",
                "ingress.priority",
            ),
            (
                "[ingress]\nbusy_poll = true\ncpu = 3\n[rt]\ncpu = 3",
                "ingress.cpu",
            ),
        ];
        for (text, key) in cases {
            let c = Config::parse(text).unwrap_or_else(|e| panic!("{text}: {e}"));
            let e = c.validate().unwrap_err();
            assert_eq!(e.key(), Some(*key), "{text}: {e}");
            assert!(e.to_string().contains(key), "{e}");
        }
    }

    #[test]
    fn sync_error_gives_the_numbers() {
        let c = Config::parse("[ppm]\nframe_us = 19000\n").unwrap();
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("16000") && e.contains("4000"), "{e}");
    }

    #[test]
    fn ingress_allow_and_seq_file() {
        let c = Config::parse(
            "name = 'v1'\n[ingress]\nallow = ['10.0.0.0/24', '127.0.0.1', '::1/128']\n",
        )
        .unwrap();
        c.validate().unwrap();
        let nets: Vec<String> = c.allow().unwrap().iter().map(|n| n.to_string()).collect();
        assert_eq!(nets, ["10.0.0.0/24", "127.0.0.1/32", "::1/128"]);
        assert_eq!(c.seq_file(), PathBuf::from("/tmp/ppm/v1.last_seq"));
        let c = Config::parse("[ingress]\nseq_file = '/var/lib/ppm/seq'\nauth_key = '/etc/ppm/k'")
            .unwrap();
        assert_eq!(c.seq_file(), PathBuf::from("/var/lib/ppm/seq"));
        assert_eq!(c.ingress.auth_key, Some(PathBuf::from("/etc/ppm/k")));
        let e = Config::parse("[ingress]\nallow = ['10.1.2.3/40']")
            .unwrap()
            .validate()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ingress.allow") && e.contains("10.1.2.3/40"),
            "{e}"
        );
    }
}

#[cfg(test)]
mod units_tests {
    use super::*;

    #[test]
    fn unit_keys_parse_and_validate() {
        let text = "[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\nunit = 'deg'\nunit_us_min = 1100.0\nunit_us_max = 1900.0\nreverse = true\ntrim_us = -12.5\n[ppm.channel.rud]\nreverse = true\ntrim_us = 5.0";
        let m = Config::parse(text).unwrap().validate().unwrap();
        let a = m.mapping(0);
        assert_eq!(
            (a.units, a.us_lo, a.us_hi, a.reverse, a.trim_us),
            (Some((-15.0, 15.0)), 1_100.0, 1_900.0, true, -12.5)
        );
        let r = m.mapping(3);
        assert_eq!(
            (r.units, r.us_lo, r.us_hi, r.reverse, r.trim_us),
            (None, 1_000.0, 2_000.0, true, 5.0),
            "norm works on every channel: min_us..max_us"
        );
    }

    #[test]
    fn invalid_unit_keys_are_named() {
        let r = "[ppm.channel.ail]\nunit_min = -15.0\nunit_max = 15.0\n";
        let cases: &[(&str, &str)] = &[
            (
                "[ppm.channel.ail]\nunit_min = -15.0",
                "ppm.channel.ail.unit_max",
            ),
            (
                "[ppm.channel.ele]\nunit_max = 15.0",
                "ppm.channel.ele.unit_min",
            ),
            (
                "[ppm.channel.ail]\nunit_min = 5.0\nunit_max = 5.0",
                "ppm.channel.ail.unit_min",
            ),
            (
                "[ppm.channel.ail]\nunit_min = 6.0\nunit_max = -5.0",
                "ppm.channel.ail.unit_min",
            ),
            (
                "[ppm.channel.ail]\nunit_min = -inf\nunit_max = 5.0",
                "ppm.channel.ail.unit_min",
            ),
            (
                "[ppm.channel.ail]\nunit_min = 0.0\nunit_max = nan",
                "ppm.channel.ail.unit_max",
            ),
            (
                &format!("{r}unit_us_min = 799.0"),
                "ppm.channel.ail.unit_us_min",
            ),
            (
                &format!("{r}unit_us_max = 2200.5"),
                "ppm.channel.ail.unit_us_max",
            ),
            (
                &format!("{r}unit_us_max = nan"),
                "ppm.channel.ail.unit_us_max",
            ),
            (
                &format!("{r}unit_us_min = 2000.0"),
                "ppm.channel.ail.unit_us_min",
            ),
            (
                &format!("{r}unit_us_min = 1600.0\nunit_us_max = 1400.0"),
                "ppm.channel.ail.unit_us_min",
            ),
            (&format!("{r}trim_us = 500.5"), "ppm.channel.ail.trim_us"),
            (
                "[ppm.channel.thr]\ntrim_us = -501.0",
                "ppm.channel.thr.trim_us",
            ),
            (
                "[ppm.channel.thr]\ntrim_us = nan",
                "ppm.channel.thr.trim_us",
            ),
            (
                "[ppm.channel.thr]\nunit_us_min = 1100.0",
                "ppm.channel.thr.unit_us_min",
            ),
            ("[ppm.channel.thr]\nunit = 'deg'", "ppm.channel.thr.unit"),
        ];
        for (text, key) in cases {
            let c = Config::parse(text).unwrap_or_else(|e| panic!("{text}: {e}"));
            let e = c.validate().unwrap_err();
            assert_eq!(e.key(), Some(*key), "{text}: {e}");
            assert!(e.to_string().contains(key), "{e}");
        }
        // Limits and trim at their edges are fine.
        let ok = format!("{r}unit_us_min = 800.0\nunit_us_max = 2200.0\ntrim_us = -500.0");
        Config::parse(&ok).unwrap().validate().unwrap();
    }

    /// Found by fuzz/config_structured: a unit range whose width overflows
    /// f64 validated, and a `units` value at its end then mapped through
    /// inf / inf = NaN to a 0 ns channel period (below min_us).
    #[test]
    fn unit_range_wider_than_f64_is_refused() {
        for (lo, hi) in [
            ("-1e308", "1e308"),
            ("-1.7976931348623157e308", "1.7976931348623157e308"),
        ] {
            let text = format!("[ppm.channel.ail]\nunit_min = {lo}\nunit_max = {hi}");
            let e = Config::parse(&text).unwrap().validate().unwrap_err();
            assert_eq!(e.key(), Some("ppm.channel.ail.unit_max"), "{text}: {e}");
            assert!(e.to_string().contains("too wide"), "{e}");
        }
        // The widest ranges with a finite width still map within the limits.
        let text = "[ppm.channel.ail]\nunit_min = -8e307\nunit_max = 8e307";
        let m = Config::parse(text).unwrap().validate().unwrap();
        assert_eq!(m.units_to_ns(0, 8e307), Some((2_000_000, false)));
        assert_eq!(m.units_to_ns(0, f64::MAX), Some((2_000_000, true)));
        assert_eq!(m.units_to_ns(0, f64::MIN), Some((1_000_000, true)));
        let cmd = crate::protocol::parse(br#"{"units": {"ail": 1e308}}"#, &m).unwrap();
        assert_eq!(cmd.channels.as_ns()[0], 2_000_000);
    }

    /// Two outputs, plane and rover, over shared top-level settings.
    const TWO_OUTPUTS: &str = include_str!("../testdata/two-outputs.toml");

    #[test]
    fn outputs_inherit_the_top_level_and_override_it() {
        let cfg = Config::parse(TWO_OUTPUTS).unwrap();
        let outs = cfg.validate_outputs().unwrap();
        assert_eq!(outs.len(), 2);
        let ((plane, pm), (rover, rm)) = (&outs[0], &outs[1]);
        assert_eq!(plane.name, "plane");
        assert_eq!(plane.ppmd.output, "sim:plane.trace");
        assert_eq!(plane.ppmd.frame_log, Some(PathBuf::from("plane.jsonl")));
        assert_eq!(plane.ingress.listen.port(), 5005);
        assert_eq!(pm.channels(), 8);
        assert_eq!(plane.failsafe.after_ms, 150);
        assert_eq!(plane.failsafe.action, FailsafeAction::Silence);
        assert_eq!(rover.ppmd.output, "gpio:gpiochip0:18");
        assert_eq!(rover.ppmd.frame_log, None);
        assert_eq!(rover.ingress.listen.port(), 5006);
        assert_eq!(rm.channels(), 6);
        assert_eq!(rm.names()[..4], ["thr", "ail", "ele", "rud"]);
        assert_eq!(rm.frame_ns(), 20_000_000);
        assert_eq!(rover.failsafe.after_ms, 150, "inherited");
        assert_eq!(rover.failsafe.action, FailsafeAction::Hold);
        // ppm.channel merges key by key: rover keeps the inherited ail reverse.
        assert!(rover.ppm.channel["ail"].reverse);
        assert_eq!(rover.ppm.channel["thr"].max_us, Some(1900.0));
        assert!(!plane.ppm.channel.contains_key("thr"));
        // The shared sections stay shared.
        assert_eq!(plane.rt, rover.rt);
        assert_eq!(plane.ipc, rover.ipc);
    }

    fn refusal(text: &str) -> ConfigError {
        match Config::parse(text) {
            Ok(c) => c
                .validate_outputs()
                .map(|_| ())
                .expect_err(&text[text.len().saturating_sub(300)..]),
            Err(e) => e,
        }
    }

    #[test]
    fn output_entries_are_checked_and_named() {
        let with = |extra: &str| format!("{TWO_OUTPUTS}{extra}");
        let e = refusal(&TWO_OUTPUTS.replace("channels = 6", "channels = 17"));
        assert_eq!(e.key(), Some("outputs[1].ppm.channels"), "{e}");
        let e = refusal(&TWO_OUTPUTS.replace("\"0.0.0.0:5006\"", "\"0.0.0.0:5005\""));
        assert_eq!(e.key(), Some("outputs[1].ingress.listen"), "{e}");
        assert!(e.to_string().contains("`plane`"), "{e}");
        let e = refusal(&TWO_OUTPUTS.replace("name = \"rover\"", "name = \"plane\""));
        assert_eq!(e.key(), Some("outputs[1].name"), "{e}");
        let e = refusal(&TWO_OUTPUTS.replace("gpio:gpiochip0:18", "sim:plane.trace"));
        assert_eq!(e.key(), Some("outputs[1].output"), "{e}");
        let e = refusal(&TWO_OUTPUTS.replace("name = \"rover\"\n", ""));
        assert_eq!(e.key(), Some("outputs[1].name"), "{e}");
        // An inherited value that fails for one output keeps its own key.
        let e =
            refusal(&TWO_OUTPUTS.replace("order = \"AETR\"", "order = \"AETR\"\nchannels = 12"));
        assert_eq!(e.key(), Some("ppm.frame_us"), "{e}");
        assert!(e.to_string().contains("output `plane`"), "{e}");
        let e = refusal(&with("[rt]\npriority = 100\n"));
        assert_eq!(e.key(), Some("rt.priority"), "{e}");
        let e = refusal(&format!("name = \"x\"\n{TWO_OUTPUTS}"));
        assert_eq!(e.key(), Some("name"), "{e}");
        let e = refusal(&TWO_OUTPUTS.replace("frame_log = \"plane.jsonl\"", "rt.priority = 10"));
        assert!(
            e.to_string().contains("outputs[0]: unknown key `rt`"),
            "{e}"
        );
        let e = refusal(&TWO_OUTPUTS.replace("channels = 6", "chanels = 6"));
        assert!(
            e.to_string().contains("outputs[1]") && e.to_string().contains("chanels"),
            "{e}"
        );
        let many: String = (0..9)
            .map(|i| {
                format!(
                    "[[outputs]]\nname = \"o{i}\"\ningress.listen = \"127.0.0.1:{}\"\n",
                    6000 + i
                )
            })
            .collect();
        assert_eq!(refusal(&many).key(), Some("outputs"));
    }

    #[test]
    fn select_picks_one_output() {
        let cfg = Config::parse(TWO_OUTPUTS).unwrap();
        assert_eq!(cfg.select(Some("rover")).unwrap().ppm.channels, 6);
        let e = cfg.select(None).unwrap_err().to_string();
        assert!(
            e.contains("2 outputs (plane, rover)") && e.contains("--name"),
            "{e}"
        );
        let e = cfg.select(Some("boat")).unwrap_err().to_string();
        assert!(
            e.contains("no output `boat`") && e.contains("plane, rover"),
            "{e}"
        );
        // Without [[outputs]] --name renames the one output.
        assert_eq!(Config::default().select(Some("x")).unwrap().name, "x");
        assert_eq!(Config::default().output_names(), ["ppm"]);
    }
}
