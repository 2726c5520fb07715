//! TUM trajectory text, the format of the run's trajectory files (trajectory.tum,
//! keyframes.tum, live_trajectory.tum) and of `egoslam localize`'s.

use egoslam_geometry::StampedPose;

/// The live (revision 0) poses of a run as they were published, one line per frame (the
/// merger's live tracker writes it; `egoslam eval` scores it).
pub const LIVE_TRAJECTORY_FILE: &str = "live_trajectory.tum";

/// The first line of the run's TUM files.
pub const TUM_HEADER: &str = "# timestamp tx ty tz qx qy qz qw (world_from_camera)\n";

/// TUM trajectory text: `timestamp tx ty tz qx qy qz qw`.
pub fn tum_text(poses: &[StampedPose]) -> String {
    String::from(TUM_HEADER) + &tum_rows(poses)
}

/// The rows of [`tum_text`], without its header.
pub fn tum_rows(poses: &[StampedPose]) -> String {
    let mut s = String::new();
    for p in poses {
        let q = p.rotation.quaternion();
        s.push_str(&format!(
            "{:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6}\n",
            p.timestamp, p.position.x, p.position.y, p.position.z, q.i, q.j, q.k, q.w
        ));
    }
    s
}
