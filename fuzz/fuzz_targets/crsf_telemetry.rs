//! Raw bytes through the CRSF telemetry reader, as a flight controller's TX
//! line might deliver them, and through each firmware's RC framing.
//!
//! The reader: never panics; every frame it yields has a CRC that holds and
//! appears in the input as it is; split at any point (the first byte picks
//! where) it reads the same frames and counts the same; every byte is
//! accounted for (in a good frame, dropped as a bad one's first byte,
//! skipped as junk, or buffered); a gap empties it. The framers: never
//! panic, and (Betaflight, ArduPilot) take only frames whose CRC holds.
#![no_main]

use libfuzzer_sys::fuzz_target;
use ppm_shared::crsf::{self, CrsfReceiver, Framer, Telemetry, TelemetryReader};

fuzz_target!(|data: &[u8]| {
    let whole = read(data, data.len());
    let cut = data
        .first()
        .map_or(0, |&b| usize::from(b) % (data.len() + 1));
    assert_eq!(read(data, cut), whole, "split at {cut}");
    frame(data);
});

/// What the reader yields and counts for `data` fed in two parts.
fn read(data: &[u8], cut: usize) -> (Vec<(Vec<u8>, Telemetry)>, crsf::TelemetryCounts) {
    let mut r = TelemetryReader::new();
    let mut out = Vec::new();
    let mut on = |raw: &[u8], t: Telemetry| {
        assert!(crsf::crc_holds(raw), "bad CRC yielded: {raw:02X?}");
        assert!(
            data.windows(raw.len()).any(|w| w == raw),
            "not in the input: {raw:02X?}"
        );
        out.push((raw.to_vec(), t));
    };
    r.feed(&data[..cut], &mut on);
    r.feed(&data[cut..], &mut on);
    let c = *r.counts();
    assert_eq!(
        data.len() as u64,
        c.frame_bytes + c.bad_crc + c.bad_length + c.truncated + c.junk_bytes + r.buffered() as u64
    );
    r.gap(|raw, _| assert!(crsf::crc_holds(raw)));
    assert_eq!(r.buffered(), 0);
    (out, c)
}

/// Each firmware's framing over `data`, bytes 23.8 us apart, with a gap of
/// 2 ms wherever the byte 0xC8 follows a byte below 0x10.
fn frame(data: &[u8]) {
    for r in CrsfReceiver::ALL {
        let mut f = Framer::new(r);
        let mut t = 0u64;
        let mut prev = 0xFFu8;
        for &b in data {
            t += 23_810;
            if b == crsf::ADDRESS_FLIGHT_CONTROLLER && prev < 0x10 {
                t += 2_000_000;
            }
            prev = b;
            if let Some(taken) = f.push(b, t) {
                assert!(taken.len >= 4 && taken.len <= crsf::MAX_FRAME_LEN);
                let _ = r.verdict(&taken);
                if r != CrsfReceiver::Inav {
                    assert!(
                        crsf::crc_holds(taken.frame()),
                        "{r:?}: {:02X?}",
                        taken.frame()
                    );
                }
            }
        }
    }
}
