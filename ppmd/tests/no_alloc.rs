//! Nothing allocates in the timing loop after start: the loop runs with the
//! real iceoryx2 command source (fed by a publisher in another thread), the
//! simulated line and the meter's interval hand-over, under a global allocator
//! that counts every allocation made on the loop's thread once the first
//! frames are out.

use ppm_shared::config::{Config, FailsafeAction, Timing};
use ppm_shared::frame::{Level, Protocol};
use ppm_shared::ipc::{self, CommandSample};
use ppm_shared::protocol::parse;
use ppmd::clock::{self, Margin};
use ppmd::emitter::{self, EmitterConfig, LineRef, Output, Recording, Stats};
use ppmd::line::{spi, Bank, FrameLine, LineError, SimFrameLine, SimLine, WholeFrame};
use ppmd::source::{CommandSource, IpcSource};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
}

struct CountingAllocator;

fn note() {
    if COUNTING.try_with(Cell::get).unwrap_or(false) {
        ALLOCATIONS.fetch_add(1, Relaxed);
    }
}

unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        note();
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: CountingAllocator = CountingAllocator;

/// Passes the real source through; starts counting once `warmup` frames are
/// out and stops the loop once `frames` are (counted by the loop's own stats,
/// so polls while the line is still silent do not count).
struct Counted {
    inner: Box<dyn CommandSource>,
    stats: Arc<Stats>,
    warmup: u64,
    frames: u64,
    stop: Arc<AtomicBool>,
}

impl CommandSource for Counted {
    fn wake_fd(&self) -> Option<std::os::fd::RawFd> {
        self.inner.wake_fd()
    }
    fn clear_wake(&mut self) -> bool {
        self.inner.clear_wake()
    }
    fn newest(&mut self) -> Option<CommandSample> {
        let emitted = self.stats.frames.load(Relaxed);
        if emitted >= self.warmup {
            COUNTING.with(|c| c.set(true));
        }
        if emitted >= self.frames {
            self.stop.store(true, Relaxed);
        }
        self.inner.newest()
    }
}

/// The loop's spin margin in these tests: ppmd's default.
const MARGIN: Margin = Margin::Auto {
    min_ns: 20_000,
    max_ns: 1_000_000,
};

/// The outputs' settings in these tests: the failsafe holding the last
/// command after 200 ms.
fn emitter_config() -> EmitterConfig {
    EmitterConfig {
        failsafe_after_ns: 200_000_000,
        failsafe_action: FailsafeAction::Hold,
        startup: FailsafeAction::Silence,
    }
}

#[test]
fn the_timing_loop_does_not_allocate_after_start() {
    // Grid: commands faster than frames. Follow: slower, so the loop sleeps
    // on the wake-up between frames and is woken by each command.
    run_without_allocating(Timing::Grid, 5, false);
    run_without_allocating(Timing::Follow, 25, false);
    // A line that takes whole frames, encoding each as the SPI line
    // does into its preallocated buffer.
    run_without_allocating(Timing::Grid, 5, true);
}

/// The SPI line without the device: each frame encoded into the buffer
/// sized at start, as [`ppmd::line::spi::SpiLine`] does before its ioctl.
struct SpiStandIn {
    buf: Vec<u8>,
    bytes: u64,
}

impl FrameLine for SpiStandIn {
    fn park(&mut self, _: Level) -> Result<(), LineError> {
        Ok(())
    }
    fn write_frame(&mut self, frame: WholeFrame<'_>) -> Result<(), LineError> {
        let n = match frame {
            WholeFrame::Ppm { edges, .. } => spi::encode(edges, 1_000_000, &mut self.buf),
            WholeFrame::Bytes { bytes, .. } => {
                spi::encode_sbus(bytes.try_into().expect("an SBUS frame"), &mut self.buf)
            }
        }
        .ok_or(LineError::FrameTooLong)?;
        self.bytes += n as u64;
        Ok(())
    }
}

/// SBUS frames, written whole: on the simulated line (each frame's UART
/// waveform into the trace) and encoded for SPI.
#[test]
fn the_timing_loop_does_not_allocate_after_start_with_sbus() {
    run_with(Timing::Grid, 3, false, Protocol::Sbus);
    run_with(Timing::Follow, 10, false, Protocol::Sbus);
    run_with(Timing::Follow, 10, true, Protocol::Sbus);
}

