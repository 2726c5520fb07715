//! The merger service: window solutions from the bus -> one map -> result files and zenoh.
//!
//! After every window the state is checkpointed and the files rewritten (atomically); a
//! killed merger restarts from its checkpoint and recovers the windows it had not applied
//! from the solver's journal, so nothing is lost (docs/durability.md). The same state goes
//! out over zenoh (docs/egress.md).

mod background_refinement;
mod frame_poses;
pub(crate) mod map_state;
use crate::cli::ServiceArgs;
use crate::convert::{pose_from_pb, vec3_from_pb};
use crate::durability::checkpoint::{self, MergerState};
use crate::durability::features_log::{FeaturesLog, Keep};
use crate::durability::log_compaction;
use crate::stats::ServiceStats;
use background_refinement::BackgroundRefiner;
use map_state::{MapState, Revisions};

mod journal_recovery;
mod keyframe_culling;
mod live_tracking;
pub use live_tracking::LIVE_TRAJECTORY_FILE;
mod outputs;
mod relocalization;
use anyhow::bail;
use egoslam_bus::{Bus, BusOptions, MessageSubscriber, WINDOWS};
use egoslam_egress::{Egress, EgressOptions};
use egoslam_geometry::PinholeRadtan;
use egoslam_merger::{PointConfidenceOptions, WindowInput, WindowOutcome};
use egoslam_messages::v1 as pb;
use egoslam_relocalization::{KeyframeDatabase, MapFeature, Vocabulary};
use egoslam_solver::triangulation::TriangulationOptions;
use nalgebra::Point2;
use outputs::Outputs;
use std::collections::{BTreeSet, VecDeque};

/// The merger at work: its durable state, where it writes, what it publishes.
struct Merger {
    args: ServiceArgs,
    state: MergerState,
    outputs: Outputs,
    stats: ServiceStats,
    refiner: BackgroundRefiner,
    /// Camera of the observations (from the windows), for PnP.
    camera: Option<PinholeRadtan>,
    /// When the files and checkpoint were last written.
    last_persist: Option<std::time::Instant>,
    /// Time the next rewrite waits for (`persist_due`).
    persist_spacing: std::time::Duration,
    /// For relocalization: linking segments after a break, and the saved map.
    vocabulary: Vocabulary,
    /// Where keyframe descriptors are persisted (not in the checkpoint).
    features_log: FeaturesLog,
    /// Bag-of-words index of every keyframe, for segment linking (rebuilt on restart).
    database: KeyframeDatabase,
    /// A loop attempt fell due while a background refinement ran: it is made at the first
    /// window after the refinement is folded in (not checkpointed: a restart skips it).
    loop_attempt_owed: bool,
    /// The sightings of the loop this window closed, added to the map after the window's
    /// cross-window error is measured (`MapBuilder::add_loop_sightings`).
    loop_sightings: Vec<(u64, u64, nalgebra::Point2<f64>)>,
    /// Poses every frame as it arrives (revision 0); handed the map after each window.
    live: Option<live_tracking::LiveTracking>,
}

/// Shortest time between rewrites of the result files and the checkpoint. Rewriting both
/// after every window made a 12,000-frame walk spend 370 of its 428 s there (they grow
/// with the map); the journal makes waiting safe.
const PERSIST_INTERVAL: std::time::Duration = std::time::Duration::from_secs(5);

/// Average bytes per second the checkpoint's rewrites may write (512 KiB/s, 1.8 GiB per
/// hour): a rewrite waits, beyond [`PERSIST_INTERVAL`], as long as the last checkpoint's
/// size takes at that rate. The checkpoint is the whole map (80 MB after 6 minutes of a
/// looped walk), and rewritten every 5 s it wrote ~16 MB/s: flash wear that would end a
/// wearable's storage within months. Windows in between stay in the solver's journal.
/// `EGOSLAM_PERSIST_BUDGET_BYTES_PER_S` sets another rate ("inf": every 5 s).
const PERSIST_BUDGET_BYTES_PER_S: f64 = 512.0 * 1024.0;

fn persist_budget() -> f64 {
    std::env::var("EGOSLAM_PERSIST_BUDGET_BYTES_PER_S")
        .ok()
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|b| *b > 0.0)
        .unwrap_or(PERSIST_BUDGET_BYTES_PER_S)
}

