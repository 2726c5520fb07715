//! The live pose of every frame as it arrives, before its window is solved (ORB-SLAM's
//! tracking thread in spirit: PnP on the map points in view from a constant-velocity prior).
//!
//! The merged map lags the frames by a window (0.5-1.5 s of head motion), so many tracks of
//! a new frame have no map point yet. The tracker therefore also triangulates such tracks
//! itself, from their first tracked sighting and a later one with enough parallax, using
//! its own tracked poses; these local points serve until the map brings its own (refined)
//! point for the track, which then wins. The points are only ever those of the live tracks:
//! the state is bounded by what is in view.

use crate::frame_localization::localize_frame;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, UnitQuaternion, Vector3};
use rustc_hash::FxHashMap;
use std::collections::VecDeque;

mod first_gauge;
mod local_adjustment;
mod options;
mod own_points;
mod pace_limit;
pub mod recording;
mod rotation_from_rays;
mod walked_on;

use rotation_from_rays::rotation_between;

pub use local_adjustment::LocalAdjustmentOptions;
pub use options::LiveTrackerOptions;
use own_points::Sighting;

/// Local adjustments at most while the frames since a new map's keyframe are re-tracked
/// (1-2.5 s of frames in a real-time run, while the stream's next frame waits): with one
/// on every second frame, a development build's live poses of the rendered 300-frame walk
/// came 110-120 ms late at the 95th percentile, up to 0.7 s.
const RETRACK_ADJUSTMENTS: usize = 6;

/// Timestamps closer than this are the same frame, seconds.
const SAME_FRAME_S: f64 = 1e-6;

/// How a live pose was obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackingState {
    /// PnP on the map (and the tracker's own points).
    Tracking,
    /// No map point in view: the orientation from the tracks' rays (a turn in place), the
    /// position held.
    Rotation,
    /// No PnP: moved on from the last tracked pose by a motion prior (at constant
    /// velocity, or, with no point in view while walking, along the direction the tracks'
    /// rays give at the map's walking pace; walked_on.rs).
    Predicted,
    /// No PnP for longer than a prediction is worth: the last tracked pose.
    Lost,
}

/// One frame's live pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LivePose {
    pub pose: StampedPose,
    /// The map segment the pose is in.
    pub segment: u32,
    pub state: TrackingState,
    /// PnP inliers (tracking) or tracks agreeing with the rotation (rotation); else 0.
    pub inliers: usize,
}

/// What the merger hands the tracker after each window: the points of its newest keyframes
/// in the current segment, and the newest keyframe's pose (the prior when nothing was
/// tracked yet).
#[derive(Debug, Clone, Default)]
pub struct MapView {
    pub camera: Option<PinholeRadtan>,
    pub segment: u32,
    pub points: FxHashMap<u64, Vector3<f64>>,
    pub newest_keyframe: Option<StampedPose>,
    /// The segment's recent walking pace, map units per second (`MapBuilder::recent_walking_pace`).
    pub pace: Option<f64>,
}

/// A frame's tracks: `(track id, undistorted pixel)`.
pub type FrameTracks = Vec<(u64, Point2<f64>)>;

/// The live tracker's state: the map view, its own points, the last two tracked poses.
#[derive(Debug, Default)]
pub struct LiveTracker {
    options: LiveTrackerOptions,
    map: MapView,
    local_points: FxHashMap<u64, Vector3<f64>>,
    sightings: FxHashMap<u64, Sighting>,
    /// The last tracked pose and the one before it (for the velocity).
    last: Option<StampedPose>,
    before_last: Option<StampedPose>,
    /// The last `history_s` of frames: timestamp and tracks.
    history: VecDeque<(f64, FrameTracks)>,
    /// The last frame posed from its tracks (PnP or rotation): its pose and its tracks'
    /// rays in the camera frame.
    previous: Option<(StampedPose, FxHashMap<u64, Vector3<f64>>)>,
    /// The frames posed from their tracks over the last `walk_anchor_s`, oldest first.
    recent: VecDeque<(StampedPose, FxHashMap<u64, Vector3<f64>>)>,
    /// The frames tracked by PnP over the last `local_window_s`, oldest first.
    tracked: VecDeque<local_adjustment::TrackedFrame>,
    /// The timestamp of the last frame that asked for a local adjustment.
    last_adjusted: Option<f64>,
    /// A new stream's frames before its first window, held to the segment's gauge.
    first_gauge: Option<first_gauge::FirstGauge>,
}

