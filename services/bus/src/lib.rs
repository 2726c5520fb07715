//! Every iceoryx2 service of egoslam in one place: its name, payload type and QoS.
//!
//! | channel     | payload                          | producer  | consumer | delivery |
//! |-------------|----------------------------------|-----------|----------|----------|
//! | `frames`    | `[u8]` grey pixels + [`FrameMeta`] header | replay    | frontend | zero-copy; lossless (blocks) or real-time (drops new frames, counted) |
//! | `keyframes` | `[u8]` = protobuf `egoslam.internal.v1.Keyframe` | frontend  | solver   | lossless: producer blocks |
//! | `windows`   | `[u8]` = protobuf `egoslam.internal.v1.WindowSolution` | solver | merger | lossless: producer blocks |
//!
//! Lossless channels have safe overflow off and the `RetryUntilDelivered` backpressure
//! strategy: a slow consumer slows its producer down, nothing is overwritten. A consumer that
//! stops reading altogether (hung) makes the producer fail after
//! [`BusOptions::delivery_timeout`] instead of blocking forever; see docs/bus.md.
//!
//! Service names carry a namespace (`egoslam/<namespace>/<channel>`), so that several
//! pipelines (parallel tests, two cameras) can share one machine.

mod channel;
mod error;
mod frame;
mod message;
mod port;
mod stop;

pub use channel::{Channel, Delivery, FRAMES, KEYFRAMES, LIVE_FRAMES, WINDOWS};
pub use error::{BusOpenError, ReceiveError, SendError};
pub use frame::{unix_now_ns, FrameMeta, FramePublisher, FrameSubscriber, ReceivedFrame};
pub use message::{MessagePublisher, MessageSubscriber};
pub use stop::{
    stop_requested, watch_stop_requests, StoppedBySignal, STOP_DEADLINE_EXIT, STOP_GRACE,
};

use iceoryx2::prelude::*;
use std::time::Duration;

/// Options shared by all ports of one process.
#[derive(Debug, Clone)]
pub struct BusOptions {
    /// Namespace of the service names (default "default"); tests use a unique one each.
    pub namespace: String,
    /// How long a lossless send may wait for a consumer that does not read (default 30 s,
    /// longer than any window solve, shorter than an operator's patience).
    pub delivery_timeout: Duration,
    /// How long a producer waits at start for its consumer to connect (default 30 s).
    pub connect_timeout: Duration,
}

impl Default for BusOptions {
    fn default() -> Self {
        Self {
            namespace: "default".into(),
            delivery_timeout: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(30),
        }
    }
}

/// One iceoryx2 node per process; ports are created from it.
pub struct Bus {
    node: Node<ipc::Service>,
    options: BusOptions,
}

impl Bus {
    /// Creates the node of this process, named after the service (`frontend`, ...), with the
    /// configuration of [`config_path`].
    pub fn open(process_name: &str, options: BusOptions) -> Result<Self, BusOpenError> {
        let config = load_config();
        let name =
            NodeName::new(process_name).map_err(|_| BusOpenError::BadName(process_name.into()))?;
        let node = NodeBuilder::new()
            .name(&name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::HandleTerminationRequests)
            .create::<ipc::Service>()
            .map_err(|e| BusOpenError::Node(format!("{e:?}")))?;
        // A service restarted after SIGKILL finds its predecessor's ports still registered;
        // removing dead nodes' resources first frees their slots and stops producers from
        // delivering into a buffer nobody will read.
        let _ = node.try_cleanup_dead_nodes();
        // iceoryx2 installs its signal handler on the first wait, replacing any handler set
        // before (it does not chain): wait once so that the stop watch chains it.
        let _ = node.wait(Duration::ZERO);
        watch_stop_requests();
        Ok(Self { node, options })
    }

    /// The full iceoryx2 service name of a channel in this bus's namespace.
    pub fn service_name(&self, channel: &Channel) -> String {
        format!("egoslam/{}/{}", self.options.namespace, channel.name)
    }

    /// The options this bus was opened with.
    pub fn options(&self) -> &BusOptions {
        &self.options
    }

    pub(crate) fn node(&self) -> &Node<ipc::Service> {
        &self.node
    }

    /// Sleeps up to `duration` (waking early on a signal). Returns `false` when the process
    /// was asked to terminate (SIGINT/SIGTERM): callers then finish cleanly.
    pub fn idle(&self, duration: Duration) -> bool {
        self.node.wait(duration).is_ok()
    }
}

/// The iceoryx2 configuration file: `EGOSLAM_ICEORYX2_CONFIG`, else the repository's
/// `config/iceoryx2.toml` (iceoryx2's defaults: dead-node cleanup on, see docs/bus.md).
/// Loading it as iceoryx2's *global* configuration matters: dead-node cleanup of other
/// processes consults the global one, which would otherwise be searched for in `./config`
/// and warn on every start.
pub fn config_path() -> std::path::PathBuf {
    std::env::var_os("EGOSLAM_ICEORYX2_CONFIG")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/iceoryx2.toml")
        })
}

fn load_config() -> Config {
    let path = config_path();
    let loaded = path
        .to_str()
        .and_then(|p| FilePath::new(p.as_bytes()).ok())
        .and_then(|file| Config::setup_global_config_from_file(&file).ok());
    match loaded {
        Some(config) => config.clone(),
        None => {
            tracing::warn!(path = %path.display(), "iceoryx2 config not loaded; using its defaults");
            Config::default()
        }
    }
}

/// Milliseconds since [`PROCESS_START`] of the last sign of life (see [`last_activity`]).
static LAST_ACTIVITY_MS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
static PROCESS_START: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();

fn process_start() -> std::time::Instant {
    *PROCESS_START.get_or_init(std::time::Instant::now)
}

/// Records that the calling thread is alive and making progress (the bus's waiting loops
/// call it; so should a service's main loop). Feeds the systemd watchdog.
pub fn record_activity() {
    let ms = process_start().elapsed().as_millis() as u64;
    LAST_ACTIVITY_MS.store(ms, std::sync::atomic::Ordering::Relaxed);
}

/// When activity was last recorded.
pub fn last_activity() -> std::time::Instant {
    process_start()
        + Duration::from_millis(LAST_ACTIVITY_MS.load(std::sync::atomic::Ordering::Relaxed))
}

/// Polls `f` until it yields a value, idling between attempts with a short backoff. Returns
/// `Ok(None)` when the process is asked to terminate.
pub(crate) fn poll_until<T, E>(
    bus: &Bus,
    timeout: Option<Duration>,
    mut f: impl FnMut() -> Result<Option<T>, E>,
    on_timeout: impl FnOnce() -> E,
) -> Result<Option<T>, E> {
    let start = std::time::Instant::now();
    let mut spins = 0u32;
    loop {
        record_activity();
        if let Some(v) = f()? {
            return Ok(Some(v));
        }
        if timeout.is_some_and(|t| start.elapsed() > t) {
            return Err(on_timeout());
        }
        spins += 1;
        if spins < 64 {
            std::thread::yield_now();
        } else if !bus.idle(Duration::from_micros(200)) {
            return Ok(None);
        }
    }
}
