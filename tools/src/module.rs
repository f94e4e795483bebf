//! A simulated ExpressLRS transmitter module and a simulated pilot's
//! radio, for the module output's tests and benchmark.
//!
//! [`SimModule`] is the handset side of an ExpressLRS module on the bytes
//! as they arrive: it frames them as the module does
//! ([`HandsetParser`], a port of `CRSFHandset::handleInput`), keeps its own
//! radio packet timer, measures at each packet how long before it the
//! newest RC frame came (`JustSentRFpacket`, with its averaging window and
//! its forced resync when no frame came for a whole interval), and answers
//! after a good frame, at most every 200 ms, with a timing correction and
//! link statistics (`handleOutput`, `sendSyncPacketToTX`), each starting
//! with the sync byte 0xC8 as on its serial port.

use ppm_shared::crsf::module::{
    Correction, HandsetParser, MODEL_ID_FRAME_LEN, SAFE_MARGIN_TENTHS, TYPE_COMMAND,
};
use ppm_shared::crsf::{self, LinkStatistics};
use ppm_shared::time::now_ns;
use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::SeqCst};
use std::time::Duration;

/// How often the module answers with a correction, ns
/// (`OpenTXsyncPacketInterval`).
const SYNC_EVERY_NS: u64 = 200_000_000;

/// The simulated module.
pub struct SimModule {
    /// Its packet interval, us (`RequestedRCpacketInterval`).
    interval_us: i64,
    /// Its link statistics, sent with each correction.
    link: LinkStatistics,
    /// Its framing of what the handset sends.
    pub parser: HandsetParser,
    /// `dataLastRecv`: when the newest good frame came.
    last_recv: Option<u64>,
    /// The radio's next packet, once frames come.
    next_tick: Option<u64>,
    /// `OpenTXsyncOffset`, tenths of a us, and `OpenTXsyncWindow`.
    offset: i64,
    window: i64,
    last_sync: Option<u64>,
    /// Every packet: when it went, and how long before it the newest frame
    /// came, ns.
    pub ticks: Vec<(u64, u64)>,
    /// Every good RC frame: when it came, its bytes.
    pub frames: Vec<(u64, Vec<u8>)>,
    /// Every model ID command: when it came, the ID.
    pub model_ids: Vec<(u64, u8)>,
    /// Good frames of other types.
    pub other: u64,
}

impl SimModule {
    /// A module sending a packet every `interval_us`, with `link` as its
    /// link statistics.
    pub fn new(interval_us: i64, link: LinkStatistics) -> SimModule {
        SimModule {
            interval_us,
            link,
            parser: HandsetParser::default(),
            last_recv: None,
            next_tick: None,
            offset: 0,
            window: 0,
            last_sync: None,
            ticks: Vec::new(),
            frames: Vec::new(),
            model_ids: Vec::new(),
            other: 0,
        }
    }

    /// Bytes from the handset at `now`: the module's answer.
    pub fn bytes(&mut self, now: u64, bytes: &[u8]) -> Vec<u8> {
        self.ticks_until(now);
        let mut frames = Vec::new();
        self.parser.feed(bytes, |f| frames.push(f.to_vec()));
        if frames.is_empty() {
            return Vec::new();
        }
        self.last_recv = Some(now);
        // The radio's timer runs on its own: its phase is anything.
        self.next_tick.get_or_insert(now + 1_234_567);
        for f in frames {
            match f[2] {
                crsf::TYPE_RC_CHANNELS_PACKED => self.frames.push((now, f)),
                TYPE_COMMAND if f.len() == MODEL_ID_FRAME_LEN => self.model_ids.push((now, f[7])),
                _ => self.other += 1,
            }
        }
        if self.last_sync.is_some_and(|s| now - s < SYNC_EVERY_NS) {
            return Vec::new();
        }
        self.last_sync = Some(now);
        let c = Correction {
            rate_tenths: (self.interval_us * 10) as i32,
            offset_tenths: (self.offset - i64::from(SAFE_MARGIN_TENTHS)) as i32,
        };
        let mut out = c.encode().to_vec();
        out.extend(crsf::frame(
            crsf::ADDRESS_FLIGHT_CONTROLLER,
            crsf::TYPE_LINK_STATISTICS,
            &self.link.encode()[3..3 + LinkStatistics::PAYLOAD_LEN],
        ));
        out
    }

    /// `JustSentRFpacket` at every packet up to `now`.
    fn ticks_until(&mut self, now: u64) {
        let (Some(last), Some(mut tick)) = (self.last_recv, self.next_tick) else {
            return;
        };
        let interval = self.interval_us as u64 * 1_000;
        let size = (20_000 / self.interval_us).max(1);
        while tick <= now {
            let delta_us = (tick.saturating_sub(last) / 1_000) as i64;
            if delta_us >= self.interval_us {
                self.offset = -(delta_us % self.interval_us) * 10;
                self.window = 0;
                self.last_sync = self.last_sync.map(|s| s.saturating_sub(SYNC_EVERY_NS));
            } else {
                self.window = (self.window + 1).min(size);
                self.offset = (self.offset * (self.window - 1) + delta_us * 10) / self.window;
            }
            self.ticks.push((tick, tick.saturating_sub(last)));
            tick += interval;
        }
        self.next_tick = Some(tick);
    }
}

/// What the simulated pilot's sticks send on channels 1 to 4, us.
pub const PILOT_STICKS_US: [u64; 4] = [1_600, 1_450, 1_100, 1_550];

/// The pilot's radio: 8 channels every 22.5 ms into `out` (a trace of the
/// simulated line, for `ppmd.pilot = "sim:PATH"`), channel 5 the takeover
/// switch (2000 us while `takeover` is set, 1000 us otherwise), the sticks
/// at [`PILOT_STICKS_US`]; each edge written once its time has passed, as
/// the kernel reports edges. `flipped_at` gets the start of the first
/// frame after each flip. Returns when `stop` is set.
pub fn pilot_radio(out: &Path, takeover: &AtomicBool, flipped_at: &AtomicU64, stop: &AtomicBool) {
    let mut file = std::fs::File::create(out).expect("creating the pilot's trace");
    file.write_all(b"# idle_level 0\n")
        .expect("writing the pilot's trace");
    let mut next = now_ns();
    let mut pending = std::collections::VecDeque::new();
    let mut was = false;
    while !stop.load(SeqCst) {
        let now = now_ns();
        let mut text = String::new();
        while pending.front().is_some_and(|(t, _)| *t <= now) {
            let (t, level) = pending.pop_front().expect("an edge");
            text.push_str(&format!("{t} {t} {level}\n"));
        }
        if !text.is_empty() {
            file.write_all(text.as_bytes())
                .and_then(|_| file.flush())
                .expect("writing the pilot's trace");
        }
        if now < next {
            std::thread::sleep(Duration::from_nanos((next - now).min(500_000)));
            continue;
        }
        let start = next;
        next += 22_500_000;
        let on = takeover.load(SeqCst);
        if on != was {
            was = on;
            flipped_at.store(start, SeqCst);
        }
        let switch = if on { 2_000 } else { 1_000 };
        let mut us = [1_500; 8];
        us[..4].copy_from_slice(&PILOT_STICKS_US);
        us[4] = switch;
        pending.extend(crate::radio::frame_edges(start, &us));
    }
}
