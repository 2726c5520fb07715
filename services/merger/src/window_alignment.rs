//! The similarity that maps a window (or a segment, or a refined block) onto the map from
//! the keyframes and points they share (paper, section 5: 7-DoF alignment of successive
//! windows). Kept apart from the map bookkeeping in `chaining.rs`.

use crate::map::{MapBuilder, PointPair, ScaleSource, WindowInput};
use crate::speed_continuity::SpeedContinuityOptions;
use egoslam_geometry::{nearest_rotation, Similarity, StampedPose};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

/// Rotation `R` minimising `sum ||R_map_i - R R_win_i||_F` (chordal L2 mean of the relative
/// rotations, Hartley et al., "Rotation Averaging", IJCV 2013, section 5.3).
fn chordal_mean(rotations: &[Rotation3<f64>]) -> Rotation3<f64> {
    let sum: Matrix3<f64> = rotations.iter().map(|r| r.matrix()).sum();
    nearest_rotation(&sum)
}

/// Fewest shared points for the point-based scale (below, the centres are used).
pub(crate) const MIN_SHARED_POINTS: usize = 10;

/// Fewest shared points for a chained window's scale to be taken from them without first
/// trying a relocalized scale and the walking pace, and fewest relocalized point pairs for
/// a relocalized scale to come before the pace (30: on the rendered walks a window sharing
/// 10 points after a stop took a scale 60 % off from them).
pub(crate) const MIN_CHAINING_POINTS: usize = 30;

/// Fewest inlier observations some keyframe shared by a window and the map must have on
/// both sides for the shared points to give the window's scale (50). Points shared through
/// keyframes one side barely sees are triangulated from a few rays there: after a 4 s stop
/// on the 12,000-frame walk a window shared 37 points with one of 25 points in all (its
/// shared keyframes had 21-25 observations in the map, 381-569 in the window), and the
/// scale they gave was 2.2x off; the walking pace gives it right.
pub(crate) const MIN_JOIN_OBSERVATIONS: usize = 50;

/// Largest factor by which a firmly joined window's shared-point scale may disagree with
/// the walking pace ([`crate::speed_continuity`]) before the pace gives the scale instead
/// (4). Where both are measured they agree within 0.96-1.04 on a rendered global-shutter
/// walk and within 0.76-1.92 on two walks rendered with a rolling shutter (the extremes at
/// sharp turns; one window left out, below); a car's speed
/// changes more (KITTI 0.43-1.40) and a hand-held camera's pace means little (TUM 0.60),
/// so only a several-fold jump overrides the points. On a 1500-frame walk rendered with
/// a 20 ms readout one window's points said 0.022 of the pace: they had collapsed the map
/// 40x at a turn.
pub(crate) const MAX_PACE_DISAGREEMENT: f64 = 4.0;

/// Similarity mapping a window onto the map from what they share.
///
/// The rotation comes from the shared keyframes' orientations (well determined even under
/// pure rotation, the egocentric case where the centres barely move). The scale comes from
/// the shared points when there are enough: the median over points and shared keyframes of
/// the ratio of camera-to-point distances, map over window; points sit metres away while a
/// window's baselines are centimetres, so this ratio is far better conditioned than one from
/// the centres. Otherwise (rotation-only windows have no points) the scale comes from the
/// centres given the rotation (Umeyama 1991 with the rotation fixed); when they have no
/// spread either (the previous window was rotation-only) from the scene depth
/// ([`align_shared_or_by_depth`]), and stays 1 only when nothing measures it. The
/// translation then maps the centroid of the shared centres.
pub fn align_shared(
    window: &[StampedPose],
    map: &[StampedPose],
    shared_points: &[(Vector3<f64>, Vector3<f64>)],
) -> (Similarity, f64) {
    align_shared_or_by_depth(window, map, shared_points, None)
}

