//! Reading what the other tools read, off any timing path: one thread
//! subscribes to each output's iceoryx2 services (`ppm/NAME/stats`,
//! `/line`, `/readback`, `/command`) and makes the [`State`] about 40 times
//! a second; one thread per output asks its udp-ingress for its status
//! reply 10 times a second.
//!
//! - [`Watched`]: what the configuration says of one output.
//! - [`Reader::start`]: the threads, and [`Reader::state`], the newest
//!   state as JSON text.
//! - Shared memory that cannot be opened (no root yet, a fault) is tried
//!   again every second; a service whose receive fails is opened again.

use super::state::{
    age_ms, line_state, us, CommandView, HistoryWindow, IngressView, LineView, OutputView,
    PpmdView, ReadbackView, State, PPMD_STALE_NS,
};
use ppm_shared::frame::MAX_CHANNELS;
use ppm_shared::ipc::{self, CommandSample, LineSample, ReadbackSample, TimingSnapshot};
use ppm_shared::status::StatusReply;
use ppm_shared::time::now_ns;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How often the shared memory is read (the page asks 20 times a second).
const IPC_PERIOD: Duration = Duration::from_millis(25);
/// How often each udp-ingress is asked for its status.
const STATUS_PERIOD: Duration = Duration::from_millis(100);
/// How long a status reply is waited for.
const STATUS_TIMEOUT: Duration = Duration::from_millis(400);
/// How long before shared memory that could not be opened is tried again.
const RETRY: Duration = Duration::from_secs(1);

/// One output to show, as the configuration describes it.
#[derive(Debug, Clone)]
pub struct Watched {
    /// Its name.
    pub name: String,
    /// `ppm`, `sbus` or `crsf`.
    pub protocol: &'static str,
    /// Its line (`ppmd.output`).
    pub output: String,
    /// Its channel names.
    pub channels: Vec<String>,
    /// Each channel's limits, us.
    pub min_us: Vec<f64>,
    /// See `min_us`.
    pub max_us: Vec<f64>,
    /// The fingerprint of its channel model: commands made under another
    /// are shown as refused.
    pub model: u64,
    /// Its read-back input, if one is configured.
    pub readback: Option<String>,
    /// Where its udp-ingress answers status queries.
    pub status_to: SocketAddr,
}

type Sub<T> = iceoryx2::port::subscriber::Subscriber<iceoryx2::service::ipc::Service, T, ()>;
type StatsService = ipc::StatsService;

/// One output's subscriptions and what they last gave.
struct Subscriptions {
    stats_service: StatsService,
    stats: Sub<TimingSnapshot>,
    line: Sub<LineSample>,
    readback: Option<Sub<ReadbackSample>>,
    command: Sub<CommandSample>,
}

/// What one output's samples last said.
#[derive(Default)]
struct Newest {
    stats: Option<TimingSnapshot>,
    line: Option<LineSample>,
    readback: Option<ReadbackSample>,
    command: Option<CommandSample>,
    /// When udp-ingress received the first command with the newest
    /// command's values (CLOCK_MONOTONIC ns).
    changed_at: Option<u64>,
    /// ns from `changed_at` to the first line sample seen carrying those
    /// values.
    line_carrying: Option<u64>,
    window: HistoryWindow,
}

/// The newest status reply of one udp-ingress, or why there is none.
#[derive(Clone, Default)]
struct StatusSlot {
    reply: Option<(Instant, StatusReply)>,
    error: Option<String>,
}

/// The reading threads, and the newest state they made.
pub struct Reader {
    state: Arc<Mutex<Arc<String>>>,
}

impl Reader {
    /// Starts reading `outputs` under the shared-memory root `root`; the
    /// threads stop when `stop` is set.
    pub fn start(outputs: Vec<Watched>, root: PathBuf, stop: Arc<AtomicBool>) -> Reader {
        let started = Instant::now();
        let empty = State {
            version: env!("CARGO_PKG_VERSION"),
            uptime_ms: 0,
            outputs: vec![],
        };
        let state = Arc::new(Mutex::new(Arc::new(to_json(&empty))));
        let slots: Arc<Vec<Mutex<StatusSlot>>> = Arc::new(
            outputs
                .iter()
                .map(|_| Mutex::new(StatusSlot::default()))
                .collect(),
        );
        for (i, o) in outputs.iter().enumerate() {
            let (to, slots, stop) = (o.status_to, slots.clone(), stop.clone());
            std::thread::Builder::new()
                .name(format!("status-{i}"))
                .spawn(move || ask_status(to, &slots[i], &stop))
                .expect("starting a status thread");
        }
        let shared = state.clone();
        std::thread::Builder::new()
            .name("ipc".into())
            .spawn(move || read_ipc(&outputs, &root, &slots, &shared, &stop, started))
            .expect("starting the shared-memory thread");
        Reader { state }
    }

