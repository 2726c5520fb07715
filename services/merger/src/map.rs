//! The map as data: keyframe poses and points per segment ([`MapBuilder`], checkpointed as
//! [`MapParts`]), the solved window the merger takes in ([`WindowInput`]), and what
//! chaining a window did ([`WindowOutcome`], [`ScaleSource`]). Chaining itself (chaining.rs)
//! and the scale estimates it chooses between build on these types; this module depends
//! on none of them.

use crate::map_points::{Changed, MapPoints};
use egoslam_geometry::{Similarity, StampedPose};
use nalgebra::Vector3;
use std::collections::BTreeMap;

/// One physical point's position in two frames (window or segment, then map).
pub(crate) type PointPair = (Vector3<f64>, Vector3<f64>);

/// One solved window as the merger needs it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WindowInput {
    /// `(keyframe id, pose in the window's frame)`, in keyframe order.
    pub poses: Vec<(u64, StampedPose)>,
    /// `(track id, position in the window's frame)`.
    pub points: Vec<(u64, Vector3<f64>)>,
    /// Inlier observations `(keyframe id, track id, undistorted pixel)`.
    pub observations: Vec<(u64, u64, nalgebra::Point2<f64>)>,
    /// Observations of tracks too weakly seen to triangulate in the window (same layout).
    pub weak_observations: Vec<(u64, u64, nalgebra::Point2<f64>)>,
}

impl WindowInput {
    /// Inlier observations per keyframe id: how well the window's points pin each pose.
    pub fn observation_counts(&self) -> std::collections::HashMap<u64, usize> {
        let mut counts = std::collections::HashMap::new();
        for (kf, _, _) in &self.observations {
            *counts.entry(*kf).or_default() += 1;
        }
        counts
    }

    /// Whether every pose, point and observation is finite: a window that is not (a
    /// corrupted message) must be refused before it poisons the map.
    pub fn is_finite(&self) -> bool {
        let pose_ok = |p: &StampedPose| {
            p.position.iter().all(|v| v.is_finite())
                && p.rotation.coords.iter().all(|v| v.is_finite())
        };
        let px_ok =
            |(_, _, px): &(u64, u64, nalgebra::Point2<f64>)| px.x.is_finite() && px.y.is_finite();
        self.poses.iter().all(|(_, p)| pose_ok(p))
            && self
                .points
                .iter()
                .all(|(_, x)| x.iter().all(|v| v.is_finite()))
            && self.observations.iter().all(px_ok)
            && self.weak_observations.iter().all(px_ok)
    }
}

#[cfg(test)]
impl WindowInput {
    /// A window whose keyframes, all but the first `unseen`, each observe every point (at
    /// a dummy pixel): the fixture of the scale tests.
    pub(crate) fn seeing_all(
        poses: Vec<(u64, StampedPose)>,
        points: Vec<(u64, Vector3<f64>)>,
        unseen: usize,
    ) -> Self {
        let observations = poses
            .iter()
            .skip(unseen)
            .flat_map(|(kf, _)| {
                points
                    .iter()
                    .map(move |(t, _)| (*kf, *t, nalgebra::Point2::new(0.0, 0.0)))
            })
            .collect();
        Self {
            poses,
            points,
            observations,
            weak_observations: Vec::new(),
        }
    }
}

/// What happened to a window.
#[derive(Debug, Clone, PartialEq)]
pub enum WindowOutcome {
    /// It started a new map segment (first window, or after a break).
    NewSegment { segment: u32 },
    /// It was aligned to the current segment; `residual` is the RMS distance of the shared
    /// keyframe centres after alignment, in map units.
    Aligned {
        segment: u32,
        transform: Similarity,
        residual: f64,
        /// What gave the scale.
        scale_source: ScaleSource,
    },
}

