//! Where ppmd's commands come from.

use ppm_shared::ipc::{self, CommandSample, CommandService, IpcError, Node};
use std::path::Path;

/// A source of commands, polled once per frame by the timing loop.
pub trait CommandSource {
    /// The newest command published since the last call, if any. Must not
    /// block; must not allocate in steady state.
    fn newest(&mut self) -> Option<CommandSample>;

    /// Receive errors so far (read outside the loop).
    fn errors(&self) -> u64 {
        0
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

type Subscriber =
    iceoryx2::port::subscriber::Subscriber<iceoryx2::service::ipc::Service, CommandSample, ()>;

/// Commands from udp-ingress through the iceoryx2 command service.
pub struct IpcSource {
    subscriber: Subscriber,
    errors: u64,
    _service: CommandService,
    _node: Node,
}

impl IpcSource {
    /// Subscribes to output `name`'s command service (creating it if ingress
    /// has not started yet).
    pub fn open(root: &Path, name: &str) -> Result<IpcSource, IpcError> {
        let node = ipc::create_node(root, &format!("ppmd-{name}"))?;
        let service = ipc::open_command_service(&node, name)?;
        let subscriber = service
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .map_err(|e| IpcError {
                what: format!("subscribing to `{}`", ipc::command_service_name(name)),
                detail: format!("{e:?}"),
            })?;
        Ok(IpcSource {
            subscriber,
            errors: 0,
            _service: service,
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
}