#[test]
fn the_timing_loop_does_not_allocate_after_start_with_crsf() {
    run_with(Timing::Grid, 3, false, Protocol::Crsf);
    // No spi: output carries CRSF, so no stand-in for one.
    run_with(Timing::Follow, 10, false, Protocol::Crsf);
}

fn run_without_allocating(timing: Timing, every_ms: u64, whole_frames: bool) {
    run_with(timing, every_ms, whole_frames, Protocol::Ppm);
}

fn run_with(timing: Timing, every_ms: u64, whole_frames: bool, protocol: Protocol) {
    ALLOCATIONS.store(0, Relaxed);
    let name = format!(
        "noalloc{}{}{}{}",
        std::process::id(),
        timing.name(),
        whole_frames as u8,
        protocol.name()
    );
    let dir = std::env::temp_dir().join(format!("ppmd-{name}"));
    std::fs::create_dir_all(&dir).unwrap();
    let root = dir.join("ipc");
    let mut cfg = Config::default();
    cfg.ppm.timing = timing;
    cfg.ppm.protocol = protocol;
    let model = cfg.validate().unwrap();

    // The publisher: a fresh command every `every_ms` until told to stop,
    // each followed by a wake-up, as udp-ingress sends them.
    let done = Arc::new(AtomicBool::new(false));
    let publisher = {
        let (done, root, name, model) = (done.clone(), root.clone(), name.clone(), model.clone());
        std::thread::spawn(move || {
            let node = ipc::create_node(&root, "noalloc-pub").unwrap();
            let service = ipc::open_command_service(&node, &name).unwrap();
            let p = service.publisher_builder().create().unwrap();
            let wake = ipc::open_wake_service(&node, &name).unwrap();
            let notifier = wake.notifier_builder().create().unwrap();
            let mut k = 0u64;
            while !done.load(Relaxed) {
                k += 1;
                let cmd = parse(format!("[{}]", 1000 + k % 1000).as_bytes(), &model).unwrap();
                let s = CommandSample::new(&cmd, model.fingerprint(), k, clock::now_ns(), 0);
                p.loan_uninit().unwrap().write_payload(s).send().unwrap();
                notifier.notify().unwrap();
                std::thread::sleep(Duration::from_millis(every_ms));
            }
        })
    };

    let stop = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(Stats::default());
    let (mut meter, mut reader) = ppmd::meter::meter(100_000_000);
    let reader_stop = Arc::new(AtomicBool::new(false));
    let drained = Arc::new(AtomicU64::new(0));
    let reader_thread = {
        let (reader_stop, drained) = (reader_stop.clone(), drained.clone());
        std::thread::spawn(move || {
            let mut drain = || {
                reader.drain(|_| {
                    drained.fetch_add(1, Relaxed);
                })
            };
            while !reader_stop.load(Relaxed) {
                drain();
                std::thread::sleep(Duration::from_millis(20));
            }
            // What the loop handed over last, at its end.
            drain();
        })
    };
    let looper = {
        let (stop, stats, model, trace) = (
            stop.clone(),
            stats.clone(),
            model.clone(),
            dir.join("t.trace"),
        );
        std::thread::spawn(move || {
            let mut source = Counted {
                inner: Box::new(IpcSource::open(&root, &name, timing == Timing::Follow).unwrap()),
                stats: stats.clone(),
                warmup: 10,
                frames: 60,
                stop: stop.clone(),
            };
            let mut spi = whole_frames.then(|| SpiStandIn {
                buf: vec![0; 8192],
                bytes: 0,
            });
            let mut sim = (!whole_frames && protocol == Protocol::Ppm)
                .then(|| SimLine::create(&trace, &["idle_level 0".into()], u64::MAX).unwrap());
            let mut sim_sbus = (!whole_frames && model.wire().uart().is_some()).then(|| {
                let sim = SimLine::create(&trace, &["idle_level 1".into()], u64::MAX).unwrap();
                SimFrameLine::new(sim, Level::High, model.wire().uart(), clock::now_ns)
            });
            let line = match (&mut spi, &mut sim, &mut sim_sbus) {
                (Some(spi), _, _) => LineRef::Whole(spi),
                (_, Some(sim), _) => LineRef::Edges(sim),
                (_, _, Some(sim)) => LineRef::Whole(sim),
                _ => unreachable!("one of the three"),
            };
            let cfg = emitter_config();
            emitter::run(
                &model,
                &cfg,
                MARGIN,
                &mut source,
                line,
                &stop,
                &stats,
                &mut meter,
                None,
            );
            COUNTING.with(|c| c.set(false));
        })
    };
    looper.join().unwrap();
    done.store(true, Relaxed);
    reader_stop.store(true, Relaxed);
    publisher.join().unwrap();
    reader_thread.join().unwrap();

    let frames = stats.frames.load(Relaxed);
    assert!(frames >= 50, "only {frames} frames");
    // A frame aborted at a late edge (this thread is not real-time) goes
    // out again without a new command in follow timing.
    let (commands, aborted) = (
        stats.commands.load(Relaxed),
        stats.aborted_frames.load(Relaxed),
    );
    assert!(
        commands + aborted >= 50,
        "{commands} commands, {aborted} aborted frames"
    );
    // Intervals went over while the loop ran and at its end (how many
    // the reader got in between depends on how often it ran: the ring
    // holds four, and the loop counts a hand-over it could not make).
    assert!(
        drained.load(Relaxed) >= 2,
        "the meter handed intervals over: {}",
        drained.load(Relaxed)
    );
    assert_eq!(
        ALLOCATIONS.load(Relaxed),
        0,
        "the timing loop allocated after its first frames ({} timing{})",
        timing.name(),
        if whole_frames { ", whole frames" } else { "" }
    );
    if whole_frames {
        assert_eq!(stats.write_errors.load(Relaxed), 0, "every frame encoded");
    }
    let _ = std::fs::remove_dir_all(dir);
}

