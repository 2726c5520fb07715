//! The merger as one session: window solutions in, one map out. A `MergerSession` holds the
//! map and everything about it the merger must not lose ([`MergerState`]), the background
//! refinement, the bag-of-words index of the keyframes and the loop-closure state; the
//! service (egoslam's `merger/`) is a loop around it: receive a window, hand it the
//! keyframes' descriptors it logged, [`MergerSession::apply_window`], publish, persist.
//!
//! No I/O: the keyframe descriptors are read through [`KeyframeFeatureSource`], which the
//! service backs with its features log.

pub mod background_refinement;
pub mod frame_poses;
pub mod frame_retirement;
pub mod frame_tables;
pub mod frames;
mod keyframe_culling;
pub mod publication;
mod relocalization;
pub mod state;
pub mod tally;

use crate::point_reassociation::ReassociationOptions;
use crate::{KeyframeFeatureSource, TurnScaleStepOptions, WindowInput, WindowOutcome};
use background_refinement::BackgroundRefiner;
use egoslam_geometry::PinholeRadtan;
use egoslam_messages::internal::v1 as internal;
use egoslam_relocalization::wire::{camera_from_pb, pose_from_pb, vec3_from_pb};
use egoslam_relocalization::{KeyframeDatabase, MapFeature, Vocabulary};
use egoslam_solver::triangulation::TriangulationOptions;
use nalgebra::Point2;
pub use state::MergerState;
use std::collections::BTreeSet;
pub use tally::Tally;

/// The merger's policy, as the pipeline options set it (egoslam's `--global-ba-px`, ...).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SessionOptions {
    /// Start a background bundle adjustment when a window's median cross-window
    /// reprojection error exceeds this many pixels (infinite: never).
    pub global_ba_px: f64,
    /// Keyframes in that bundle adjustment, newest first (0: the whole segment).
    pub refine_keyframes: usize,
    /// Fold it exactly this many windows after it started (0: whenever finished).
    pub refinement_lag: u32,
    /// Close loops inside a segment (docs/merger.md, "Loop closure").
    pub loop_closure: bool,
    /// Keep the points a new keyframe sees again as its sightings for the refinement
    /// (crate::point_reassociation; docs/merger.md, "Points seen again").
    pub reassociate_points: bool,
    /// Cull redundant keyframes (docs/merger.md, "Keyframe culling").
    pub cull_keyframes: bool,
    /// Keyframes the map aims to keep at most (0: no ceiling).
    pub max_map_keyframes: usize,
    /// Seconds of stream time a keyframe's patches (pixels of the wearer's surroundings)
    /// are kept; infinite: as long as the map needs them (docs/durability.md, "Retention").
    pub patch_retention_s: f64,
}

impl Default for SessionOptions {
    /// The pipeline's defaults (docs/config.md gives the reasons).
    fn default() -> Self {
        Self {
            global_ba_px: 1.5,
            refine_keyframes: 1500,
            refinement_lag: 3,
            loop_closure: true,
            reassociate_points: true,
            cull_keyframes: true,
            max_map_keyframes: 3000,
            patch_retention_s: f64::INFINITY,
        }
    }
}

/// How a window's stream relates to the state's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamStart {
    /// The stream the state belongs to.
    Same,
    /// A new stream while the previous one was unfinished: the solver was restarted
    /// mid-stream and the map goes on in a new segment.
    SolverRestarted,
    /// A new map (the first stream, or one after a finished stream): the state was reset,
    /// and what the service keeps beside it (the features log) starts afresh too.
    NewMap,
}

/// The merger's map and what it needs to grow it, window after window.
pub struct MergerSession {
    /// The durable part, checkpointed by the service.
    pub state: MergerState,
    options: SessionOptions,
    refiner: BackgroundRefiner,
    /// Camera of the observations (from the windows), for PnP.
    camera: Option<PinholeRadtan>,
    /// For relocalization inside the map: linking segments after a break, loops.
    vocabulary: Vocabulary,
    /// Bag-of-words index of every keyframe (rebuilt on restart).
    database: KeyframeDatabase,
    /// The sightings of the loop this window closed, added to the map after the window's
    /// cross-window error is measured (`MapBuilder::add_loop_sightings`).
    loop_sightings: Vec<(u64, u64, Point2<f64>)>,
    /// Time per stage and counters since the service last took them.
    pub tally: Tally,
}

