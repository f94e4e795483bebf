//! Logic shared by `ppmd` and `udp-ingress`: no I/O beyond reading the
//! configuration file, and [`sched`]'s scheduling of the calling thread.
//!
//! - [`config`]: the TOML configuration both binaries read: its schema, the
//!   `[[outputs]]` entries, the checks, and the [`config::Plan`] the file and
//!   a program's flags resolve into.
//! - [`signal`]: line levels, channel and edge limits, frame timing.
//! - [`wire`]: what a frame is on the wire, per protocol (PPM, SBUS, CRSF): the
//!   seam everything that differs between protocols is asked through.
//! - [`frame`]: the frame model, built and checked from the `[ppm]`
//!   section ([`FrameModel::build`]), and the encoder that turns channel
//!   values into one frame's edge schedule.
//! - [`decode`]: a decoder with transmitter semantics that reads any waveform back.
//! - [`capture`]: reading PPM back from an input line: where, its edges, and the capture decoder.
//! - [`receiver`]: PPM input as EdgeTX, OpenTX, Betaflight and ArduPilot
//!   decode it, each modelled on its firmware.
//! - [`sbus`]: the SBUS frame, its encoder, and SBUS input as EdgeTX,
//!   Betaflight and ArduPilot frame and read it, each modelled on its firmware.
//! - [`crsf`]: the CRSF frame, its RC encoder and link statistics, CRSF input as
//!   Betaflight, iNav and ArduPilot frame and read it, and a telemetry reader.
//! - [`protocol`]: the UDP wire protocol (JSON commands) and its parser.
//! - [`mavlink`]: MAVLink 1 and 2 commands (RC_CHANNELS_OVERRIDE,
//!   MANUAL_CONTROL) on the same socket, and their frames.
//! - [`files`]: bounded reads of the configuration, key and seq files.
//! - [`auth`]: the key, HMAC-SHA256 signatures and the signed envelope.
//! - [`logging`]: log lines for a terminal or for systemd's journal.
//! - [`daemon`]: the options both daemons take, and their logs' set-up.
//! - [`line`](mod@line): the line's state and its names.
//! - [`ipc`]: the fixed-size payload types carried through iceoryx2 shared memory.
//! - [`framelog`]: a row of ppmd's frame log, written by ppmd and read by the tools and tests.
//! - [`status`]: the reply to a status query, written by udp-ingress and read by the tools.
//! - [`trace`]: the simulated line's trace format.
//! - [`uart`]: bytes on a UART in a protocol's format (baud, parity, stop
//!   bits), as edges and read back.
//! - [`time`]: CLOCK_MONOTONIC and CLOCK_REALTIME reads in nanoseconds.
//! - [`sched`]: CPU pinning and SCHED_FIFO of the calling thread (ppmd's
//!   timing thread, udp-ingress's receive thread).

pub mod auth;
pub mod capture;
pub mod config;
pub mod crsf;
pub mod daemon;
pub mod decode;
pub mod files;
pub mod frame;
pub mod framelog;
pub mod ipc;
pub mod line;
pub mod logging;
pub mod mavlink;
pub mod protocol;
pub mod receiver;
pub mod sbus;
pub mod sched;
pub mod signal;
pub mod status;
pub mod time;
pub mod trace;
pub mod uart;
pub mod wire;

pub use config::{Config, ConfigError, Plan};
pub use frame::{Channels, Edge, EdgeSchedule, FrameModel, Level, MAX_CHANNELS};

/// Nanoseconds per microsecond.
pub const NS_PER_US: u64 = 1_000;
