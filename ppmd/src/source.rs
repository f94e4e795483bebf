//! Where ppmd's commands come from.

use ppm_shared::ipc::{self, CommandSample, CommandService, IpcError, Node};
use std::os::fd::RawFd;
use std::path::Path;

/// A source of commands, polled once per frame by the timing loop.
pub trait CommandSource {
    /// The newest command published since the last call, if any. Must not
    /// block; must not allocate in steady state.
    fn newest(&mut self) -> Option<CommandSample>;

    /// Whether no command may go out now, not the newest, nor a held one,
    /// nor the failsafe's defaults: the line goes silent, and the command
    /// the loop kept is forgotten (a pilot's radio that is not read:
    /// nobody could take over). Called once per decision, after
    /// [`Self::newest`], with the loop's time; must not block or allocate.
    fn withdrawn(&mut self, _now_ns: u64) -> bool {
        false
    }

    /// Receive errors so far (read outside the loop).
    fn errors(&self) -> u64 {
        0
    }

    /// A file descriptor that becomes readable when a command is published,
    /// so that `follow` timing can sleep until one comes; `None` when the
    /// source has none (the loop then looks for commands every
    /// [`crate::emitter::FOLLOW_POLL_NS`] while it waits for one).
    fn wake_fd(&self) -> Option<RawFd> {
        None
    }

    /// Clears the wake-ups received so far (called before [`Self::newest`],
    /// so a command published after it wakes the loop again); false when
    /// that failed (the loop then stops watching the fd, which might stay
    /// readable, and looks for commands every
    /// [`crate::emitter::FOLLOW_POLL_NS`]). Must not block or allocate.
    fn clear_wake(&mut self) -> bool {
        true
    }
}

/// The same command, freshly stamped, every frame; asks the loop to stop
/// (through `stop`) after `frames` frames. For benchmarks and test drivers.
pub struct RepeatSource {
    /// The command handed out.
    pub sample: CommandSample,
    /// Frames left before `stop` is set.
    pub frames: u64,
    /// Set when the frames are used up.
    pub stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl CommandSource for RepeatSource {
    fn newest(&mut self) -> Option<CommandSample> {
        if self.frames == 0 {
            self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        }
        self.frames = self.frames.saturating_sub(1);
        self.sample.recv_mono_ns = crate::clock::now_ns();
        Some(self.sample)
    }
}

/// A fresh command (the same one, freshly stamped) each time a ticker
/// thread ticks, `hz` times a second, with a wake-up on a socket after each
/// tick, as udp-ingress sends them; asks the loop to stop (through `stop`)
/// after `commands` commands. For benchmarks and test drivers of follow
/// timing. Lock-free: the ticker only counts.
pub struct TickSource {
    sample: CommandSample,
    ticks: std::sync::Arc<std::sync::atomic::AtomicU64>,
    taken: u64,
    commands: u64,
    rx: std::os::unix::net::UnixDatagram,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    ticker: Option<std::thread::JoinHandle<()>>,
}

impl TickSource {
    /// Starts the ticker.
    pub fn start(
        sample: CommandSample,
        hz: f64,
        commands: u64,
        stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    ) -> std::io::Result<TickSource> {
        use std::sync::atomic::Ordering::Relaxed;
        let (tx, rx) = std::os::unix::net::UnixDatagram::pair()?;
        rx.set_nonblocking(true)?;
        tx.set_nonblocking(true)?;
        let ticks = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
        let ticker = {
            let (ticks, stop) = (ticks.clone(), stop.clone());
            let period = (1e9 / hz) as u64;
            std::thread::spawn(move || {
                let mut next = crate::clock::now_ns() + period;
                while !stop.load(Relaxed) {
                    crate::clock::sleep_until(next);
                    ticks.fetch_add(1, Relaxed);
                    let _ = tx.send(&[1]);
                    next += period;
                }
            })
        };
        Ok(TickSource {
            sample,
            ticks,
            taken: 0,
            commands,
            rx,
            stop,
            ticker: Some(ticker),
        })
    }
}

impl Drop for TickSource {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(t) = self.ticker.take() {
            let _ = t.join();
        }
    }
}