impl Merger {
    fn checkpoint_path(&self) -> std::path::PathBuf {
        crate::output::state_dir(&self.args.out).join(checkpoint::FILE_NAME)
    }

    /// Makes `stream_id` the current solver stream. A new stream while the previous one
    /// is unfinished means the solver was restarted mid-stream: the map goes on in a new
    /// segment (keyframe ids stay unique: the frontend continues them). After a finished
    /// stream, a new one starts a new map.
    fn begin_stream(&mut self, stream_id: u64) -> anyhow::Result<()> {
        if self.state.stream_id == Some(stream_id) {
            return Ok(());
        }
        if self.state.stream_id.is_some() && !self.state.finished {
            tracing::warn!(
                stream = stream_id,
                "a new solver stream: the map continues in a new segment"
            );
            self.state.stream_id = Some(stream_id);
            self.state.last_sequence = None;
            self.state.map.break_segment();
            self.stats.count("solver_restarts", 1);
        } else {
            self.state = MergerState::for_stream(stream_id);
            self.features_log.truncate()?;
            if let Some(path) = self.args.map.map_in.clone() {
                self.extend_saved_map(&path)?;
            }
        }
        Ok(())
    }

    /// Applies message `sequence`, checkpoints, and writes/publishes the results.
    fn apply(&mut self, sequence: u64, w: &pb::WindowSolution) -> anyhow::Result<()> {
        self.begin_stream(w.stream_id)?;
        for k in &w.keyframes {
            self.state.frames.add_stamp(k);
        }
        for f in &w.keyframe_features {
            use egoslam_relocalization::saved_map::{features_from_pb, patches_from_pb};
            match features_from_pb(f).zip(patches_from_pb(f)) {
                Some((features, patches)) => {
                    if !self.database.contains(f.keyframe_id) {
                        self.index_keyframe(f.keyframe_id, &features);
                    }
                    self.features_log.append(f)?;
                    let patched = crate::durability::features_log::patched_tracks(&patches);
                    self.state.patched_tracks.insert(f.keyframe_id, patched);
                }
                None => {
                    tracing::warn!(
                        keyframe = f.keyframe_id,
                        "inconsistent keyframe descriptors ignored"
                    );
                    self.stats.count("invalid_features", 1);
                }
            }
        }
        // Loop closure and linking read descriptors back from the log.
        self.features_log.flush()?;
        for f in &w.trailing_frames {
            self.state.frames.frames.insert(f.frame_id, f.timestamp_s);
        }
        // A refinement started earlier is folded in before this window when due (see
        // `BackgroundRefiner::fold`; at the end of the stream a running one is waited for).
        self.refiner
            .fold(&mut self.state.map, w.end_of_stream, &mut self.stats);
        // Culling waits while a refinement runs, and a window may start the next one: here,
        // right after a fold, it gets its turn. Keyframes older than this window's first
        // are in no later window.
        if let (false, Some(first)) = (w.end_of_stream, w.keyframe_ids.first()) {
            self.cull_keyframes(*first);
        }
        if w.end_of_stream {
            self.state.finished = true;
        } else {
            self.add_window(w);
        }
        if let Some(camera) = window_camera(w) {
            self.camera = Some(camera);
        }
        if let Some(camera) = &self.camera {
            let (frames, map) = (&mut self.state.frames, &self.state.map);
            let stats = &mut self.stats;
            let start = std::time::Instant::now();
            let oldest = w.keyframe_ids.first().copied().unwrap_or(0);
            frame_poses::localize_pending(frames, map, camera, oldest, stats);
            stats.add_time("localize_frames", start.elapsed().as_secs_f64() * 1e3);
        }
        if let Some(live) = &self.live {
            live.update(&self.state.map, self.camera.as_ref(), &w.keyframe_ids);
        }
        self.state.last_sequence = Some(sequence);
        // Publish first, then checkpoint (with the revisions just published): a kill in
        // between re-applies this window from the journal, which publishes the same again.
        let changed: Vec<u64> = w.points.iter().map(|p| p.track_id).collect();
        let write_start = std::time::Instant::now();
        let state = if self.state.finished {
            pb::ServiceState::Finished
        } else {
            pb::ServiceState::Running
        };
        let persist = self.persist_due();
        self.emit(&changed, state, persist)?;
        self.stats
            .add_time("write", write_start.elapsed().as_secs_f64() * 1e3);
        if persist {
            self.state.revisions = self
                .outputs
                .revisions
                .lock()
                .map_err(|_| anyhow::anyhow!("revisions poisoned"))?
                .numbers();
            let save_start = std::time::Instant::now();
            self.prune_culled_patches();
            let (map, patched) = (&self.state.map, &self.state.patched_tracks);
            let keep = |keyframe: u64| {
                if map.keyframe(keyframe).is_some() {
                    Keep::Whole
                } else if let Some(tracks) = patched.get(&keyframe) {
                    Keep::Tracks(tracks.iter().map(|(t, _)| *t).collect())
                } else {
                    Keep::Nothing
                }
            };
            if self.features_log.compact_if_due(keep)? > 0 {
                self.stats.count("features_log_compactions", 1);
            }
            self.features_log.sync()?;
            self.state.save(&self.checkpoint_path())?;
            // The solver may now drop the journal's records before the next one.
            if let Some(stream) = self.state.stream_id {
                log_compaction::write_mark(
                    &crate::output::state_dir(&self.args.out).join(log_compaction::MERGER_MARK),
                    stream,
                    self.state.next_sequence(),
                )?;
            }
            self.stats
                .add_time("checkpoint", save_start.elapsed().as_secs_f64() * 1e3);
            self.last_persist = Some(std::time::Instant::now());
            let bytes = std::fs::metadata(self.checkpoint_path()).map_or(0, |m| m.len());
            self.persist_spacing = PERSIST_INTERVAL.max(
                std::time::Duration::try_from_secs_f64(bytes as f64 / persist_budget())
                    .unwrap_or(PERSIST_INTERVAL),
            );
            self.stats.count("checkpoints", 1);
        }
        Ok(())
    }

