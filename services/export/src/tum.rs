//! TUM trajectory text, the format of the run's trajectory files (trajectory.tum,
//! keyframes.tum, live_trajectory.tum) and of `egoslam localize`'s.

use egoslam_geometry::StampedPose;

/// The live (revision 0) poses of a run as they were published, one line per frame (the
/// merger's live tracker writes it; `egoslam eval` scores it).
pub const LIVE_TRAJECTORY_FILE: &str = "live_trajectory.tum";

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
