//! The merger's live tracker: a thread that poses every frame as the frontend sends it
//! (`egoslam_merger::LiveTracker`, iceoryx2 `live_frames`) and publishes that pose at once
//! as the frame's revision 0 over zenoh; the window's pose comes later as a higher revision.
//! The merger's main loop hands it the map after each window.

use crate::map_state::Revisions;
use anyhow::Context;
use egoslam_bus::{Bus, BusOptions, MessageSubscriber, LIVE_FRAMES};
use egoslam_egress::Egress;
use egoslam_merger::{
    live_tracking::recording, LivePose, LiveTracker, LiveTrackerOptions, MapBuilder, MapView,
    TrackingState,
};
use egoslam_messages::internal::v1 as internal;
use egoslam_messages::v1 as pb;
use egoslam_runtime::ServiceStats;
use nalgebra::Point2;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use egoslam_export::tum::LIVE_TRAJECTORY_FILE;

/// How long the thread waits for a frame before it looks at its stop flag and the map.
const POLL: Duration = Duration::from_millis(20);

/// The running tracker thread.
pub(super) struct LiveTracking {
    maps: mpsc::Sender<MapView>,
    stop: Arc<AtomicBool>,
    thread: std::thread::JoinHandle<anyhow::Result<ServiceStats>>,
}

/// What the thread publishes with.
pub(super) struct Publication {
    pub egress: Option<Arc<Egress>>,
    pub revisions: Arc<Mutex<Revisions>>,
    /// The segment a new stream's map begins in when it is known before its first window
    /// (a new map: 0); the frames until that window are then posed from the stream's first
    /// frame (`LiveTracker::begin_at_origin`).
    pub origin_segment: Option<u32>,
}

impl LiveTracking {
    /// Starts the thread: it opens its own bus node (iceoryx2 ports stay in their thread).
    /// `fresh`: a new run (not a restarted merger), whose live trajectory starts empty.
    pub(super) fn start(
        namespace: &str,
        out: &Path,
        fresh: bool,
        publication: Publication,
    ) -> Self {
        let (maps, updates) = mpsc::channel();
        let stop = Arc::new(AtomicBool::new(false));
        let (namespace, out, flag) = (namespace.to_string(), out.to_path_buf(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("live-tracker".into())
            .spawn(move || run(&namespace, &out, fresh, &publication, &updates, &flag))
            .expect("spawning a thread");
        Self { maps, stop, thread }
    }

    /// Hands the tracker the map around the newest window (`window`: its keyframe ids):
    /// the points its keyframes see, and its last keyframe's pose.
    pub(super) fn update(
        &self,
        map: &MapBuilder,
        camera: Option<&egoslam_geometry::PinholeRadtan>,
        window: &[u64],
    ) {
        let (Some(first), Some(last)) = (window.first(), window.last()) else {
            return;
        };
        let Some((segment, newest)) = map.keyframe(*last) else {
            return;
        };
        let view = MapView {
            camera: camera.copied(),
            segment,
            points: map.points_seen_since(*first, segment).into_iter().collect(),
            newest_keyframe: Some(*newest),
            pace: map.recent_walking_pace(segment, *last),
        };
        tracing::debug!(
            segment,
            points = view.points.len(),
            pace = ?view.pace,
            newest_keyframe_s = newest.timestamp,
            "map for the live tracker"
        );
        // A tracker that ended (its error comes out at `finish`) no longer takes maps.
        let _ = self.maps.send(view);
    }

    /// Stops the thread once the frames sent so far are posed; its statistics.
    pub(super) fn finish(self) -> anyhow::Result<ServiceStats> {
        self.stop.store(true, Ordering::Relaxed);
        self.thread
            .join()
            .map_err(|_| anyhow::anyhow!("the live tracker panicked"))?
    }
}

fn run(
    namespace: &str,
    out: &Path,
    fresh: bool,
    publication: &Publication,
    maps: &mpsc::Receiver<MapView>,
    stop: &AtomicBool,
) -> anyhow::Result<ServiceStats> {
    let mut stats = ServiceStats::new("live_tracker");
    let bus = Bus::open(
        "merger-live",
        BusOptions {
            namespace: namespace.to_string(),
            ..BusOptions::default()
        },
    )?;
    let mut frames = MessageSubscriber::<internal::LiveFrame>::create(&bus, LIVE_FRAMES)?;
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    let mut file = LiveTrajectory::open(&out.join(LIVE_TRAJECTORY_FILE), fresh)?;
    let mut record = LiveRecord::from_env();
    loop {
        // The last map first: a frame is posed on the newest one there is.
        if let Some(view) = maps.try_iter().last() {
            record.add(|| recording::map_line(&view));
            tracker.set_map(view);
        }
        let stopping = stop.load(Ordering::Relaxed) || egoslam_bus::stop_requested();
        let Some(frame) = frames.receive_lossy_within(POLL)? else {
            if stopping {
                break;
            }
            continue;
        };
        stats.latency_since("live_received", frame.captured_unix_ns);
        let tracks: Vec<(u64, Point2<f64>)> = frame
            .tracks
            .iter()
            .map(|t| (t.track_id, Point2::new(f64::from(t.x), f64::from(t.y))))
            .collect();
        let camera = frame
            .intrinsics
            .as_ref()
            .and_then(egoslam_relocalization::wire::camera_from_pb);
        let origin = match (frame.first_of_stream, publication.origin_segment, camera) {
            (true, Some(segment), Some(camera)) if !tracker.has_map() => Some((segment, camera)),
            _ => None,
        };
        record.add(|| {
            Some(match origin {
                Some((segment, camera)) => {
                    recording::origin_line(segment, &camera, frame.timestamp_s, &tracks)
                }
                None => recording::frame_line(frame.timestamp_s, &tracks),
            })
        });
        let located = stats.time("live_track", || match origin {
            Some((segment, camera)) => {
                Some(tracker.begin_at_origin(camera, segment, frame.timestamp_s, &tracks))
            }
            None => tracker.track(frame.timestamp_s, &tracks),
        });
        let Some(live) = located else {
            stats.count("live_before_map", 1);
            continue;
        };
        stats.count(state_counter(live.state), 1);
        publish(publication, frame.frame_id, &live)?;
        stats.latency_since("live_published", frame.captured_unix_ns);
        file.append(&live)?;
        stats.frames += 1;
    }
    stats.count("live_frames_missed", frames.missed());
    file.flush()?;
    Ok(stats)
}

fn state_counter(state: TrackingState) -> &'static str {
    match state {
        TrackingState::Tracking => "live_tracking",
        TrackingState::Rotation => "live_rotation",
        TrackingState::Predicted => "live_predicted",
        TrackingState::Lost => "live_lost",
    }
}

fn tracking_to_pb(state: TrackingState) -> pb::TrackingState {
    match state {
        TrackingState::Tracking => pb::TrackingState::Tracking,
        TrackingState::Rotation => pb::TrackingState::Rotation,
        TrackingState::Predicted => pb::TrackingState::Predicted,
        TrackingState::Lost => pb::TrackingState::Lost,
    }
}

/// Publishes the pose as the frame's first revision, unless a window already posed the frame.
fn publish(publication: &Publication, frame_id: u64, live: &LivePose) -> anyhow::Result<()> {
    let claimed = publication
        .revisions
        .lock()
        .map_err(|_| anyhow::anyhow!("revisions poisoned"))?
        .claim_live(frame_id, &live.pose);
    if let (Some(revision), Some(egress)) = (claimed, &publication.egress) {
        let pose = pb::Pose {
            revision,
            tracking: tracking_to_pb(live.state) as i32,
            inliers: live.inliers as u32,
            ..egoslam_relocalization::wire::pose_to_pb(frame_id, live.segment, &live.pose)
        };
        egress.publish_poses(&[pose])?;
    }
    Ok(())
}

/// `EGOSLAM_DUMP_LIVE=FILE`: the tracker's inputs in the order it took them, for
/// `live_replay` (egoslam_merger::live_tracking::recording); off without the variable. A
/// developer's tool, buffered: a crash loses the last lines.
struct LiveRecord {
    writer: Option<std::io::BufWriter<std::fs::File>>,
}

impl LiveRecord {
    fn from_env() -> Self {
        let writer = std::env::var_os("EGOSLAM_DUMP_LIVE").and_then(|path| {
            std::fs::File::create(&path)
                .map_err(|e| tracing::warn!(error = %e, ?path, "live tracker record not written"))
                .ok()
                .map(std::io::BufWriter::new)
        });
        Self { writer }
    }

