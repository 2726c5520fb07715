//! Focal-length and radial self-calibration (`--calibrate-focal`, `--calibrate-radial`,
//! `frontend.calibrate_*`): the solver solves a recorded input's first windows with the
//! intrinsics free (`egoslam_solver::focal_calibration`, asked by `egoslam run`:
//! supervision/stream_calibration.rs) and, when they agree on a focal length clearly
//! different from the calibration's, the run starts again with the calibration's fx and
//! fy scaled (or, on a clear radial distortion the calibration leaves, with it added to
//! k1), so that every process (tracker, solver, merger, relocalization) and the saved
//! camera.yaml use the same camera. A live camera runs with the calibration as given.

use crate::options::PipelineArgs;
use egoslam_geometry::PinholeRadtan;
use egoslam_solver::focal_calibration::FocalCalibrationOptions;
use egoslam_solver::window_solver::WindowSolverOptions;

/// `camera` with its focal lengths multiplied by `scale`.
pub fn scaled(camera: &PinholeRadtan, scale: f64) -> PinholeRadtan {
    PinholeRadtan {
        fx: camera.fx * scale,
        fy: camera.fy * scale,
        ..*camera
    }
}

/// `camera` with `k` added to its first distortion coefficient: what the radial
/// self-calibration measures (on a pinhole, to first order the residual `(1 + k r^2)` of
/// its undistorted points; through a fisheye, the model's own first term).
pub fn with_radial(camera: &PinholeRadtan, k: f64) -> PinholeRadtan {
    let mut distortion = camera.distortion;
    distortion[0] += k;
    PinholeRadtan {
        distortion,
        ..*camera
    }
}

/// The camera to localize a recording in a saved map with: the map's intrinsics when the
/// map was built by the same camera self-calibrated (same size and principal point; focal
/// lengths in the same ratio, within the 20 % the focal self-calibration believes; the same
/// distortion but for a first radial coefficient within the 0.1 the radial one believes),
/// so that queries use the camera their map was built with; else `calibrated` as given.
/// (Maps saved before they recorded their distortion read as distortion-free: for a lens
/// with distortion terms they are another camera, and queries use the calibration.)
pub fn with_the_maps_focal(calibrated: &PinholeRadtan, map: &PinholeRadtan) -> PinholeRadtan {
    let options = FocalCalibrationOptions::default();
    let same_camera = (calibrated.width, calibrated.height) == (map.width, map.height)
        && calibrated.lens == map.lens
        && calibrated.cx == map.cx
        && calibrated.cy == map.cy
        && calibrated.distortion[1..] == map.distortion[1..]
        && (calibrated.distortion[0] - map.distortion[0]).abs() <= options.max_radial_correction;
    let scale = map.fx / calibrated.fx;
    if same_camera
        && map != calibrated
        && (map.fy / calibrated.fy - scale).abs() < 1e-9
        && scale.ln().abs() <= (1.0 + options.max_correction).ln()
    {
        tracing::info!(
            scale,
            k1 = map.distortion[0],
            "the map's camera is the calibration self-calibrated: queries use it"
        );
        return *map;
    }
    *calibrated
}

/// The focal and radial estimates' options for `pipeline`: the windows and solver the run
/// will use.
pub fn calibration_options(
    pipeline: &PipelineArgs,
) -> (FocalCalibrationOptions, WindowSolverOptions) {
    let options = FocalCalibrationOptions {
        window: usize::from(pipeline.window),
        overlap: pipeline.overlap,
        ..FocalCalibrationOptions::default()
    };
    let mut solver = WindowSolverOptions::default();
    solver.view_graph.loop_closure_span = usize::from(pipeline.loop_closures);
    (options, solver)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_radial_term_adds_to_k1_only() {
        let c =
            PinholeRadtan::new(640, 480, [500.0, 502.0, 320.0, 240.0], [0.1; 5]).expect("camera");
        let r = with_radial(&c, 0.02);
        assert!((r.distortion[0] - 0.12).abs() < 1e-12);
        assert_eq!(r.distortion[1..], c.distortion[1..]);
        assert_eq!(
            PinholeRadtan {
                distortion: c.distortion,
                ..r
            },
            c
        );
    }

    #[test]
    fn scaling_keeps_everything_but_the_focal_lengths() {
        let c =
            PinholeRadtan::new(640, 480, [500.0, 502.0, 320.0, 240.0], [0.1; 5]).expect("camera");
        let s = scaled(&c, 0.97);
        assert!((s.fx - 485.0).abs() < 1e-9 && (s.fy - 486.94).abs() < 1e-9);
        assert_eq!(
            (s.cx, s.cy, s.distortion, s.width),
            (320.0, 240.0, [0.1; 5], 640)
        );
    }

    #[test]
    fn a_query_takes_its_maps_self_calibrated_focal_only_for_the_same_camera() {
        let c =
            PinholeRadtan::new(640, 480, [500.0, 502.0, 320.0, 240.0], [0.1; 5]).expect("camera");
        let map = scaled(&c, 0.97);
        assert_eq!(with_the_maps_focal(&c, &map), map);
        // Another camera (principal point), or a focal beyond the 20 % bound: as calibrated.
        let other = PinholeRadtan { cx: 330.0, ..map };
        assert_eq!(with_the_maps_focal(&c, &other), c);
        assert_eq!(with_the_maps_focal(&c, &scaled(&c, 0.5)), c);
        // Focal lengths in another ratio are not a self-calibration.
        let stretched = PinholeRadtan { fy: c.fy, ..map };
        assert_eq!(with_the_maps_focal(&c, &stretched), c);
        // A self-calibrated radial term, with or without the focal: the map's camera; a
        // first coefficient beyond the 0.1 bound, or another second one: as calibrated.
        let radial = with_radial(&map, 0.02);
        assert_eq!(with_the_maps_focal(&c, &radial), radial);
        let radial_only = with_radial(&c, -0.02);
        assert_eq!(with_the_maps_focal(&c, &radial_only), radial_only);
        assert_eq!(with_the_maps_focal(&c, &with_radial(&c, 0.2)), c);
        let mut other_k2 = with_radial(&c, 0.02);
        other_k2.distortion[1] += 0.01;
        assert_eq!(with_the_maps_focal(&c, &other_k2), c);
        assert_eq!(with_the_maps_focal(&c, &c), c);
    }
}
