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
                    Similarity::identity(),
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

    /// Map points with their segment.
    pub fn points(&self) -> impl Iterator<Item = (u64, u32, &Vector3<f64>)> {
        self.points.iter().map(|(id, (s, p))| (*id, *s, p))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, UnitQuaternion};

    fn pose(t: f64, p: Vector3<f64>, yaw: f64) -> StampedPose {
        StampedPose {
            timestamp: t,
            position: p,
            rotation: UnitQuaternion::from_euler_angles(0.0, yaw, 0.1 * yaw),
        }
    }

    #[test]
    fn second_window_in_another_frame_is_brought_back() {
        let truth: Vec<StampedPose> = (0..15)
            .map(|i| {
                pose(
                    i as f64,
                    Vector3::new(i as f64 * 0.1, 0.02 * i as f64, 0.0),
                    0.05 * i as f64,
                )
            })
            .collect();
        let mut map = MapBuilder::new();
        let first = WindowInput {
            poses: (0..10).map(|i| (i as u64, truth[i])).collect(),
            points: vec![(7, Vector3::new(1.0, 2.0, 3.0))],
            ..WindowInput::default()
        };
        assert_eq!(
            map.add_window(&first),
            WindowOutcome::NewSegment { segment: 0 }
        );
        // The second window's frame: scaled by 3, rotated, shifted.
        let g = Similarity {
            scale: 3.0,
            rotation: Rotation3::from_euler_angles(0.4, -0.2, 1.0),
            translation: Vector3::new(5.0, -1.0, 2.0),
        };
        let second = WindowInput {
            poses: (5..15)
                .map(|i| (i as u64, transform_pose(&g, &truth[i])))
                .collect(),
            points: vec![(8, g.apply(&Vector3::new(-1.0, 0.5, 4.0)))],
            ..WindowInput::default()
        };
        match map.add_window(&second) {
            WindowOutcome::Aligned { residual, .. } => assert!(residual < 1e-9),
            other => panic!("{other:?}"),
        }
        for (id, seg, p) in map.keyframes() {
            assert_eq!(seg, 0);
            let t = truth[id as usize];
            assert!((p.position - t.position).norm() < 1e-9, "kf {id}");
            assert!(p.rotation.angle_to(&t.rotation) < 1e-9);
        }
        let (_, _, x) = map.points().find(|(id, _, _)| *id == 8).expect("point 8");
        assert!((x - Vector3::new(-1.0, 0.5, 4.0)).norm() < 1e-9);
        map.break_segment();
        assert_eq!(
            map.add_window(&first),
            WindowOutcome::NewSegment { segment: 1 }
        );
        assert_eq!(map.segments(), 2);
    }
}

#[cfg(test)]
mod rotation_only_tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn a_rotation_only_window_after_a_moving_one_stays_finite() {
        let mut map = MapBuilder::new();
        let moving = WindowInput {
            poses: (0..10u64)
                .map(|i| {
                    (
                        i,
                        StampedPose {
                            timestamp: i as f64,
                            position: Vector3::new(0.1 * i as f64, 0.0, 0.0),
                            rotation: UnitQuaternion::from_euler_angles(0.0, 0.1 * i as f64, 0.0),
                        },
                    )
                })
                .collect(),
            points: vec![],
            ..WindowInput::default()
        };
        map.add_window(&moving);
        let still = WindowInput {
            poses: (5..15u64)
                .map(|i| {
                    (
                        i,
                        StampedPose {
                            timestamp: i as f64,
                            position: Vector3::zeros(),
                            rotation: UnitQuaternion::from_euler_angles(
                                0.0,
                                0.1 * (i - 5) as f64,
                                0.0,
                            ),
                        },
                    )
                })
                .collect(),
            points: vec![],
            ..WindowInput::default()
        };
        map.add_window(&still);
        map.add_window(&WindowInput {
            poses: still.poses.iter().map(|(i, p)| (i + 5, *p)).collect(),
            points: vec![],
            ..WindowInput::default()
        });
        for (id, _, p) in map.keyframes() {
            assert!(p.position.iter().all(|v| v.is_finite()), "kf {id} {p:?}");
            assert!(
                p.rotation.coords.iter().all(|v| v.is_finite()),
                "kf {id} {p:?}"
            );
        }
    }
}

