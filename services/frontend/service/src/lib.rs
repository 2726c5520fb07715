//! The frontend service: frames from the bus -> tracker (egoslam_frontend) -> keyframes on
//! the bus, and every frame's tracks to the merger's live tracker.

mod keyframe_message;
pub mod online_readout;
pub mod readout_hold;
pub mod resume;

use anyhow::{bail, Context};
use egoslam_bus::{Bus, BusOptions, FrameSubscriber, MessagePublisher, KEYFRAMES, LIVE_FRAMES};
use egoslam_durability::log_compaction;
use egoslam_durability::record_log::RecordLog;
use egoslam_frontend::tracker::ResumePoint;
use egoslam_frontend::{KeyframeTracks, Tracker, TrackerError, TrackerOptions};
use egoslam_messages::internal::v1 as internal;
use egoslam_messages::v1 as pb;
use egoslam_relocalization::descriptors::{DescriberOptions, OrbDescriber};
use egoslam_runtime::ServiceStats;
use egoslam_sources::calibration::read_calibration_file;
use keyframe_message::{describe_tracks, keyframe_message, track_message};
use opencv::core::Mat;
use opencv::prelude::*;
use std::collections::HashSet;
use std::path::PathBuf;
use std::time::Instant;

/// What a frontend service is told (the launcher's `egoslam frontend` flags,
/// docs/config.md).
#[derive(Debug, Clone)]
pub struct FrontendServiceOptions {
    /// Bus namespace (iceoryx2 service names egoslam/<namespace>/...).
    pub namespace: String,
    /// Output folder: statistics, and the state folder (keyframe log, ids, readout).
    pub out: PathBuf,
    /// Calibration YAML in egoslam's format (the launcher writes OUT/camera.yaml).
    pub camera: Option<PathBuf>,
    /// The tracker's options; its readout is set from `rolling_shutter_ms`.
    pub tracker: TrackerOptions,
    /// Rolling-shutter readout, ms (None: `auto`, estimated online, `online_readout`).
    pub rolling_shutter_ms: Option<f64>,
    /// Frames the online readout estimate is made from.
    pub readout_frames: u32,
    /// Hold the keyframes of those frames until the estimate and correct them
    /// (readout_hold.rs); else they go out uncorrected at once.
    pub hold_for_readout: bool,
    /// A saved map the run extends: keyframe and track ids start above its own.
    pub map_in: Option<PathBuf>,
}

/// Logs a keyframe message, then sends it: whatever the solver may have received is in the
/// log. Flushed to the kernel (not synced): the threat is a killed process, and the page
/// cache survives it.
fn log_and_send(
    log: &mut CompactingLog,
    publisher: &mut MessagePublisher<internal::Keyframe>,
    message: &internal::Keyframe,
) -> anyhow::Result<()> {
    log.append(message)?;
    publisher.send(message)?;
    log.compact_if_due()
}

/// The keyframe log with its compaction (log_compaction.rs): keyframes older than the
/// solver's mark are dropped once the log outgrows its schedule. The log's keyframe ids
/// only grow (a restarted frontend continues them), so everything before the first
/// record the mark still needs goes: an index of record offsets finds that cut without
/// decoding the log, which would stall the frame loop (decoding a 45 MB log took 0.37 s).
struct CompactingLog {
    log: RecordLog,
    schedule: log_compaction::CompactionSchedule,
    solver_mark: std::path::PathBuf,
    /// `(byte offset, keyframe id, end of stream)` of every record in the log, in order.
    index: std::collections::VecDeque<(u64, u64, bool)>,
}

impl CompactingLog {
    /// The log at `path`: continued and indexed when `resuming` (a restarted frontend's
    /// log holds its predecessor's records: read once here), else emptied.
    fn open(
        path: &std::path::Path,
        solver_mark: std::path::PathBuf,
        resuming: bool,
    ) -> anyhow::Result<Self> {
        let mut log = RecordLog::open(path)?;
        let index = if resuming {
            egoslam_durability::record_log::read_records_at::<internal::Keyframe>(path)?
                .into_iter()
                .map(|(offset, k)| (offset, k.keyframe_id, k.end_of_stream))
                .collect()
        } else {
            log.truncate()?;
            Default::default()
        };
        Ok(Self {
            log,
            schedule: log_compaction::CompactionSchedule::from_env(),
            solver_mark,
            index,
        })
    }