/// A GPIO bank's write fills a preallocated value set (the ioctl itself
/// takes it by reference): every mask and level pattern, without allocating.
#[test]
fn filling_a_bank_value_set_does_not_allocate() {
    use gpiocdev::line::{Value, Values};
    use ppmd::line::gpio::fill_values;
    let offsets = [18u32, 3, 27, 4];
    let mut values = Values::from_offsets(&offsets);
    fill_values(&mut values, &offsets, 0, 0);
    COUNTING.with(|c| c.set(true));
    for round in 0..1_000u64 {
        let mask = round % 16;
        let levels = round.rotate_left(3) % 16;
        fill_values(&mut values, &offsets, mask, levels);
        let held = (0..4).filter(|i| mask & (1 << i) != 0).count();
        assert_eq!(values.len(), held);
    }
    COUNTING.with(|c| c.set(false));
    assert_eq!(
        ALLOCATIONS.load(Relaxed),
        0,
        "filling the value set allocated"
    );
    fill_values(&mut values, &offsets, 0b0101, 0b0001);
    assert_eq!(values.get(18), Some(Value::Active));
    assert_eq!(values.get(27), Some(Value::Inactive));
    assert_eq!(values.get(3), None);
}

/// A fresh command every few ms, from a sample made before the loop runs;
/// counts from the `warmup`-th frame of `stats` on and stops the loop at
/// `frames`.
struct Synthetic {
    sample: CommandSample,
    every_ns: u64,
    next_ns: u64,
    stats: Arc<Stats>,
    warmup: u64,
    frames: u64,
    stop: Arc<AtomicBool>,
}

impl CommandSource for Synthetic {
    fn newest(&mut self) -> Option<CommandSample> {
        let emitted = self.stats.frames.load(Relaxed);
        if emitted >= self.warmup {
            COUNTING.with(|c| c.set(true));
        }
        if emitted >= self.frames {
            self.stop.store(true, Relaxed);
        }
        let now = clock::now_ns();
        (now >= self.next_ns).then(|| {
            self.next_ns = now + self.every_ns;
            let mut s = self.sample;
            s.recv_mono_ns = now;
            s
        })
    }
}

/// Two lines of one bank: the levels go to a preallocated word, as the GPIO
/// bank fills its preallocated value set.
struct BankStandIn {
    levels: u64,
    writes: u64,
}

impl Bank for BankStandIn {
    fn write(&mut self, _scheduled_ns: u64, mask: u64, levels: u64) -> Result<(), LineError> {
        self.levels = (self.levels & !mask) | (levels & mask);
        self.writes += 1;
        Ok(())
    }
    fn park(&mut self, _bit: u32, _level: Level) -> Result<(), LineError> {
        Ok(())
    }
}

