//! Poses of the frames between keyframes.
//!
//! Only keyframes are solved; the frames in between get the pose interpolated at their
//! timestamp (linear in position, spherical-linear in rotation) between the two keyframes
//! that enclose them, when both lie in the same map segment. Frames outside such a pair stay
//! unposed rather than extrapolated.

use egoslam_geometry::StampedPose;

/// Poses at `timestamps` from keyframe poses sorted by time, each with its segment.
/// Returns `(index into timestamps, pose, segment)` for every frame that could be posed.
pub fn interpolate_frames(
    keyframes: &[(u32, StampedPose)],
    timestamps: &[f64],
) -> Vec<(usize, StampedPose, u32)> {
    let mut out = Vec::new();
    for (i, &t) in timestamps.iter().enumerate() {
        let after = keyframes.partition_point(|(_, k)| k.timestamp < t);
        if let Some((seg, k)) = keyframes.get(after) {
            if k.timestamp == t {
                out.push((i, *k, *seg));
                continue;
            }
        }
        if after == 0 || after >= keyframes.len() {
            continue;
        }
        let ((s0, a), (s1, b)) = (keyframes[after - 1], keyframes[after]);
        if s0 != s1 {
            continue;
        }
        out.push((i, interpolate_between(&a, &b, t), s0));
    }
    out
}

/// The pose at time `t` between keyframes `a` and `b` (linear centre, slerp rotation).
pub fn interpolate_between(a: &StampedPose, b: &StampedPose, t: f64) -> StampedPose {
    let span = b.timestamp - a.timestamp;
    let w = if span.abs() > 0.0 {
        ((t - a.timestamp) / span).clamp(0.0, 1.0)
    } else {
        0.0
    };
    StampedPose {
        timestamp: t,
        position: a.position.lerp(&b.position, w),
        rotation: a.rotation.slerp(&b.rotation, w),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    #[test]
    fn midpoints_and_segment_gaps() {
        let k = |t: f64, x: f64, yaw: f64| StampedPose {
            timestamp: t,
            position: Vector3::new(x, 0.0, 0.0),
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        };
        let kfs = vec![
            (0, k(0.0, 0.0, 0.0)),
            (0, k(1.0, 2.0, 0.4)),
            (1, k(2.0, 9.0, 0.0)),
        ];
        let out = interpolate_frames(&kfs, &[-0.5, 0.25, 1.0, 1.5]);
        assert_eq!(
            out.len(),
            2,
            "before the first and across a break are unposed"
        );
        assert_eq!(out[0].0, 1);
        assert!((out[0].1.position.x - 0.5).abs() < 1e-12);
        assert!((out[0].1.rotation.angle() - 0.1).abs() < 1e-12);
        assert_eq!(out[1].0, 2);
    }
}