    /// Publishes over zenoh; with `persist`, also rewrites the result files.
    fn emit(
        &mut self,
        changed: &[u64],
        state: pb::ServiceState,
        persist: bool,
    ) -> anyhow::Result<()> {
        self.stats.windows = self.state.windows;
        self.stats
            .counters
            .insert("unsolved_windows".into(), self.state.unsolved_windows);
        self.outputs.emit(
            &self.args.out,
            &self.state,
            self.camera.as_ref(),
            changed,
            state,
            &mut self.stats,
            persist,
        )
    }

    /// Whether the files and the checkpoint are due: at most every
    /// [`PERSIST_INTERVAL`] or as the write budget allows ([`PERSIST_BUDGET_BYTES_PER_S`]),
    /// and always at the end of the stream. Windows in between are safe in the solver's
    /// journal, from which a restarted merger replays them.
    fn persist_due(&self) -> bool {
        self.state.finished
            || self
                .last_persist
                .is_none_or(|t| t.elapsed() >= self.persist_spacing)
    }

    fn add_window(&mut self, w: &pb::WindowSolution) {
        self.state.windows += 1;
        let status = w
            .quality
            .as_ref()
            .map_or(pb::SolveStatus::Unspecified, |q| q.status());
        if status != pb::SolveStatus::Solved || w.poses.is_empty() {
            let reason = w
                .quality
                .as_ref()
                .map(|q| q.reason.clone())
                .unwrap_or_default();
            tracing::warn!(window = w.window_id, ?status, %reason, "window not solved: map breaks here");
            self.state.unsolved_windows += 1;
            self.state.map.break_segment();
            return;
        }
        let input = window_input(w);
        if !input.is_finite() {
            tracing::warn!(
                window = w.window_id,
                "window with non-finite poses or points refused: map breaks here"
            );
            self.state.unsolved_windows += 1;
            self.stats.count("invalid_windows", 1);
            self.state.map.break_segment();
            return;
        }
        // The points this window brings (and re-triangulation adds): the cross-window error
        // compares only the others. Collected from the window, not the whole map (O(map)
        // per window was most of the merger's time on long runs).
        let mut new_tracks: BTreeSet<u64> = input
            .points
            .iter()
            .map(|(t, _)| *t)
            .filter(|t| self.state.map.point(*t).is_none())
            .collect();
        let relocalized_scale = self.relocalized_scale(&input);
        let map = &mut self.state.map;
        let outcome = self.stats.time("align", || {
            map.add_window_with_scale(&input, relocalized_scale)
        });
        // A stretch chained with an unmeasured scale is rescaled once it walks; not while
        // a background refinement holds a copy of its keyframes (the fold would undo it).
        let held = self
            .state
            .map
            .provisional_scale()
            .is_some_and(|p| self.refiner.holds_keyframes_from(p.first_keyframe));
        if !held {
            if let Some(settled) = self.state.map.settle_provisional_scale() {
                tracing::info!(
                    first_keyframe = settled.first_keyframe,
                    scale = settled.scale,
                    keyframes = settled.keyframes,
                    points = settled.points,
                    "provisional scale settled by the walking pace"
                );
                if settled.keyframes > 0 {
                    self.stats.count("rescaled_stretches", 1);
                }
            }
        }
        if let (Some(camera), Some(first)) = (window_camera(w), w.keyframe_ids.first()) {
            let map = &mut self.state.map;
            let options = TriangulationOptions::default();
            let r = self.stats.time("retriangulate", || {
                map.retriangulate(&camera, &options, *first)
            });
            self.stats
                .count("retriangulated_points", r.added.len() as u64);
            tracing::debug!(
                window = w.window_id,
                tried = r.tried,
                added = r.added.len(),
                dropped = r.dropped,
                "weak tracks re-triangulated"
            );
            new_tracks.extend(r.added);
        }
        let segment = match &outcome {
            WindowOutcome::NewSegment { segment } | WindowOutcome::Aligned { segment, .. } => {
                *segment
            }
        };
        // Before the cross-window error may start a background refinement below: an
        // attempt is not made while one runs, and when each window started one (the error
        // staying high), every attempt fell into a run and no loop was ever closed.
        self.try_close_loop(w.window_id, segment);
        match outcome {
            WindowOutcome::NewSegment { segment } => {
                tracing::info!(window = w.window_id, segment, "new map segment")
            }
            WindowOutcome::Aligned {
                residual,
                transform,
                ..
            } => {
                tracing::debug!(
                    window = w.window_id,
                    residual,
                    scale = transform.scale,
                    "window aligned"
                );
                if let Some(camera) = window_camera(w) {
                    let ids: Vec<u64> = input.poses.iter().map(|(id, _)| *id).collect();
                    let error = self.refiner.after_window(
                        &self.state.map,
                        &camera,
                        &ids,
                        &new_tracks,
                        &mut self.stats,
                    );
                    tracing::info!(window = w.window_id, cross_window_px = ?error, "window aligned");
                }
            }
        }
        let sightings = std::mem::take(&mut self.loop_sightings);
        if !sightings.is_empty() {
            let added = self.state.map.add_loop_sightings(segment, &sightings);
            self.stats.count("loop_sightings", added as u64);
        }
        self.try_link(w.window_id, segment);
    }
}