/// Two outputs on one bank (one grid, one follow), each with its own source,
/// stats and meter, the first with a frame log: the loop that serves several
/// outputs does not allocate either, nor does queueing frame-log rows.
#[test]
fn two_outputs_on_a_bank_do_not_allocate() {
    let log_path =
        std::env::temp_dir().join(format!("ppmd-noalloc-{}-two.jsonl", std::process::id()));
    let (mut producer, mut log_writer) = ppmd::framelog::open(&log_path, u64::MAX).unwrap();
    let mut grid_cfg = Config::default();
    grid_cfg.ppm.timing = Timing::Grid;
    let grid = grid_cfg.validate().unwrap();
    let mut follow_cfg = Config::default();
    follow_cfg.ppm.timing = Timing::Follow;
    let follow = follow_cfg.validate().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let stats = [Arc::new(Stats::default()), Arc::new(Stats::default())];
    let looper = {
        let (stop, stats) = (stop.clone(), stats.clone());
        std::thread::spawn(move || {
            let producer = &mut producer;
            let source = |model: &ppm_shared::FrameModel, st: &Arc<Stats>, every_ms: u64| {
                let cmd = parse(b"[1100, 1900, 1300]", model).unwrap();
                Synthetic {
                    sample: CommandSample::new(&cmd, model.fingerprint(), 1, 0, 0),
                    every_ns: every_ms * 1_000_000,
                    next_ns: 0,
                    stats: st.clone(),
                    warmup: 10,
                    frames: 60,
                    stop: stop.clone(),
                }
            };
            let mut sources = [source(&grid, &stats[0], 5), source(&follow, &stats[1], 20)];
            let (mut m0, _r0) = ppmd::meter::meter(100_000_000);
            let (mut m1, _r1) = ppmd::meter::meter(100_000_000);
            let cfg = emitter_config();
            let mut bank = BankStandIn {
                levels: 0,
                writes: 0,
            };
            {
                let [s0, s1] = &mut sources;
                let mut outputs = [
                    Output {
                        model: &grid,
                        cfg,
                        source: s0,
                        line: LineRef::Banked { bank: 0, bit: 0 },
                        rec: Recording {
                            stats: &stats[0],
                            meter: &mut m0,
                            log: Some(producer),
                        },
                        sync: None,
                    },
                    Output {
                        model: &follow,
                        cfg,
                        source: s1,
                        line: LineRef::Banked { bank: 0, bit: 1 },
                        rec: Recording {
                            stats: &stats[1],
                            meter: &mut m1,
                            log: None,
                        },
                        sync: None,
                    },
                ];
                let mut banks: [&mut dyn Bank; 1] = [&mut bank];
                emitter::run_outputs(
                    &ppmd::clock::SystemClock,
                    MARGIN,
                    &mut outputs,
                    &mut banks,
                    &stop,
                );
            }
            COUNTING.with(|c| c.set(false));
            bank.writes
        })
    };
    let writes = looper.join().unwrap();
    log_writer.finish();
    let rows = std::fs::read_to_string(&log_path).unwrap().lines().count() as u64;
    let _ = std::fs::remove_file(&log_path);
    assert!(
        rows >= stats[0].frames.load(Relaxed),
        "{rows} frame-log rows for {} frames",
        stats[0].frames.load(Relaxed)
    );
    for (i, s) in stats.iter().enumerate() {
        assert!(
            s.frames.load(Relaxed) >= 10,
            "output {i}: {} frames",
            s.frames.load(Relaxed)
        );
        assert_eq!(s.write_errors.load(Relaxed), 0);
    }
    assert!(writes > 0);
    assert_eq!(
        ALLOCATIONS.load(Relaxed),
        0,
        "the loop of two outputs on a bank allocated after its first frames"
    );
}

