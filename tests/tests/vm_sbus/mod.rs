//! The SBUS half of the real-kernel test (a helper module of vm.rs): ppmd's
//! SBUS on the guest's second serial port (a 16550, whose bytes QEMU writes
//! to a host file) and through spidev on the spi-gpio master, each frame's
//! bits rebuilt from the kernel's gpio_value trace and read as a UART
//! receiver of true SBUS reads them.
//!
//! Bit timing inside emulation means nothing: the emulated 16550's 1.8432
//! MHz clock cannot make 100 000 baud (the kernel picks the nearest
//! divisor, 115 200 baud, and keeps the 100 000 asked for in the
//! settings), QEMU's file backend gets bytes without their bits, and
//! spi-gpio clocks as fast as gpiolib goes. What is checked is what the
//! kernel holds and every byte and bit.

use super::{logged_frames, read};
use crate::vm_spi::{parse_spi_lines, spi_transfers, trace_sets};
use ppm_shared::frame::Level;
use ppm_shared::sbus::{self, uart, SbusReceiver, Verdict};
use std::path::Path;

/// What EdgeTX reads of the guest's command: ail 1000, ele 1200, thr 1700,
/// rud 2000, aux1..aux11 at their default (1500), aux12 1900, us.
fn command_us() -> [u64; sbus::CHANNELS] {
    let mut v = [1_500; sbus::CHANNELS];
    v[..4].copy_from_slice(&[1_000, 1_200, 1_700, 2_000]);
    v[15] = 1_900;
    v
}

/// Checks one frame as EdgeTX reads it: the command, exactly.
fn check_frame(frame: &[u8; sbus::FRAME_LEN], what: &str) {
    match SbusReceiver::EdgeTx.verdict(frame) {
        Verdict::Used(r) => {
            let us = r.channels_ns.map(|ns| ns / 1_000);
            assert_eq!(us, command_us(), "{what}: {frame:02x?}");
        }
        v => panic!("{what}: EdgeTX gives {v:?} for {frame:02x?}"),
    }
}

/// SBUS on ttyS1: the kernel holds 100 000 baud, 8 data bits, even parity,
/// 2 stop bits, raw, no flow control; the port carried whole frames only,
/// each the command exactly, one per frame logged.
pub(crate) fn check_sbus_serial(out: &Path, flavor: &str) {
    let log = read(out, "sbus_ppmd.log");
    assert_eq!(read(out, "sbus_ppmd_exit.txt").trim(), "0", "{log}");
    assert!(log.contains("serial /dev/ttyS1"), "{log}");
    assert!(log.contains(" 0 write errors"), "{log}");
    let tty = read(out, "sbus_tty.txt");
    for want in [
        "ispeed 100000",
        "ospeed 100000",
        "data_bits 8",
        "parity Even",
        "stop_bits 2",
        "raw true",
        "flow_control false",
        "local_and_read true",
    ] {
        assert!(
            tty.lines().any(|l| l == want),
            "ttyS1 on {flavor}: no `{want}` in\n{tty}"
        );
    }
    let bytes = std::fs::read(out.join("serial1.bin")).expect("serial1.bin");
    assert_eq!(
        bytes.len() % sbus::FRAME_LEN,
        0,
        "{} bytes on ttyS1 on {flavor}: not whole frames",
        bytes.len()
    );
    let frames = bytes.len() / sbus::FRAME_LEN;
    assert!(frames >= 40, "{frames} frames on ttyS1 on {flavor}");
    for (k, f) in bytes.chunks(sbus::FRAME_LEN).enumerate() {
        check_frame(
            f.try_into().unwrap(),
            &format!("frame {k} on ttyS1 on {flavor}"),
        );
    }
    assert_eq!(
        logged_frames(out, "sbus_frames.jsonl").len(),
        frames,
        "frames logged and sent on ttyS1 on {flavor}"
    );
    eprintln!(
        "sbus on ttyS1 on {flavor}: {frames} frames, the kernel holds {}",
        tty.replace('\n', ", ")
    );
}

/// SBUS through spidev: every frame one transfer of 38 bytes at 100 kHz,
/// read as true SBUS (MOSI idles low) by a UART receiver: 25 characters
/// back to back, parity and stop bits right, the command exactly; MOSI low
/// and still between transfers.
pub(crate) fn check_sbus_spi(out: &Path, flavor: &str) {
    let log = read(out, "sbus_spi_ppmd.log");
    assert_eq!(read(out, "sbus_spi_ppmd_exit.txt").trim(), "0", "{log}");
    assert!(
        log.contains("spi /dev/spidev0.0 at 100000 Hz (true SBUS"),
        "{log}"
    );
    assert!(log.contains(" 0 write errors"), "{log}");
    let lines = parse_spi_lines(&read(out, "spi_lines.txt"));
    let sets = trace_sets(
        &read(out, "sbus_spi_trace.txt"),
        &[lines.sck, lines.mosi, lines.cs],
    );
    let bus = spi_transfers(&sets, &lines);
    assert_eq!(
        bus.sck_rises_outside, 0,
        "SCK clocked with CS high on {flavor}"
    );
    assert!(
        bus.mosi_changes_outside.is_empty(),
        "MOSI changed between transfers on {flavor} at {:?} us",
        bus.mosi_changes_outside
    );
    let (mut frames, mut parks) = (Vec::new(), Vec::new());
    for (k, x) in bus.transfers.iter().enumerate() {
        let what = format!("transfer {k} of the SBUS spi output on {flavor}");
        if x.bits.iter().all(|&b| b == 0) {
            // ppmd parking the line low when it opens the device and at
            // exit: only before the first frame or after the last.
            parks.push(k);
            continue;
        }
        assert_eq!(x.bits.len(), 304, "{what}: 38 bytes");
        // Bit k at k * 10 us: edges where the level changes.
        let mut edges = Vec::new();
        let mut level = Level::Low;
        for (i, &b) in x.bits.iter().enumerate() {
            let l = Level::from_bit(b == 1);
            if l != level {
                edges.push((i as u64 * uart::BIT_NS, l));
                level = l;
            }
        }
        let chars = uart::decode(&edges, Level::Low);
        assert_eq!(chars.len(), sbus::FRAME_LEN, "{what}: {chars:?}");
        for (i, c) in chars.iter().enumerate() {
            assert!(c.parity_ok && c.stop_ok, "{what}: character {i} {c:?}");
            assert_eq!(
                c.start_ns,
                i as u64 * 120_000,
                "{what}: character {i} not back to back"
            );
        }
        let frame: [u8; sbus::FRAME_LEN] = std::array::from_fn(|i| chars[i].byte);
        check_frame(&frame, &what);
        assert_eq!(bus.mosi_after[k], Some(0), "{what}: MOSI not low after it");
        frames.push(k);
    }
    assert!(
        frames.len() >= 40,
        "{} SBUS transfers on {flavor}",
        frames.len()
    );
    let (first, last) = (frames[0], frames[frames.len() - 1]);
    assert!(
        parks.iter().all(|&k| k < first || k > last),
        "idle transfers {parks:?} among the frames {first}..={last} on {flavor}"
    );
    assert_eq!(
        logged_frames(out, "sbus_spi_frames.jsonl").len(),
        frames.len(),
        "frames logged and sent through spi on {flavor}"
    );
    eprintln!(
        "sbus through spi on {flavor}: {} frames of 304 bits, each 25 characters back to back (reported: bit timing under emulation means nothing)",
        frames.len()
    );
}
