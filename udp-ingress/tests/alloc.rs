//! What the ingress's accept path allocates: one datagram offered to the
//! [`Intake`] and taken, counted by a counting allocator. The JSON is read
//! into serde_json's `Value` (its arrays and maps allocate); nothing else on
//! the path may: no message is formatted for an error that did not happen.

use ppm_shared::config::Config;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};
use udp_ingress::{Intake, Outcome};

struct Counting;
static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);
thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.with(Cell::get) {
            ALLOCATIONS.fetch_add(1, Relaxed);
        }
        System.alloc(layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if COUNTING.with(Cell::get) {
            ALLOCATIONS.fetch_add(1, Relaxed);
        }
        System.realloc(ptr, layout, new_size)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static A: Counting = Counting;

/// Allocations of one accepted datagram, after a warm-up.
fn allocations_of(datagram: &[u8]) -> u64 {
    let model = Config::default().validate().unwrap();
    let mut intake = Intake::new("ppm", model, Duration::from_secs(1));
    let from = "127.0.0.1:9".parse().unwrap();
    let now = Instant::now();
    for _ in 0..3 {
        assert_eq!(intake.offer(datagram, from, 1, 1, now), Outcome::Accepted);
        intake.take().unwrap();
    }
    ALLOCATIONS.store(0, Relaxed);
    COUNTING.with(|c| c.set(true));
    let outcome = intake.offer(datagram, from, 1, 1, now);
    let taken = intake.take();
    COUNTING.with(|c| c.set(false));
    assert_eq!(outcome, Outcome::Accepted);
    assert!(taken.is_some());
    ALLOCATIONS.load(Relaxed)
}

#[test]
fn the_accept_path_allocates_only_the_json_tree() {
    // The bare array: the array's Vec (grown as serde_json reads it).
    let array = allocations_of(b"[1500, 1000, 1500, 1500, 1800, 1500, 1500, 1500]");
    // Named channels: the map's entries and their key strings.
    let named = allocations_of(br#"{"ail": 1500, "thr": 1000, "aux1": 1800}"#);
    eprintln!("allocations per accepted datagram: array {array}, named {named}");
    // serde_json's Value tree for 8 values takes a few (the Vec grows 4, 8);
    // a message formatted per value would add 8.
    assert!(array <= 4, "{array} allocations for an 8-value array");
    // One map and its three keys (a BTreeMap node and three Strings).
    assert!(named <= 6, "{named} allocations for three named values");
}