    /// The newest state, as the JSON text `GET /api/state` answers.
    pub fn state(&self) -> Arc<String> {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

fn to_json(state: &State) -> String {
    serde_json::to_string(state).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"))
}

/// Asks the udp-ingress at `to` for its status every [`STATUS_PERIOD`].
fn ask_status(to: SocketAddr, slot: &Mutex<StatusSlot>, stop: &AtomicBool) {
    while !stop.load(Ordering::Relaxed) {
        let began = Instant::now();
        let got = crate::status::query(to, STATUS_TIMEOUT)
            .and_then(|text| crate::status::parse(&text, to));
        {
            let mut s = slot.lock().unwrap_or_else(|e| e.into_inner());
            match got {
                Ok(reply) => {
                    s.reply = Some((Instant::now(), reply));
                    s.error = None;
                }
                Err(e) => s.error = Some(format!("{e:#}")),
            }
        }
        if let Some(rest) = STATUS_PERIOD.checked_sub(began.elapsed()) {
            std::thread::sleep(rest);
        }
    }
}

/// Opens one output's subscriptions.
fn subscribe(node: &ipc::Node, w: &Watched) -> Result<Subscriptions, ipc::IpcError> {
    let sub_err = |e| ipc::IpcError::new("creating a subscriber", e);
    let stats_service = ipc::open_stats_service(node, &w.name)?;
    let stats = stats_service
        .subscriber_builder()
        .buffer_size(1)
        .create()
        .map_err(sub_err)?;
    let line = ipc::open_line_service(node, &w.name)?
        .subscriber_builder()
        .buffer_size(1)
        .create()
        .map_err(sub_err)?;
    let readback = match w.readback {
        Some(_) => Some(
            ipc::open_readback_service(node, &w.name)?
                .subscriber_builder()
                .buffer_size(1)
                .create()
                .map_err(sub_err)?,
        ),
        None => None,
    };
    let command = ipc::open_command_service(node, &w.name)?
        .subscriber_builder()
        .buffer_size(1)
        .create()
        .map_err(sub_err)?;
    Ok(Subscriptions {
        stats_service,
        stats,
        line,
        readback,
        command,
    })
}

/// The newest sample `sub` holds, if any; an error means the subscription
/// is to be made again.
fn newest<T: Copy + std::fmt::Debug + iceoryx2::prelude::ZeroCopySend>(
    sub: &Sub<T>,
) -> Result<Option<T>, String> {
    let mut got = None;
    loop {
        match sub.receive() {
            Ok(Some(sample)) => got = Some(*sample.payload()),
            Ok(None) => return Ok(got),
            Err(e) => return Err(format!("receiving: {e:?}")),
        }
    }
}

/// The shared-memory thread: reads every output, makes the state.
fn read_ipc(
    outputs: &[Watched],
    root: &std::path::Path,
    slots: &[Mutex<StatusSlot>],
    state: &Mutex<Arc<String>>,
    stop: &AtomicBool,
    started: Instant,
) {
    let node_name = format!("ppm-web-{}", std::process::id());
    let mut node: Option<ipc::Node> = None;
    let mut subs: Vec<Option<Subscriptions>> = outputs.iter().map(|_| None).collect();
    let mut errors: Vec<Option<String>> = outputs.iter().map(|_| None).collect();
    let mut newest_of: Vec<Newest> = outputs.iter().map(|_| Newest::default()).collect();
    let mut next_try = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        let began = Instant::now();
        if began >= next_try && (node.is_none() || subs.iter().any(Option::is_none)) {
            next_try = began + RETRY;
            if node.is_none() {
                match ipc::create_node(root, &node_name) {
                    Ok(n) => node = Some(n),
                    Err(e) => errors.fill(Some(format!("{}", ppm_shared::logging::Chain(&e)))),
                }
            }
            if let Some(n) = &node {
                for (i, w) in outputs.iter().enumerate() {
                    if subs[i].is_none() {
                        match subscribe(n, w) {
                            Ok(s) => {
                                subs[i] = Some(s);
                                errors[i] = None;
                            }
                            Err(e) => {
                                errors[i] = Some(format!("{}", ppm_shared::logging::Chain(&e)))
                            }
                        }
                    }
                }
            }
        }
        let now = now_ns();
        let mut views = Vec::with_capacity(outputs.len());
        for (i, w) in outputs.iter().enumerate() {
            let n = &mut newest_of[i];
            let mut publishers = 0;
            if let Some(s) = &subs[i] {
                if let Err(e) = take(s, n) {
                    errors[i] = Some(e);
                    subs[i] = None;
                } else {
                    use iceoryx2::service::port_factory::PortFactory;
                    publishers = s.stats_service.dynamic_config().number_of_publishers();
                }
            }
            let status = slots[i].lock().unwrap_or_else(|e| e.into_inner()).clone();
            views.push(view(w, n, publishers, errors[i].clone(), status, now));
        }
        let s = State {
            version: env!("CARGO_PKG_VERSION"),
            uptime_ms: started.elapsed().as_millis() as u64,
            outputs: views,
        };
        *state.lock().unwrap_or_else(|e| e.into_inner()) = Arc::new(to_json(&s));
        if let Some(rest) = IPC_PERIOD.checked_sub(began.elapsed()) {
            std::thread::sleep(rest);
        }
    }
}

/// Takes the newest samples of one output's subscriptions into `n`.
fn take(s: &Subscriptions, n: &mut Newest) -> Result<(), String> {
    if let Some(v) = newest(&s.stats)? {
        n.window.push(&v);
        n.stats = Some(v);
    }
    if let Some(v) = newest(&s.command)? {
        let k = (v.channel_count as usize).min(MAX_CHANNELS);
        let same = n.command.is_some_and(|c| {
            c.channel_count == v.channel_count && c.values_ns[..k] == v.values_ns[..k]
        });
        if !same {
            n.changed_at = Some(v.recv_mono_ns);
            n.line_carrying = None;
        }
        n.command = Some(v);
    }
    if let Some(v) = newest(&s.line)? {
        n.line = Some(v);
        if let (Some(c), Some(changed), None) = (&n.command, n.changed_at, n.line_carrying) {
            let k = (v.channels as usize).min(MAX_CHANNELS);
            // Within 1 us: the line's values are as measured.
            let carries = c.channel_count as usize == k
                && v.values_ns[..k]
                    .iter()
                    .zip(&c.values_ns[..k])
                    .all(|(a, b)| a.abs_diff(*b) <= 1_000);
            if v.start_mono_ns >= changed && carries {
                n.line_carrying = Some(v.start_mono_ns - changed);
            }
        }
    }
    if let Some(r) = &s.readback {
        if let Some(v) = newest(r)? {
            n.readback = Some(v);
        }
    }
    Ok(())
}

/// The view of one output.
fn view(
    w: &Watched,
    n: &mut Newest,
    publishers: usize,
    ipc_error: Option<String>,
    status: StatusSlot,
    now: u64,
) -> OutputView {
    let fresh = n
        .stats
        .as_ref()
        .filter(|s| now.saturating_sub(s.mono_ns) <= PPMD_STALE_NS);
    let running = publishers > 0 && fresh.is_some();
    if !running {
        n.window.clear();
    }
    let ppmd = fresh.filter(|_| running).map(|s| PpmdView::of(s, now));
    let histogram = fresh
        .filter(|_| running)
        .and_then(|s| n.window.view(s.uptime_ns as f64 / 1e9));
    let command = n.command.as_ref().map(|c| {
        let k = (c.channel_count as usize).min(MAX_CHANNELS);
        CommandView {
            ch_us: us(&c.values_ns[..k]),
            age_ms: age_ms(c.recv_mono_ns, now),
            seq: c.seq(),
            clamped: c.clamped,
            other_model: c.model != w.model,
            to_line_ms: n.line_carrying.map(|t| t as f64 / 1e6),
        }
    });
    let line = n.line.as_ref().filter(|_| running).map(|l| {
        let k = (l.channels as usize).min(MAX_CHANNELS);
        LineView {
            ch_us: us(&l.values_ns[..k]),
            frame: l.frame,
            age_ms: age_ms(l.start_mono_ns, now),
        }
    });
    let readback = w
        .readback
        .as_ref()
        .map(|input| ReadbackView::of(input.clone(), n.readback.as_ref(), now));
    let (running_ingress, reply_age) = match &status.reply {
        Some((at, _)) if status.error.is_none() => (true, Some(at.elapsed())),
        Some((at, _)) => (false, Some(at.elapsed())),
        None => (false, None),
    };
    OutputView {
        name: w.name.clone(),
        protocol: w.protocol,
        output: w.output.clone(),
        channels: w.channels.clone(),
        min_us: w.min_us.clone(),
        max_us: w.max_us.clone(),
        line_state: line_state(running, n.line.as_ref(), now),
        ipc_error,
        ppmd,
        command,
        line,
        readback,
        ingress: IngressView {
            address: w.status_to.to_string(),
            running: running_ingress,
            error: status.error,
            status: status.reply.map(|(_, r)| r),
            status_age_ms: reply_age.map(|d| d.as_secs_f64() * 1e3),
        },
        histogram,
    }
}