    /// Appends the line `line` makes, if recording (the line is only made then).
    fn add(&mut self, line: impl FnOnce() -> Option<String>) {
        let Some(writer) = self.writer.as_mut() else {
            return;
        };
        if let Some(line) = line() {
            if let Err(e) = writeln!(writer, "{line}") {
                tracing::warn!(error = %e, "live tracker record stopped");
                self.writer = None;
            }
        }
    }
}

/// `live_trajectory.tum`: appended per frame, flushed about once a second.
struct LiveTrajectory {
    path: PathBuf,
    writer: std::io::BufWriter<std::fs::File>,
    unflushed: usize,
}

impl LiveTrajectory {
    /// Opened for appending: a restarted merger goes on after its predecessor's frames;
    /// a new run (`fresh`) starts it empty.
    fn open(path: &Path, fresh: bool) -> anyhow::Result<Self> {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .truncate(false)
            .open(path)
            .and_then(|f| {
                if fresh {
                    f.set_len(0)?;
                }
                Ok(f)
            })
            .with_context(|| format!("opening {}", path.display()))?;
        Ok(Self {
            path: path.to_path_buf(),
            writer: std::io::BufWriter::new(file),
            unflushed: 0,
        })
    }

    fn append(&mut self, live: &LivePose) -> anyhow::Result<()> {
        let (p, q) = (live.pose.position, live.pose.rotation.quaternion());
        writeln!(
            self.writer,
            "{:.6} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
            live.pose.timestamp, p.x, p.y, p.z, q.i, q.j, q.k, q.w
        )
        .with_context(|| format!("writing {}", self.path.display()))?;
        self.unflushed += 1;
        if self.unflushed >= 30 {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> anyhow::Result<()> {
        self.unflushed = 0;
        self.writer
            .flush()
            .with_context(|| format!("writing {}", self.path.display()))
    }
}