impl LiveTracker {
    pub fn new(options: LiveTrackerOptions) -> Self {
        Self {
            options,
            ..Self::default()
        }
    }

    /// Takes the merger's newest view of the map and re-tracks the frames since its newest
    /// keyframe on it. Tracks live a fraction of a second in head motion, so by the time a
    /// window is merged most tracks of the current frame are younger than its points: the
    /// frames in between carry the pose from the map's keyframe to now, and triangulate the
    /// young tracks on the way. Everything the tracker built on the previous map goes (it
    /// drifted with the tracker; the new map is refined).
    pub fn set_map(&mut self, map: MapView) {
        // A window is merged: the map holds the gauge from now on.
        self.first_gauge = None;
        if self.cannot_retrack_from(&map) {
            // The map's newest keyframe is older than the frames kept (a solver far behind
            // the frontend, as in a lossless replay of a fast stream): starting again from
            // it would pose the current frame from a keyframe seconds away. The tracker
            // goes on from its own last poses, its points replaced by the map's where the
            // map has them.
            self.map = map;
            return;
        }
        self.local_points.clear();
        self.sightings.clear();
        self.last = None;
        self.before_last = None;
        self.previous = None;
        self.recent.clear();
        self.tracked.clear();
        self.map = map;
        let Some(keyframe) = self.map.newest_keyframe else {
            return;
        };
        // The keyframe's own frame must be in the history: the re-tracking starts there.
        if !self.history_reaches_back_to(keyframe.timestamp) {
            return;
        }
        self.last = Some(keyframe);
        self.previous = self
            .history
            .iter()
            .find(|(t, _)| (t - keyframe.timestamp).abs() <= SAME_FRAME_S)
            .and_then(|(_, tracks)| Some((keyframe, rays(&self.map.camera?, tracks))));
        self.recent.extend(self.previous.clone());
        let history = std::mem::take(&mut self.history);
        let since: Vec<&(f64, FrameTracks)> = history
            .iter()
            .filter(|(t, _)| *t > keyframe.timestamp + SAME_FRAME_S)
            .collect();
        // The frames since the keyframe are re-tracked while the stream waits: the local
        // adjustment runs on `RETRACK_ADJUSTMENTS` of them, evenly spread, the last included.
        let stride = since.len().div_ceil(RETRACK_ADJUSTMENTS).max(1);
        for (i, (timestamp, tracks)) in since.iter().enumerate() {
            let adjust = (since.len() - 1 - i).is_multiple_of(stride);
            self.locate(*timestamp, tracks, adjust);
        }
        self.history = history;
    }

    /// Whether `map` continues the current segment but its newest keyframe's frame has left
    /// the history, while the tracker has a pose of its own to go on from.
    fn cannot_retrack_from(&self, map: &MapView) -> bool {
        let continues = self.map.camera.is_some() && map.segment == self.map.segment;
        let keyframe_gone = map.newest_keyframe.is_some_and(|k| {
            !self.history.is_empty() && !self.history_reaches_back_to(k.timestamp)
        });
        continues && keyframe_gone && self.last.is_some()
    }

    /// Whether the frames kept go back to `timestamp` (its frame or an older one is held).
    fn history_reaches_back_to(&self, timestamp: f64) -> bool {
        self.history
            .front()
            .is_some_and(|(t, _)| *t <= timestamp + SAME_FRAME_S)
    }

