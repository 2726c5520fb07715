//! Chaining windows into map segments.

pub use crate::window_alignment::align_shared;
pub(crate) use crate::window_alignment::transform_pose;
pub use crate::window_alignment::ScaleSource;
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
    /// Segment new windows are aligned to (`None` after a break).
    pub current_segment: Option<u32>,
    /// Segments created so far.
    pub segments: u32,
    /// A stretch chained with an unmeasured scale, waiting for a pace (provisional_scale.rs).
    pub provisional: Option<crate::provisional_scale::ProvisionalScale>,
    /// `(segment, keyframe)`: the newest keyframe a closed loop put onto the older map
    /// (loop_closure.rs); a later loop is spread only over the keyframes after it.
    pub loop_pinned: Option<(u32, u64)>,
}

/// The growing map: keyframe poses and points per segment.
#[derive(Debug, Default)]
pub struct MapBuilder {
    /// keyframe id -> (segment, pose in the segment's frame).
    pub(crate) keyframes: BTreeMap<u64, (u32, StampedPose)>,
    /// track id -> (segment, position).
    pub(crate) points: BTreeMap<u64, (u32, Vector3<f64>)>,
    /// (keyframe id, track id) -> undistorted pixel: every inlier observation of the
    /// windows, kept for the joint refinement of recent keyframes.
    pub(crate) observations: BTreeMap<(u64, u64), nalgebra::Point2<f64>>,
    /// track id -> keyframe id -> undistorted pixel: tracks not triangulated yet
    /// (retriangulation.rs).
    pub(crate) weak: BTreeMap<u64, BTreeMap<u64, nalgebra::Point2<f64>>>,
    pub(crate) current_segment: Option<u32>,
    segments: u32,
    /// See [`MapParts::provisional`].
    pub(crate) provisional: Option<crate::provisional_scale::ProvisionalScale>,
    /// See [`MapParts::loop_pinned`].
    pub(crate) loop_pinned: Option<(u32, u64)>,
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

    /// Adds a solved window: aligned on the keyframes it shares with the current segment,
    /// or a new segment when it shares fewer than two.
    pub fn add_window(&mut self, window: &WindowInput) -> WindowOutcome {
        self.add_window_with_scale(window, None)
    }

    /// Whether `window` would be chained onto the current segment without shared points
    /// that can give its scale ([`Self::weakly_joined`]): then a scale measured otherwise
    /// ([`crate::relocalized_scale`]) is worth the cost.
    pub fn lacks_shared_points(&self, window: &WindowInput) -> bool {
        let Some(segment) = self.current_segment else {
            return false;
        };
        let (keyframes, points) = self.shared_with(window, segment);
        keyframes.len() >= 2 && self.weakly_joined(segment, window, points.len())
    }

    /// What `window` shares with `segment`: `(window pose, map pose)` of each keyframe and
    /// `(window position, map position)` of each point.
    fn shared_with(
        &self,
        window: &WindowInput,
        segment: u32,
    ) -> (Vec<(StampedPose, StampedPose)>, Vec<PointPair>) {
        let keyframes = window
            .poses
            .iter()
            .filter_map(|(id, p)| match self.keyframes.get(id) {
                Some((s, m)) if *s == segment => Some((*p, *m)),
                _ => None,
            })
            .collect();
        let points = self
            .shared_points(window, segment)
            .map(|(_, pair)| pair)
            .collect();
        (keyframes, points)
    }

