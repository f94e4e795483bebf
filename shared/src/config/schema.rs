//! The configuration file's schema: its sections as serde reads them, with
//! every default. [`Config::load`] reads a file; [`Config::parse`] (in
//! [`merge`](super::merge)) parses its text.

use super::keys::SetKeys;
use super::merge::ConfigFile;
use super::ConfigError;
use crate::frame::PpmSection;
use crate::mavlink::Thrust;
use serde::Deserialize;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

/// An output's name when the configuration gives none.
pub const DEFAULT_NAME: &str = "ppm";

/// The whole configuration file (and, for an `[[outputs]]` entry, the
/// file as that output sees it).
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
    /// How frames read back from the radio are read and judged.
    pub readback: ReadbackSection,
    /// How the pilot's radio (`ppmd.pilot`) is read and its takeover
    /// switch judged.
    pub pilot: PilotSection,
    /// Real-time setup of ppmd's timing thread.
    pub rt: RtSection,
    /// What ppmd does when commands stop.
    pub failsafe: FailsafeSection,
    /// Shared memory between the two processes.
    pub ipc: IpcSection,
    /// MAVLink commands on the command socket.
    pub mavlink: MavlinkSection,
    /// The keys the file set, and the keys a command-line option gave
    /// (not a setting: ignored by `==`).
    #[serde(skip)]
    pub set: SetKeys,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            name: DEFAULT_NAME.into(),
            ppm: PpmSection::default(),
            ingress: IngressSection::default(),
            ppmd: PpmdSection::default(),
            readback: ReadbackSection::default(),
            pilot: PilotSection::default(),
            rt: RtSection::default(),
            failsafe: FailsafeSection::default(),
            ipc: IpcSection::default(),
            mavlink: MavlinkSection::default(),
            set: SetKeys::default(),
        }
    }
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
    /// `ppm-NAME.trace`), `"sim:PATH"`, `"sim-spi:PATH"` (the simulated
    /// line written whole frame by frame, as an SPI output sends),
    /// `"gpio:CHIP:LINE"`, or
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
    /// The read-back of this output: an input carrying what the radio
    /// this output feeds transmits (its module bay set to PPM):
    /// `"gpio:CHIP:LINE"`, `"gpio:LINE"` or `"sim:PATH"` (a trace in the
    /// simulated line's format, read while it grows). Default: none.
    pub readback: Option<String>,
    /// Read-back log: one JSON line per frame read and per read-back state
    /// change, appended to this file. Default: none.
    pub readback_log: Option<PathBuf>,
    /// The pilot's radio of this output: an input carrying a radio's
    /// trainer signal (PPM) whose takeover switch (`pilot.switch_channel`)
    /// makes ppmd send the pilot's channels instead of the groundstation's:
    /// `"gpio:CHIP:LINE"`, `"gpio:LINE"` or `"sim:PATH"`. Default: none.
    pub pilot: Option<String>,
}

impl Default for PpmdSection {
    fn default() -> Self {
        PpmdSection {
            output: "sim".into(),
            frame_log: None,
            frame_log_max_mb: 64,
            trace_max_mb: 256,
            spi_hz: 1_000_000,
            readback: None,
            readback_log: None,
            pilot: None,
        }
    }
}

/// `[readback]`: how the frames read from `ppmd.readback` are read and
/// compared with what the line carried (see docs/readback.md).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReadbackSection {
    /// Largest difference per channel, us, 1..=500, between a value read
    /// and one the line carried that still counts as the radio following
    /// ppm. Default 10.
    pub tolerance_us: u32,
    /// How long after ppm's line carried a frame the radio may still be
    /// transmitting it, ms, 10..=2000. Default 100.
    pub window_ms: u32,
    /// Frames read in a row that must agree before the state changes,
    /// 1..=10. Default 2.
    pub frames: u8,
    /// The input's idle level, `"low"` or `"high"`. Default: found from
    /// the signal.
    pub idle_level: Option<crate::signal::Level>,
    /// Channels in a frame read, 1..=16. Default: found from the signal.
    pub channels: Option<u8>,
}