    /// Appends a keyframe message and hands it to the kernel.
    fn append(&mut self, message: &internal::Keyframe) -> anyhow::Result<()> {
        let offset = self.log.len_bytes()?;
        self.log.append(message)?;
        self.log.flush()?;
        self.index
            .push_back((offset, message.keyframe_id, message.end_of_stream));
        Ok(())
    }

    fn compact_if_due(&mut self) -> anyhow::Result<()> {
        let len = self.log.len_bytes()?;
        if !self.schedule.outgrown(len) {
            return Ok(());
        }
        let mark = log_compaction::read_mark(&self.solver_mark);
        if let Some(mark @ (_, first)) = self.schedule.fresh(mark) {
            let dropped = self
                .index
                .iter()
                .position(|(_, id, end)| *end || *id >= first)
                .unwrap_or(self.index.len());
            let cut = self
                .index
                .get(dropped)
                .map_or(len, |(offset, _, _)| *offset);
            if dropped > 0 {
                let kept_at = self.log.cut_before(cut)?;
                self.index.drain(..dropped);
                for entry in &mut self.index {
                    entry.0 = entry.0 - cut + kept_at;
                }
                tracing::info!(dropped, "keyframe log compacted");
            }
            self.schedule.compacted(mark, self.log.len_bytes()?);
        }
        Ok(())
    }
}

/// File (in the output folder) with the ids a restarted frontend continues from.
pub const ID_STATE_FILE: &str = "frontend.ids";

/// Tracks sent with each frame between keyframes: enough for a PnP with RANSAC, a
/// fraction of a keyframe's message.
const TRACKS_PER_FRAME: usize = 300;

/// Sends keyframe `k` as `msg` ([`log_and_send`]), counts it, and records the ids a
/// restarted frontend continues from.
fn publish(
    stats: &mut ServiceStats,
    (log, publisher): (
        &mut CompactingLog,
        &mut MessagePublisher<internal::Keyframe>,
    ),
    msg: &internal::Keyframe,
    tracker: &Tracker,
    state_path: &std::path::Path,
    k: &KeyframeTracks,
) -> anyhow::Result<()> {
    stats.time("publish", || log_and_send(log, publisher, msg))?;
    stats.keyframes += 1;
    let (kf, track) = tracker.next_ids();
    let ids = serde_json::json!({"next_keyframe_id": kf, "next_track_id": track});
    egoslam_durability::write_atomically(state_path, ids.to_string().as_bytes())?;
    tracing::debug!(keyframe = k.keyframe_id, frame = k.frame_id, tracks = k.tracks.len(), reason = ?k.reason, "keyframe");
    Ok(())
}

/// A restarted frontend continues from its predecessor's last frame (resume.rs);
/// a fresh one removes what an earlier stream of its namespace left.
fn continue_tracks(
    tracker: &mut Tracker,
    path: Option<&std::path::Path>,
    resuming: bool,
    stats: &mut ServiceStats,
) {
    let Some(path) = path else { return };
    if !resuming {
        let _ = std::fs::remove_file(path);
        return;
    }
    let resumed = resume::load(path).and_then(|saved| {
        tracker.resume_from(&ResumePoint {
            frame_id: saved.frame_id,
            timestamp_s: saved.timestamp_s,
            image: &saved.image,
            tracks: &saved.tracks,
        })?;
        Ok((saved.frame_id, saved.tracks.len()))
    });
    match resumed {
        Ok((frame_id, tracks)) => {
            tracing::warn!(
                frame_id,
                tracks,
                "continuing the tracks of the frame before the restart"
            );
            stats.count("resumed_tracks", tracks as u64);
        }
        Err(e) => tracing::warn!("{e:#}: new tracks begin after the restart"),
    }
}

