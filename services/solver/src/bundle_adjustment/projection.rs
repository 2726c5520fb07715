//! Where bundle adjustment measures a residual, and the projection with the refinable
//! intrinsics (a focal scale `s` and a first distortion term `k`).
//!
//! Tracks arrive as ideal pinhole pixels (the frontend undoes the lens), and the residuals
//! are measured there. Refining a fisheye's intrinsics cannot be done on that plane: a
//! fisheye's focal or first term changes a ray's image as a function of its angle from the
//! axis, which no focal scale and `(1 + k r^2)` of the pinhole plane reproduce (at 70 deg
//! a 4 % longer equidistant focal moves a point 4 % along the image radius, the pinhole
//! plane's image of it 14 %). So there each track is carried back through the given lens to
//! its raw pixel, and the point is projected through the lens with `fx s, fy s` and `k`
//! added to the model's first coefficient (equidistant k1, double sphere xi): the image
//! plane of the model, as Kalibr and Basalt calibrate.

use super::Observation;
use egoslam_geometry::PinholeRadtan;
use nalgebra::{Matrix2, Matrix2x3, Vector2, Vector3};

/// The projection a bundle adjustment's residuals are measured with.
pub(super) struct Projection<'a> {
    camera: &'a PinholeRadtan,
    /// Residuals in raw pixels through the camera's fisheye model (module doc).
    through_lens: bool,
}

/// A projected point: its pixel, d(pixel)/d(camera point) and d(pixel)/d(s, k).
pub(super) type Projected = (Vector2<f64>, Matrix2x3<f64>, Matrix2<f64>);

impl<'a> Projection<'a> {
    /// Through the lens when the intrinsics are refined and the camera is a fisheye; on the
    /// ideal pinhole plane otherwise.
    pub(super) fn new(camera: &'a PinholeRadtan, refine_intrinsics: bool) -> Self {
        Self {
            camera,
            through_lens: refine_intrinsics && camera.lens.is_fisheye(),
        }
    }

    /// The position `o` is compared with: its pixel, or through the lens its raw pixel
    /// (`None` where the given lens has no image of its ray).
    pub(super) fn target(&self, o: &Observation) -> Option<Vector2<f64>> {
        if !self.through_lens {
            return Some(o.pixel.coords);
        }
        let ray = self.camera.bearing_from_undistorted(o.pixel);
        self.camera.project_raw(&ray).map(|p| p.coords)
    }

    /// `pc`'s image with focal scale `s` and first term `k`; `None` behind the camera or
    /// outside the lens's image.
    pub(super) fn project(&self, s: f64, k: f64, pc: &Vector3<f64>) -> Option<Projected> {
        if self.through_lens {
            through_lens(self.camera, s, k, pc)
        } else {
            on_ideal_plane(self.camera, s, k, pc)
        }
    }
}

/// On the ideal pinhole plane, `k` a residual `(1 + k r^2)` of it.
fn on_ideal_plane(camera: &PinholeRadtan, s: f64, k: f64, pc: &Vector3<f64>) -> Option<Projected> {
    if pc.z <= 1e-9 {
        return None;
    }
    let (xn, yn) = (pc.x / pc.z, pc.y / pc.z);
    let r2 = xn * xn + yn * yn;
    let d = 1.0 + k * r2;
    let (fx, fy) = (camera.fx * s, camera.fy * s);
    let pixel = Vector2::new(fx * d * xn + camera.cx, fy * d * yn + camera.cy);
    // d pixel / d (xn, yn)
    let j_n = Matrix2::new(
        fx * (d + 2.0 * k * xn * xn),
        fx * 2.0 * k * xn * yn,
        fy * 2.0 * k * xn * yn,
        fy * (d + 2.0 * k * yn * yn),
    );
    let iz = 1.0 / pc.z;
    let j_pc = Matrix2x3::new(iz, 0.0, -xn * iz, 0.0, iz, -yn * iz);
    let j_intr = Matrix2::new(
        camera.fx * d * xn,
        fx * r2 * xn,
        camera.fy * d * yn,
        fy * r2 * yn,
    );
    Some((pixel, j_n * j_pc, j_intr))
}

