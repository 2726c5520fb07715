//! TUM trajectory text, the format of the run's trajectory files (trajectory.tum,
//! keyframes.tum, live_trajectory.tum) and of `egoslam localize`'s.

use egoslam_geometry::StampedPose;

/// TUM trajectory text: `timestamp tx ty tz qx qy qz qw`.
pub fn tum_text(poses: &[StampedPose]) -> String {
    let mut s = String::from("# timestamp tx ty tz qx qy qz qw (world_from_camera)\n");
    for p in poses {
        let q = p.rotation.quaternion();
        s.push_str(&format!(
            "{:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6}\n",
            p.timestamp, p.position.x, p.position.y, p.position.z, q.i, q.j, q.k, q.w
        ));
    }
    s
}
