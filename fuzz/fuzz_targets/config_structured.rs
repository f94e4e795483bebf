//! Structured configurations (built with `arbitrary`, many of them valid or one
//! step from valid) through `Config::validate`: the text target rarely gets
//! past the TOML parser with per-channel limits and odd floats (NaN, inf,
//! values that round across a limit), this one does. Same invariants.
#![no_main]

use arbitrary::Arbitrary;
use libfuzzer_sys::fuzz_target;
use ppm_fuzz::check_model;
use ppm_shared::config::{
    channel_names, ChannelOverride, Config, CpuChoice, FailsafeAction, SpinMargin, Timing,
};
use ppm_shared::frame::{Level, Protocol};
use ppm_shared::receiver::{Receiver, ReceiverChoice};

/// A float in microseconds, biased towards the limits that matter.
#[derive(Arbitrary, Debug, Clone, Copy)]
enum Us {
    /// One of the interesting values.
    Special(u8),
    /// Whole microseconds plus thousandths: `us + milli / 1000`.
    Milli(u16, u16),
    /// Near a limit: `SPECIAL[k] + delta * 1e-4`.
    Near(u8, i8),
    /// Anything.
    Raw(f64),
}

const SPECIAL: &[f64] = &[
    800.0,
    2200.0,
    1000.0,
    1500.0,
    2000.0,
    50.0,
    300.0,
    4000.0,
    19000.0,
    22500.0,
    0.0,
    -0.0,
    f64::NAN,
    f64::INFINITY,
    f64::NEG_INFINITY,
    1e300,
    -1e300,
    f64::MIN_POSITIVE,
    799.9995,
    2200.0005,
    2200.0004999,
    799.99950001,
    49.9999,
    0.0005,
    0.00049,
    u64::MAX as f64 / 1000.0,
    4.294967295e6,
    4.294967296e6,
    -1.0,
    1.0,
    -15.0,
    15.0,
    500.0,
    -500.0,
    500.0000001,
    f64::MAX,
    f64::MIN,
    1e308,
    -1e308,
    5e-324,
];

impl Us {
    fn get(self) -> f64 {
        match self {
            Us::Special(k) => SPECIAL[k as usize % SPECIAL.len()],
            Us::Milli(us, milli) => us as f64 + (milli % 1000) as f64 / 1000.0,
            Us::Near(k, d) => SPECIAL[k as usize % SPECIAL.len()] + d as f64 * 1e-4,
            Us::Raw(f) => f,
        }
    }
}

#[derive(Arbitrary, Debug)]
enum Frame {
    /// Somewhere between the two sync limits for the channel limits chosen
    /// (`pick` / 255 of the way), when such a frame exists.
    Fitting(u8),
    /// Any value.
    Any(Us),
}

/// `[ppm.channel.NAME]`.
#[derive(Arbitrary, Debug)]
struct Override {
    /// A channel of the order, or any name.
    who: Result<u8, String>,
    default_us: Option<Us>,
    min_us: Option<Us>,
    max_us: Option<Us>,
    unit_min: Option<Us>,
    unit_max: Option<Us>,
    unit_us_min: Option<Us>,
    unit_us_max: Option<Us>,
    reverse: bool,
    trim_us: Option<Us>,
    unit: Option<String>,
}

#[derive(Arbitrary, Debug)]
struct Input {
    channels: u8,
    order: u8,
    order_text: Option<String>,
    /// `ppm.idle_level`: unset, high or low.
    idle_high: Option<bool>,
    /// `ppm.protocol = "sbus"`.
    sbus: bool,
    frame: Frame,
    pulse: Us,
    default: Option<Us>,
    min: Option<Us>,
    max: Option<Us>,
    overrides: Vec<Override>,
    allow: Vec<String>,
    auth_key: Option<String>,
    seq_file: Option<String>,
    name: Option<String>,
    output: Option<String>,
    root: Option<String>,
    recv_buffer_bytes: Option<u32>,
    priority: Option<u8>,
    cpu: Option<u16>,
    spin: Option<u32>,
    spin_min: Option<u32>,
    spin_max: Option<u32>,
    after_ms: Option<u64>,
    action: u8,
    startup: u8,
    frame_log_max_mb: Option<u64>,
    trace_max_mb: Option<u64>,
    /// Follow timing, with its sync limits when given.
    follow: Option<(Option<Us>, Option<Us>)>,
    /// `ppm.receiver`: any, or one of the four.
    receiver: u8,
    follow_sync_min: Option<Us>,
}

/// `ppm.receiver`: any, or one of the four.
fn receiver(k: u8) -> ReceiverChoice {
    match k % 5 {
        0 => ReceiverChoice::Any,
        k => ReceiverChoice::One(Receiver::ALL[k as usize - 1]),
    }
}

const ORDERS: &[&str] = &[
    "AETR", "TAER", "ATER", "RETA", "aetr", "AETRA", "AER", "XETR", "",
];