#[cfg(test)]
mod robustness_tests {
    use super::*;
    use nalgebra::{Rotation3, UnitQuaternion};

    #[test]
    fn a_window_with_nan_is_recognised() {
        let good = WindowInput {
            poses: vec![(
                0,
                StampedPose {
                    timestamp: 0.0,
                    position: Vector3::zeros(),
                    rotation: UnitQuaternion::identity(),
                },
            )],
            points: vec![(1, Vector3::new(1.0, 2.0, 3.0))],
            ..WindowInput::default()
        };
        assert!(good.is_finite());
        let mut bad = good.clone();
        bad.points[0].1.y = f64::NAN;
        assert!(!bad.is_finite());
        let mut bad = good.clone();
        bad.poses[0].1.position.x = f64::INFINITY;
        assert!(!bad.is_finite());
        let mut bad = good;
        bad.observations
            .push((0, 1, nalgebra::Point2::new(f64::NAN, 0.0)));
        assert!(!bad.is_finite());
    }

    /// Two overlapping windows of a forward walk with different scales, noisy shared
    /// keyframes and 30 % of the shared points wrong: merged keyframes within 0.5 % of the
    /// path length (issue: "merge to < 0.5 % of path length ATE").
    #[test]
    fn noisy_windows_with_wrong_points_merge_within_half_a_percent() {
        let mut state = 99u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let truth: Vec<StampedPose> = (0..30)
            .map(|i| StampedPose {
                timestamp: i as f64,
                position: Vector3::new(0.02 * (0.4 * i as f64).sin(), 0.0, 0.1 * i as f64),
                rotation: UnitQuaternion::from_euler_angles(
                    0.0,
                    0.03 * (0.3 * i as f64).sin(),
                    0.0,
                ),
            })
            .collect();
        let path: f64 = truth
            .windows(2)
            .map(|w| (w[1].position - w[0].position).norm())
            .sum();
        let points: Vec<Vector3<f64>> = (0..200)
            .map(|_| Vector3::new(8.0 * uniform(), 3.0 * uniform(), 6.0 + 8.0 * uniform()))
            .collect();
        // Window-frame noise: 0.1 % of the path on centres, 0.2 deg on rotations, 1 % of
        // depth on points.
        let mut noisy = |p: &StampedPose, g: &Similarity| {
            let n = Vector3::new(uniform(), uniform(), uniform()) * 0.002 * path;
            let r = UnitQuaternion::from_euler_angles(uniform(), uniform(), uniform()).powf(0.007);
            transform_pose(
                g,
                &StampedPose {
                    position: p.position + n,
                    rotation: r * p.rotation,
                    ..*p
                },
            )
        };
        let first = WindowInput {
            poses: (0..20)
                .map(|i| (i as u64, noisy(&truth[i], &Similarity::identity())))
                .collect(),
            points: points
                .iter()
                .enumerate()
                .map(|(t, x)| (t as u64, *x))
                .collect(),
            ..WindowInput::default()
        };
        let g = Similarity {
            scale: 0.2,
            rotation: Rotation3::from_euler_angles(-0.3, 0.9, 0.1),
            translation: Vector3::new(1.0, 2.0, -3.0),
        };
        let second = WindowInput {
            poses: (15..30).map(|i| (i as u64, noisy(&truth[i], &g))).collect(),
            points: points
                .iter()
                .enumerate()
                .map(|(t, x)| {
                    let wrong = t % 10 < 3;
                    let x = if wrong {
                        Vector3::new(
                            10.0 * uniform(),
                            5.0 * uniform(),
                            3.0 + 20.0 * (uniform() + 0.5),
                        )
                    } else {
                        x * (1.0 + 0.01 * uniform())
                    };
                    (t as u64, g.apply(&x))
                })
                .collect(),
            ..WindowInput::default()
        };
        let mut map = MapBuilder::new();
        map.add_window(&first);
        assert!(matches!(
            map.add_window(&second),
            WindowOutcome::Aligned { .. }
        ));
        let est: Vec<StampedPose> = map.keyframes().map(|(_, _, p)| *p).collect();
        let ate = egoslam_geometry::absolute_trajectory_error(&est, &truth, 1e-3).expect("ate");
        assert!(
            ate.rmse < 0.005 * path,
            "ATE {} over a {} path",
            ate.rmse,
            path
        );
    }
}