/// How long a starting frontend waits for the merger's live tracker before it takes
/// frames: the merger starts beside it (the launcher, systemd) and connects within a
/// second; a frontend run without a merger goes on after this.
const LIVE_TRACKER_PATIENCE: std::time::Duration = std::time::Duration::from_secs(2);

/// Sends the frame's live tracks to the merger's live tracker. A failed send costs that
/// frame's live pose only (its refined pose comes with its keyframe): counted, not fatal.
fn send_live_frame(
    publisher: &mut MessagePublisher<internal::LiveFrame>,
    meta: &egoslam_bus::FrameMeta,
    tracker: &Tracker,
    intrinsics: &pb::Intrinsics,
    first_of_stream: bool,
    stats: &mut ServiceStats,
) {
    let started = Instant::now();
    let message = internal::LiveFrame {
        intrinsics: Some(intrinsics.clone()),
        first_of_stream,
        frame_id: meta.frame_id,
        timestamp_s: meta.timestamp,
        captured_unix_ns: meta.captured_unix_ns,
        tracks: tracker
            .live_track_points()
            .iter()
            .map(track_message)
            .collect(),
    };
    // The stream's first frame anchors the live poses until the first window: it is worth
    // a short wait for the live tracker to connect.
    let sent = if first_of_stream {
        publisher
            .send_patiently(&message, std::time::Duration::from_millis(500))
            .map(|_| ())
    } else {
        publisher.send(&message)
    };
    if let Err(e) = sent {
        tracing::debug!(error = %e, "live frame not sent");
        stats.count("live_frames_not_sent", 1);
    }
    stats.latency_since("frontend_tracked", meta.captured_unix_ns);
    stats.add_time("publish_live", started.elapsed().as_secs_f64() * 1e3);
}