impl MergerSession {
    pub fn new(options: SessionOptions, vocabulary: Vocabulary) -> Self {
        Self {
            state: MergerState::default(),
            options,
            refiner: BackgroundRefiner::new(
                options.global_ba_px,
                options.refine_keyframes,
                options.refinement_lag,
            ),
            camera: None,
            vocabulary,
            database: KeyframeDatabase::new(),
            loop_sightings: Vec::new(),
            tally: Tally::default(),
        }
    }

    /// Whether keyframe `keyframe`'s patches are older than the retention allows (the
    /// features log then drops them at its next compaction).
    pub fn patches_expired(&self, keyframe: u64) -> bool {
        let retention = self.options.patch_retention_s;
        retention.is_finite()
            && self
                .state
                .frames
                .keyframe_age_s(keyframe)
                .is_some_and(|age| age > retention)
    }

    /// The ideal camera of the observations, once a window brought it.
    pub fn camera(&self) -> Option<&PinholeRadtan> {
        self.camera.as_ref()
    }

    pub fn vocabulary(&self) -> &Vocabulary {
        &self.vocabulary
    }

    /// Whether the next window would have to wait for the running background refinement.
    pub fn holds_next_window(&self) -> bool {
        self.refiner.holds_next_window()
    }

    /// Makes `stream_id` the current solver stream (see [`StreamStart`]).
    pub fn begin_stream(&mut self, stream_id: u64) -> StreamStart {
        if self.state.stream_id == Some(stream_id) {
            return StreamStart::Same;
        }
        if self.state.stream_id.is_some() && !self.state.finished {
            tracing::warn!(
                stream = stream_id,
                "a new solver stream: the map continues in a new segment"
            );
            self.state.stream_id = Some(stream_id);
            self.state.last_sequence = None;
            self.state.map.break_segment();
            self.tally.count("solver_restarts", 1);
            StreamStart::SolverRestarted
        } else {
            self.state = MergerState::for_stream(stream_id);
            StreamStart::NewMap
        }
    }

    /// Adds a keyframe's descriptors to the index (once) and records the tracks it holds
    /// patches of (`patched`: track and grey level).
    pub fn add_keyframe(
        &mut self,
        keyframe: u64,
        features: &[MapFeature],
        patched: Vec<(u64, u8)>,
    ) {
        if !self.database.contains(keyframe) {
            self.index_keyframe(keyframe, features);
        }
        self.state.patched_tracks.insert(keyframe, patched);
    }

    /// Adds a keyframe's bag of words to the index.
    pub fn index_keyframe(&mut self, keyframe: u64, features: &[MapFeature]) {
        let descriptors: Vec<_> = features.iter().map(|f| f.descriptor).collect();
        self.database
            .add(keyframe, &self.vocabulary.bag_of_words(&descriptors));
    }

    /// Applies window message `sequence` of the current stream (after
    /// [`Self::begin_stream`] and its keyframes' [`Self::add_keyframe`]): folds a due
    /// refinement, culls, chains the window onto the map (or ends the stream), closes
    /// loops, links segments, and poses the frames it completes. `features` reads the
    /// descriptors of every keyframe added so far.
    pub fn apply_window(
        &mut self,
        sequence: u64,
        w: &internal::WindowSolution,
        features: &dyn KeyframeFeatureSource,
    ) {
        for k in &w.keyframes {
            self.state.frames.add_stamp(k);
        }
        for f in &w.trailing_frames {
            self.state.frames.frames.insert(f.frame_id, f.timestamp_s);
        }
        // A refinement started earlier is folded in before this window when due (see
        // `BackgroundRefiner::fold`; at the end of the stream a running one is waited for).
        let folded = self
            .refiner
            .fold(&mut self.state.map, w.end_of_stream, &mut self.tally);
        if folded {
            for step in self
                .state
                .map
                .mend_turn_scale_steps_again(&TurnScaleStepOptions::default())
            {
                tracing::info!(
                    after_keyframe = step.after_keyframe,
                    pace_ratio = step.pace_ratio,
                    keyframes = step.keyframes,
                    "a mended step of the scale mended again after the refinement"
                );
                self.tally.count("mended_turn_steps_again", 1);
            }
        }
        // Culling waits while a refinement runs, and a window may start the next one: here,
        // right after a fold, it gets its turn. Keyframes older than this window's first
        // are in no later window.
        if let (false, Some(first)) = (w.end_of_stream, w.keyframe_ids.first()) {
            self.cull_keyframes(*first);
        }
        if w.end_of_stream {
            self.state.finished = true;
        } else {
            self.add_window(w, features);
        }
        if let Some(camera) = window_camera(w) {
            self.camera = Some(camera);
        }
        if let Some(camera) = &self.camera {
            let (frames, map) = (&mut self.state.frames, &self.state.map);
            let tally = &mut self.tally;
            let start = std::time::Instant::now();
            let oldest = w.keyframe_ids.first().copied().unwrap_or(0);
            frames::localize_pending(frames, map, camera, oldest, tally);
            tally.add_time("localize_frames", start.elapsed().as_secs_f64() * 1e3);
        }
        self.state.last_sequence = Some(sequence);
    }