impl Default for ReadbackSection {
    fn default() -> Self {
        ReadbackSection {
            tolerance_us: 10,
            window_ms: 100,
            frames: 2,
            idle_level: None,
            channels: None,
        }
    }
}

/// `[pilot]`: how the pilot's radio (`ppmd.pilot`) is read and when its
/// takeover switch gives the pilot the controls (see docs/crsf.md).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PilotSection {
    /// The channel (1..=16) of the pilot's radio that carries the takeover
    /// switch. No default: a takeover switch is named, never guessed.
    pub switch_channel: Option<u8>,
    /// The pilot flies while the switch channel reads above this, us,
    /// 900..=2100. Default 1500.
    pub switch_above_us: u32,
    /// The input's idle level, `"low"` or `"high"`. Default: found from
    /// the signal.
    pub idle_level: Option<crate::signal::Level>,
    /// Channels in a frame read, 1..=16. Default: found from the signal.
    pub channels: Option<u8>,
}

impl Default for PilotSection {
    fn default() -> Self {
        PilotSection {
            switch_channel: None,
            switch_above_us: 1_500,
            idle_level: None,
            channels: None,
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

/// `[mavlink]`: MAVLink commands, taken on the command socket
/// ([`crate::mavlink`]).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MavlinkSection {
    /// ppm's MAVLink system id, 1..=255: a command's target system must be
    /// it, or 0 (any). Default 1.
    pub system_id: u8,
    /// ppm's MAVLink component id, 1..=255: an RC_CHANNELS_OVERRIDE's
    /// target component must be it, or 0 (any). Default 1.
    pub component_id: u8,
    /// The channels MANUAL_CONTROL's x, y, z and r axes drive, by name, or
    /// `"none"`. Default (`None`) `["ele", "ail", "thr", "rud"]`, those of
    /// them the frame has.
    pub axes: Option<Vec<String>>,
    /// How z, the thrust axis, is read: `"positive"` (0..1000, what
    /// QGroundControl sends) or `"signed"` (-1000..1000). Default
    /// `"positive"`.
    pub thrust: Thrust,
    /// The channels MANUAL_CONTROL's buttons drive, by name: the first
    /// for button 1, ... (up to 32); pressed is the channel's `max_us`,
    /// released its `min_us`. Default none.
    pub buttons: Vec<String>,
    /// Key file for MAVLink 2 message signing (64 hex characters, mode
    /// 600, as `ingress.auth_key`). When set, only MAVLink frames signed
    /// with it are taken, and ppm signs its replies. Default: none.
    pub key_file: Option<PathBuf>,
    /// With `key_file`: the file the newest signing timestamp accepted is
    /// kept in, so that a restarted udp-ingress takes no frame it took
    /// before. Default `<ipc.root>/<name>.mavlink_timestamp`.
    pub timestamp_file: Option<PathBuf>,
    /// RC_CHANNELS (the values on the line) sent to each groundstation
    /// heard from, per second, 0..=10 (0: none until a groundstation asks
    /// with MAV_CMD_SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM). Default 4.
    pub rc_channels_hz: u8,
    /// The kind of vehicle ppm's HEARTBEAT says: `"generic"` (the
    /// default), `"fixed_wing"`, `"quadrotor"`, `"helicopter"`,
    /// `"ground_rover"`, `"surface_boat"`, `"submarine"`, `"hexarotor"` or
    /// `"octorotor"`.
    pub vehicle_type: crate::mavlink::VehicleType,
}

impl Default for MavlinkSection {
    fn default() -> Self {
        MavlinkSection {
            system_id: 1,
            component_id: 1,
            axes: None,
            thrust: Thrust::Positive,
            buttons: Vec::new(),
            key_file: None,
            timestamp_file: None,
            rc_channels_hz: crate::mavlink::RC_CHANNELS_HZ,
            vehicle_type: crate::mavlink::VehicleType::Generic,
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
    /// to its own sticks; default), `"hold"` (repeat the last command),
    /// `"default"` (the configured default of every channel) or, with
    /// `protocol = "sbus"`, `"flag"` (frames of the defaults with SBUS's
    /// failsafe flag set).
    pub action: FailsafeAction,
    /// What ppmd emits from start until the first command: `"silence"`
    /// (default), `"default"` or (SBUS) `"flag"` (`"hold"` has nothing to
    /// hold yet).
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
    /// SBUS only: emit every channel's default with the failsafe flag set,
    /// which receivers take as failsafe at once (EdgeTX drops the frames,
    /// so its trainer input is lost after 1 s; a flight controller enters
    /// its failsafe).
    Flag,
}

impl FailsafeAction {
    /// Its name in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            FailsafeAction::Silence => "silence",
            FailsafeAction::Hold => "hold",
            FailsafeAction::Default => "default",
            FailsafeAction::Flag => "flag",
        }
    }
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
    /// The simulated line: every edge is written to a trace file. `whole`
    /// (`sim-spi`): each PPM frame is handed to the line whole at its
    /// start and leaves timed by the line's own clock, as an SPI output
    /// sends it, so no edge inside a frame waits on the timing thread;
    /// else (`sim`) edge by edge, each at its time as the loop keeps it, as
    /// a GPIO line.
    Sim { path: Option<PathBuf>, whole: bool },
    /// A GPIO line through the GPIO character device; an empty `chip`
    /// (`gpio:LINE`): the chip that has a line named `line`.
    Gpio { chip: String, line: String },
    /// A spidev device: each frame is one SPI transfer on MOSI.
    Spi { device: PathBuf },
    /// A tty (a UART): each SBUS frame is one write, sent at 100 000 baud,
    /// 8E2.
    Serial { device: PathBuf },
}

impl std::str::FromStr for OutputSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.split_once(':') {
            None if s == "sim" || s == "sim-spi" => Ok(OutputSpec::Sim {
                path: None,
                whole: s == "sim-spi",
            }),
            Some((kind @ ("sim" | "sim-spi"), path)) if !path.is_empty() => Ok(OutputSpec::Sim {
                path: Some(PathBuf::from(path)),
                whole: kind == "sim-spi",
            }),
            Some(("spi", device)) if !device.is_empty() => Ok(OutputSpec::Spi {
                device: PathBuf::from(device),
            }),
            Some(("spi", _)) => Err(format!(
                "`{s}`: an spi output is spi:DEVICE, e.g. spi:/dev/spidev0.0"
            )),
            Some(("serial", device)) if !device.is_empty() => Ok(OutputSpec::Serial {
                device: PathBuf::from(device),
            }),
            Some(("serial", _)) => Err(format!(
                "`{s}`: a serial output is serial:DEVICE, e.g. serial:/dev/ttyAMA0"
            )),
            Some(("gpio", rest)) => match rest.rsplit_once(':') {
                Some((chip, line)) if !chip.is_empty() && !line.is_empty() => {
                    Ok(OutputSpec::Gpio {
                        chip: chip.into(),
                        line: line.into(),
                    })
                }
                // gpio:LINE: the chip that has a line of this name.
                None if !rest.is_empty() => Ok(OutputSpec::Gpio {
                    chip: String::new(),
                    line: rest.into(),
                }),
                _ => Err(format!(
                    "`{s}`: a gpio output is gpio:CHIP:LINE (e.g. gpio:gpiochip0:18) or gpio:LINE (e.g. gpio:GPIO18, on whichever chip has a line of that name)"
                )),
            },
            _ => Err(format!(
                "`{s}` is not an output: use sim, sim:PATH, sim-spi:PATH, gpio:CHIP:LINE, spi:DEVICE or serial:DEVICE"
            )),
        }
    }
}

impl Config {
    /// Reads (a regular file of at most
    /// [`CONFIG_MAX_BYTES`](crate::files::CONFIG_MAX_BYTES)) and parses a
    /// configuration file. The PPM settings are checked by
    /// [`Config::validate`].
    pub fn load(path: &Path) -> Result<ConfigFile, ConfigError> {
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
    pub fn load_or_default(path: Option<&Path>) -> Result<ConfigFile, ConfigError> {
        path.map_or_else(|| Ok(ConfigFile::default()), Config::load)
    }
}