    /// The first frame of a new map's stream, before any window: the map's frame is its
    /// first keyframe's camera (this frame, identity at the origin) and its scale one unit
    /// per second of walking (`speed_continuity::NEW_SEGMENT_PACE`), so the frames until
    /// the first window can be posed by rotation from it and walked on at that pace.
    pub fn begin_at_origin(
        &mut self,
        camera: PinholeRadtan,
        segment: u32,
        timestamp: f64,
        tracks: &[(u64, Point2<f64>)],
    ) -> LivePose {
        let origin = StampedPose {
            timestamp,
            position: Vector3::zeros(),
            rotation: UnitQuaternion::identity(),
        };
        *self = Self {
            options: self.options,
            map: MapView {
                camera: Some(camera),
                segment,
                // The new segment's gauge, which its first window will be put in.
                pace: Some(crate::speed_continuity::NEW_SEGMENT_PACE),
                ..MapView::default()
            },
            previous: Some((origin, rays(&camera, tracks))),
            last: Some(origin),
            first_gauge: Some(first_gauge::FirstGauge::default()),
            ..Self::default()
        };
        // The origin anchors the first walk, as a map's newest keyframe does (set_map).
        self.recent.extend(self.previous.clone());
        self.history.push_back((timestamp, tracks.to_vec()));
        LivePose {
            pose: origin,
            segment,
            state: TrackingState::Rotation,
            inliers: tracks.len(),
        }
    }

    /// Whether a map (or the origin of a stream) has been given.
    pub fn has_map(&self) -> bool {
        self.map.camera.is_some()
    }

    /// Map points and the tracker's own points held now.
    pub fn points(&self) -> (usize, usize) {
        (self.map.points.len(), self.local_points.len())
    }

    /// The live pose of a frame from its tracks `(track id, undistorted pixel)`; `None`
    /// until the merger has a map.
    pub fn track(&mut self, timestamp: f64, tracks: &[(u64, Point2<f64>)]) -> Option<LivePose> {
        while self
            .history
            .front()
            .is_some_and(|(t, _)| *t < timestamp - self.options.history_s)
        {
            self.history.pop_front();
        }
        self.history.push_back((timestamp, tracks.to_vec()));
        let interval = self.options.local_adjustment_interval_s;
        let adjust = self
            .last_adjusted
            .is_none_or(|t| timestamp - t >= interval - SAME_FRAME_S);
        if adjust {
            self.last_adjusted = Some(timestamp);
        }
        self.locate(timestamp, tracks, adjust)
    }

