//! A GPIO line read as an input: requested through the GPIO character
//! device (uAPI v2) with both edges detected, no debounce and
//! CLOCK_MONOTONIC timestamps taken by the kernel in its interrupt handler,
//! so an edge's time does not depend on when this thread wakes.
//!
//! - [`GpioInput::open`]: resolves CHIP and LINE as an output's line is
//!   resolved ([`crate::line::gpio::resolve_line`]) and requests the line.
//! - [`EVENT_BUFFER_SIZE`]: how many edges the kernel keeps for us while
//!   the reader is held up, and how it is worked out.
//! - [`GpioInput`]'s [`EdgeSource::read`]: one `ppoll`, then one `read`
//!   of every event available (up to the caller's slice) into a buffer
//!   allocated at open.

use super::{EdgeSource, InputError};
use crate::line::gpio::{describe_line, input_request_error, resolve_line};
use gpiocdev::line::{EdgeDetection, EdgeKind, EventClock};
use gpiocdev::Request;
use ppm_shared::capture::{EdgeEvent, InputSpec};
use ppm_shared::signal::{Level, MAX_EDGES};
use std::time::Duration;

/// The fastest frame rate a PPM input is sized for.
pub const MAX_FRAME_HZ: u32 = 50;

/// How long the reader may be held up without losing an edge, at most
/// (the kernel's cap may give less; see [`EVENT_BUFFER_SIZE`]).
pub const HOLD_UP_MS: u32 = 1000;

/// The most edge events the kernel buffers for one request: it silently
/// caps `event_buffer_size` at `GPIO_V2_LINES_MAX * 16` (64 * 16 = 1024;
/// `linereq_create` in `drivers/gpio/gpiolib-cdev.c`).
pub const KERNEL_EVENT_BUFFER_MAX: u32 = (gpiocdev_uapi::NUM_LINES_MAX * 16) as u32;

/// Edge events the kernel is asked to buffer: [`HOLD_UP_MS`] of the
/// busiest input, [`MAX_EDGES`] edges a frame (16 channels: 17 pulses, 2
/// edges each, 34) at [`MAX_FRAME_HZ`], 1700 edges a second, rounded up to
/// a power of two (the kernel's FIFO is one), 2048, and capped at
/// [`KERNEL_EVENT_BUFFER_MAX`]: 1024, so 0.6 s of that input. A real
/// 16-channel frame is longer than 20 ms (16 channels of up to 2.2 ms and
/// a sync of 4 ms or more: 39 ms, about 26 Hz, 870 edges a second), so
/// 1024 events hold more than a second of any input a radio sends.
pub const EVENT_BUFFER_SIZE: u32 = event_buffer_size(MAX_EDGES as u32, MAX_FRAME_HZ, HOLD_UP_MS);

/// Events to buffer for `hold_up_ms` of frames of `edges_per_frame` edges
/// at `frame_hz`: rounded up to a power of two, at most
/// [`KERNEL_EVENT_BUFFER_MAX`].
pub const fn event_buffer_size(edges_per_frame: u32, frame_hz: u32, hold_up_ms: u32) -> u32 {
    let edges = (edges_per_frame as u64 * frame_hz as u64 * hold_up_ms as u64).div_ceil(1000);
    let pow2 = if edges <= 1 {
        1
    } else {
        edges.next_power_of_two()
    };
    if pow2 > KERNEL_EVENT_BUFFER_MAX as u64 {
        KERNEL_EVENT_BUFFER_MAX
    } else {
        pow2 as u32
    }
}

/// The line's level after an edge: the line is requested active-high, so
/// a rising edge (inactive to active) leaves it high.
pub fn level_after(kind: EdgeKind) -> Level {
    match kind {
        EdgeKind::Rising => Level::High,
        EdgeKind::Falling => Level::Low,
    }
}

