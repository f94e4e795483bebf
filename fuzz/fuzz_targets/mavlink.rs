//! Raw datagram bytes through the MAVLink reader, as udp-ingress reads a
//! datagram whose first byte is 0xFE or 0xFD.
//!
//! Read twice: as given (a CRC that holds is rare), and with every frame's
//! CRC made right for its message id, so the fuzzer reaches the payloads.
//! A datagram read whole: each frame written again from its fields reads
//! back to the same message, every strict prefix of a one-frame datagram is
//! `mavlink_truncated`, and its command, under every model and two sets of
//! MAVLink settings, is accepted with every channel within its limits (the
//! checks of the `wire` target) or refused with a counted reason. A
//! datagram refused: a reason from `RejectReason::ALL` with a detail.
#![no_main]

use libfuzzer_sys::fuzz_target;
use ppm_fuzz::{check_accepted, check_rejected, models};
use ppm_shared::mavlink::{self, Settings, Thrust};

fuzz_target!(|data: &[u8]| {
    check(data);
    let fixed = fix_crcs(data);
    if fixed != data {
        check(&fixed);
    }
});

fn check(data: &[u8]) {
    let d = match mavlink::read_datagram(data) {
        Ok(d) => d,
        Err(e) => {
            check_rejected(&e);
            return;
        }
    };
    assert!(d.frames >= 1 || data.is_empty());
    if d.frames == 1 {
        for cut in 1..data.len() {
            let e = mavlink::read_datagram(&data[..cut]).unwrap_err();
            assert_eq!(e.reason.as_str(), "mavlink_truncated", "cut at {cut}: {e}");
        }
    }
    // Every request reads back from what it encodes to (compared as
    // bytes: a parameter may be NaN).
    for (h, message) in &d.requests {
        let (spec, payload) = message.encode();
        assert_eq!(spec.id, h.msgid);
        // MAVLink 1 carries ids up to 255 only.
        let versions: &[u8] = if spec.id > 255 { &[2] } else { &[1, 2] };
        for &version in versions {
            let again = mavlink::frame(version, (h.seq, h.sysid, h.compid), spec, &payload);
            let (_, m2, len) = mavlink::read_frame(&again).expect("written again");
            assert_eq!((m2.encode().1, len), (payload.clone(), again.len()));
        }
    }
    let Some((h, message)) = d.command else {
        return;
    };
    let (spec, payload) = message.encode();
    assert_eq!(spec.id, h.msgid);
    for version in [1, 2] {
        let again = mavlink::frame(version, (h.seq, h.sysid, h.compid), spec, &payload);
        let (h2, m2, len) = mavlink::read_frame(&again).expect("written again");
        assert_eq!((m2, len, h2.version), (message, again.len(), version));
    }
    for m in models() {
        let all: Vec<usize> = (0..m.channels()).collect();
        for s in [
            Settings::defaults_for(m),
            Settings {
                system_id: 7,
                component_id: 190,
                thrust: Thrust::Signed,
                buttons: all.clone(),
                ..Settings::defaults_for(m)
            },
        ] {
            match mavlink::command(&message, m, &s, &m.defaults()) {
                Ok(cmd) => {
                    assert_eq!(cmd.seq, None);
                    check_accepted(m, &cmd);
                }
                Err(e) => check_rejected(&e),
            }
        }
    }
}

/// `data` with the CRC of every frame it can walk through made right for
/// the frame's message id (left as it is for an id ppm does not know).
fn fix_crcs(data: &[u8]) -> Vec<u8> {
    let mut out = data.to_vec();
    let mut at = 0;
    while at < out.len() {
        let header = match out[at] {
            mavlink::STX_V1 => 6,
            mavlink::STX_V2 => 10,
            _ => break,
        };
        if out.len() < at + header {
            break;
        }
        let len = out[at + 1] as usize;
        let (id, signed) = if header == 6 {
            (out[at + 5] as u32, false)
        } else {
            (
                u32::from_le_bytes([out[at + 7], out[at + 8], out[at + 9], 0]),
                out[at + 2] & mavlink::IFLAG_SIGNED != 0,
            )
        };
        let end = at + header + len;
        if out.len() < end + 2 {
            break;
        }
        if let Some(spec) = mavlink::spec(id) {
            let crc = mavlink::frame_crc(spec, &out[at + 1..end]);
            out[end..end + 2].copy_from_slice(&crc.to_le_bytes());
        }
        at = end + 2 + if signed { mavlink::SIGNATURE_LEN } else { 0 };
    }
    out
}