    /// [`Self::track`] without the history; the local adjustment only if `adjust`.
    fn locate(
        &mut self,
        timestamp: f64,
        tracks: &[(u64, Point2<f64>)],
        adjust: bool,
    ) -> Option<LivePose> {
        let camera = self.map.camera?;
        let prior = self.prior(timestamp)?;
        let correspondences: Vec<(Vector3<f64>, Point2<f64>)> = tracks
            .iter()
            .filter_map(|(t, px)| {
                self.map
                    .points
                    .get(t)
                    .or_else(|| self.local_points.get(t))
                    .map(|x| (*x, *px))
            })
            .collect();
        let mut localization = self.options.localization;
        if let Some(last) = &self.last {
            let gap_s = (timestamp - last.timestamp - 0.05).max(0.0);
            localization.max_rotation_from_prior_deg += self.options.max_turn_rate_deg_s * gap_s;
        }
        let located = localize_frame(&camera, &correspondences, &prior, &localization)
            .map_err(|e| e.to_string())
            .and_then(|l| self.within_pace(&l.pose).map(|()| l));
        let rays_now = rays(&camera, tracks);
        let live = match located {
            Ok(l) => {
                let mut pose = self.adjusted(
                    adjust,
                    &camera,
                    StampedPose {
                        timestamp,
                        ..l.pose
                    },
                    tracks,
                );
                self.before_last = self.last.replace(pose);
                self.triangulate(&camera, &pose, tracks);
                self.remember(pose, rays_now);
                self.hold_first_gauge(&mut pose, &correspondences);
                LivePose {
                    pose,
                    segment: self.map.segment,
                    state: TrackingState::Tracking,
                    inliers: l.inliers,
                }
            }
            Err(e) => {
                // Where the rays fit no rotation alone (walking on with parallax, as a car
                // or a wearer looking ahead does), the frame may still be moved on from an
                // earlier one: the walk needs only the frame's time.
                let turned = self.turned(&camera, timestamp, &rays_now);
                let now = turned.map_or(prior, |(pose, _)| pose);
                match (
                    self.walked(&camera, &now, &rays_now, turned.is_some()),
                    turned,
                ) {
                    (Some(walked), _) => {
                        // Moving on at the pace: the velocity from the frame it was measured from.
                        self.local_points.extend(walked.points);
                        self.before_last = Some(walked.anchor);
                        self.last = Some(walked.pose);
                        self.remember(walked.pose, rays_now);
                        LivePose {
                            pose: walked.pose,
                            segment: self.map.segment,
                            state: TrackingState::Predicted,
                            inliers: walked.inliers,
                        }
                    }
                    (None, Some((pose, inliers))) => {
                        // The velocity restarts here: a turn in place has none to extrapolate.
                        self.before_last = None;
                        self.last = Some(pose);
                        self.remember(pose, rays_now);
                        LivePose {
                            pose,
                            segment: self.map.segment,
                            state: TrackingState::Rotation,
                            inliers,
                        }
                    }
                    (None, None) => {
                        let shared = self.previous.as_ref().map_or(0, |(_, before)| {
                            rays_now.keys().filter(|t| before.contains_key(t)).count()
                        });
                        tracing::debug!(
                            error = %e,
                            correspondences = correspondences.len(),
                            local_points = self.local_points.len(),
                            tracks = tracks.len(),
                            shared_with_previous = shared,
                            "live frame not tracked"
                        );
                        let live = self.unsupported(timestamp, prior);
                        if shared < self.options.rotation_min_inliers {
                            self.reanchor(live.pose, rays_now);
                        }
                        live
                    }
                }
            }
        };
        while self
            .recent
            .front()
            .is_some_and(|(p, _)| p.timestamp < timestamp - self.options.walk_anchor_s)
        {
            self.recent.pop_front();
        }
        // Tracks end for good (ids are never reused): forget those not in this frame.
        let alive: std::collections::HashSet<u64> = tracks.iter().map(|(t, _)| *t).collect();
        self.local_points.retain(|t, _| alive.contains(t));
        self.sightings.retain(|t, _| alive.contains(t));
        tracing::trace!(timestamp, state = ?live.state, inliers = live.inliers, position = ?live.pose.position.as_slice(), "live pose");
        Some(live)
    }

    /// The frame posed from its tracks last: the rotation's reference for the next frame,
    /// and a walk's anchor for the next `walk_anchor_s`.
    fn remember(&mut self, pose: StampedPose, rays: FxHashMap<u64, Vector3<f64>>) {
        self.recent.push_back((pose, rays.clone()));
        self.previous = Some((pose, rays));
    }

    /// After frames lost to the stream (dropped by a loaded frontend, a camera stall) or a
    /// frontend that started its tracks afresh, the last posed frame shares too few tracks
    /// with this one to ever turn a later frame from, and ids never come back: this frame's
    /// predicted (or held) pose becomes the reference the next frames are turned and walked
    /// from, so that a gap costs the turn made during it rather than every pose until the
    /// next map. The motion prior stays with the last tracked pose: PnP's allowance for
    /// the turn since grows with the time from it.
    fn reanchor(&mut self, pose: StampedPose, rays: FxHashMap<u64, Vector3<f64>>) {
        self.recent.clear();
        self.remember(pose, rays);
    }

    /// A frame neither PnP nor a rotation places: the prior while the last tracked pose is
    /// recent (PREDICTED), else that pose (LOST).
    fn unsupported(&self, timestamp: f64, prior: StampedPose) -> LivePose {
        let (pose, state) = match self.last {
            Some(last) if timestamp - last.timestamp > self.options.max_prediction_s => {
                (StampedPose { timestamp, ..last }, TrackingState::Lost)
            }
            _ => (prior, TrackingState::Predicted),
        };
        LivePose {
            pose,
            segment: self.map.segment,
            state,
            inliers: 0,
        }
    }