impl Merger {
    /// Adds a keyframe's bag of words to the linking index.
    fn index_keyframe(&mut self, keyframe: u64, features: &[MapFeature]) {
        let descriptors: Vec<_> = features.iter().map(|f| f.descriptor).collect();
        self.database
            .add(keyframe, &self.vocabulary.bag_of_words(&descriptors));
    }
}

/// The ideal pinhole camera of a window's (undistorted) observations.
fn window_camera(w: &pb::WindowSolution) -> Option<PinholeRadtan> {
    // The map's geometry uses the ideal pinhole only (the observations are undistorted);
    // the lens model rides along for the saved map and relocalization's raw pixels.
    crate::convert::camera_from_pb(w.intrinsics.as_ref()?)
}

/// The geometry of a window message, as the map builder takes it.
pub(crate) fn window_input(w: &pb::WindowSolution) -> WindowInput {
    WindowInput {
        poses: w
            .poses
            .iter()
            .filter_map(|kp| kp.pose.as_ref().map(|p| (kp.keyframe_id, pose_from_pb(p))))
            .collect(),
        points: w
            .points
            .iter()
            .map(|p| (p.track_id, vec3_from_pb(&p.position)))
            .collect(),
        observations: w.observations.iter().map(observation).collect(),
        weak_observations: w.weak_observations.iter().map(observation).collect(),
    }
}