fuzz_target!(|input: Input| {
    let mut c = Config::default();
    let p = &mut c.ppm;
    if input.sbus {
        p.protocol = Protocol::Sbus;
    }
    p.channels = match input.channels {
        // The protocol's default (8, or SBUS's 16).
        0 => None,
        c if c < 200 => Some((c % 18) as u32),
        c => Some(u32::MAX - c as u32),
    };
    p.order = match input.order_text {
        Some(t) if input.order % 8 == 7 => t,
        _ => ORDERS[input.order as usize % ORDERS.len()].to_string(),
    };
    p.idle_level = match input.idle_high {
        None => None,
        Some(true) => Some(Level::High),
        Some(false) => Some(Level::Low),
    };
    p.pulse_us = input.pulse.get();
    if let Some(v) = input.default {
        p.default_us = v.get();
    }
    if let Some(v) = input.min {
        p.min_us = v.get();
    }
    if let Some(v) = input.max {
        p.max_us = v.get();
    }
    let names = channel_names(&p.order, (p.channels() as usize).min(16)).unwrap_or_default();
    for o in input.overrides.iter().take(20) {
        let key = match &o.who {
            Ok(i) if !names.is_empty() => names[*i as usize % names.len()].clone(),
            Ok(i) => format!("aux{i}"),
            Err(s) => s.clone(),
        };
        p.channel.insert(
            key,
            ChannelOverride {
                default_us: o.default_us.map(Us::get),
                min_us: o.min_us.map(Us::get),
                max_us: o.max_us.map(Us::get),
                unit_min: o.unit_min.map(Us::get),
                unit_max: o.unit_max.map(Us::get),
                unit_us_min: o.unit_us_min.map(Us::get),
                unit_us_max: o.unit_us_max.map(Us::get),
                reverse: o.reverse,
                trim_us: o.trim_us.map_or(0.0, Us::get),
                unit: o.unit.clone(),
            },
        );
    }
    p.frame_us = Some(match input.frame {
        Frame::Any(v) => v.get(),
        Frame::Fitting(pick) => {
            // The channel limits as validation will resolve them (the
            // limits themselves may still be invalid; then any frame does).
            let (mut sum_min, mut sum_max) = (0.0, 0.0);
            for n in &names {
                let o = p.channel.get(n);
                sum_min += o.and_then(|o| o.min_us).unwrap_or(p.min_us);
                sum_max += o.and_then(|o| o.max_us).unwrap_or(p.max_us);
            }
            let rules = receiver(input.receiver).rules();
            let (lo, hi) = (
                sum_max + rules.sync_min_us.0,
                sum_min + rules.sync_max_us.0.min(30_000.0),
            );
            (lo + (hi - lo) * pick as f64 / 255.0).round()
        }
    });

    c.ingress.allow = input.allow;
    c.ingress.auth_key = input.auth_key.map(Into::into);
    c.ingress.seq_file = input.seq_file.map(Into::into);
    if let Some(n) = input.name {
        c.name = n;
    }
    if let Some(o) = input.output {
        c.ppmd.output = o;
    }
    if let Some(r) = input.root {
        c.ipc.root = r.into();
    }
    if let Some(v) = input.recv_buffer_bytes {
        c.ingress.recv_buffer_bytes = v;
    }
    if let Some(v) = input.priority {
        c.rt.priority = v;
    }
    if let Some(v) = input.cpu {
        c.rt.cpu = match v {
            0xffff => CpuChoice::None,
            0xfffe => CpuChoice::Last,
            n => CpuChoice::Index(n as usize),
        };
    }
    if let Some(v) = input.spin {
        c.rt.spin_margin_us = if v == u32::MAX {
            SpinMargin::Auto
        } else {
            SpinMargin::Fixed(v)
        };
    }
    if let Some(v) = input.spin_min {
        c.rt.spin_margin_min_us = v;
    }
    if let Some(v) = input.spin_max {
        c.rt.spin_margin_max_us = v;
    }
    if let Some(v) = input.after_ms {
        c.failsafe.after_ms = v;
    }
    let action = |k: u8| {
        [
            FailsafeAction::Silence,
            FailsafeAction::Hold,
            FailsafeAction::Default,
            FailsafeAction::Flag,
        ][k as usize % 4]
    };
    c.failsafe.action = action(input.action);
    c.failsafe.startup = action(input.startup);
    if let Some(v) = input.frame_log_max_mb {
        c.ppmd.frame_log_max_mb = v;
    }
    if let Some(v) = input.trace_max_mb {
        c.ppmd.trace_max_mb = v;
    }

    c.ppm.receiver = receiver(input.receiver);
    if let Some((min, max)) = input.follow {
        c.ppm.timing = Timing::Follow;
        if let Some(v) = min {
            c.ppm.follow_sync_min_us = Some(v.get());
        }
        if let Some(v) = max {
            c.ppm.follow_sync_max_us = Some(v.get());
        }
    } else if let Some(v) = input.follow_sync_min {
        // Checked in grid timing too.
        c.ppm.follow_sync_min_us = Some(v.get());
    }

    match c.validate() {
        Ok(m) => {
            check_model(&m);
            assert_eq!(m.timing(), c.ppm.timing);
            assert_eq!(m.channels(), c.ppm.channels() as usize);
            assert_eq!(m.protocol(), c.ppm.protocol);
            assert_eq!(
                m.names(),
                channel_names(&c.ppm.order, m.channels()).unwrap()
            );
            for i in 0..m.channels() {
                let o = c.ppm.channel.get(&m.names()[i]);
                let min = o.and_then(|o| o.min_us).unwrap_or(c.ppm.min_us);
                let max = o.and_then(|o| o.max_us).unwrap_or(c.ppm.max_us);
                assert!((800.0..=2200.0).contains(&min) && min <= max && max <= 2200.0);
                let map = m.mapping(i);
                assert_eq!(map.units, o.and_then(|o| o.unit_min.zip(o.unit_max)));
                assert_eq!(map.reverse, o.is_some_and(|o| o.reverse));
            }
            assert_eq!(c.allow().expect("validated").len(), c.ingress.allow.len());
        }
        Err(e) => {
            let key = e
                .key()
                .expect("a validation error names its key")
                .to_string();
            assert!(e.to_string().contains(&key), "{e}");
        }
    }
});