/// An output that drives a transmitter module, its commands through a
/// pilot's radio: while another thread flips who flies every 30 ms, stores
/// a pilot's frame every 10 ms and leaves a module's correction every
/// 20 ms, the loop takes them all without allocating.
#[test]
fn a_module_output_through_a_pilots_radio_does_not_allocate() {
    use ppm_shared::crsf::module::Correction;
    use ppmd::emitter::module::ModuleTiming;
    use ppmd::pilot::{PilotFrame, PilotMux, PilotSlot, PilotState};
    ALLOCATIONS.store(0, Relaxed);
    let name = format!("noallocmodule{}", std::process::id());
    let dir = std::env::temp_dir().join(format!("ppmd-{name}"));
    std::fs::create_dir_all(&dir).unwrap();
    let root = dir.join("ipc");
    let model = Config::parse(
        "[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\n[ppmd]\npilot = 'sim:p.trace'\n[pilot]\nswitch_channel = 5",
    )
    .unwrap()
    .validate()
    .unwrap();
    let slot = Arc::new(PilotSlot::default());
    let timing = Arc::new(ModuleTiming::default());
    let done = Arc::new(AtomicBool::new(false));
    let feeder = {
        let (done, root, name, model, slot, timing) = (
            done.clone(),
            root.clone(),
            name.clone(),
            model.clone(),
            slot.clone(),
            timing.clone(),
        );
        std::thread::spawn(move || {
            let node = ipc::create_node(&root, "noalloc-pub").unwrap();
            let service = ipc::open_command_service(&node, &name).unwrap();
            let p = service.publisher_builder().create().unwrap();
            let mut k = 0u64;
            while !done.load(Relaxed) {
                k += 1;
                let cmd = parse(format!("[{}]", 1000 + k % 1000).as_bytes(), &model).unwrap();
                let s = CommandSample::new(&cmd, model.fingerprint(), k, clock::now_ns(), 0);
                p.loan_uninit().unwrap().write_payload(s).send().unwrap();
                let state = if (k / 3).is_multiple_of(2) {
                    PilotState::Groundstation
                } else {
                    PilotState::Pilot
                };
                let now = clock::now_ns();
                slot.store(&PilotFrame {
                    frame: k,
                    end_mono_ns: now,
                    end_real_ns: ppm_shared::time::realtime_ns(),
                    state,
                    channels: 8,
                    values_ns: [1_600_000; 16],
                });
                slot.set_state(state);
                if k.is_multiple_of(2) {
                    let c = Correction {
                        rate_tenths: 40_000 + (k % 7) as i32 * 1_000,
                        offset_tenths: (k % 5) as i32 * 500 - 1_000,
                    };
                    timing.set(c, now);
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        })
    };
    let stop = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(Stats::default());
    let looper = {
        let (stop, stats, model, trace, slot, timing) = (
            stop.clone(),
            stats.clone(),
            model.clone(),
            dir.join("t.trace"),
            slot.clone(),
            timing.clone(),
        );
        std::thread::spawn(move || {
            let ground = Box::new(IpcSource::open(&root, &name, false).unwrap());
            let mut source = Counted {
                inner: Box::new(PilotMux::new(ground, slot, &model)),
                stats: stats.clone(),
                warmup: 10,
                frames: 150,
                stop: stop.clone(),
            };
            let sim = SimLine::create(&trace, &["idle_level 1".into()], u64::MAX).unwrap();
            let mut line = SimFrameLine::new(sim, Level::High, model.wire().uart(), clock::now_ns);
            let (mut meter, _reader) = ppmd::meter::meter(100_000_000);
            let mut outputs = [Output {
                model: &model,
                cfg: emitter_config(),
                source: &mut source,
                line: LineRef::Whole(&mut line),
                rec: Recording {
                    stats: &stats,
                    meter: &mut meter,
                    log: None,
                },
                sync: Some(&timing),
            }];
            emitter::run_outputs(
                &ppmd::clock::SystemClock,
                MARGIN,
                &mut outputs,
                &mut [],
                &stop,
            );
            COUNTING.with(|c| c.set(false));
        })
    };
    looper.join().unwrap();
    done.store(true, Relaxed);
    feeder.join().unwrap();
    assert!(
        stats.frames.load(Relaxed) >= 150,
        "{} frames",
        stats.frames.load(Relaxed)
    );
    assert!(timing.count() >= 10, "{} corrections", timing.count());
    assert_eq!(
        ALLOCATIONS.load(Relaxed),
        0,
        "the timing loop allocated after its first frames (module, pilot's radio)"
    );
    let _ = std::fs::remove_dir_all(dir);
}
