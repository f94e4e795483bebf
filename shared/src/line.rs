//! What ppmd's line is doing, and its one spelling: in the frame log, in
//! the timing snapshot (as its code), in the status reply and in the logs.

use serde::{Deserialize, Serialize};

/// What the line is doing. Serialized as its [`name`](LineState::name)
/// (the frame log's `state`, `from`, `to`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[repr(u8)]
pub enum LineState {
    /// No pulses: no command yet, or failsafe `silence`.
    Silent = 0,
    /// Emitting fresh commands.
    Active = 1,
    /// Emitting a failsafe frame (`hold` or `default`).
    Failsafe = 2,
}

impl LineState {
    /// Every state, in code order.
    pub const ALL: [LineState; 3] = [LineState::Silent, LineState::Active, LineState::Failsafe];

    /// Its name: `silent`, `active`, `failsafe`.
    pub fn name(self) -> &'static str {
        match self {
            LineState::Silent => "silent",
            LineState::Active => "active",
            LineState::Failsafe => "failsafe",
        }
    }

    /// Its code in the timing snapshot.
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The state of a code, if it is one.
    pub fn from_code(code: u32) -> Option<LineState> {
        LineState::ALL.into_iter().find(|s| s.code() as u32 == code)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_and_names_round_trip() {
        for s in LineState::ALL {
            assert_eq!(LineState::from_code(s.code() as u32), Some(s));
        }
        let names: Vec<&str> = LineState::ALL.iter().map(|s| s.name()).collect();
        assert_eq!(names, ["silent", "active", "failsafe"]);
        assert_eq!(LineState::from_code(3), None);
    }
}
