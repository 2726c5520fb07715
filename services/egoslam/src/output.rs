//! Result files: TUM trajectories, egoslam calibration YAML (written atomically with
//! `egoslam_durability::write_atomically`).

use egoslam_geometry::{PinholeRadtan, StampedPose};
use std::path::Path;

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

/// The calibration in egoslam's own YAML format (docs/config.md).
pub fn camera_yaml(camera: &PinholeRadtan, origin: &Path) -> String {
    let d = camera.distortion;
    format!(
        "# resolved by egoslam from {}\nmodel: {}\nwidth: {}\nheight: {}\nfx: {}\nfy: {}\ncx: {}\ncy: {}\ndistortion: [{}, {}, {}, {}, {}]\n",
        origin.display(),
        camera.lens.name(),
        camera.width,
        camera.height,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        d[0],
        d[1],
        d[2],
        d[3],
        d[4]
    )
}
