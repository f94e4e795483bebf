//! What a MAVLink command needs from the configuration ([`Settings`]):
//! ppm's ids, the channels MANUAL_CONTROL drives, the signing key's files,
//! the RC_CHANNELS rate and the kind of vehicle ppm says it is.

use crate::frame::FrameModel;

/// The kind of vehicle ppm says it is in its HEARTBEAT (MAV_TYPE):
/// QGroundControl keeps its joystick mode per kind, and shows the kind's
/// icon.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VehicleType {
    /// MAV_TYPE_GENERIC (0): a vehicle of no particular kind.
    #[default]
    Generic,
    /// MAV_TYPE_FIXED_WING (1).
    FixedWing,
    /// MAV_TYPE_QUADROTOR (2).
    Quadrotor,
    /// MAV_TYPE_HELICOPTER (4).
    Helicopter,
    /// MAV_TYPE_GROUND_ROVER (10).
    GroundRover,
    /// MAV_TYPE_SURFACE_BOAT (11).
    SurfaceBoat,
    /// MAV_TYPE_SUBMARINE (12).
    Submarine,
    /// MAV_TYPE_HEXAROTOR (13).
    Hexarotor,
    /// MAV_TYPE_OCTOROTOR (14).
    Octorotor,
}

impl VehicleType {
    /// Its MAV_TYPE.
    pub fn mav_type(self) -> u8 {
        match self {
            VehicleType::Generic => 0,
            VehicleType::FixedWing => 1,
            VehicleType::Quadrotor => 2,
            VehicleType::Helicopter => 4,
            VehicleType::GroundRover => 10,
            VehicleType::SurfaceBoat => 11,
            VehicleType::Submarine => 12,
            VehicleType::Hexarotor => 13,
            VehicleType::Octorotor => 14,
        }
    }
}

/// How z, MANUAL_CONTROL's thrust axis, maps onto its channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Thrust {
    /// 0..1000: 0 is the channel's minimum, 1000 its maximum (what
    /// QGroundControl sends, and ArduPilot reads). A negative z clamps.
    #[default]
    Positive,
    /// -1000..1000 like the other axes (-1000 the minimum, 0 the middle).
    Signed,
}

/// What a MAVLink command needs from the configuration.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Settings {
    /// ppm's system id: a message's target system must be it, or 0.
    pub system_id: u8,
    /// ppm's component id: an RC_CHANNELS_OVERRIDE's target component must
    /// be it, or 0.
    pub component_id: u8,
    /// The channels MANUAL_CONTROL's x, y, z and r drive (`None`: that
    /// axis is not used).
    pub axes: [Option<usize>; 4],
    /// How z is read.
    pub thrust: Thrust,
    /// The channels buttons 1.. drive (pressed: the channel's maximum,
    /// released: its minimum).
    pub buttons: Vec<usize>,
    /// The signing key's file (`mavlink.key_file`), if any.
    pub key_file: Option<std::path::PathBuf>,
    /// Where the newest signing timestamp accepted is kept
    /// (`mavlink.timestamp_file`, resolved), used with `key_file`.
    pub timestamp_file: Option<std::path::PathBuf>,
    /// RC_CHANNELS per second to each peer, unless it asks otherwise
    /// (`mavlink.rc_channels_hz`, 0..=[`RC_CHANNELS_MAX_HZ`]).
    pub rc_channels_hz: u8,
    /// The HEARTBEAT's type (`mavlink.vehicle_type`).
    pub vehicle_type: VehicleType,
}

/// RC_CHANNELS a second to each groundstation by default.
pub const RC_CHANNELS_HZ: u8 = 4;
/// The most RC_CHANNELS a second: ppmd publishes its line every tenth of a
/// second, so more would repeat the same frame.
pub const RC_CHANNELS_MAX_HZ: u8 = 10;

impl Settings {
    /// Ids 1 and 1, and the axes onto ele, ail, thr and rud, those of them
    /// the frame has.
    pub fn defaults_for(model: &FrameModel) -> Settings {
        Settings {
            system_id: 1,
            component_id: 1,
            axes: DEFAULT_AXES.map(|n| model.index_of(n)),
            thrust: Thrust::Positive,
            buttons: Vec::new(),
            key_file: None,
            timestamp_file: None,
            rc_channels_hz: RC_CHANNELS_HZ,
            vehicle_type: VehicleType::Generic,
        }
    }
}

/// True when a message's `target` (system or component) addresses ppm's
/// `id`: it is that id, or 0 (any).
pub fn addressed(target: u8, id: u8) -> bool {
    target == 0 || target == id
}

/// The channels MANUAL_CONTROL's x, y, z and r drive by default.
pub const DEFAULT_AXES: [&str; 4] = ["ele", "ail", "thr", "rud"];
