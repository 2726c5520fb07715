//! Results of egoslam over zenoh, as protobuf (`proto/egoslam/v1`), for clients in any
//! language (docs/egress.md).
//!
//! | key expression | payload | when |
//! |---|---|---|
//! | `egoslam/<device>/pose` | `Pose` | every newly posed or re-posed frame, with its revision |
//! | `egoslam/<device>/trajectory` | `Trajectory` | all keyframe poses, after every window |
//! | `egoslam/<device>/map` | `MapPoints` | new and changed points, in chunks of 4096 |
//! | `egoslam/<device>/status` | `Status` | after every window and at the end |
//! | `egoslam/<device>/snapshot` | `Snapshot` (queryable) | on request: the whole current state |
//!
//! The session listens on loopback only by default (`tcp/127.0.0.1:7447`), peer mode, with
//! multicast and gossip scouting off: clients connect to that endpoint explicitly. Remote
//! sessions may only subscribe and query; TLS (optionally mutual) for other hosts
//! ([`NetworkOptions`]).

use egoslam_messages::v1 as pb;
use prost::Message;
use std::sync::{Arc, Mutex};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::Wait;

/// Points per `map` message (keeps each under ~200 KB).
pub const MAP_CHUNK: usize = 4096;

/// Largest message the egress session accepts from the network, bytes (zenoh's
/// `transport/link/rx/max_message_size`, 1 GiB by default). What arrives is small
/// (subscriptions, queries); larger messages are dropped by zenoh before they are
/// reassembled, so a peer cannot make the merger buffer a gigabyte.
pub const MAX_INCOMING_MESSAGE_BYTES: usize = 1 << 20;

mod network;

pub use network::{zenoh_config, NetworkOptions, TlsOptions};

/// Where and as whom results are published.
#[derive(Debug, Clone, PartialEq)]
pub struct EgressOptions {
    /// Device name in the key expressions (default "default").
    pub device: String,
    /// Endpoints, TLS and access control (default: `tcp/127.0.0.1:7447`, loopback only,
    /// remote sessions read-only).
    pub network: NetworkOptions,
}

impl Default for EgressOptions {
    fn default() -> Self {
        Self {
            device: "default".into(),
            network: NetworkOptions::default(),
        }
    }
}

/// Errors of [`Egress`].
#[derive(Debug, thiserror::Error)]
pub enum EgressError {
    /// The zenoh configuration was rejected (bad endpoint, device name or TLS combination).
    #[error("zenoh configuration: {0}")]
    Config(String),
    /// A TLS certificate or key file cannot be read.
    #[error("zenoh TLS {what} {path}: {reason}")]
    Tls {
        what: String,
        path: std::path::PathBuf,
        reason: String,
    },
    /// The session could not be opened (e.g. the listen port is taken).
    #[error("cannot open the zenoh session (--zenoh-listen {listen:?}): {reason}")]
    Open { listen: Vec<String>, reason: String },
    /// A publisher or queryable could not be declared.
    #[error("cannot declare {key}: {reason}")]
    Declare { key: String, reason: String },
    /// A put failed.
    #[error("cannot publish on {key}: {reason}")]
    Put { key: String, reason: String },
}

/// What the snapshot queryable answers: the encoded `Snapshot`, made on request.
type SnapshotSource = Arc<dyn Fn() -> Vec<u8> + Send + Sync>;

/// The publishers and the snapshot queryable of one device.
pub struct Egress {
    /// Held so that the session lives as long as its publishers and queryable.
    session: zenoh::Session,
    prefix: String,
    pose: zenoh::pubsub::Publisher<'static>,
    trajectory: zenoh::pubsub::Publisher<'static>,
    map: zenoh::pubsub::Publisher<'static>,
    status: zenoh::pubsub::Publisher<'static>,
    snapshot: Arc<Mutex<SnapshotSource>>,
    _queryable: zenoh::query::Queryable<()>,
}