/// Runs the frontend service until the stream's end (or a signal: an error).
pub fn run(args: FrontendServiceOptions) -> anyhow::Result<()> {
    let mut stats = ServiceStats::new("frontend");
    let calib_path = args
        .camera
        .clone()
        .context("the frontend needs --camera (calibration YAML)")?;
    let calib = read_calibration_file(&calib_path)?;
    let (w, h) = (
        calib.width.context("camera file lacks width")?,
        calib.height.context("camera file lacks height")?,
    );
    let camera = calib.camera_for(w, h)?;
    let intrinsics = egoslam_relocalization::intrinsics_to_pb(&camera);
    // The readout is in range: checked where the flag is parsed. `auto` reaches this service
    // only for a live stream: it is estimated from the first frames (online_readout.rs).
    let (readout_s, mut online_readout) =
        online_readout::service_readout(args.rolling_shutter_ms, args.readout_frames, &args.out);
    let options = TrackerOptions {
        rolling_shutter_s: readout_s,
        ..args.tracker
    };
    let mut tracker = Tracker::new(camera, options);
    // Keyframes wait for the readout estimate while it is made (readout_hold.rs).
    let mut hold = online_readout
        .as_ref()
        .filter(|_| args.hold_for_readout)
        .map(|_| readout_hold::ReadoutHold::default());
    let mut describer = OrbDescriber::new(DescriberOptions::default())?;
    // Live tracks whose patch went out with an earlier keyframe.
    let mut patched: HashSet<u64> = HashSet::new();
    // A restarted frontend continues the ids of its predecessor (docs/durability.md).
    let state = egoslam_durability::create_state_dir(&args.out)?;
    let state_path = state.join(ID_STATE_FILE);
    let resuming = state_path.exists();
    let solver_mark = state.join(log_compaction::SOLVER_MARK);
    if !resuming {
        // The mark of an earlier run names its keyframe ids, which this one reuses.
        log_compaction::remove_mark(&solver_mark)?;
    }
    let mut keyframe_log = CompactingLog::open(
        &egoslam_durability::keyframe_log_path(&args.out, &args.namespace),
        solver_mark,
        resuming,
    )?;
    if let Ok(text) = std::fs::read_to_string(&state_path) {
        let ids: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("{}: unreadable", state_path.display()))?;
        let (Some(kf), Some(track)) = (
            ids["next_keyframe_id"].as_u64(),
            ids["next_track_id"].as_u64(),
        ) else {
            bail!("{}: missing ids", state_path.display())
        };
        tracing::warn!(
            next_keyframe_id = kf,
            next_track_id = track,
            "resuming after a restart"
        );
        tracker.resume_ids(kf, track);
        stats.count("restarts", 1);
    } else if let Some(path) = &args.map_in {
        // The run extends a saved map: its ids start above the map's, which are older.
        let first = egoslam_durability::map_file::next_free_id(path)?;
        tracing::info!(first_id = first, map = %path.display(), "extending a saved map");
        tracker.resume_ids(first, first);
    }
    let mut resume_path = resume::path(&args.namespace);
    continue_tracks(&mut tracker, resume_path.as_deref(), resuming, &mut stats);
    let bus = Bus::open(
        "frontend",
        BusOptions {
            namespace: args.namespace.clone(),
            ..BusOptions::default()
        },
    )?;
    // The outputs first, the frames last: the camera (or replay) starts sending when the
    // frames' subscriber appears, and a frontend still waiting for a consumer then would
    // let a real-time stream's first frames overflow its 4-frame buffer and be dropped.
    let mut keyframes = MessagePublisher::<internal::Keyframe>::create(&bus, KEYFRAMES)?;
    let mut live_frames = MessagePublisher::<internal::LiveFrame>::create_lossy(&bus, LIVE_FRAMES)?;
    if !live_frames.wait_for_consumer(LIVE_TRACKER_PATIENCE) {
        tracing::info!(
            waited_s = LIVE_TRACKER_PATIENCE.as_secs_f64(),
            "no live tracker connected: frames go on without live poses until one does"
        );
    }
    let frames = FrameSubscriber::create(&bus)?;
    egoslam_runtime::systemd::ready("frontend");
    let mut skipped: Vec<internal::FrameStamp> = Vec::new();
    let mut last_stamp: Option<internal::FrameStamp> = None;
    // With a rolling shutter a keyframe waits for the next frame, which centres its
    // correction (`Tracker::centre_keyframe`); described, with its skipped frames taken.
    let mut pending: Option<(KeyframeTracks, internal::Keyframe)> = None;
    // The last frame, for the descriptors of the final keyframe (made after the stream).
    let mut last_image = Mat::default();
    let started = Instant::now();
    loop {
        let Some(frame) = frames.receive()? else {
            bail!(egoslam_bus::StoppedBySignal { during: "" })
        };
        let meta = *frame.meta();
        if meta.is_end_of_stream() {
            break;
        }
        stats.latency_since("frontend_received", meta.captured_unix_ns);
        let image =
            Mat::new_rows_cols_with_data(meta.height as i32, meta.width as i32, frame.pixels())
                .with_context(|| format!("frame {}: wrapping shared memory", meta.frame_id))?;
        let outcome = match stats.time("track", || {
            tracker.process_timed(meta.frame_id, meta.timestamp, &image)
        }) {
            Ok(o) => o,
            // A frame that does not fit the stream is skipped, not fatal (docs/bus.md).
            Err(e @ (TrackerError::SizeMismatch { .. } | TrackerError::NotGrey { .. })) => {
                tracing::warn!(error = %e, "frame skipped");
                stats.count("rejected_frames", 1);
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        // First, before anything else the frame causes: a live pose waits for this.
        let first_of_stream = !resuming && stats.frames == 0;
        send_live_frame(
            &mut live_frames,
            &meta,
            &tracker,
            &intrinsics,
            first_of_stream,
            &mut stats,
        );
        if let Some((mut k, mut msg)) = pending.take() {
            if tracker.centre_keyframe(&mut k) > 0 {
                for (m, t) in msg.tracks.iter_mut().zip(&k.tracks) {
                    (m.x, m.y) = (t.undistorted.x, t.undistorted.y);
                }
            }
            if let Some(hold) = &mut hold {
                hold.hold(k, msg);
            } else {
                let sender = (&mut keyframe_log, &mut keyframes);
                publish(&mut stats, sender, &msg, &tracker, &state_path, &k)?;
            }
        }
        if let Some(path) = &resume_path {
            let tracks = tracker.resumable_tracks();
            if let Err(e) = resume::save(path, meta.frame_id, meta.timestamp, &image, tracks) {
                tracing::warn!("{e:#}: a restarted frontend will start new tracks");
                resume_path = None;
            }
        }
        let mut described = None;
        if let Some(k) = &outcome.keyframe {
            let mut msg = keyframe_message(k, meta.timestamp, &intrinsics, Vec::new());
            stats.time("describe", || {
                describe_tracks(&mut describer, &image, &mut msg, &mut patched)
            });
            described = Some(msg);
        } else {
            image.copy_to(&mut last_image)?;
        }
        drop(image);
        drop(frame);
        stats.frames += 1;
        let mut attempt_over = false;
        if let Some(online) = &mut online_readout {
            let decided = stats.time("readout_estimate", || {
                online_readout::observe_online(online, &mut tracker, meta.timestamp, &args.out)
            })?;
            if decided {
                online_readout = None;
                attempt_over = true;
            } else {
                attempt_over = !online.in_first_attempt();
            }
        }
        // This frame's keyframe was made uncorrected: corrected as a new one would be.
        let mut correct_this_keyframe = false;
        if let Some(held) = hold.take_if(|_| attempt_over) {
            let readout_s = tracker.rolling_shutter_s();
            correct_this_keyframe = readout_s > 0.0;
            let count = held.len();
            let started = Instant::now();
            for (k, msg) in held.release(&tracker, readout_s, &mut skipped) {
                let sender = (&mut keyframe_log, &mut keyframes);
                publish(&mut stats, sender, &msg, &tracker, &state_path, &k)?;
            }
            stats.add_time("release_held", started.elapsed().as_secs_f64() * 1e3);
            tracing::info!(
                keyframes = count,
                readout_ms = readout_s * 1e3,
                "keyframes held for the readout estimate published"
            );
        }
        if outcome.blind {
            stats.count("blind_frames", 1);
        }
        stats.count(
            "rejected_forward_backward",
            outcome.rejected_forward_backward as u64,
        );
        let stamp = internal::FrameStamp {
            frame_id: meta.frame_id,
            timestamp_s: meta.timestamp,
            tracks: Vec::new(),
        };
        match (outcome.keyframe, described) {
            (Some(mut k), Some(mut msg)) => {
                msg.frames_since_previous = std::mem::take(&mut skipped);
                if correct_this_keyframe {
                    let readout_s = tracker.rolling_shutter_s();
                    readout_hold::recorrect(&tracker, readout_s, &mut k.tracks, &mut msg.tracks);
                }
                // Held keyframes wait for the next frame too: it centres their velocity.
                if tracker.rolling_shutter_s() > 0.0 || hold.is_some() {
                    pending = Some((k, msg));
                } else {
                    let sender = (&mut keyframe_log, &mut keyframes);
                    publish(&mut stats, sender, &msg, &tracker, &state_path, &k)?;
                }
            }
            _ => {
                let points = tracker.sample_tracks(TRACKS_PER_FRAME);
                skipped.push(internal::FrameStamp {
                    tracks: points.iter().map(track_message).collect(),
                    ..stamp
                });
                if let Some(hold) = &mut hold {
                    hold.note_frame(points);
                }
            }
        }
        last_stamp = Some(stamp);
    }
    // No frame came after it to centre its correction.
    if let Some((k, msg)) = pending.take() {
        if let Some(hold) = &mut hold {
            hold.hold(k, msg);
        } else {
            let sender = (&mut keyframe_log, &mut keyframes);
            publish(&mut stats, sender, &msg, &tracker, &state_path, &k)?;
        }
    }
    // A stream shorter than the estimation's frames: estimated from all of it.
    if let Some(online) = online_readout.take().filter(|o| o.in_first_attempt()) {
        let readout_s = online_readout::finish_online(online, &mut tracker, &args.out)?;
        for (k, msg) in hold
            .take()
            .map(|held| held.release(&tracker, readout_s, &mut skipped))
            .unwrap_or_default()
        {
            let sender = (&mut keyframe_log, &mut keyframes);
            publish(&mut stats, sender, &msg, &tracker, &state_path, &k)?;
        }
    }
    // The last frame becomes a keyframe so that every frame lies between two keyframes.
    if let (Some(k), Some(last)) = (tracker.finish(), last_stamp) {
        skipped.retain(|s| s.frame_id != last.frame_id);
        let mut msg = keyframe_message(
            &k,
            last.timestamp_s,
            &intrinsics,
            std::mem::take(&mut skipped),
        );
        if !last_image.empty() {
            describe_tracks(&mut describer, &last_image, &mut msg, &mut patched);
        }
        log_and_send(&mut keyframe_log, &mut keyframes, &msg)?;
        stats.keyframes += 1;
    }
    let end = internal::Keyframe {
        end_of_stream: true,
        trailing_frames: skipped,
        ..Default::default()
    };
    log_and_send(&mut keyframe_log, &mut keyframes, &end)?;
    let secs = started.elapsed().as_secs_f64();
    tracing::info!(
        frames = stats.frames,
        keyframes = stats.keyframes,
        "frontend finished ({:.1} frames/s)",
        stats.frames as f64 / secs
    );
    stats.count("dropped_messages", frames.dropped());
    stats.write(&args.out)?;
    if let Some(path) = &resume_path {
        // The stream is over: nothing to continue.
        let _ = std::fs::remove_file(path);
    }
    // Stay until the solver has read everything (see MessagePublisher::finish).
    if !keyframes.finish() {
        bail!(egoslam_bus::StoppedBySignal {
            during: " while the solver was reading the last keyframes"
        })
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::keyframe_message::tests::keyframe;
    use egoslam_durability::KEYFRAME_LOG;

    #[test]
    fn the_keyframe_log_drops_what_the_solver_no_longer_needs_once_it_has_grown() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(KEYFRAME_LOG);
        let mut log =
            CompactingLog::open(&path, dir.path().join(log_compaction::SOLVER_MARK), false)
                .expect("log");
        log.schedule = log_compaction::CompactionSchedule::new(1);
        let numbered = |id: u64| internal::Keyframe {
            keyframe_id: id,
            ..keyframe(&[1, 2, 3])
        };
        let ids = |path: &std::path::Path| -> Vec<u64> {
            egoslam_durability::record_log::read_records::<internal::Keyframe>(path)
                .expect("read")
                .iter()
                .map(|k| k.keyframe_id)
                .collect()
        };
        for id in 0..4 {
            log.append(&numbered(id)).expect("append");
            // No mark yet (the solver has published no window): nothing is dropped.
            log.compact_if_due().expect("compact");
        }
        assert_eq!(ids(&path), [0, 1, 2, 3]);
        log_compaction::write_mark(&log.solver_mark, 9, 2).expect("mark");
        log.append(&numbered(4)).expect("append");
        log.compact_if_due().expect("compact");
        assert_eq!(ids(&path), [2, 3, 4]);
        // The mark has not moved: the log is not rewritten, only appended to.
        log.append(&numbered(5)).expect("append");
        log.compact_if_due().expect("compact");
        assert_eq!(ids(&path), [2, 3, 4, 5]);
        // A restarted frontend indexes what its predecessor logged and cuts it the same way.
        drop(log);
        let mut log =
            CompactingLog::open(&path, dir.path().join(log_compaction::SOLVER_MARK), true)
                .expect("log");
        log.schedule = log_compaction::CompactionSchedule::new(1);
        log_compaction::write_mark(&log.solver_mark, 9, 4).expect("mark");
        log.append(&numbered(6)).expect("append");
        log.compact_if_due().expect("compact");
        assert_eq!(ids(&path), [4, 5, 6]);
    }
}
