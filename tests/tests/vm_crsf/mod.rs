//! The CRSF part of the real-kernel test (a helper module of vm.rs): ppmd's
//! CRSF output on the guest's third serial port, ttyS2, a 16550 whose bytes
//! QEMU writes to a host file (serial2.bin), read back byte for byte.
//!
//! As with SBUS, bit timing inside emulation means nothing (QEMU's file
//! backend gets bytes without their bits). What is checked is every byte,
//! the order of the commands, what Betaflight's framing and scaling make
//! of each write, and the settings the kernel holds for the port against
//! what its 8250 driver can make of 420 000 baud with the UART's clock.

use super::{logged_frames, read};
use ppm_shared::crsf::{self, on_wire, CrsfReceiver, Framer, LinkStatistics, Verdict};
use std::path::Path;

/// The aileron of the guest's four commands, in the order sent
/// (tests/vm/pipeline-test.sh), us.
pub(crate) const AILERON_US: [u64; 4] = [1_100, 1_300, 1_600, 1_900];

/// One ppmd write: an RC frame, then LINK_STATISTICS.
const WRITE_LEN: usize = crsf::RC_FRAME_LEN + LinkStatistics::FRAME_LEN;

/// The baud ppmd asks for (`ppm.crsf_baud`'s default).
const ASKED_BAUD: u64 = 420_000;

/// What Betaflight reads of a command with aileron `ail`: ele 1200,
/// thr 1700, rud 2000, aux1..aux11 at their default (1500), aux12 1900, us.
pub(crate) fn command_us(ail: u64) -> [u64; crsf::CHANNELS] {
    let mut v = [1_500; crsf::CHANNELS];
    v[..4].copy_from_slice(&[ail, 1_200, 1_700, 2_000]);
    v[15] = 1_900;
    v
}

/// The byte-for-byte check of what a CRSF serial port carried: whole
/// writes of 40 bytes, each an RC_CHANNELS_PACKED frame (0xC8, len 24,
/// type 0x16, its CRC-8/DVB-S2 holding) then exactly
/// `LinkStatistics::WIRED.encode()`; Betaflight's framing (fed each write
/// back to back at 420 000 baud, 4 ms apart) takes from each write the RC
/// frame, used, then the link statistics; every channel Betaflight reads is
/// within half its 0.625 us step of a command's whole microsecond; the
/// commands come in the order sent, each at least once, none after a later
/// one. Returns the writes carrying each command.
pub(crate) fn check_crsf_bytes(
    bytes: &[u8],
    commands: &[[u64; crsf::CHANNELS]],
) -> Result<Vec<usize>, String> {
    if !bytes.len().is_multiple_of(WRITE_LEN) {
        return Err(format!(
            "{} bytes: not whole writes of {WRITE_LEN}",
            bytes.len()
        ));
    }
    let link = LinkStatistics::WIRED.encode();
    let bf = CrsfReceiver::Betaflight;
    let mut per_command = vec![0usize; commands.len()];
    let mut last = 0usize;
    for (k, w) in bytes.chunks(WRITE_LEN).enumerate() {
        let (rc, ls) = w.split_at(crsf::RC_FRAME_LEN);
        if rc[..3]
            != [
                crsf::ADDRESS_FLIGHT_CONTROLLER,
                24,
                crsf::TYPE_RC_CHANNELS_PACKED,
            ]
        {
            return Err(format!("write {k}: RC frame head {:02x?}", &rc[..3]));
        }
        let crc = crsf::crc8(&rc[2..crsf::RC_FRAME_LEN - 1]);
        if crc != rc[crsf::RC_FRAME_LEN - 1] || !crsf::crc_holds(rc) {
            return Err(format!(
                "write {k}: RC frame CRC {:02x}, computed {crc:02x}: {rc:02x?}",
                rc[crsf::RC_FRAME_LEN - 1]
            ));
        }
        if ls != link {
            return Err(format!(
                "write {k}: link statistics {ls:02x?}, want {link:02x?}"
            ));
        }
        // Betaflight's framing and reading, the write back to back.
        let w: &[u8; WRITE_LEN] = w.try_into().unwrap();
        let mut framer = Framer::new(bf);
        let taken: Vec<Verdict> = on_wire(w, 1_000_000_000 + k as u64 * 4_000_000)
            .iter()
            .filter_map(|&(b, t)| framer.push(b, t))
            .map(|t| bf.verdict(&t))
            .collect();
        let channels_ns = match taken[..] {
            [Verdict::Used { channels_ns }, Verdict::LinkStatistics(l)]
                if l == LinkStatistics::WIRED =>
            {
                channels_ns
            }
            _ => return Err(format!("write {k}: Betaflight takes {taken:?}")),
        };
        let us = channels_ns.map(|ns| (ns + 500) / 1_000);
        if let Some(i) = (0..crsf::CHANNELS)
            .find(|&i| channels_ns[i].abs_diff(us[i] * 1_000) > bf.whole_us_error_ns())
        {
            return Err(format!(
                "write {k}: Betaflight reads channel {} at {} ns, off a whole us",
                i + 1,
                channels_ns[i]
            ));
        }
        let Some(c) = commands.iter().position(|c| *c == us) else {
            return Err(format!("write {k}: Betaflight reads {us:?}, no command"));
        };
        if c < last {
            return Err(format!(
                "write {k}: command {c} after command {last}: out of order"
            ));
        }
        last = c;
        per_command[c] += 1;
    }
    if let Some(c) = per_command.iter().position(|&n| n == 0) {
        return Err(format!(
            "command {c} ({:?}) never sent: writes per command {per_command:?}",
            commands[c]
        ));
    }
    Ok(per_command)
}