/// Everything a [`MapBuilder`] holds, as plain data: what a checkpoint stores so that a
/// restarted merger continues exactly where the killed one stopped.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MapParts {
    /// keyframe id -> (segment, pose in the segment's frame).
    pub keyframes: BTreeMap<u64, (u32, StampedPose)>,
    /// track id -> (segment, position).
    pub points: BTreeMap<u64, (u32, Vector3<f64>)>,
    /// (keyframe id, track id) -> undistorted pixel.
    pub observations: BTreeMap<(u64, u64), nalgebra::Point2<f64>>,
    /// track id -> keyframe id -> undistorted pixel, of tracks not triangulated yet.
    pub weak: BTreeMap<u64, BTreeMap<u64, nalgebra::Point2<f64>>>,
    /// (keyframe id, track id) -> undistorted pixel: a keyframe's sightings of points of
    /// older keyframes (point_reassociation.rs), for the refinement only.
    pub seen_again: BTreeMap<(u64, u64), nalgebra::Point2<f64>>,
    /// Segment new windows are aligned to (`None` after a break).
    pub current_segment: Option<u32>,
    /// Segments created so far.
    pub segments: u32,
    /// A stretch chained with an unmeasured scale, waiting for a pace (provisional_scale.rs).
    pub provisional: Option<ProvisionalScale>,
    /// `(segment, keyframe)`: the newest keyframe a closed loop put onto the older map
    /// (loop_closure.rs); a later loop is spread only over the keyframes after it.
    pub loop_pinned: Option<(u32, u64)>,
    /// `(segment, keyframe)`: the steps of the scale mended after a turn, each after the
    /// keyframe (turn_scale_step.rs), mended again after each refinement.
    pub mended_steps: Vec<(u32, u64)>,
}

/// The growing map: keyframe poses and points per segment.
#[derive(Debug, Default)]
pub struct MapBuilder {
    /// keyframe id -> (segment, pose in the segment's frame).
    pub(crate) keyframes: BTreeMap<u64, (u32, StampedPose)>,
    /// track id -> (segment, position).
    pub(crate) points: MapPoints,
    /// (keyframe id, track id) -> undistorted pixel: every inlier observation of the
    /// windows, kept for the joint refinement of recent keyframes.
    pub(crate) observations: BTreeMap<(u64, u64), nalgebra::Point2<f64>>,
    /// track id -> keyframe id -> undistorted pixel: tracks not triangulated yet
    /// (retriangulation.rs).
    pub(crate) weak: BTreeMap<u64, BTreeMap<u64, nalgebra::Point2<f64>>>,
    /// See [`MapParts::seen_again`]: kept apart from `observations`, which decide which
    /// points are published (point_confidence.rs) with the positions the windows gave
    /// them; only the refinement, which moves the points with them, reads these.
    pub(crate) seen_again: BTreeMap<(u64, u64), nalgebra::Point2<f64>>,
    pub(crate) current_segment: Option<u32>,
    pub(crate) segments: u32,
    /// See [`MapParts::provisional`].
    pub(crate) provisional: Option<ProvisionalScale>,
    /// See [`MapParts::loop_pinned`].
    pub(crate) loop_pinned: Option<(u32, u64)>,
    /// See [`MapParts::mended_steps`].
    pub(crate) mended_steps: Vec<(u32, u64)>,
}

/// What gave a chained window its scale, best evidence first (logged per window).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScaleSource {
    /// At least [`crate::window_alignment::MIN_CHAINING_POINTS`] points shared with the map, through a keyframe
    /// well seen on both sides ([`crate::window_alignment::MIN_JOIN_OBSERVATIONS`]).
    SharedPoints,
    /// Its keyframes relocalized in the map ([`crate::relocalized_scale`]): on at least
    /// [`crate::window_alignment::MIN_CHAINING_POINTS`] point pairs before the pace is tried, on fewer after.
    Relocalized,
    /// The wearer's pace before and after the boundary ([`crate::speed_continuity`]):
    /// when nothing else measures the scale, or when the shared points disagree with it
    /// by more than [`crate::window_alignment::MAX_PACE_DISAGREEMENT`].
    WalkingPace,
    /// Whatever was left: the shared points of a weak join (at least 10), the shared
    /// centres, the scene-depth ratio ([`crate::window_alignment::align_shared_or_by_depth`]), or 1.
    Weak,
}