    /// The pose from the rays of the tracks shared with the previous posed frame, if a
    /// rotation alone explains them (see [`LiveTrackerOptions::rotation_threshold_px`]).
    fn turned(
        &self,
        camera: &PinholeRadtan,
        timestamp: f64,
        rays_now: &FxHashMap<u64, Vector3<f64>>,
    ) -> Option<(StampedPose, usize)> {
        let (previous, previous_rays) = self.previous.as_ref()?;
        let threshold = self.options.rotation_threshold_px / camera.fx;
        let (rotation, inliers) = rotation_between(previous_rays, rays_now, threshold)?;
        let shared = rays_now
            .keys()
            .filter(|t| previous_rays.contains_key(t))
            .count();
        let supported = inliers >= self.options.rotation_min_inliers
            && inliers as f64 >= self.options.rotation_min_inlier_share * shared as f64;
        supported.then(|| {
            let pose = StampedPose {
                timestamp,
                position: previous.position,
                rotation: previous.rotation * rotation,
            };
            (pose, inliers)
        })
    }

    /// [`walked_on::walked_on`] from the newest recent posed frame whose shared tracks'
    /// rays differ by the walk's parallax (the oldest such frame would take a stop before
    /// the walk for walking), when the map has a pace. Of `now` (the frame's turned pose,
    /// or its prior) only the time is used; `turned`: a rotation alone fits its rays.
    fn walked(
        &self,
        camera: &PinholeRadtan,
        now: &StampedPose,
        rays_now: &FxHashMap<u64, Vector3<f64>>,
        turned: bool,
    ) -> Option<walked_on::Walked> {
        let pace = self.map.pace?;
        let o = &self.options;
        let check = walked_on::WalkCheck {
            min_inliers: o.rotation_min_inliers,
            min_inlier_share: o.rotation_min_inlier_share,
            max_triangulation_error_px: o.max_triangulation_error_px,
            min_track_share: o.walk_min_track_share,
        };
        let min_parallax = o.min_walk_parallax_px / camera.fx;
        let (anchor, anchor_rays) = self.recent.iter().rev().find(|(_, rays)| {
            walked_on::rotation_residual(rays, rays_now, o.rotation_min_inliers)
                .is_some_and(|p| p >= min_parallax)
        })?;
        walked_on::walked_on(
            camera,
            (anchor, anchor_rays),
            (now, rays_now),
            pace,
            &check,
            turned,
        )
    }

    /// Constant velocity from the last two tracked poses; the last tracked pose when there
    /// is one; else the map's newest keyframe.
    fn prior(&self, timestamp: f64) -> Option<StampedPose> {
        match (self.before_last, self.last) {
            (Some(a), Some(b)) if b.timestamp > a.timestamp => Some(extrapolate(&a, &b, timestamp)),
            (_, Some(b)) => Some(StampedPose { timestamp, ..b }),
            _ => self
                .map
                .newest_keyframe
                .map(|k| StampedPose { timestamp, ..k }),
        }
    }
}

/// Unit rays in the camera frame of tracks `(id, undistorted pixel)`.
fn rays(camera: &PinholeRadtan, tracks: &[(u64, Point2<f64>)]) -> FxHashMap<u64, Vector3<f64>> {
    tracks
        .iter()
        .map(|(t, px)| (*t, camera.bearing_from_undistorted(*px)))
        .collect()
}

/// Pose `b` moved on to `timestamp` at the velocity from `a` to `b` (at most three of
/// their intervals ahead: a prediction further out is no better than standing still).
fn extrapolate(a: &StampedPose, b: &StampedPose, timestamp: f64) -> StampedPose {
    let ratio = ((timestamp - b.timestamp) / (b.timestamp - a.timestamp)).clamp(0.0, 3.0);
    let turn = (b.rotation * a.rotation.inverse()).scaled_axis() * ratio;
    StampedPose {
        timestamp,
        position: b.position + (b.position - a.position) * ratio,
        rotation: UnitQuaternion::from_scaled_axis(turn) * b.rotation,
    }
}

#[cfg(test)]
mod tests;
