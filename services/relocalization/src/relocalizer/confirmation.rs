//! Whether a relocalization's pose is to be trusted: the pose from appearance matches
//! refined on the matches found by projection only where the refinement stayed near it,
//! and a second chance, once every candidate group has failed, for a pose whose appearance
//! matches were too few to accept alone (a tentative hypothesis the projection must
//! confirm).

use super::{MapKeyframe, QueryFeatures, Relocalization, Relocalizer, RelocalizerOptions};
use crate::absolute_pose::{solve_pnp, PnpOptions, PnpSolution};
use crate::keyframe_database::Candidate;
use crate::rotation_relocalization::relocalize_by_rotation;
use egoslam_geometry::StampedPose;
use nalgebra::{Point2, Vector3};

/// A pose from appearance matches too weak to accept alone, kept as a hypothesis and
/// accepted only when the matching by projection confirms it: ORB-SLAM's relocalization
/// (Mur-Artal and Tardos 2017, `Tracking::Relocalization`) takes a PnP hypothesis from 10
/// inliers and accepts it at 50 after a search by projection. Tried only after every
/// candidate group and the placement by rotation have failed, so a frame the strict test
/// places is placed as without it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TentativePoseOptions {
    /// Fewest appearance inliers that make a hypothesis (default 8: the TUM clip's frames
    /// refused at 15 had 4-12; 4 AP3P points and a few more that agree leave almost no
    /// room for a wrong pose that also passes the confirmation below).
    pub min_inliers: usize,
    /// Fewest inliers of the refinement on the matches found by projection that confirm
    /// it (default 15: the strict minimum of the appearance PnP; on the TUM clip 30 took
    /// 2 of its 12 refused frames, 20 took 5 and 15 took 6, all within 1.2-4.5 cm of the
    /// ground truth, against the map's own 1.4 cm).
    pub min_confirmed_inliers: usize,
}

impl Default for TentativePoseOptions {
    fn default() -> Self {
        Self {
            min_inliers: 8,
            min_confirmed_inliers: 15,
        }
    }
}

impl Relocalizer {
    /// The pose of `hypothesis` checked against the keyframe poses and refined on the
    /// matches found by projection; `None` when a check refuses it. With `tentative` (a
    /// hypothesis short of the strict minimum) the refinement must reach its
    /// `min_confirmed_inliers`, and the appearance pose never stands in for it.
    pub(super) fn place(
        &self,
        query: &QueryFeatures,
        hypothesis: &Hypothesis,
        tentative: Option<&TentativePoseOptions>,
        options: &RelocalizerOptions,
    ) -> Option<Relocalization> {
        let camera = &self.map.camera;
        let solution = &hypothesis.solution;
        // The known keyframe poses reject a pose no candidate could have seen the
        // frame from (paper: "reject outliers using the pre-computed trajectory").
        // The candidate viewing most like the pose: by optical axis, not by position
        // (a head turning in place has all its keyframes at one spot).
        let axis = |p: &StampedPose| p.rotation * Vector3::z();
        let angle = |k: &MapKeyframe| axis(&solution.pose).angle(&axis(&k.pose));
        let nearest = hypothesis
            .group
            .iter()
            .map(|&k| &self.map.keyframes[k])
            .min_by(|a, b| angle(a).total_cmp(&angle(b)))?;
        if angle(nearest).to_degrees() > options.max_view_angle_deg {
            return None;
        }
        // Pose-only refinement on the matches found by projection.
        let local = self.local_keyframes(hypothesis.group, options.neighbours);
        let projected = self.match_projection(query, &local, &solution.pose, options);
        let refine = PnpOptions {
            min_inlier_ratio: 0.0,
            ransac_iterations: 50,
            ransac_threshold_px: options.refine_threshold_px,
            ..options.pnp
        };
        let projected_pairs = self.correspondences(query, &projected);
        let refined = solve_pnp(camera, &projected_pairs, Some(&solution.pose), &refine);
        // A refinement that left its start is not a refinement of it: a RANSAC from the
        // pose can settle on another that counts mirrored points behind the camera.
        let refined = refined.ok().filter(|r| {
            stays_near(
                options,
                &solution.pose,
                solution.inliers.len(),
                r,
                &projected_pairs,
            )
        });
        let needed = tentative.map_or(solution.inliers.len(), |t| t.min_confirmed_inliers);
        let ((pose, angular_velocity), inliers) = match refined {
            Some(s) if s.inliers.len() >= needed => (
                self.unrolled(
                    s.pose,
                    s.inliers.iter().map(|&i| projected_pairs[i]),
                    options,
                ),
                s.inliers.iter().map(|&i| projected[i]).collect(),
            ),
            _ if tentative.is_some() => return None,
            _ => (
                self.unrolled(
                    solution.pose,
                    solution
                        .inliers
                        .iter()
                        .map(|&i| hypothesis.correspondences[i]),
                    options,
                ),
                solution
                    .inliers
                    .iter()
                    .map(|&i| hypothesis.matches[i])
                    .collect(),
            ),
        };
        let found = Relocalization {
            pose,
            segment: hypothesis.segment,
            keyframe_id: nearest.keyframe_id,
            inliers,
            angular_velocity,
        };
        Some(self.searched_with_turn(query, &local, found, options))
    }
}

