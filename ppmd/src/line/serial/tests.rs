use super::*;
use std::ffi::CStr;
use std::fs::File;
use std::io::Read;
use std::os::fd::{AsRawFd, FromRawFd};
use std::time::{Duration, Instant};

/// A pseudo-terminal: the master end, and the slave's path for
/// [`SerialLine::open`].
struct Pty {
    master: File,
    slave: PathBuf,
}

fn pty() -> Pty {
    // SAFETY: plain libc calls on a descriptor this function owns; the
    // name buffer outlives ptsname_r, which NUL-terminates within it.
    unsafe {
        let fd = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC);
        assert!(fd >= 0, "posix_openpt: {}", io::Error::last_os_error());
        let master = File::from_raw_fd(fd);
        assert_eq!(
            libc::grantpt(fd),
            0,
            "grantpt: {}",
            io::Error::last_os_error()
        );
        assert_eq!(
            libc::unlockpt(fd),
            0,
            "unlockpt: {}",
            io::Error::last_os_error()
        );
        let mut name = [0 as libc::c_char; 128];
        assert_eq!(libc::ptsname_r(fd, name.as_mut_ptr(), name.len()), 0);
        let slave = PathBuf::from(CStr::from_ptr(name.as_ptr()).to_str().unwrap());
        Pty { master, slave }
    }
}

