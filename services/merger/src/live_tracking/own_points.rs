//! The tracker's own points: tracks without a map point, triangulated from their first
//! tracked sighting and a later one with enough parallax, both from the tracker's poses.

use super::LiveTracker;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Vector3};

/// A track's first sighting from a tracked frame: the camera centre and the ray in the
/// world frame.
#[derive(Debug, Clone, Copy)]
pub(super) struct Sighting {
    pub(super) centre: Vector3<f64>,
    pub(super) ray: Vector3<f64>,
}

impl LiveTracker {
    /// Triangulates the tracks without a point whose ray turned far enough since their
    /// first tracked sighting; records the first sighting of the others.
    pub(super) fn triangulate(
        &mut self,
        camera: &PinholeRadtan,
        pose: &StampedPose,
        tracks: &[(u64, Point2<f64>)],
    ) {
        let min_cos = self.options.min_triangulation_angle_deg.to_radians().cos();
        let r_cw = pose.rotation.inverse();
        for (track, px) in tracks {
            if self.map.points.contains_key(track) || self.local_points.contains_key(track) {
                continue;
            }
            let ray = pose.rotation * camera.bearing_from_undistorted(*px);
            let Some(first) = self.sightings.get(track).copied() else {
                self.sightings.insert(
                    *track,
                    Sighting {
                        centre: pose.position,
                        ray,
                    },
                );
                continue;
            };
            if first.ray.dot(&ray) > min_cos {
                continue;
            }
            let Some(x) = closest_point(&first, pose.position, ray) else {
                continue;
            };
            let in_camera = r_cw * (x - pose.position);
            let reprojected = camera.project_undistorted(&in_camera);
            if reprojected
                .is_some_and(|p| (p - px).norm() <= self.options.max_triangulation_error_px)
            {
                self.local_points.insert(*track, x);
                self.sightings.remove(track);
            }
        }
    }
}

/// The midpoint of the shortest segment between two rays, if it lies in front of both.
pub(super) fn closest_point(
    first: &Sighting,
    centre: Vector3<f64>,
    ray: Vector3<f64>,
) -> Option<Vector3<f64>> {
    let w = first.centre - centre;
    let b = first.ray.dot(&ray);
    let denominator = 1.0 - b * b;
    if denominator < 1e-9 {
        return None;
    }
    let (d, e) = (first.ray.dot(&w), ray.dot(&w));
    let s = (b * e - d) / denominator; // along the first ray
    let t = (e - b * d) / denominator; // along the second
    (s > 0.0 && t > 0.0).then(|| 0.5 * ((first.centre + first.ray * s) + (centre + ray * t)))
}
