//! Live view and recording of egoslam's results (docs/viewer.md).
//!
//! A [`Viewer`] republishes what the merger sends over zenoh ([`feed`]) on Foxglove's
//! well-known schemas ([`convert`]): to a Foxglove WebSocket server (the Foxglove app or any
//! client of the `foxglove.sdk.v1` protocol connects to it) and to an MCAP file, with the
//! same channels and schemas in both:
//!
//! | topic | schema | when |
//! |---|---|---|
//! | `/egoslam/pose` | `foxglove.PoseInFrame` | every frame's pose, each revision |
//! | `/tf` | `foxglove.FrameTransform` | `map` -> `camera`, at every new frame |
//! | `/egoslam/keyframes` | `foxglove.PosesInFrame` | the keyframe trajectory, after each window |
//! | `/egoslam/map` | `foxglove.PointCloud` | all points, at most every `cloud_interval` (longer for a large map) and at the end |
//! | `/egoslam/status` | `foxglove.Log` | each status of the merger |

pub mod convert;
pub mod feed;

use egoslam_messages::v1 as pb;
use foxglove::messages::{FrameTransform, Log, PointCloud, PoseInFrame, PosesInFrame, Timestamp};
use foxglove::{Channel, Context, McapWriterHandle, WebSocketServerHandle};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Where the view goes.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewerOptions {
    /// `HOST:PORT` of the Foxglove WebSocket server (port 0: any free port); `None`: no
    /// server. Loopback unless a host is given on purpose: the stream shows what the
    /// wearer sees.
    pub foxglove: Option<String>,
    /// MCAP file to record into (replaced if present); `None`: no recording.
    pub record: Option<PathBuf>,
    /// The whole point cloud is sent at most this often (and once at the end).
    pub cloud_interval: Duration,
    /// ... and at most at this many bytes per second on average, so that a day's recording
    /// stays within bounds (a map of 150k points is 1.8 MB a message: every 18 s at the
    /// default 100 kB/s, 360 MB an hour).
    pub cloud_bytes_per_second: f64,
}

impl Default for ViewerOptions {
    fn default() -> Self {
        Self {
            foxglove: None,
            record: None,
            cloud_interval: Duration::from_secs(2),
            cloud_bytes_per_second: 100e3,
        }
    }
}

/// Why the viewer could not start or finish.
#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    #[error("--foxglove {0}: expected HOST:PORT, e.g. 127.0.0.1:8765")]
    Address(String),
    #[error("starting the Foxglove WebSocket server on {address}: {source}")]
    Server {
        address: String,
        source: foxglove::FoxgloveError,
    },
    #[error("recording into {path}: {source}")]
    Record {
        path: PathBuf,
        source: foxglove::FoxgloveError,
    },
    #[error("creating {path}: {source}")]
    CreateRecording {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("subscribing to {key}: {reason}")]
    Subscribe { key: String, reason: String },
}

struct Channels {
    pose: Channel<PoseInFrame>,
    tf: Channel<FrameTransform>,
    keyframes: Channel<PosesInFrame>,
    map: Channel<PointCloud>,
    status: Channel<Log>,
}

/// The map's points by track id, and when the cloud was last sent.
struct Cloud {
    points: BTreeMap<u64, [f32; 3]>,
    changed: bool,
    sent: Option<Instant>,
}

/// The live view: a Foxglove server and/or an MCAP recording of egoslam's results.
pub struct Viewer {
    // Kept alive: channels log into the sinks of their context.
    _context: Arc<Context>,
    channels: Channels,
    server: Mutex<Option<WebSocketServerHandle>>,
    port: Option<u16>,
    recording: Mutex<Option<(PathBuf, McapWriterHandle<BufWriter<File>>)>>,
    cloud: Mutex<Cloud>,
    cloud_interval: Duration,
    cloud_bytes_per_second: f64,
}

/// Splits `HOST:PORT` (IPv6 hosts in brackets).
fn host_port(address: &str) -> Result<(String, u16), ViewerError> {
    let bad = || ViewerError::Address(address.to_string());
    let (host, port) = address.rsplit_once(':').ok_or_else(bad)?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() {
        return Err(bad());
    }
    Ok((host.to_string(), port.parse().map_err(|_| bad())?))
}

fn record_into(
    context: &Arc<Context>,
    path: &Path,
) -> Result<McapWriterHandle<BufWriter<File>>, ViewerError> {
    let file = File::create(path).map_err(|source| ViewerError::CreateRecording {
        path: path.to_path_buf(),
        source,
    })?;
    context
        .mcap_writer()
        .create(BufWriter::new(file))
        .map_err(|source| ViewerError::Record {
            path: path.to_path_buf(),
            source,
        })
}