/// Through the camera's fisheye model with `fx s, fy s` and `k` added to its first
/// coefficient. The focal's derivative is exact (the raw pixel is the focal times the
/// model's point plus the centre); the point's and `k`'s are central differences, which
/// serve every model alike (a pre-pass's few windows, not the run's).
fn through_lens(camera: &PinholeRadtan, s: f64, k: f64, pc: &Vector3<f64>) -> Option<Projected> {
    let lens = |k: f64| {
        let mut distortion = camera.distortion;
        distortion[0] += k;
        PinholeRadtan {
            fx: camera.fx * s,
            fy: camera.fy * s,
            distortion,
            ..*camera
        }
    };
    let at = |c: &PinholeRadtan, p: &Vector3<f64>| c.project_raw(p).map(|q| q.coords);
    let here = lens(k);
    let pixel = at(&here, pc)?;
    let h = 1e-6 * pc.norm().max(1e-9);
    let mut j_pc = Matrix2x3::zeros();
    for d in 0..3 {
        let step = Vector3::ith(d, h);
        let ahead = at(&here, &(pc + step))?;
        let behind = at(&here, &(pc - step))?;
        j_pc.set_column(d, &((ahead - behind) / (2.0 * h)));
    }
    let hk = 1e-6;
    let j_k = (at(&lens(k + hk), pc)? - at(&lens(k - hk), pc)?) / (2.0 * hk);
    let centre = Vector2::new(camera.cx, camera.cy);
    let j_s = (pixel - centre) / s;
    Some((pixel, j_pc, Matrix2::from_columns(&[j_s, j_k])))
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_geometry::LensModel;

    #[test]
    fn through_a_fisheye_the_projection_meets_the_raw_pixel_and_its_derivatives_the_differences() {
        let camera = PinholeRadtan::new(
            640,
            480,
            [260.0, 260.0, 320.0, 240.0],
            [0.01, 0.0, 0.0, 0.0, 0.0],
        )
        .and_then(|c| c.with_lens(LensModel::Equidistant))
        .expect("camera");
        let projection = Projection::new(&camera, true);
        // 60 degrees off the axis: the ideal pixel is far from the raw one.
        let pc = Vector3::new(1.5, 0.4, 1.0);
        let ideal = camera.project_undistorted(&pc).expect("in front");
        let o = Observation {
            camera: 0,
            point: 0,
            pixel: ideal,
        };
        let raw = camera.project_raw(&pc).expect("imaged").coords;
        let target = projection.target(&o).expect("imaged");
        assert!((target - raw).norm() < 1e-6, "{target} against {raw}");
        let (pixel, _, j_intr) = projection.project(1.0, 0.0, &pc).expect("imaged");
        assert!((pixel - raw).norm() < 1e-9);
        // The focal scale's column against a difference of the projection itself.
        let (longer, _, _) = projection.project(1.0 + 1e-5, 0.0, &pc).expect("imaged");
        let ds = (longer - pixel) / 1e-5;
        assert!(
            (ds - j_intr.column(0)).norm() < 1e-3,
            "{ds} against {}",
            j_intr.column(0)
        );
        // On the ideal plane the same point keeps its pinhole pixel.
        let ideal_plane = Projection::new(&camera, false);
        assert_eq!(ideal_plane.target(&o), Some(ideal.coords));
        let (on_plane, _, _) = ideal_plane.project(1.0, 0.0, &pc).expect("in front");
        assert!((on_plane - ideal.coords).norm() < 1e-9);
        assert!(
            (on_plane - raw).norm() > 50.0,
            "ideal and raw differ at 60 degrees"
        );
    }
}