    /// The points `window` shares with `segment`: track id, `(window position, map
    /// position)`.
    pub(crate) fn shared_points<'a>(
        &'a self,
        window: &'a WindowInput,
        segment: u32,
    ) -> impl Iterator<Item = (u64, PointPair)> + 'a {
        window
            .points
            .iter()
            .filter_map(move |(track, x)| match self.points.get(track) {
                Some((s, xm)) if *s == segment => Some((*track, (*x, *xm))),
                _ => None,
            })
    }

    /// [`Self::add_window`]; when too few points are shared, `relocalized_scale` (if any)
    /// gives the scale before the walking pace and the scene-depth ratio are tried
    /// ([`Self::chaining_transform`]).
    pub fn add_window_with_scale(
        &mut self,
        window: &WindowInput,
        relocalized_scale: Option<crate::RelocalizedScale>,
    ) -> WindowOutcome {
        let first_new = window
            .poses
            .iter()
            .position(|(id, _)| {
                !matches!(self.keyframes.get(id), Some((s, _)) if Some(*s) == self.current_segment)
            })
            .unwrap_or(window.poses.len());
        let options = crate::interior_cut::InteriorCutOptions::default();
        let rescaled = crate::interior_cut::rescale_after_weak_cut(window, first_new, &options);
        let window = match &rescaled {
            Some((rescaled, cut, scale)) => {
                tracing::info!(
                    after_keyframe = window.poses[cut.after].0,
                    transfer_points = cut.transfer_points,
                    scale,
                    "cut inside the window (weak, or the pace jumps across it): the keyframes after it take the pace before"
                );
                rescaled
            }
            None => window,
        };
        let shared = self
            .current_segment
            .map(|seg| (seg, self.shared_with(window, seg)));
        let (segment, transform, outcome) = match shared {
            Some((seg, (shared, shared_points))) if shared.len() >= 2 => {
                let (w, m): (Vec<_>, Vec<_>) = shared.into_iter().unzip();
                let (transform, residual, scale_source) = self.chaining_transform(
                    seg,
                    window,
                    (&w, &m),
                    &shared_points,
                    relocalized_scale,
                );
                tracing::debug!(
                    first_keyframe = window.poses.first().map(|(id, _)| *id),
                    shared_points = shared_points.len(),
                    ?scale_source,
                    scale = transform.scale,
                    "window scale"
                );
                if let Some((id, _)) = window.poses.get(first_new) {
                    self.note_chaining_scale(seg, *id, scale_source);
                }
                (
                    seg,
                    transform,
                    WindowOutcome::Aligned {
                        segment: seg,
                        transform,
                        residual,
                        scale_source,
                    },
                )
            }
            _ => {
                let seg = self.segments;
                self.segments += 1;
                self.current_segment = Some(seg);
                (
                    seg,
                    crate::speed_continuity::new_segment_gauge(window),
                    WindowOutcome::NewSegment { segment: seg },
                )
            }
        };
        for (id, p) in &window.poses {
            // Keyframes already in this segment keep their pose (the older window anchored
            // them); new ones are added in the segment's frame.
            let keep = matches!(self.keyframes.get(id), Some((s, _)) if *s == segment);
            if !keep {
                self.keyframes
                    .insert(*id, (segment, transform_pose(&transform, p)));
            }
        }
        for (track, x) in &window.points {
            // Points already in the map keep their (refined) position; new ones come in.
            let known = matches!(self.points.get(track), Some((s, _)) if *s == segment);
            if !known {
                self.points.insert(*track, (segment, transform.apply(x)));
            }
        }
        for (kf, track, px) in &window.observations {
            self.observations.insert((*kf, *track), *px);
            // Triangulated now: what was kept of it as weak joins its observations.
            if let Some(views) = self.weak.remove(track) {
                for (k, p) in views {
                    self.observations.entry((k, *track)).or_insert(p);
                }
            }
        }
        self.add_weak_observations(&window.weak_observations);
        outcome
    }

    /// The whole state, for a checkpoint.
    pub fn to_parts(&self) -> MapParts {
        MapParts {
            keyframes: self.keyframes.clone(),
            points: self.points.clone(),
            observations: self.observations.clone(),
            weak: self.weak.clone(),
            current_segment: self.current_segment,
            segments: self.segments,
            provisional: self.provisional,
            loop_pinned: self.loop_pinned,
        }
    }

    /// A map resumed from a checkpoint's state.
    pub fn from_parts(parts: MapParts) -> Self {
        Self {
            keyframes: parts.keyframes,
            points: parts.points,
            observations: parts.observations,
            weak: parts.weak,
            current_segment: parts.current_segment,
            segments: parts.segments,
            provisional: parts.provisional,
            loop_pinned: parts.loop_pinned,
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

    /// Map points with their segment.
    pub fn points(&self) -> impl Iterator<Item = (u64, u32, &Vector3<f64>)> {
        self.points.iter().map(|(id, (s, p))| (*id, *s, p))
    }
}

#[cfg(test)]
mod tests;