/// [`align_shared`], with `depth_scale` (scene_depth.rs: the ratio of the median scene
/// depths on either side of the boundary) taking the place of the centres when too few
/// points are shared. Used for chaining; segment linking and refinement carry points.
pub fn align_shared_or_by_depth(
    window: &[StampedPose],
    map: &[StampedPose],
    shared_points: &[(Vector3<f64>, Vector3<f64>)],
    depth_scale: Option<f64>,
) -> (Similarity, f64) {
    let (rotation, mu_w, mu_m) = shared_frame(window, map);
    let mut ratios: Vec<f64> = Vec::new();
    if shared_points.len() >= MIN_SHARED_POINTS {
        for (w, m) in window.iter().zip(map) {
            for (xw, xm) in shared_points {
                let (dw, dm) = ((xw - w.position).norm(), (xm - m.position).norm());
                if dw > 1e-12 && dm > 1e-12 {
                    ratios.push(dm / dw);
                }
            }
        }
    }
    let scale = if let Some(s) = crate::median(ratios) {
        s
    } else {
        let (mut num, mut den, mut map_spread) = (0.0, 0.0, 0.0);
        for (w, m) in window.iter().zip(map) {
            let rw = rotation * (w.position - mu_w);
            num += (m.position - mu_m).dot(&rw);
            den += rw.norm_squared();
            map_spread += (m.position - mu_m).norm_squared();
        }
        if den > 1e-18 && map_spread > 1e-18 && num > 0.0 {
            num / den
        } else {
            depth_scale
                .filter(|s| s.is_finite() && *s > 0.0)
                .unwrap_or(1.0)
        }
    };
    align_with_scale(window, map, scale)
}

/// The similarity with the shared keyframes' mean rotation and the given `scale`, the
/// translation mapping the centroid of their centres; with the RMS residual of the centres.
pub(crate) fn align_with_scale(
    window: &[StampedPose],
    map: &[StampedPose],
    scale: f64,
) -> (Similarity, f64) {
    let (rotation, mu_w, mu_m) = shared_frame(window, map);
    let n = window.len() as f64;
    let translation = mu_m - scale * (rotation * mu_w);
    let transform = Similarity {
        scale,
        rotation,
        translation,
    };
    let residual = (window
        .iter()
        .zip(map)
        .map(|(w, m)| (transform.apply(&w.position) - m.position).norm_squared())
        .sum::<f64>()
        / n)
        .sqrt();
    (transform, residual)
}

/// The chordal mean of the shared keyframes' relative rotations (map from window) and the
/// centroids of their centres in the window and in the map.
fn shared_frame(
    window: &[StampedPose],
    map: &[StampedPose],
) -> (Rotation3<f64>, Vector3<f64>, Vector3<f64>) {
    let rel: Vec<Rotation3<f64>> = window
        .iter()
        .zip(map)
        .map(|(w, m)| (m.rotation * w.rotation.inverse()).to_rotation_matrix())
        .collect();
    let n = window.len() as f64;
    let mu_w = window.iter().map(|p| p.position).sum::<Vector3<f64>>() / n;
    let mu_m = map.iter().map(|p| p.position).sum::<Vector3<f64>>() / n;
    (chordal_mean(&rel), mu_w, mu_m)
}

/// `p` mapped by the similarity `t` (centre and orientation).
pub(crate) fn transform_pose(t: &Similarity, p: &StampedPose) -> StampedPose {
    StampedPose {
        timestamp: p.timestamp,
        position: t.apply(&p.position),
        rotation: UnitQuaternion::from_rotation_matrix(&t.rotation) * p.rotation,
    }
}

impl MapBuilder {
    /// Whether `window`, sharing `shared_points` points with `segment`, is too weakly joined
    /// to it for those points to give its scale: fewer than [`MIN_CHAINING_POINTS`], or no
    /// shared keyframe with [`MIN_JOIN_OBSERVATIONS`] inlier observations both in the window
    /// and in the map.
    pub(crate) fn weakly_joined(
        &self,
        segment: u32,
        window: &WindowInput,
        shared_points: usize,
    ) -> bool {
        if shared_points < MIN_CHAINING_POINTS {
            return true;
        }
        let seen = window.observation_counts();
        !window.poses.iter().any(|(id, _)| {
            matches!(self.keyframe(*id), Some((s, _)) if s == segment)
                && seen.get(id).copied().unwrap_or(0) >= MIN_JOIN_OBSERVATIONS
                && self.observed_points(*id) >= MIN_JOIN_OBSERVATIONS
        })
    }

