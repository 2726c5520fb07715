//! Placing a replayed head trajectory in free space.
//!
//! A recorded trajectory (Project Aria, HOT3D) comes from another building; replayed from
//! the walker's start in the rendered room, it can walk through a box or a wall. The
//! Aria sample did: its camera came within 4 cm of a box face and through it (frames
//! 150-158), so the frontend saw 0.5 s of a featureless blur at point-blank range and the
//! map broke there, a failure no head could cause. The trajectory is therefore turned about
//! the vertical through its start by the yaw that keeps it farthest from every surface.

use crate::scene::Scene;
use egoslam_geometry::StampedPose;
use nalgebra::{UnitQuaternion, Vector3};

/// Closest approach, metres, of `poses` to the scene's surfaces.
pub fn clearance(poses: &[StampedPose], scene: &Scene) -> f64 {
    poses
        .iter()
        .map(|p| scene.clearance(&p.position))
        .fold(f64::INFINITY, f64::min)
}

/// `poses` turned by `yaw` (radians) about the vertical (+y, gravity) through the first.
fn turned(poses: &[StampedPose], yaw: f64) -> Vec<StampedPose> {
    let Some(first) = poses.first() else {
        return Vec::new();
    };
    let turn = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw);
    poses
        .iter()
        .map(|p| StampedPose {
            timestamp: p.timestamp,
            position: first.position + turn * (p.position - first.position),
            rotation: turn * p.rotation,
        })
        .collect()
}

/// The trajectory turned (in steps of 15 deg) to keep at least `wanted` metres from every
/// surface, preferring the smallest turn that does, else the turn with the largest
/// clearance; returns it with the turn (radians) and its clearance.
pub fn place_in_free_space(
    poses: &[StampedPose],
    scene: &Scene,
    wanted: f64,
) -> (Vec<StampedPose>, f64, f64) {
    let mut best: Option<(Vec<StampedPose>, f64, f64)> = None;
    for step in 0..24 {
        // 0, +15, -15, +30, -30, ... deg: the smallest turn first.
        let k = (step + 1) / 2;
        let sign = if step % 2 == 1 { 1.0 } else { -1.0 };
        let yaw = sign * f64::from(k) * 15f64.to_radians();
        let candidate = turned(poses, yaw);
        let c = clearance(&candidate, scene);
        if c >= wanted {
            return (candidate, yaw, c);
        }
        if best.as_ref().is_none_or(|(_, _, b)| c > *b) {
            best = Some((candidate, yaw, c));
        }
    }
    best.unwrap_or_else(|| (poses.to_vec(), 0.0, clearance(poses, scene)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Plane;
    use crate::texture::Texture;

    #[test]
    fn a_walk_into_a_wall_is_turned_away_from_it() {
        // A 4 x 3 m wall 2 m ahead (z = 2), and a walk 3 m straight along +z.
        let wall = Plane::new(
            Vector3::new(-2.0, -1.5, 2.0),
            Vector3::new(4.0, 0.0, 0.0),
            Vector3::new(0.0, 3.0, 0.0),
            Texture {
                seed: 1,
                scale_m: 0.5,
                base: 0.5,
            },
        );
        let scene = Scene { planes: vec![wall] };
        let walk: Vec<StampedPose> = (0..31)
            .map(|i| StampedPose {
                timestamp: i as f64 * 0.1,
                position: Vector3::new(0.0, 0.0, 0.1 * i as f64),
                rotation: UnitQuaternion::identity(),
            })
            .collect();
        assert_eq!(clearance(&walk, &scene), 0.0, "straight through the wall");
        let (placed, yaw, c) = place_in_free_space(&walk, &scene, 0.5);
        assert!(c >= 0.5, "clearance {c}");
        assert!(yaw.abs() > 0.0);
        // Turned as a whole: the same start, the same length, the heading turned by yaw.
        assert_eq!(placed[0].position, walk[0].position);
        let length = (placed[30].position - placed[0].position).norm();
        assert!((length - 3.0).abs() < 1e-9);
        let heading = placed[30].rotation * Vector3::z();
        assert!((heading.x.atan2(heading.z) - yaw).abs() < 1e-9);
    }
}