/// A wire observation as `(keyframe id, track id, undistorted pixel)`.
fn observation(o: &pb::Observation) -> (u64, u64, Point2<f64>) {
    let px = Point2::new(f64::from(o.x), f64::from(o.y));
    (o.keyframe_id, o.track_id, px)
}

fn open_egress(args: &ServiceArgs) -> anyhow::Result<Option<Egress>> {
    if args.egress.zenoh_listen.iter().any(|e| e == "none") {
        return Ok(None);
    }
    let e = Egress::open(&EgressOptions {
        device: args.egress.device.clone(),
        network: args.egress.network(),
    })?;
    tracing::info!(prefix = e.prefix(), listen = ?args.egress.zenoh_listen, "publishing over zenoh");
    Ok(Some(e))
}

/// Fault injection for the durability tests (docs/durability.md):
/// `EGOSLAM_FAULT=merger-abort-at-window:N` makes a merger that did not resume from a
/// checkpoint abort as soon as it has received message N, before applying it, i.e. with a
/// window in flight. Only the first merger of a run obeys it (a restarted one resumes).
fn injected_fault() -> Option<u64> {
    let spec = std::env::var("EGOSLAM_FAULT").ok()?;
    let n = spec.strip_prefix("merger-abort-at-window:")?.parse().ok();
    if n.is_none() {
        tracing::warn!(%spec, "EGOSLAM_FAULT not understood; ignored");
    }
    n
}

/// This run's id: the launcher's (`EGOSLAM_RUN_ID`, inherited), else the namespace and this
/// merger's start time, so that a restarted unit keeps no stale id of a run long gone.
fn run_id(namespace: &str) -> String {
    std::env::var("EGOSLAM_RUN_ID").unwrap_or_else(|_| {
        let started = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        format!("{namespace}-{started}")
    })
}