/// gpiocdev's edge event as an [`EdgeEvent`]: its timestamp (CLOCK_MONOTONIC
/// as requested), the level after it, and its sequence number on the line,
/// widened to 64 bits by `wraps` (the kernel's is 32 bits: it wraps after
/// about 29 days of 16-channel frames at 50 Hz).
pub fn edge_of(e: &gpiocdev::line::EdgeEvent, wraps: &mut Unwrap) -> EdgeEvent {
    EdgeEvent {
        at_ns: e.timestamp_ns,
        level: level_after(e.kind),
        seq: wraps.widen(e.line_seqno),
    }
}

/// Widens the kernel's 32-bit sequence numbers: one that is smaller than
/// the one before by more than half the range has wrapped.
#[derive(Debug, Clone, Copy, Default)]
pub struct Unwrap {
    high: u64,
    last: Option<u32>,
}

impl Unwrap {
    /// The 64-bit sequence number of `seq`.
    pub fn widen(&mut self, seq: u32) -> u64 {
        if let Some(last) = self.last {
            if seq < last && last - seq > u32::MAX / 2 {
                self.high += 1 << 32;
            }
        }
        self.last = Some(seq);
        self.high + u64::from(seq)
    }
}

/// A GPIO line requested as an input with edge detection. Released when
/// dropped.
pub struct GpioInput {
    request: Request,
    description: String,
    /// Raw events as the kernel writes them: room for the whole kernel
    /// buffer, so one `read` can empty it.
    raw: Vec<u64>,
    /// The size of one raw event, in `u64`s.
    event_words: usize,
    /// The line's sequence numbers, widened.
    wraps: Unwrap,
}

impl std::fmt::Debug for GpioInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpioInput")
            .field("line", &self.description)
            .finish_non_exhaustive()
    }
}

impl GpioInput {
    /// Resolves `gpio:CHIP:LINE` (an empty CHIP: the chip that has a line
    /// named LINE) and requests the line as an active-high input with
    /// `consumer` as its label, both edges detected, CLOCK_MONOTONIC
    /// timestamps, no debounce and a kernel buffer of
    /// [`EVENT_BUFFER_SIZE`] events.
    pub fn open(chip: &str, line: &str, consumer: &str) -> Result<GpioInput, InputError> {
        let input = InputSpec::Gpio {
            chip: chip.into(),
            line: line.into(),
        }
        .to_string();
        let (handle, summary, info) =
            resolve_line(chip, line).map_err(|error| InputError::Gpio {
                input: input.clone(),
                error,
            })?;
        let request = Request::builder()
            .on_chip(&summary.path)
            .with_consumer(consumer)
            .with_kernel_event_buffer_size(EVENT_BUFFER_SIZE)
            .with_line(info.offset)
            .as_input()
            .as_active_high()
            .with_edge_detection(EdgeDetection::BothEdges)
            .with_event_clock(EventClock::Monotonic)
            .with_debounce_period(Duration::ZERO)
            .request()
            .map_err(|e| InputError::Gpio {
                input,
                error: input_request_error(&handle, &summary, &info, &e),
            })?;
        let event_words = request.edge_event_u64_size();
        Ok(GpioInput {
            raw: vec![0; EVENT_BUFFER_SIZE as usize * event_words],
            event_words,
            wraps: Unwrap::default(),
            description: format!("{} on {summary}", describe_line(&info)),
            request,
        })
    }

    fn failed(&self, op: &'static str, e: &gpiocdev::Error) -> InputError {
        InputError::GpioRead {
            line: self.description.clone(),
            op,
            detail: e.to_string(),
        }
    }
}

/// Whether a gpiocdev error is EINTR (a signal cut the wait short).
fn interrupted(e: &gpiocdev::Error) -> bool {
    matches!(
        e,
        gpiocdev::Error::Uapi(_, gpiocdev_uapi::Error::Os(n)) | gpiocdev::Error::Os(n)
            if n.0 == libc::EINTR
    )
}

