//! The centres of a refinement's newest keyframes that no point holds.

use egoslam_solver::bundle_adjustment::Observation;
use egoslam_solver::triangulation::CameraPose;
use egoslam_solver::unobserved_keyframes::{place_unobserved_centres, UnobservedKeyframeOptions};
use nalgebra::Vector3;

/// A tail keyframe's refined centre is replaced when it departs from the placed one by
/// more than this fraction of the median distance from the cameras to the points they see
/// (0.1). The final stop of a rendered 900-frame walk had its keyframes 20-25 % of that
/// off. Where the refined centres were the better, they departed less: by 0.5 % at the
/// rendered fisheye walk's stop (placed, its ATE went 0.011 -> 0.018 m), and by up to 6 %
/// on the fast head shake of tests/head_shake.rs, whose orientation went 2.0 -> 6.4 deg
/// when those were placed at 5 %.
const MAX_TAIL_DEPARTURE: f64 = 0.1;

/// Places the centres of the keyframes after the job's last well-observed one from the
/// motion before them, as a window's unobserved keyframes are placed
/// (`egoslam_solver::unobserved_keyframes::place_unobserved_centres`), where the
/// adjustment moved them away ([`MAX_TAIL_DEPARTURE`]); returns how many. Nothing holds
/// such keyframes (the stop at a stream's end, whose windows are rotation-only, sees no
/// point): on that walk two keyframes of the final stop went 0.3-0.6 m off, and the
/// keyframes added while the refinement ran were carried by them 1 m off. `depth` gives
/// the median distance from the cameras to the points they see, from the adjusted poses.
pub(super) fn place_tail_centres(
    poses: &mut [CameraPose],
    timestamps: &[f64],
    inliers: &[usize],
    depth: impl FnOnce(&[CameraPose]) -> Option<f64>,
    options: &UnobservedKeyframeOptions,
) -> usize {
    let Some(last) = inliers.iter().rposition(|&n| n >= options.min_observations) else {
        return 0;
    };
    // Measured only when there is a tail: most jobs end on well-observed keyframes.
    if last + 1 == poses.len() {
        return 0;
    }
    let Some(depth) = depth(poses) else {
        return 0;
    };
    let mut placed = poses.to_vec();
    place_unobserved_centres(&mut placed, timestamps, inliers, options);
    let mut count = 0;
    for k in last + 1..poses.len() {
        if (poses[k].centre - placed[k].centre).norm() > MAX_TAIL_DEPARTURE * depth {
            poses[k].centre = placed[k].centre;
            count += 1;
        }
    }
    count
}

/// The median distance from the cameras to the points they observe.
pub(super) fn median_observation_distance(
    poses: &[CameraPose],
    points: &[Vector3<f64>],
    observations: &[Observation],
) -> Option<f64> {
    let distances: Vec<f64> = observations
        .iter()
        .filter_map(|o| Some((points.get(o.point)? - poses.get(o.camera)?.centre).norm()))
        .collect();
    crate::median(distances)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    /// Keyframes 0.1 apart along x at 10 per second; the first `seen` with 50 inliers, the
    /// rest with none.
    fn walk(n: usize, seen: usize) -> (Vec<CameraPose>, Vec<f64>, Vec<usize>) {
        let poses = (0..n)
            .map(|k| CameraPose {
                rotation: Rotation3::identity(),
                centre: Vector3::new(0.1 * k as f64, 0.0, 0.0),
            })
            .collect();
        let times = (0..n).map(|k| 0.1 * k as f64).collect();
        let inliers = (0..n).map(|k| if k < seen { 50 } else { 0 }).collect();
        (poses, times, inliers)
    }

    #[test]
    fn a_tail_keyframe_the_adjustment_threw_off_is_placed_by_the_motion_before() {
        let (mut poses, times, inliers) = walk(12, 8);
        poses[9].centre.y += 1.0; // 25 % of a scene 4 away
        poses[10].centre.y += 0.1; // 2.5 %: kept
        let options = UnobservedKeyframeOptions::default();
        let placed = place_tail_centres(&mut poses, &times, &inliers, |_| Some(4.0), &options);
        assert_eq!(placed, 1);
        assert!(
            (poses[9].centre - Vector3::new(0.9, 0.0, 0.0)).norm() < 1e-9,
            "{:?}",
            poses[9].centre
        );
        assert!((poses[10].centre.y - 0.1).abs() < 1e-12);
        // An interior unobserved keyframe is the adjustment's.
        let (mut poses, times, mut inliers) = walk(12, 12);
        inliers[5] = 0;
        poses[5].centre.y += 1.0;
        assert_eq!(
            place_tail_centres(&mut poses, &times, &inliers, |_| Some(4.0), &options),
            0
        );
        assert!((poses[5].centre.y - 1.0).abs() < 1e-12);
    }
}
