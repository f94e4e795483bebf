//! The schedule out of the timing loop, without touching the loop:
//!
//! - [`Recorder`]: a [`Line`] that forwards every call to the real line
//!   and, for each write that went through, puts the edge (scheduled time,
//!   the loop's time just before the write, level) into a ring.
//! - [`ring`]: that ring, single producer (the timing thread), single
//!   consumer (the main thread), fixed size, lock-free: a push is a few
//!   atomic loads and stores, never an allocation, a lock or a syscall.
//!   A push into a full ring drops the edge and counts it.

use ppm_shared::frame::Level;
use ppm_shared::trace::TraceEdge;
use ppmd::line::{Line, LineError};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;

/// One edge's place in the ring: each field an atomic, so the ring needs
/// no `unsafe`; the producer's `tail` (Release) publishes them.
#[derive(Default)]
struct Slot {
    scheduled_ns: AtomicU64,
    actual_ns: AtomicU64,
    high: AtomicBool,
}

struct Shared {
    slots: Box<[Slot]>,
    /// Edges taken by the consumer (it alone stores).
    head: AtomicUsize,
    /// Edges pushed by the producer (it alone stores).
    tail: AtomicUsize,
    /// Edges dropped because the ring was full.
    dropped: AtomicU64,
}

/// The timing thread's end of the ring.
pub struct Producer {
    shared: Arc<Shared>,
}

/// The main thread's end of the ring.
pub struct Consumer {
    shared: Arc<Shared>,
}

/// A ring of `capacity` edges (at least 1), allocated here, once.
pub fn ring(capacity: usize) -> (Producer, Consumer) {
    let slots: Box<[Slot]> = (0..capacity.max(1)).map(|_| Slot::default()).collect();
    let shared = Arc::new(Shared {
        slots,
        head: AtomicUsize::new(0),
        tail: AtomicUsize::new(0),
        dropped: AtomicU64::new(0),
    });
    (
        Producer {
            shared: shared.clone(),
        },
        Consumer { shared },
    )
}

impl Producer {
    /// Puts `edge` in the ring; false (and counted) when it is full.
    pub fn push(&mut self, edge: &TraceEdge) -> bool {
        let s = &*self.shared;
        let tail = s.tail.load(Ordering::Relaxed);
        let head = s.head.load(Ordering::Acquire);
        if tail.wrapping_sub(head) >= s.slots.len() {
            s.dropped.fetch_add(1, Ordering::Relaxed);
            return false;
        }
        let slot = &s.slots[tail % s.slots.len()];
        slot.scheduled_ns
            .store(edge.scheduled_ns, Ordering::Relaxed);
        slot.actual_ns.store(edge.actual_ns, Ordering::Relaxed);
        slot.high
            .store(edge.level == Level::High, Ordering::Relaxed);
        s.tail.store(tail.wrapping_add(1), Ordering::Release);
        true
    }
}

impl Consumer {
    /// Moves every edge in the ring to `out`, oldest first; returns how
    /// many.
    pub fn drain(&mut self, out: &mut Vec<TraceEdge>) -> usize {
        let s = &*self.shared;
        let head = s.head.load(Ordering::Relaxed);
        let tail = s.tail.load(Ordering::Acquire);
        let n = tail.wrapping_sub(head);
        for i in 0..n {
            let slot = &s.slots[head.wrapping_add(i) % s.slots.len()];
            out.push(TraceEdge {
                scheduled_ns: slot.scheduled_ns.load(Ordering::Relaxed),
                actual_ns: slot.actual_ns.load(Ordering::Relaxed),
                level: Level::from_bit(slot.high.load(Ordering::Relaxed)),
            });
        }
        s.head.store(tail, Ordering::Release);
        n
    }

    /// Edges dropped so far because the ring was full.
    pub fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }
}

/// The real line, with every edge written to it recorded in a ring (see
/// the module's docs).
pub struct Recorder {
    line: Box<dyn Line>,
    ring: Producer,
}

impl Recorder {
    /// Records the edges written to `line` into `ring`.
    pub fn new(line: Box<dyn Line>, ring: Producer) -> Recorder {
        Recorder { line, ring }
    }
}

impl Line for Recorder {
    fn write(&mut self, edge: &TraceEdge) -> Result<(), LineError> {
        // An edge the line refused is not on it: only the others are
        // expected back.
        self.line.write(edge)?;
        self.ring.push(edge);
        Ok(())
    }

    fn park(&mut self, level: Level) -> Result<(), LineError> {
        self.line.park(level)
    }

    fn stamped(&self) -> bool {
        self.line.stamped()
    }
}