    /// The similarity chaining `window` onto `segment` from the `shared` keyframes (window
    /// poses, map poses) and points, with what gave its scale: the shared points when the
    /// window is firmly joined ([`Self::weakly_joined`]); else `relocalized_scale` (measured
    /// by the caller, which owns the descriptors) if it rests on [`MIN_CHAINING_POINTS`]
    /// pairs; else the walking pace; else the relocalized scale on fewer pairs; else the
    /// points, centres or scene depth that are left. Returns the RMS residual of the shared
    /// centres too.
    pub(crate) fn chaining_transform(
        &self,
        segment: u32,
        window: &WindowInput,
        (w, m): (&[StampedPose], &[StampedPose]),
        shared_points: &[PointPair],
        relocalized_scale: Option<crate::RelocalizedScale>,
    ) -> (Similarity, f64, ScaleSource) {
        if !self.weakly_joined(segment, window, shared_points.len()) {
            let rated = self.better_determined_shared_points(segment, window, MIN_CHAINING_POINTS);
            let (t, r) = align_shared(w, m, &rated);
            // A join whose points say the wearer's pace changed several-fold across it
            // is a broken window, not a change of pace.
            let pace =
                self.speed_continuity_scale(segment, window, &SpeedContinuityOptions::default());
            if let Some(pace) = pace.filter(|p| p.is_finite() && *p > 0.0) {
                if (t.scale / pace).ln().abs() > MAX_PACE_DISAGREEMENT.ln() {
                    tracing::info!(
                        first_keyframe = window.poses.first().map(|(id, _)| *id),
                        shared_points_scale = t.scale,
                        pace_scale = pace,
                        "the shared points' scale is a broken window's: the walking pace gives it"
                    );
                    let (t, r) = align_with_scale(w, m, pace);
                    return (t, r, ScaleSource::WalkingPace);
                }
            }
            return (t, r, ScaleSource::SharedPoints);
        }
        let valid = |s: &f64| s.is_finite() && *s > 0.0;
        let relocalized = relocalized_scale.filter(|r| valid(&r.scale));
        if let Some(r) = relocalized.filter(|r| r.point_pairs >= MIN_CHAINING_POINTS) {
            let (t, res) = align_with_scale(w, m, r.scale);
            return (t, res, ScaleSource::Relocalized);
        }
        let pace = self.speed_continuity_scale(segment, window, &SpeedContinuityOptions::default());
        if let Some(scale) = pace.filter(valid) {
            let (t, r) = align_with_scale(w, m, scale);
            return (t, r, ScaleSource::WalkingPace);
        }
        // Relocalized on fewer pairs: noisier than the pace, better than what is left.
        if let Some(r) = relocalized {
            let (t, res) = align_with_scale(w, m, r.scale);
            return (t, res, ScaleSource::Relocalized);
        }
        // The scene-depth ratio, measured once and only when the shared points are too few
        // to give the scale.
        let depth_scale = (shared_points.len() < MIN_SHARED_POINTS)
            .then(|| {
                let map_depth = self.recent_scene_depth(segment);
                let window_depth = crate::scene_depth::window_scene_depth(window);
                map_depth.zip(window_depth).map(|(m, w)| m / w)
            })
            .flatten();
        let (t, r) = align_shared_or_by_depth(w, m, shared_points, depth_scale);
        tracing::debug!(
            first_keyframe = window.poses.first().map(|(id, _)| *id),
            scale = t.scale,
            depth_scale,
            pace = pace,
            "weak join"
        );
        (t, r, ScaleSource::Weak)
    }
}