/// Reads from `master` until `want` bytes came or 5 s passed, waiting in
/// poll (never sleeping) for each chunk.
fn read_exactly(master: &mut File, want: usize) -> Vec<u8> {
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut got = Vec::new();
    let mut buf = [0u8; 256];
    while got.len() < want && Instant::now() < deadline {
        let mut pfd = libc::pollfd {
            fd: master.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        // SAFETY: one live pollfd for the whole call.
        let ready = unsafe { libc::poll(&mut pfd, 1, 500) };
        assert!(ready >= 0, "poll: {}", io::Error::last_os_error());
        if ready == 1 {
            let n = master.read(&mut buf).expect("read from the pty master");
            got.extend_from_slice(&buf[..n]);
        }
    }
    got
}

/// Whether `err` says termios2 itself is missing: a user-mode emulator
/// (qemu-user, which runs the Pi's unit tests in CI) answers TCGETS2 with
/// ENOSYS, where any kernel answers a tty and refuses a non-tty (ENOTTY).
/// The tests then say so and stop: they hold on a kernel, native or in the
/// VM, not here.
fn no_termios2_here(err: &SerialError) -> bool {
    let missing = matches!(
        err,
        SerialError::Device { step: SerialStep::ReadSettings, source, .. }
            if source.raw_os_error() == Some(libc::ENOSYS)
    );
    if missing {
        eprintln!("not tested here: this environment does not implement TCGETS2 ({err})");
    }
    missing
}

/// The pty's slave opened as an SBUS serial line; `None` without termios2.
fn open_slave(pty: &Pty) -> Option<SerialLine> {
    open_slave_as(pty, ppm_shared::sbus::uart::FORMAT)
}

/// The pty's slave opened as a serial line in `format`; `None` without
/// termios2.
fn open_slave_as(pty: &Pty, format: UartFormat) -> Option<SerialLine> {
    match SerialLine::open(&pty.slave, format) {
        Ok(line) => Some(line),
        Err(e) if no_termios2_here(&e) => None,
        Err(e) => panic!("open the pty slave: {e:?}"),
    }
}

#[test]
fn pty_holds_100000_baud_8_data_2_stop_raw_and_drops_parity() {
    let pty = pty();
    let Some(line) = open_slave(&pty) else {
        return;
    };
    assert_eq!(line.path(), pty.slave);
    let s = line.settings().expect("TCGETS2");
    assert_eq!((s.ispeed, s.ospeed), (100_000, 100_000));
    assert_eq!(s.data_bits, 8);
    assert_eq!(s.stop_bits, 2);
    // The pty driver (pty_set_termios) clears PARENB: a pty has no wire and
    // no parity bit. A UART keeps PARENB and sends the even parity bit; only
    // a real tty can check that part of 8E2.
    assert_eq!(s.parity, Parity::None);
    assert_eq!(s.flags[2] & libc::PARODD, 0);
    assert!(s.raw, "not raw: flags {:#x?}", s.flags);
    let [iflag, oflag, _, lflag] = s.flags;
    for (flag, name) in [
        (libc::ICRNL, "ICRNL"),
        (libc::INLCR, "INLCR"),
        (libc::IGNCR, "IGNCR"),
        (libc::ISTRIP, "ISTRIP"),
        (libc::IXON, "IXON"),
        (libc::IXOFF, "IXOFF"),
    ] {
        assert_eq!(iflag & flag, 0, "{name} set");
    }
    assert_eq!(oflag & libc::OPOST, 0, "OPOST set");
    for (flag, name) in [
        (libc::ICANON, "ICANON"),
        (libc::ECHO, "ECHO"),
        (libc::ISIG, "ISIG"),
        (libc::IEXTEN, "IEXTEN"),
    ] {
        assert_eq!(lflag & flag, 0, "{name} set");
    }
    assert!(!s.flow_control);
    assert!(s.local_and_read);
    assert_eq!(s.vmin_vtime, (0, 0));
}

#[test]
fn the_format_comes_from_the_wire_8n1_at_420000_one_stop_bit() {
    let pty = pty();
    let format = UartFormat {
        baud: 420_000,
        parity: Parity::None,
        stop_bits: 1,
    };
    let Some(line) = open_slave_as(&pty, format) else {
        return;
    };
    let s = line.settings().expect("TCGETS2");
    assert_eq!((s.ispeed, s.ospeed), (420_000, 420_000));
    assert_eq!((s.data_bits, s.stop_bits, s.parity), (8, 1, Parity::None));
    assert_eq!(s.flags[2] & (libc::PARENB | libc::CSTOPB), 0);
    assert!(s.raw);
    // What another program opening the tty sees.
    let other = SerialLine::settings_of(&pty.slave).expect("TCGETS2");
    assert_eq!((other.ospeed, other.stop_bits), (420_000, 1));
}

#[test]
fn two_frames_come_out_of_the_pty_byte_for_byte() {
    let mut pty = pty();
    let Some(mut line) = open_slave(&pty) else {
        return;
    };
    // Bytes a cooked tty would change or act on: NL, CR, XON, XOFF, DEL,
    // 0xFF (PARMRK's escape), NUL, and the ^C/^D/^Z signal characters.
    let mut first = [0u8; FRAME_LEN];
    first[0] = 0x0F;
    first[1..13].copy_from_slice(&[
        0x0A, 0x0D, 0x11, 0x13, 0x7F, 0xFF, 0x00, 0x03, 0x04, 0x1A, 0x1B, 0x80,
    ]);
    for (i, b) in first.iter_mut().enumerate().skip(13) {
        *b = (i as u8).wrapping_mul(37);
    }
    let mut second = [0u8; FRAME_LEN];
    for (i, b) in second.iter_mut().enumerate() {
        *b = 0xFF - i as u8;
    }
    second[24] = 0x00;
    line.write_frame(&first).expect("first frame");
    line.write_frame(&second).expect("second frame");
    let got = read_exactly(&mut pty.master, 2 * FRAME_LEN);
    let want: Vec<u8> = first.iter().chain(&second).copied().collect();
    assert_eq!(got, want);
    assert_eq!(line.short_writes(), 0);
}

#[test]
fn a_missing_path_fails_opening_and_names_it() {
    let path = std::env::temp_dir().join(format!("ppmd-serial-missing-{}", std::process::id()));
    let err = SerialLine::open(&path, ppm_shared::sbus::uart::FORMAT).expect_err("no such file");
    match &err {
        SerialError::Device {
            path: p,
            step,
            source,
        } => {
            assert_eq!(p, &path);
            assert_eq!(*step, SerialStep::Open);
            assert_eq!(source.kind(), io::ErrorKind::NotFound);
        }
        other => panic!("wrong error: {other:?}"),
    }
    let msg = err.to_string();
    assert!(
        msg.starts_with(&format!("opening {}: ", path.display())),
        "{msg}"
    );
    assert!(
        msg.ends_with("is the UART enabled (enable_uart=1 or a dtoverlay on a Raspberry Pi)?"),
        "{msg}"
    );
}

#[test]
fn a_regular_file_is_refused_as_not_a_tty() {
    let dir = std::env::temp_dir().join(format!("ppmd-serial-notty-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("plain");
    std::fs::write(&path, b"").unwrap();
    let err = SerialLine::open(&path, ppm_shared::sbus::uart::FORMAT)
        .expect_err("a regular file is no tty");
    std::fs::remove_dir_all(&dir).unwrap();
    if no_termios2_here(&err) {
        return;
    }
    match &err {
        SerialError::NotATty { path: p } => assert_eq!(p, &path),
        other => panic!("wrong error: {other:?}"),
    }
    assert_eq!(
        err.to_string(),
        format!(
            "{} is not a tty (TCGETS2: inappropriate ioctl for device): name a serial device such as /dev/ttyAMA0 or /dev/ttyUSB0",
            path.display()
        )
    );
}

#[test]
fn permission_denied_says_to_join_dialout() {
    let err = SerialError::Device {
        path: PathBuf::from("/dev/ttyAMA0"),
        step: SerialStep::Open,
        source: io::Error::from_raw_os_error(libc::EACCES),
    };
    assert_eq!(
        err.to_string(),
        "opening /dev/ttyAMA0: Permission denied (os error 13): add the user to the dialout group"
    );
}

#[test]
fn a_rate_the_uart_could_not_make_is_told_apart_from_its_rounding() {
    // A 16550 at 1.8432 MHz: 100000 asked runs at 115200 (15 % off), 420000
    // keeps 9600; a 48 MHz PL011 makes 420000 within 0.1 %.
    assert!(baud_off(100_000, 115_200));
    assert!(baud_off(420_000, 9_600));
    assert!(!baud_off(420_000, 420_168));
    assert!(!baud_off(100_000, 100_000));
    assert!(!baud_off(100_000, 101_900));
    assert!(baud_off(100_000, 102_100));
}