impl EdgeSource for GpioInput {
    /// Waits for the request's file to be readable (`ppoll`), then reads
    /// every event available, at most `out.len()` and the kernel buffer's
    /// depth, in one `read`; allocates nothing. A gap in `seq` between two
    /// edges is events the kernel dropped when its buffer was full.
    fn read(&mut self, out: &mut [EdgeEvent], timeout: Duration) -> Result<usize, InputError> {
        if out.is_empty() {
            return Ok(0);
        }
        match self.request.wait_edge_event(timeout) {
            Ok(true) => {}
            Ok(false) => return Ok(0),
            Err(e) if interrupted(&e) => return Ok(0),
            Err(e) => return Err(self.failed("waiting for edge events", &e)),
        }
        let w = self.event_words;
        let want = out.len().min(self.raw.len() / w);
        let words = match self
            .request
            .read_edge_events_into_slice(&mut self.raw[..want * w])
        {
            Ok(words) => words,
            Err(e) if interrupted(&e) => return Ok(0),
            Err(e) => return Err(self.failed("reading edge events", &e)),
        };
        let n = words / w;
        for (slot, raw) in out.iter_mut().zip(self.raw[..n * w].chunks_exact(w)) {
            let event = self
                .request
                .edge_event_from_slice(raw)
                .map_err(|e| self.failed("decoding an edge event", &e))?;
            *slot = edge_of(&event, &mut self.wraps);
        }
        Ok(n)
    }

    fn description(&self) -> &str {
        &self.description
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kernels_32_bit_sequence_numbers_widen_across_a_wrap() {
        let mut w = Unwrap::default();
        let got: Vec<u64> = [u32::MAX - 1, u32::MAX, 0, 1, 3]
            .into_iter()
            .map(|s| w.widen(s))
            .collect();
        let top = u64::from(u32::MAX);
        assert_eq!(got, [top - 1, top, top + 1, top + 2, top + 4]);
        // Going back a little is no wrap (the decoder counts it as a loss).
        let mut w = Unwrap::default();
        assert_eq!((w.widen(10), w.widen(9)), (10, 9));
    }

    #[test]
    fn the_kernel_buffer_is_as_deep_as_the_kernel_allows() {
        assert_eq!(MAX_EDGES, 34, "16 channels: 17 pulses of 2 edges");
        assert_eq!(KERNEL_EVENT_BUFFER_MAX, 1024);
        // 34 * 50 = 1700 edges a second, 2048 rounded up, capped.
        assert_eq!(event_buffer_size(34, 50, 1000), 1024);
        assert_eq!(EVENT_BUFFER_SIZE, 1024);
        // Below the cap: rounded up to a power of two.
        assert_eq!(event_buffer_size(18, 50, 500), 512); // 450
        assert_eq!(event_buffer_size(34, 50, 100), 256); // 170
        assert_eq!(event_buffer_size(2, 1, 1000), 2);
        assert_eq!(event_buffer_size(0, 50, 1000), 1);
        // What it holds: 0.6 s of the busiest input, more than a second of
        // a 16-channel frame at its real rate (39.2 ms: 25.5 Hz).
        let held_ms = |edges_per_s: f64| EVENT_BUFFER_SIZE as f64 / edges_per_s * 1000.0;
        assert!(held_ms(34.0 * 50.0) > 600.0);
        assert!(held_ms(34.0 * 1000.0 / 39.2) > 1000.0);
    }

    #[test]
    fn edges_carry_the_level_after_them_the_kernel_time_and_the_line_seqno() {
        assert_eq!(level_after(EdgeKind::Rising), Level::High);
        assert_eq!(level_after(EdgeKind::Falling), Level::Low);
        let e = gpiocdev::line::EdgeEvent {
            timestamp_ns: 123_456_789_012,
            kind: EdgeKind::Falling,
            offset: 17,
            seqno: 99,
            line_seqno: 42,
        };
        assert_eq!(
            edge_of(&e, &mut Unwrap::default()),
            EdgeEvent {
                at_ns: 123_456_789_012,
                level: Level::Low,
                seq: 42
            }
        );
    }
}