    fn add_window(&mut self, w: &internal::WindowSolution, features: &dyn KeyframeFeatureSource) {
        self.state.windows += 1;
        let status = w
            .quality
            .as_ref()
            .map_or(internal::SolveStatus::Unspecified, |q| q.status());
        if status != internal::SolveStatus::Solved || w.poses.is_empty() {
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
            self.tally.count("invalid_windows", 1);
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
        let fresh_keyframes: Vec<u64> = input
            .poses
            .iter()
            .map(|(id, _)| *id)
            .filter(|id| !self.state.map.keyframes.contains_key(id))
            .collect();
        let relocalized_scale = self.relocalized_scale(&input, features);
        let map = &mut self.state.map;
        let outcome = self.tally.time("align", || {
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
                    self.tally.count("rescaled_stretches", 1);
                }
            }
        }
        let refiner = &self.refiner;
        let mended = self.tally.time("mend_turn_scale_step", || {
            self.state
                .map
                .mend_turn_scale_step(&TurnScaleStepOptions::default(), |k| {
                    !refiner.holds_keyframes_from(k)
                })
        });
        if let Some(step) = mended {
            tracing::info!(
                after_keyframe = step.after_keyframe,
                pace_ratio = step.pace_ratio,
                keyframes = step.keyframes,
                points = step.points,
                "a step of the scale in a turn mended by the walking pace"
            );
            self.tally.count("mended_turn_steps", 1);
        }
        if let (Some(camera), Some(first)) = (window_camera(w), w.keyframe_ids.first()) {
            let map = &mut self.state.map;
            let options = TriangulationOptions::default();
            let r = self.tally.time("retriangulate", || {
                map.retriangulate(&camera, &options, *first)
            });
            self.tally
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
        // Before the cross-window error may start a background refinement below, which
        // would then hold the keyframes as they were before the loop.
        self.try_close_loop(w.window_id, segment, features);
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
                        &mut self.tally,
                    );
                    tracing::info!(window = w.window_id, cross_window_px = ?error, "window aligned");
                }
            }
        }
        // After the cross-window error is measured: counted there, the drift these
        // sightings measure started refinements while a turn in place was being
        // chained, and the rendered 1500-frame walk ended 2.8x worse.
        if let (true, Some(camera)) = (self.options.reassociate_points, window_camera(w)) {
            let map = &mut self.state.map;
            let options = ReassociationOptions::default();
            let r = self.tally.time("reassociate_points", || {
                map.reassociate_points(&camera, features, &fresh_keyframes, &options)
            });
            self.tally.count("points_seen_again", r.sightings as u64);
            tracing::debug!(
                window = w.window_id,
                keyframes = r.keyframes,
                sightings = r.sightings,
                median_px = crate::median(r.residuals_px),
                "points seen again"
            );
        }
        let sightings = std::mem::take(&mut self.loop_sightings);
        if !sightings.is_empty() {
            let added = self.state.map.add_loop_sightings(segment, &sightings);
            self.tally.count("loop_sightings", added as u64);
        }
        self.try_link(w.window_id, segment, features);
    }
}

/// The ideal pinhole camera of a window's (undistorted) observations.
pub fn window_camera(w: &internal::WindowSolution) -> Option<PinholeRadtan> {
    // The map's geometry uses the ideal pinhole only (the observations are undistorted);
    // the lens model rides along for the saved map and relocalization's raw pixels.
    camera_from_pb(w.intrinsics.as_ref()?)
}

/// The geometry of a window message, as the map builder takes it.
pub fn window_input(w: &internal::WindowSolution) -> WindowInput {
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
fn observation(o: &internal::Observation) -> (u64, u64, Point2<f64>) {
    let px = Point2::new(f64::from(o.x), f64::from(o.y));
    (o.keyframe_id, o.track_id, px)
}
