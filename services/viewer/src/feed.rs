//! The viewer's input: a zenoh session subscribed to one device's results
//! (`egoslam/<device>/{pose,trajectory,map,status}`, docs/egress.md), each message decoded
//! and handed to a [`ResultSink`] (the [`crate::Viewer`], a progress display).

use crate::ViewerError;
use egoslam_egress::NetworkOptions;
use egoslam_messages::v1 as pb;
use prost::Message;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;
use zenoh::Wait;

/// What takes the decoded results; each kind is ignored unless implemented.
pub trait ResultSink: Send + Sync {
    fn pose(&self, _pose: &pb::Pose) {}
    fn trajectory(&self, _trajectory: &pb::Trajectory) {}
    fn map_points(&self, _points: &pb::MapPoints) {}
    fn status(&self, _status: &pb::Status) {}
}

impl ResultSink for crate::Viewer {
    fn pose(&self, pose: &pb::Pose) {
        crate::Viewer::pose(self, pose)
    }
    fn trajectory(&self, trajectory: &pb::Trajectory) {
        crate::Viewer::trajectory(self, trajectory)
    }
    fn map_points(&self, points: &pb::MapPoints) {
        crate::Viewer::map_points(self, points)
    }
    fn status(&self, status: &pb::Status) {
        crate::Viewer::status(self, status)
    }
}

/// Seen from the feed: whether the merger said it finished, and messages not understood.
#[derive(Default)]
struct Progress {
    finished: Mutex<bool>,
    changed: Condvar,
    undecodable: AtomicU64,
    received: AtomicU64,
}

/// A zenoh session feeding a [`Viewer`]; dropping it unsubscribes.
pub struct Feed {
    _session: zenoh::Session,
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    progress: Arc<Progress>,
}

fn decoded<M: Message + Default>(
    payload: &zenoh::bytes::ZBytes,
    progress: &Progress,
    key: &str,
) -> Option<M> {
    match M::decode(payload.to_bytes().as_ref()) {
        Ok(m) => Some(m),
        Err(e) => {
            if progress.undecodable.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!(key, "an undecodable message ignored (and later ones): {e}");
            }
            None
        }
    }
}

/// A `tcp/127.0.0.1:PORT` endpoint on a port free now, for a feed the merger connects to
/// (zenoh does not tell a session's own listening port in its stable API).
pub fn free_loopback_endpoint() -> std::io::Result<String> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    Ok(format!("tcp/127.0.0.1:{port}"))
}

impl Feed {
    /// Opens a session on `network` and subscribes to `device`'s results.
    pub fn open(
        network: &NetworkOptions,
        device: &str,
        sink: Arc<dyn ResultSink>,
    ) -> Result<Self, ViewerError> {
        let subscribe_error = |key: &str, reason: String| ViewerError::Subscribe {
            key: key.to_string(),
            reason,
        };
        let config = network
            .zenoh_config()
            .map_err(|e| subscribe_error("egoslam/**", e.to_string()))?;
        let session = zenoh::open(config)
            .wait()
            .map_err(|e| subscribe_error("egoslam/**", e.to_string()))?;
        let progress = Arc::new(Progress::default());
        let mut subscribers = Vec::new();
        for topic in ["pose", "trajectory", "map", "status"] {
            let key = format!("egoslam/{device}/{topic}");
            let sink = sink.clone();
            let progress = progress.clone();
            let on_sample = move |sample: zenoh::sample::Sample| {
                progress.received.fetch_add(1, Ordering::Relaxed);
                let payload = sample.payload();
                let key = sample.key_expr().as_str();
                match topic {
                    "pose" => {
                        if let Some(p) = decoded::<pb::Pose>(payload, &progress, key) {
                            sink.pose(&p);
                        }
                    }
                    "trajectory" => {
                        if let Some(t) = decoded::<pb::Trajectory>(payload, &progress, key) {
                            sink.trajectory(&t);
                        }
                    }
                    "map" => {
                        if let Some(m) = decoded::<pb::MapPoints>(payload, &progress, key) {
                            sink.map_points(&m);
                        }
                    }
                    _ => {
                        if let Some(s) = decoded::<pb::Status>(payload, &progress, key) {
                            sink.status(&s);
                            if s.state == pb::ServiceState::Finished as i32 {
                                *progress.finished.lock().unwrap_or_else(|e| e.into_inner()) = true;
                                progress.changed.notify_all();
                            }
                        }
                    }
                }
            };
            let subscriber = session
                .declare_subscriber(key.clone())
                .callback(on_sample)
                .wait()
                .map_err(|e| subscribe_error(&key, e.to_string()))?;
            subscribers.push(subscriber);
        }
        Ok(Self {
            _session: session,
            _subscribers: subscribers,
            progress,
        })
    }

    /// Waits until the merger reports FINISHED, at most `timeout`; whether it did.
    pub fn wait_finished(&self, timeout: Duration) -> bool {
        let finished = self
            .progress
            .finished
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        let (finished, _) = self
            .progress
            .changed
            .wait_timeout_while(finished, timeout, |done| !*done)
            .unwrap_or_else(|e| e.into_inner());
        *finished
    }

    /// Messages received so far.
    pub fn received(&self) -> u64 {
        self.progress.received.load(Ordering::Relaxed)
    }

    /// Messages that could not be decoded (another version of egoslam on the key).
    pub fn undecodable(&self) -> u64 {
        self.progress.undecodable.load(Ordering::Relaxed)
    }
}