impl CommandSource for TickSource {
    fn newest(&mut self) -> Option<CommandSample> {
        use std::sync::atomic::Ordering::Relaxed;
        let ticks = self.ticks.load(Relaxed);
        if ticks == self.taken {
            return None;
        }
        self.taken = ticks;
        self.commands = self.commands.saturating_sub(1);
        if self.commands == 0 {
            self.stop.store(true, Relaxed);
        }
        self.sample.recv_mono_ns = crate::clock::now_ns();
        Some(self.sample)
    }

    fn wake_fd(&self) -> Option<RawFd> {
        use std::os::fd::AsRawFd;
        Some(self.rx.as_raw_fd())
    }

    fn clear_wake(&mut self) -> bool {
        let mut b = [0u8; 64];
        while self.rx.recv(&mut b).is_ok() {}
        true
    }
}

type Subscriber =
    iceoryx2::port::subscriber::Subscriber<iceoryx2::service::ipc::Service, CommandSample, ()>;

type Listener = iceoryx2::port::listener::Listener<iceoryx2::service::ipc::Service>;

/// Commands from udp-ingress through the iceoryx2 command service, and with
/// `wake`, the wake-ups udp-ingress sends after each one.
pub struct IpcSource {
    subscriber: Subscriber,
    listener: Option<(Listener, RawFd)>,
    errors: u64,
    _services: (CommandService, Option<ipc::WakeService>),
    _node: Node,
}

impl IpcSource {
    /// Subscribes to output `name`'s command service (creating it if ingress
    /// has not started yet); with `wake`, also listens to its wake-up event
    /// service (for `follow` timing).
    pub fn open(root: &Path, name: &str, wake: bool) -> Result<IpcSource, IpcError> {
        let node = ipc::create_node(root, &format!("ppmd-{name}"))?;
        let service = ipc::open_command_service(&node, name)?;
        let subscriber = service
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .map_err(|e| {
                IpcError::new(
                    format!("subscribing to `{}`", ipc::command_service_name(name)),
                    e,
                )
            })?;
        let (wake_service, listener) = if wake {
            use iceoryx2::prelude::FileDescriptorBased;
            let events = ipc::open_wake_service(&node, name)?;
            let listener = events.listener_builder().create().map_err(|e| {
                IpcError::new(
                    format!("listening to `{}`", ipc::wake_service_name(name)),
                    e,
                )
            })?;
            // SAFETY: only the number is read; the fd lives as long as the
            // listener, which this source owns, and is only polled.
            let fd = unsafe { listener.file_descriptor().native_handle() };
            (Some(events), Some((listener, fd)))
        } else {
            (None, None)
        };
        Ok(IpcSource {
            subscriber,
            listener,
            errors: 0,
            _services: (service, wake_service),
            _node: node,
        })
    }
}

impl CommandSource for IpcSource {
    fn newest(&mut self) -> Option<CommandSample> {
        let mut newest = None;
        loop {
            match self.subscriber.receive() {
                Ok(Some(sample)) => newest = Some(*sample.payload()),
                Ok(None) => return newest,
                Err(_) => {
                    self.errors += 1;
                    return newest;
                }
            }
        }
    }

    fn errors(&self) -> u64 {
        self.errors
    }

    fn wake_fd(&self) -> Option<RawFd> {
        self.listener.as_ref().map(|(_, fd)| *fd)
    }

    fn clear_wake(&mut self) -> bool {
        let Some((listener, _)) = &self.listener else {
            return true;
        };
        let cleared = listener.try_wait(|_| {}).is_ok();
        self.errors += !cleared as u64;
        cleared
    }
}