pub fn run(args: ServiceArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.out)?;
    let state_dir = crate::output::create_state_dir(&args.out)?;
    let checkpoint_path = state_dir.join(checkpoint::FILE_NAME);
    let resumed = MergerState::load(&checkpoint_path)?;
    let bus = Bus::open(
        "merger",
        BusOptions {
            namespace: args.namespace.clone(),
            ..BusOptions::default()
        },
    )?;
    let outputs = Outputs {
        egress: open_egress(&args)?.map(std::sync::Arc::new),
        revisions: std::sync::Arc::new(std::sync::Mutex::new(Revisions::default())),
        point_confidence: PointConfidenceOptions {
            max_relative_std: args.pipeline.max_point_std,
            ..PointConfidenceOptions::default()
        },
        confidence: None,
        run_id: run_id(&args.namespace),
        all_points: args.pipeline.map_all_points,
    };
    // Subscribe before reading the journal: whatever the journal does not hold yet is sent
    // after this point and therefore reaches this subscriber.
    let mut windows = MessageSubscriber::<pb::WindowSolution>::create(&bus, WINDOWS)?;
    crate::supervision::systemd::ready("merger");
    let vocabulary = crate::map_file::load_vocabulary(args.map.vocabulary.as_deref())?;
    let (features_log, descriptions) = FeaturesLog::open(&state_dir)?;
    let (global_ba_px, refine_keyframes, refinement_lag) = (
        args.pipeline.global_ba_px,
        args.pipeline.refine_keyframes,
        args.pipeline.refinement_lag,
    );
    let mut merger = Merger {
        args,
        state: MergerState::default(),
        outputs,
        stats: ServiceStats::new("merger"),
        refiner: BackgroundRefiner::new(global_ba_px, refine_keyframes, refinement_lag),
        camera: None,
        last_persist: None,
        persist_spacing: PERSIST_INTERVAL,
        vocabulary,
        features_log,
        database: KeyframeDatabase::new(),
        loop_attempt_owed: false,
        loop_sightings: Vec::new(),
        live: None,
    };
    merger.live = Some(live_tracking::LiveTracking::start(
        &merger.args.namespace,
        &merger.args.out,
        resumed.is_none(),
        live_tracking::Publication {
            egress: merger.outputs.egress.clone(),
            revisions: merger.outputs.revisions.clone(),
            // A saved map to extend puts the new stream in a later segment, known once it
            // is loaded; a restarted merger's stream began long ago.
            origin_segment: (resumed.is_none() && merger.args.map.map_in.is_none()).then_some(0),
        },
    ));
    let fault = if resumed.is_none() {
        injected_fault()
    } else {
        None
    };
    if let Some(mut state) = resumed {
        tracing::info!(
            windows = state.windows,
            keyframes = state.map.keyframes().count(),
            next = state.next_sequence(),
            finished = state.finished,
            "resuming from the checkpoint"
        );
        merger.stats.count("restarts", 1);
        // Culled keyframes keep only their patches (and those tracks' features).
        state.patched_tracks = descriptions
            .into_iter()
            .filter(|(keyframe, patched)| {
                state.map.keyframe(*keyframe).is_some() || !patched.is_empty()
            })
            .collect();
        let keyframes: Vec<u64> = state.map.keyframes().map(|(id, ..)| id).collect();
        for keyframe in keyframes {
            if let Some(features) = merger.features_log.features_of(keyframe)? {
                merger.index_keyframe(keyframe, &features);
            }
        }
        let resumed_poses = MapState::of(&state.map, &state.frames);
        *merger
            .outputs
            .revisions
            .lock()
            .map_err(|_| anyhow::anyhow!("revisions poisoned"))? =
            Revisions::resume(&state.revisions, &resumed_poses);
        merger.state = state;
        merger.catch_up(None)?;
    }
    // Windows taken off the bus, not applied yet: while the next one waits for the
    // background refinement (`BackgroundRefiner::holds_next_window`), the merger keeps
    // taking them so that the solver's lossless send never times out.
    let mut backlog: VecDeque<(u64, pb::WindowSolution)> = VecDeque::new();
    while !merger.state.finished {
        if backlog.is_empty() {
            let Some(next) = windows.receive_numbered()? else {
                bail!("terminated by signal")
            };
            backlog.push_back(next);
        }
        while let Some(next) = windows.try_receive_numbered()? {
            backlog.push_back(next);
        }
        let waiting = backlog.front().is_some_and(|(_, w)| !w.end_of_stream)
            && merger.refiner.holds_next_window();
        if waiting {
            if !bus.idle(std::time::Duration::from_millis(20)) {
                bail!("terminated by signal")
            }
            continue;
        }
        let Some((sequence, w)) = backlog.pop_front() else {
            continue;
        };
        if fault == Some(sequence) {
            tracing::error!(sequence, "EGOSLAM_FAULT: aborting with a window in flight");
            std::process::abort();
        }
        let same_stream = merger.state.stream_id == Some(w.stream_id);
        if same_stream && sequence < merger.state.next_sequence() {
            continue; // already applied (recovered from the journal)
        }
        let expected = if same_stream {
            merger.state.next_sequence()
        } else {
            0
        };
        if sequence > expected {
            merger.catch_up(Some((sequence, w.stream_id)))?;
        }
        merger.apply(sequence, &w)?;
    }
    merger.stats.count("dropped_messages", windows.dropped());
    if let Some(live) = merger.live.take() {
        merger.stats.absorb(live.finish()?);
    }
    merger.emit(&[], pb::ServiceState::Finished, true)?;
    if let Some(path) = &merger.args.map.map_out {
        let Some(camera) = &merger.camera else {
            bail!("no window was received: there is no map to save")
        };
        // `egoslam run` hands the services the readout it estimated; a frontend left to
        // estimate it online (`auto` under systemd) saves it in the shared output folder
        // (0 until it has, or if it gave up).
        let readout_ms =
            crate::calibration::readout::known_readout_ms(&merger.args.pipeline, &merger.args.out)
                .unwrap_or(0.0);
        let readout_s = readout_ms / 1000.0;
        let patches = merger
            .features_log
            .patches(merger.state.patched_tracks.keys().copied())?;
        let map = crate::map_file::relocalization_map(
            &merger.state,
            &merger.features_log,
            &patches,
            camera,
            readout_s,
        );
        let source = merger.args.out.display().to_string();
        crate::map_file::write_map(path, &map, &merger.vocabulary, &source)?;
    }
    tracing::info!(
        windows = merger.state.windows,
        segments = merger.state.map.segments(),
        "merger finished"
    );
    Ok(())
}
