//! Structure error of a map against ground-truth depth (the paper's Table 2 metric, "structure
//! RMSE"): each map point, brought into the ground-truth frame by the trajectory's Sim(3)
//! alignment, is projected into ground-truth views; where it lands on a pixel with known
//! depth, the error is the difference between its depth and that pixel's. A point hidden in
//! one view is visible in another, so each point's error is its smallest over the views.

use crate::camera::PinholeRadtan;
use crate::trajectory::StampedPose;
use nalgebra::Vector3;

/// Structure error over the points that were seen in at least one view.
#[derive(Debug, Clone, PartialEq)]
pub struct StructureReport {
    pub points: usize,
    pub evaluated: usize,
    pub rmse_m: f64,
    pub median_m: f64,
}

/// `points` in the ground-truth frame; `views` are ground-truth camera poses with a depth
/// lookup `depth(view, column, row)` (metres, `None` where unknown).
pub fn structure_error(
    camera: &PinholeRadtan,
    points: &[Vector3<f64>],
    views: &[StampedPose],
    depth: impl Fn(usize, u32, u32) -> Option<f64>,
) -> Option<StructureReport> {
    let mut errors = Vec::new();
    for x in points {
        let mut best: Option<f64> = None;
        for (v, pose) in views.iter().enumerate() {
            let pc = pose.rotation.inverse() * (x - pose.position);
            if pc.z <= 0.05 {
                continue;
            }
            let Some(px) = camera.project_undistorted(&pc) else {
                continue;
            };
            if !camera.contains(px) {
                continue;
            }
            let Some(d) = depth(v, px.x as u32, px.y as u32) else {
                continue;
            };
            let e = (pc.z - d).abs();
            best = Some(best.map_or(e, |b: f64| b.min(e)));
        }
        errors.extend(best);
    }
    if errors.is_empty() {
        return None;
    }
    let rmse_m = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    let mid = errors.len() / 2;
    let median_m = *errors.select_nth_unstable_by(mid, f64::total_cmp).1;
    Some(StructureReport {
        points: points.len(),
        evaluated: errors.len(),
        rmse_m,
        median_m,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn points_on_a_wall_against_its_depth() {
        let camera =
            PinholeRadtan::new(64, 48, [50.0, 50.0, 32.0, 24.0], [0.0; 5]).expect("camera");
        let view = StampedPose {
            timestamp: 0.0,
            position: Vector3::zeros(),
            rotation: UnitQuaternion::identity(),
        };
        // A wall at z = 4; two points on it, one 10 cm in front, one outside the image.
        let points = [
            Vector3::new(0.0, 0.0, 4.0),
            Vector3::new(0.5, 0.2, 4.0),
            Vector3::new(-0.3, 0.1, 3.9),
            Vector3::new(50.0, 0.0, 4.0),
        ];
        let r = structure_error(&camera, &points, &[view], |_, _, _| Some(4.0)).expect("seen");
        assert_eq!((r.points, r.evaluated), (4, 3));
        assert!((r.rmse_m - (0.01f64 / 3.0).sqrt()).abs() < 1e-9, "{r:?}");
        assert!(r.median_m.abs() < 1e-12);
        assert!(structure_error(&camera, &points, &[view], |_, _, _| None).is_none());
    }
}