/// Whether `refined`, the pose a refinement from `start` (a pose of `start_inliers`) led to
/// on `pairs`, stayed near it ([`RelocalizerOptions::max_refinement_turn_deg`] and
/// [`RelocalizerOptions::max_refinement_shift_of_depth`]).
pub(super) fn stays_near(
    options: &RelocalizerOptions,
    start: &StampedPose,
    start_inliers: usize,
    refined: &PnpSolution,
    pairs: &[(Vector3<f64>, Point2<f64>)],
) -> bool {
    let near = pose_stays_near(
        options,
        start,
        &refined.pose,
        refined.inliers.iter().map(|&i| &pairs[i].0),
    );
    if !near {
        tracing::debug!(
            appearance = start_inliers,
            projected = refined.inliers.len(),
            "refinement left its start"
        );
    }
    near
}

/// Whether `refined` (world_from_camera) is within the refinement's bounds of `start`
/// ([`RelocalizerOptions::max_refinement_turn_deg`], and
/// [`RelocalizerOptions::max_refinement_shift_of_depth`] of the median depth of `points`,
/// which must lie in front).
pub(super) fn pose_stays_near<'p>(
    options: &RelocalizerOptions,
    start: &StampedPose,
    refined: &StampedPose,
    points: impl Iterator<Item = &'p Vector3<f64>>,
) -> bool {
    let r_cw = refined.rotation.inverse();
    let depth =
        egoslam_geometry::median(points.map(|x| (r_cw * (x - refined.position)).z).collect());
    let shift = (refined.position - start.position).norm();
    let turn = refined.rotation.angle_to(&start.rotation).to_degrees();
    turn <= options.max_refinement_turn_deg
        && depth > 0.0
        && shift <= options.max_refinement_shift_of_depth * depth
}

/// A candidate group's pose from its appearance matches, with what gave it.
pub(super) struct Hypothesis<'g> {
    pub(super) segment: u32,
    pub(super) group: &'g [usize],
    /// `(track, query feature)` matches, index for index with `correspondences`.
    pub(super) matches: Vec<(u64, usize)>,
    pub(super) correspondences: Vec<(Vector3<f64>, Point2<f64>)>,
    pub(super) solution: PnpSolution,
}

impl Relocalizer {
    /// `found`, a pose from points, or the placement by rotation at a candidate keyframe
    /// that turned in place when the rotation explains more matches than the points'
    /// pose has inliers: a frame of a turn in place sees few points (the stretch
    /// triangulated none), and a PnP on those few is noisier than the stretch's centre.
    pub(super) fn rotation_if_better(
        &self,
        query: &QueryFeatures,
        candidates: &[Candidate],
        found: Relocalization,
        options: &RelocalizerOptions,
    ) -> Relocalization {
        match self.placed_by_rotation(query, candidates, options) {
            Some(rotation) if rotation.inliers.len() > found.inliers.len() => rotation,
            _ => found,
        }
    }

    /// The placement by rotation at the first of `candidates` that turned in place and
    /// whose matches a rotation explains ([`relocalize_by_rotation`]); `None` when none
    /// does or the options turn it off.
    fn placed_by_rotation(
        &self,
        query: &QueryFeatures,
        candidates: &[Candidate],
        options: &RelocalizerOptions,
    ) -> Option<Relocalization> {
        if !options.place_by_rotation {
            return None;
        }
        let _span = tracing::debug_span!("placement_by_rotation").entered();
        let ranked: Vec<usize> = candidates
            .iter()
            .filter_map(|c| self.index.get(&c.keyframe_id).copied())
            .collect();
        relocalize_by_rotation(&self.map, query, &ranked, options)
    }

    /// What is tried once no candidate group gave a pose on its own: placement by
    /// rotation at a keyframe that turned in place, then the tentative hypotheses, best
    /// supported first.
    pub(super) fn second_chance(
        &self,
        query: &QueryFeatures,
        candidates: &[Candidate],
        options: &RelocalizerOptions,
        mut tentative: Vec<Hypothesis>,
    ) -> Option<Relocalization> {
        // No candidate's points gave a pose: a head turning in place leaves keyframes
        // without points, placed by rotation alone.
        if let Some(found) = self.placed_by_rotation(query, candidates, options) {
            return Some(found);
        }
        let settings = options.tentative?;
        // Stable: equal support keeps the groups' order (best bag-of-words score first).
        tentative.sort_by_key(|h| std::cmp::Reverse(h.solution.inliers.len()));
        tentative
            .iter()
            .find_map(|h| self.place(query, h, Some(&settings), options))
    }
}
