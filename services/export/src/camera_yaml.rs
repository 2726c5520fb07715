//! The calibration in egoslam's own YAML format (docs/config.md), as `egoslam run` writes
//! the camera it resolved (OUT/camera.yaml) and `egoslam synth` the rendered one.

use egoslam_geometry::PinholeRadtan;
use std::path::Path;

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