impl Egress {
    /// Opens the session and declares every key expression.
    pub fn open(options: &EgressOptions) -> Result<Self, EgressError> {
        if options.device.is_empty() || options.device.contains(['/', '*', '$', '?', '#']) {
            return Err(EgressError::Config(format!(
                "device name {:?} is not a single key chunk",
                options.device
            )));
        }
        let mut config = options.network.zenoh_config()?;
        config
            .insert_json5(
                "transport/link/rx/max_message_size",
                &MAX_INCOMING_MESSAGE_BYTES.to_string(),
            )
            .map_err(|e| EgressError::Config(format!("max_message_size: {e}")))?;
        let session = zenoh::open(config).wait().map_err(|e| EgressError::Open {
            listen: options.network.listen.clone(),
            reason: e.to_string(),
        })?;
        let prefix = format!("egoslam/{}", options.device);
        let declare = |name: &str, congestion_control: CongestionControl, priority: Priority| {
            let key = format!("{prefix}/{name}");
            session
                .declare_publisher(key.clone())
                .congestion_control(congestion_control)
                .priority(priority)
                .wait()
                .map_err(|e| EgressError::Declare {
                    key,
                    reason: e.to_string(),
                })
        };
        // A pose is superseded by the frame's next revision and must not wait behind a
        // slow link or a window's map: dropped under congestion, and sent ahead of the
        // rest (a queue of its own, zenoh's `DataHigh`). The map arrives as changes, so a
        // lost chunk would leave a hole no later message fills; it, the trajectory and the
        // status (which a client takes as "all before me arrived") block instead, at one
        // priority so they keep their order. Zenoh closes a link that stays blocked for
        // 5 s (`congestion_control/block/wait_before_close`), so a stuck client cannot
        // stall the merger for longer.
        let (pose, trajectory, map, status) = (
            declare("pose", CongestionControl::Drop, Priority::DataHigh)?,
            declare("trajectory", CongestionControl::Block, Priority::Data)?,
            declare("map", CongestionControl::Block, Priority::Data)?,
            declare("status", CongestionControl::Block, Priority::Data)?,
        );
        let empty = pb::Snapshot::default().encode_to_vec();
        let snapshot: Arc<Mutex<SnapshotSource>> =
            Arc::new(Mutex::new(Arc::new(move || empty.clone())));
        let shared = snapshot.clone();
        let key = format!("{prefix}/snapshot");
        let reply_key = key.clone();
        let queryable = session
            .declare_queryable(key.clone())
            .callback(move |query| {
                // The source is taken out of the lock before it is encoded, so a large
                // snapshot never holds up the merger replacing it.
                let source = shared.lock().map(|s| Arc::clone(&s)).ok();
                let bytes = source.map(|make| make()).unwrap_or_default();
                if let Err(e) = query.reply(reply_key.clone(), bytes).wait() {
                    tracing::warn!(%e, "snapshot reply failed");
                }
            })
            .wait()
            .map_err(|e| EgressError::Declare {
                key,
                reason: e.to_string(),
            })?;
        Ok(Self {
            session,
            prefix,
            pose,
            trajectory,
            map,
            status,
            snapshot,
            _queryable: queryable,
        })
    }

    /// The session, for observers in the same process (local subscribers are not subject
    /// to the access control, which filters what crosses the network).
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// The key expression prefix, `egoslam/<device>`.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    fn put(
        &self,
        publisher: &zenoh::pubsub::Publisher<'static>,
        bytes: Vec<u8>,
    ) -> Result<(), EgressError> {
        publisher.put(bytes).wait().map_err(|e| EgressError::Put {
            key: publisher.key_expr().to_string(),
            reason: e.to_string(),
        })
    }

    /// One message per pose.
    pub fn publish_poses(&self, poses: &[pb::Pose]) -> Result<(), EgressError> {
        poses
            .iter()
            .try_for_each(|p| self.put(&self.pose, p.encode_to_vec()))
    }

    pub fn publish_trajectory(&self, trajectory: &pb::Trajectory) -> Result<(), EgressError> {
        self.put(&self.trajectory, trajectory.encode_to_vec())
    }

    /// New and changed points, in chunks of [`MAP_CHUNK`].
    pub fn publish_map(&self, points: &[pb::MapPoint]) -> Result<(), EgressError> {
        points.chunks(MAP_CHUNK).try_for_each(|chunk| {
            self.put(
                &self.map,
                pb::MapPoints {
                    points: chunk.to_vec(),
                }
                .encode_to_vec(),
            )
        })
    }

    pub fn publish_status(&self, status: &pb::Status) -> Result<(), EgressError> {
        self.put(&self.status, status.encode_to_vec())
    }

    /// Replaces what the snapshot queryable answers.
    pub fn set_snapshot(&self, snapshot: &pb::Snapshot) {
        let bytes = snapshot.encode_to_vec();
        self.replace_snapshot(Arc::new(move || bytes.clone()));
    }

    /// Replaces what the snapshot queryable answers by what `make` returns when a client
    /// asks (the merger's snapshot grows with the stream; most are never asked for).
    pub fn set_snapshot_source(&self, make: impl Fn() -> pb::Snapshot + Send + Sync + 'static) {
        self.replace_snapshot(Arc::new(move || make().encode_to_vec()));
    }

    fn replace_snapshot(&self, source: SnapshotSource) {
        if let Ok(mut current) = self.snapshot.lock() {
            *current = source;
        }
    }
}