impl Viewer {
    /// Opens the recording and starts the server; every channel exists from here on, so a
    /// client that connects sees them advertised before the first result arrives.
    pub fn start(options: &ViewerOptions) -> Result<Self, ViewerError> {
        let context = Context::new();
        let channels = Channels {
            pose: context.channel_builder("/egoslam/pose").build(),
            tf: context.channel_builder("/tf").build(),
            keyframes: context.channel_builder("/egoslam/keyframes").build(),
            map: context.channel_builder("/egoslam/map").build(),
            status: context.channel_builder("/egoslam/status").build(),
        };
        let recording = match &options.record {
            Some(path) => Some((path.clone(), record_into(&context, path)?)),
            None => None,
        };
        let server = match &options.foxglove {
            Some(address) => {
                let (host, port) = host_port(address)?;
                let handle = context
                    .websocket_server()
                    .name("egoslam")
                    .bind(host, port)
                    .start_blocking()
                    .map_err(|source| ViewerError::Server {
                        address: address.clone(),
                        source,
                    })?;
                tracing::info!(port = handle.port(), "Foxglove WebSocket server listening");
                Some(handle)
            }
            None => None,
        };
        Ok(Self {
            _context: context,
            channels,
            port: server.as_ref().map(|s| s.port()),
            server: Mutex::new(server),
            recording: Mutex::new(recording),
            cloud: Mutex::new(Cloud {
                points: BTreeMap::new(),
                changed: false,
                sent: None,
            }),
            cloud_interval: options.cloud_interval,
            cloud_bytes_per_second: options.cloud_bytes_per_second,
        })
    }

    /// The server's port (the one chosen when asked for port 0).
    pub fn port(&self) -> Option<u16> {
        self.port
    }

    /// A frame's pose; a first pose (revision 0, or a later round's first: the low 24
    /// bits 0, see the proto) also moves the camera frame.
    pub fn pose(&self, pose: &pb::Pose) {
        self.channels.pose.log(&convert::pose_in_frame(pose));
        if egoslam_messages::first_of_round(pose.revision) {
            self.channels.tf.log(&convert::camera_transform(pose));
        }
    }

    /// The keyframe trajectory.
    pub fn trajectory(&self, trajectory: &pb::Trajectory) {
        self.channels
            .keyframes
            .log(&convert::keyframe_path(trajectory));
    }

    /// New or moved points (chunks of the newest window's).
    pub fn map_points(&self, points: &pb::MapPoints) {
        let mut cloud = self.cloud.lock().unwrap_or_else(|e| e.into_inner());
        for p in &points.points {
            if let Some(v) = p.position {
                cloud
                    .points
                    .insert(p.track_id, [v.x as f32, v.y as f32, v.z as f32]);
                cloud.changed = true;
            }
        }
    }

    /// A status of the merger: logged; the cloud is sent when due.
    pub fn status(&self, status: &pb::Status) {
        self.channels
            .status
            .log(&convert::status_log(status, Timestamp::now()));
        let finished = status.state == pb::ServiceState::Finished as i32;
        self.send_cloud(finished);
    }

    fn send_cloud(&self, now: bool) {
        let mut cloud = self.cloud.lock().unwrap_or_else(|e| e.into_inner());
        let bytes = (cloud.points.len() * 12) as f64;
        let pause = Duration::try_from_secs_f64(bytes / self.cloud_bytes_per_second)
            .unwrap_or(Duration::MAX)
            .max(self.cloud_interval);
        let due = cloud.sent.is_none_or(|t| t.elapsed() >= pause);
        if cloud.changed && (now || due) {
            self.channels.map.log(&convert::point_cloud(
                cloud.points.values(),
                Timestamp::now(),
            ));
            cloud.changed = false;
            cloud.sent = Some(Instant::now());
        }
    }

    /// Sends the last cloud, closes the recording (its summary section written, so that
    /// readers find every channel) and stops the server. Results after it are dropped.
    pub fn finish(&self) -> Result<(), ViewerError> {
        self.send_cloud(true);
        let recording = self
            .recording
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        let server = self.server.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(server) = server {
            drop(server.stop());
        }
        if let Some((path, writer)) = recording {
            writer
                .close()
                .map_err(|source| ViewerError::Record { path, source })?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_are_host_and_port() {
        assert_eq!(
            host_port("127.0.0.1:8765").ok(),
            Some(("127.0.0.1".into(), 8765))
        );
        assert_eq!(host_port("[::1]:0").ok(), Some(("::1".into(), 0)));
        for bad in ["8765", ":8765", "localhost:http", "127.0.0.1:70000"] {
            assert!(
                matches!(host_port(bad), Err(ViewerError::Address(_))),
                "{bad}"
            );
        }
    }
}