/// `key value` lines (tty-settings's output) as a lookup.
fn setting<'a>(tty: &'a str, key: &str) -> Option<&'a str> {
    tty.lines()
        .find_map(|l| l.strip_prefix(key)?.strip_prefix(' '))
}

/// The speed the kernel holds after a 16550 port at `uartclk` Hz was asked
/// for `asked` baud while it held `before`, and the rate the UART then
/// really runs at, as Linux 6.1's 8250 driver computes them
/// (`serial8250_get_baud_rate`, `uart_get_baud_rate`,
/// `serial8250_get_divisor`): a rate above `(uartclk + uartclk / 100) / 16`
/// is refused and the previous one kept (re-encoded into the settings);
/// one in range is kept as asked and made with the nearest divisor of
/// `uartclk / 16`.
fn kernel_baud(uartclk: u64, asked: u64, before: u64) -> (u64, u64) {
    let max = (uartclk + uartclk / 100) / 16;
    let held = if asked <= max { asked } else { before };
    let divisor = ((uartclk + 8 * held) / (16 * held)).max(1);
    (held, uartclk / 16 / divisor)
}

/// CRSF on ttyS2: ppmd exited cleanly with no write errors; the bytes
/// (serial2.bin) pass [`check_crsf_bytes`] for the four commands, one write
/// per logged frame, as many bytes as the kernel counted sent on the port;
/// the kernel holds 8N1, raw, no flow control, and the speed its 8250
/// driver makes of 420 000 baud with the UART's clock (reported: what the
/// port really runs at).
pub(crate) fn check_crsf_serial(out: &Path, flavor: &str) {
    // A UART that cannot make the rate stops ppmd at start, naming the
    // output and the rate it runs at, unless the run may be degraded.
    let refused = read(out, "crsf_refused.log");
    assert_eq!(read(out, "crsf_refused_exit.txt").trim(), "78", "{refused}");
    assert!(
        refused.contains("--output: output `vm-crsf`: the UART of /dev/ttyS2 runs at")
            && refused.contains("not the 420000 asked"),
        "{refused}"
    );
    let log = read(out, "crsf_ppmd.log");
    assert!(log.contains("DEGRADED RUN (rt.allow_degraded)"), "{log}");
    assert_eq!(read(out, "crsf_ppmd_exit.txt").trim(), "0", "{log}");
    assert!(log.contains("serial /dev/ttyS2"), "{log}");
    assert!(log.contains(" 0 write errors"), "{log}");

    let bytes = std::fs::read(out.join("serial2.bin")).expect("serial2.bin");
    let commands = AILERON_US.map(command_us);
    let per_command =
        check_crsf_bytes(&bytes, &commands).unwrap_or_else(|e| panic!("ttyS2 on {flavor}: {e}"));
    let writes = bytes.len() / WRITE_LEN;
    assert_eq!(
        logged_frames(out, "crsf_frames.jsonl").len(),
        writes,
        "frames logged and written on ttyS2 on {flavor}"
    );
    let proc_serial = read(out, "crsf_proc_serial.txt");
    let tx: usize = proc_serial
        .lines()
        .find(|l| l.starts_with("2:"))
        .and_then(|l| l.split_whitespace().find_map(|f| f.strip_prefix("tx:")))
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no tx count of ttyS2 in\n{proc_serial}"));
    assert_eq!(
        tx,
        bytes.len(),
        "bytes the kernel sent on ttyS2 and bytes QEMU got on {flavor}"
    );

    let tty = read(out, "crsf_tty.txt");
    for want in [
        "data_bits 8",
        "parity None",
        "stop_bits 1",
        "raw true",
        "flow_control false",
        "local_and_read true",
    ] {
        assert!(
            tty.lines().any(|l| l == want),
            "ttyS2 on {flavor}: no `{want}` in\n{tty}"
        );
    }
    let speed = |text: &str, key: &str| -> u64 {
        setting(text, key)
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no {key} in\n{text}"))
    };
    let before = read(out, "crsf_tty_before.txt");
    let uartclk: u64 = read(out, "crsf_uartclk.txt")
        .trim()
        .parse()
        .expect("ttyS2's uartclk");
    let (held, real) = kernel_baud(uartclk, ASKED_BAUD, speed(&before, "ospeed"));
    assert_eq!(
        (speed(&tty, "ispeed"), speed(&tty, "ospeed")),
        (held, held),
        "ttyS2 on {flavor} (uartclk {uartclk} Hz): the 8250 driver holds {held} for {ASKED_BAUD} asked\n{tty}"
    );
    let port = proc_serial
        .lines()
        .find(|l| l.starts_with("2:"))
        .unwrap_or_default();
    eprintln!(
        "crsf on ttyS2 on {flavor}: {writes} writes of {WRITE_LEN} bytes ({} bytes, kernel tx {tx}), writes per command {per_command:?}; \
         uartclk {uartclk} Hz, ppmd asked {ASKED_BAUD} baud, the kernel holds {held} (before: {}), the UART runs at {real} baud ({:+.2}% from {ASKED_BAUD}); {port}",
        bytes.len(),
        speed(&before, "ospeed"),
        (real as f64 / ASKED_BAUD as f64 - 1.0) * 100.0
    );
}