/// A stretch of a segment whose scale is not measured yet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProvisionalScale {
    pub segment: u32,
    /// The first keyframe chained with the unmeasured scale; every later keyframe of the
    /// segment is chained onto it.
    pub first_keyframe: u64,
    /// The segment's walking pace before it, map units per second.
    pub pace_before: f64,
    /// The segment's median scene depth before it, map units.
    pub depth_before: f64,
    /// Settling tries since (one per window the caller let it try).
    pub windows_since: u32,
}

impl MapBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    /// A window that could not be solved breaks the map: the next solved window starts a
    /// new segment.
    pub fn break_segment(&mut self) {
        self.current_segment = None;
    }

    /// The whole state, for a checkpoint.
    pub fn to_parts(&self) -> MapParts {
        MapParts {
            keyframes: self.keyframes.clone(),
            points: (*self.points).clone(),
            observations: self.observations.clone(),
            weak: self.weak.clone(),
            seen_again: self.seen_again.clone(),
            current_segment: self.current_segment,
            segments: self.segments,
            provisional: self.provisional,
            loop_pinned: self.loop_pinned,
            mended_steps: self.mended_steps.clone(),
        }
    }

    /// A map resumed from a checkpoint's state.
    pub fn from_parts(parts: MapParts) -> Self {
        Self {
            keyframes: parts.keyframes,
            points: parts.points.into(),
            observations: parts.observations,
            weak: parts.weak,
            seen_again: parts.seen_again,
            current_segment: parts.current_segment,
            segments: parts.segments,
            provisional: parts.provisional,
            loop_pinned: parts.loop_pinned,
            mended_steps: parts.mended_steps,
        }
    }

    /// Inlier observations of map points in keyframe `id`.
    pub fn observed_points(&self, id: u64) -> usize {
        self.observations.range((id, 0)..=(id, u64::MAX)).count()
    }

    /// The segment new windows are chained onto (`None` after a break).
    pub fn current_segment(&self) -> Option<u32> {
        self.current_segment
    }

    /// Number of segments so far (breaks = segments - 1).
    pub fn segments(&self) -> u32 {
        self.segments
    }

    /// A keyframe's segment and pose.
    pub fn keyframe(&self, id: u64) -> Option<(u32, &StampedPose)> {
        self.keyframes.get(&id).map(|(s, p)| (*s, p))
    }

    /// A map point's segment and position.
    pub fn point(&self, track: u64) -> Option<(u32, &Vector3<f64>)> {
        self.points.get(&track).map(|(s, x)| (*s, x))
    }

    /// Posed keyframes in id order with their segment.
    pub fn keyframes(&self) -> impl Iterator<Item = (u64, u32, &StampedPose)> {
        self.keyframes.iter().map(|(id, (s, p))| (*id, *s, p))
    }

    /// The points seen by keyframes `from_keyframe` and later of `segment`: what a camera
    /// near those keyframes has in view (the live tracker's map).
    pub fn points_seen_since(
        &self,
        from_keyframe: u64,
        segment: u32,
    ) -> std::collections::HashMap<u64, Vector3<f64>> {
        self.observations
            .range((from_keyframe, 0)..)
            .filter_map(|((_, track), _)| match self.points.get(track) {
                Some((s, x)) if *s == segment => Some((*track, *x)),
                _ => None,
            })
            .collect()
    }

    /// The points inserted, moved or removed since the last call (all of them at first).
    pub fn take_changed_points(&mut self) -> Changed {
        self.points.take_changed()
    }

    /// Map points with their segment.
    pub fn points(&self) -> impl Iterator<Item = (u64, u32, &Vector3<f64>)> {
        self.points.iter().map(|(id, (s, p))| (*id, *s, p))
    }
}