/// check_crsf_bytes on a made-up record of four commands as ppmd encodes
/// them for Betaflight: it passes the true record, and fails a payload
/// byte changed, a CRC changed, a wrong address, link statistics changed,
/// a write cut short, two commands out of order, a value 1 us off and a
/// command missing.
#[test]
fn crsf_byte_check_fails_wrong_bytes() {
    let commands = AILERON_US.map(command_us);
    let write = |c: &[u64; crsf::CHANNELS]| -> Vec<u8> {
        let ns = c.map(|us| us * 1_000);
        let mut w = crsf::encode_ns(CrsfReceiver::Betaflight, &ns).to_vec();
        w.extend_from_slice(&LinkStatistics::WIRED.encode());
        w
    };
    let record = |order: &[usize]| -> Vec<u8> {
        order
            .iter()
            .flat_map(|&c| [write(&commands[c]), write(&commands[c])].concat())
            .collect()
    };
    let good = record(&[0, 1, 2, 3]);
    assert_eq!(check_crsf_bytes(&good, &commands), Ok(vec![2, 2, 2, 2]));

    let fails = |name: &str, bytes: &[u8], want: &str| {
        let e = check_crsf_bytes(bytes, &commands)
            .err()
            .unwrap_or_else(|| panic!("{name}: passed"));
        assert!(e.contains(want), "{name}: {e}");
    };
    let changed = |at: usize, f: fn(u8) -> u8| {
        let mut b = good.clone();
        b[at] = f(b[at]);
        b
    };
    fails("payload byte", &changed(WRITE_LEN + 5, |b| b ^ 0x01), "CRC");
    fails("CRC", &changed(25, |b| b ^ 0x80), "CRC");
    fails("address", &changed(0, |_| 0xEE), "head");
    fails(
        "link statistics",
        &changed(30, |b| b ^ 0x01),
        "link statistics",
    );
    fails("cut short", &good[..good.len() - 1], "not whole writes");
    fails("order", &record(&[0, 2, 1, 3]), "out of order");
    fails("missing", &record(&[0, 1, 3]), "never sent");
    let mut off = commands;
    off[1][0] += 1;
    let mut b = good.clone();
    b.splice(WRITE_LEN * 2..WRITE_LEN * 3, write(&off[1]));
    fails("1 us off", &b, "no command");
}

/// The 8250 driver's arithmetic on the clocks that matter: a PC's 1.8432
/// MHz UART refuses 420 000 baud (keeps what it had) and makes SBUS's
/// 100 000 at 115 200; a 48 MHz clock makes 420 000 with divisor 7
/// (428 571 baud).
#[test]
fn crsf_kernel_baud_follows_the_8250_driver() {
    assert_eq!(kernel_baud(1_843_200, 420_000, 9_600), (9_600, 9_600));
    assert_eq!(kernel_baud(1_843_200, 100_000, 9_600), (100_000, 115_200));
    assert_eq!(kernel_baud(48_000_000, 420_000, 9_600), (420_000, 428_571));
}
