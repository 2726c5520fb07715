//! The camera: pinhole intrinsics and a lens model (OpenCV radial-tangential k1 k2 p1 p2
//! k3, or a fisheye model of [`crate::lens`]).
//!
//! Why in Rust and not `cv::undistortPoints`: the frontend undistorts every track of every
//! frame, and the solver and tests need the same model without an OpenCV `Mat` round trip.
//! The model and its iterative inverse are the ones of OpenCV's `calib3d` documentation.

use crate::lens::{fisheye_project, fisheye_unproject, LensModel, MAX_TANGENT_PLANE_ANGLE};
use nalgebra::{Point2, Vector3};

/// Errors of building a camera from calibration values.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    /// A focal length is zero, negative or not finite.
    #[error("focal length must be positive and finite, got fx={fx} fy={fy}")]
    BadFocal { fx: f64, fy: f64 },
    /// The image size is zero in one dimension.
    #[error("image size must be non-zero, got {width}x{height}")]
    BadSize { width: u32, height: u32 },
    /// A distortion coefficient is not finite.
    #[error("distortion coefficients must be finite, got {0:?}")]
    BadDistortion([f64; 5]),
    /// Double-sphere coefficients outside the model's range.
    #[error("double sphere needs alpha in [0, 1] and xi in (-1, 1], got xi={xi} alpha={alpha}")]
    BadDoubleSphere { xi: f64, alpha: f64 },
}

/// Pinhole intrinsics plus a lens model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PinholeRadtan {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// The lens model's coefficients ([`LensModel`]); radial-tangential in OpenCV order
    /// k1, k2, p1, p2, k3, all zero for rectified images (KITTI).
    pub distortion: [f64; 5],
    pub lens: LensModel,
}

impl PinholeRadtan {
    /// Checked constructor: calibration comes from files, so it is validated once here.
    pub fn new(
        width: u32,
        height: u32,
        [fx, fy, cx, cy]: [f64; 4],
        distortion: [f64; 5],
    ) -> Result<Self, CameraError> {
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(CameraError::BadFocal { fx, fy });
        }
        if width == 0 || height == 0 {
            return Err(CameraError::BadSize { width, height });
        }
        if distortion.iter().any(|d| !d.is_finite()) {
            return Err(CameraError::BadDistortion(distortion));
        }
        Ok(Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion,
            lens: LensModel::RadialTangential,
        })
    }

    /// The same intrinsics under another lens model, whose coefficients `distortion` holds.
    pub fn with_lens(self, lens: LensModel) -> Result<Self, CameraError> {
        if lens == LensModel::DoubleSphere {
            let [xi, alpha, ..] = self.distortion;
            if !((0.0..=1.0).contains(&alpha) && xi > -1.0 && xi <= 1.0) {
                return Err(CameraError::BadDoubleSphere { xi, alpha });
            }
        }
        Ok(Self { lens, ..self })
    }

    /// True when there is no distortion to remove (rectified input).
    pub fn is_rectified(&self) -> bool {
        self.lens == LensModel::RadialTangential && self.distortion.iter().all(|d| *d == 0.0)
    }

    /// Applies distortion to normalised coordinates (x/z, y/z); not finite where a fisheye
    /// model has no image of the ray.
    pub fn distort_normalized(&self, p: Point2<f64>) -> Point2<f64> {
        if self.lens.is_fisheye() {
            let ray = Vector3::new(p.x, p.y, 1.0);
            return fisheye_project(self.lens, &self.distortion, &ray)
                .unwrap_or(Point2::new(f64::NAN, f64::NAN));
        }
        let [k1, k2, p1, p2, k3] = self.distortion;
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        Point2::new(
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Inverse of [`Self::distort_normalized`]; `None` for a fisheye ray beyond
    /// [`MAX_TANGENT_PLANE_ANGLE`] from the axis, or outside the model's image.
    pub fn undistort_normalized(&self, d: Point2<f64>) -> Option<Point2<f64>> {
        if self.lens.is_fisheye() {
            let ray = fisheye_unproject(self.lens, &self.distortion, d)?;
            return (ray.z >= MAX_TANGENT_PLANE_ANGLE.cos())
                .then(|| Point2::new(ray.x / ray.z, ray.y / ray.z));
        }
        Some(self.undistort_radtan(d))
    }

    /// Inverse of the radial-tangential distortion by fixed-point iteration (as OpenCV's
    /// `undistortPoints`), refined with a few Gauss-Newton steps so that the round trip is
    /// exact to ~1e-10 even for the strong barrel distortion of wide lenses.
    fn undistort_radtan(&self, d: Point2<f64>) -> Point2<f64> {
        if self.is_rectified() {
            return d;
        }
        let mut p = d;
        for _ in 0..20 {
            let [k1, k2, p1, p2, k3] = self.distortion;
            let (x, y) = (p.x, p.y);
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            p = Point2::new((d.x - dx) / radial, (d.y - dy) / radial);
        }
        // Gauss-Newton polish with a numeric Jacobian.
        for _ in 0..3 {
            let f = self.distort_normalized(p) - d;
            if f.norm() < 1e-14 {
                break;
            }
            let h = 1e-7;
            let jx = (self.distort_normalized(Point2::new(p.x + h, p.y))
                - self.distort_normalized(p))
                / h;
            let jy = (self.distort_normalized(Point2::new(p.x, p.y + h))
                - self.distort_normalized(p))
                / h;
            let j = nalgebra::Matrix2::from_columns(&[jx, jy]);
            if let Some(inv) = j.try_inverse() {
                p -= inv * f;
            }
        }
        p
    }

    /// Raw pixel -> its distorted normalised coordinates (before the lens model is undone).
    fn normalized(&self, raw: Point2<f64>) -> Point2<f64> {
        Point2::new((raw.x - self.cx) / self.fx, (raw.y - self.cy) / self.fy)
    }

    /// Raw (distorted) pixel -> ideal pinhole pixel with the same fx fy cx cy; `None` for
    /// a fisheye pixel whose ray the pinhole plane does not carry
    /// ([`Self::undistort_normalized`]).
    pub fn undistort_pixel(&self, raw: Point2<f64>) -> Option<Point2<f64>> {
        let d = self.normalized(raw);
        let n = self.undistort_normalized(d)?;
        Some(Point2::new(
            n.x * self.fx + self.cx,
            n.y * self.fy + self.cy,
        ))
    }

    /// Raw (distorted) pixel -> bearing (unit vector in the camera frame), for any ray the
    /// lens images (beyond 90 degrees for a fisheye).
    pub fn bearing_from_raw(&self, raw: Point2<f64>) -> Option<Vector3<f64>> {
        let d = self.normalized(raw);
        if self.lens.is_fisheye() {
            return fisheye_unproject(self.lens, &self.distortion, d);
        }
        let n = self.undistort_radtan(d);
        Some(Vector3::new(n.x, n.y, 1.0).normalize())
    }

    /// Ideal pinhole pixel -> bearing (unit vector in the camera frame).
    pub fn bearing_from_undistorted(&self, px: Point2<f64>) -> Vector3<f64> {
        Vector3::new((px.x - self.cx) / self.fx, (px.y - self.cy) / self.fy, 1.0).normalize()
    }

    /// Camera-frame point -> ideal (undistorted) pixel; `None` behind the camera.
    pub fn project_undistorted(&self, pc: &Vector3<f64>) -> Option<Point2<f64>> {
        (pc.z > 1e-9).then(|| {
            Point2::new(
                self.fx * pc.x / pc.z + self.cx,
                self.fy * pc.y / pc.z + self.cy,
            )
        })
    }

    /// Camera-frame point -> raw (distorted) pixel; `None` behind the camera.
    pub fn project_raw(&self, pc: &Vector3<f64>) -> Option<Point2<f64>> {
        if pc.z <= 1e-9 {
            return None;
        }
        let d = if self.lens.is_fisheye() {
            fisheye_project(self.lens, &self.distortion, pc)?
        } else {
            self.distort_normalized(Point2::new(pc.x / pc.z, pc.y / pc.z))
        };
        Some(Point2::new(
            self.fx * d.x + self.cx,
            self.fy * d.y + self.cy,
        ))
    }

    /// Where row `y` is read in a rolling-shutter readout, as a signed share of the readout
    /// from the middle row: `(y - h/2) / h` (-0.5 at the top, +0.5 at the bottom). Times
    /// the readout, it is the row's capture time after the frame's timestamp, which is the
    /// middle row's; the frontend's correction, the readout estimate and the relocalizer's
    /// turn during the readout all read rows this way.
    pub fn row_offset(&self, y: f64) -> f64 {
        let h = f64::from(self.height);
        (y - h / 2.0) / h
    }

    /// True when a pixel lies inside the image (with half-pixel borders).
    pub fn contains(&self, px: Point2<f64>) -> bool {
        px.x >= -0.5
            && px.y >= -0.5
            && px.x <= self.width as f64 - 0.5
            && px.y <= self.height as f64 - 0.5
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tum_fr1() -> PinholeRadtan {
        PinholeRadtan::new(
            640,
            480,
            [517.306408, 516.469215, 318.643040, 255.313989],
            [0.262383, -0.953104, -0.005358, 0.002628, 1.163314],
        )
        .expect("valid")
    }

    #[test]
    fn undistort_inverts_distort_over_the_image() {
        let cam = tum_fr1();
        let mut worst: f64 = 0.0;
        for u in (0..640).step_by(40) {
            for v in (0..480).step_by(40) {
                let ideal = Point2::new(u as f64, v as f64);
                let pc = Vector3::new(
                    (ideal.x - cam.cx) / cam.fx,
                    (ideal.y - cam.cy) / cam.fy,
                    1.0,
                );
                let raw = cam.project_raw(&pc).expect("in front");
                let back = cam.undistort_pixel(raw).expect("radtan");
                worst = worst.max((back - ideal).norm());
            }
        }
        assert!(worst < 1e-6, "round trip error {worst} px");
    }

    #[test]
    fn distortion_moves_corners_by_the_expected_amount() {
        // The fr1 lens (k1 0.26, k2 -0.95, k3 1.16) scales the corner's ideal radius by
        // 1.045 (1 + k1 r^2 + k2 r^4 + k3 r^6 at the ideal r^2 = 0.53, the fixed point of
        // the raw r^2 = 0.58): the raw corner lies outward, so undistorting pulls it toward
        // the principal point, along the radius (the tangential terms move it ~0.2 px). A
        // sign error in k1 (factor 0.75) or a dropped term would put it elsewhere.
        let cam = tum_fr1();
        let centre = Point2::new(cam.cx, cam.cy);
        let raw = Point2::new(10.0, 10.0);
        let und = cam.undistort_pixel(raw).expect("radtan");
        let (r_raw, r_und) = ((raw - centre).norm(), (und - centre).norm());
        let factor = r_raw / r_und;
        assert!((factor - 1.045).abs() < 0.005, "radius factor {factor}");
        let along = (raw - centre).normalize().dot(&(und - centre).normalize());
        assert!(along > 0.9999, "direction cosine {along}");
    }

    #[test]
    fn a_fisheye_pixel_becomes_an_ideal_pixel_within_80_degrees_and_a_bearing_beyond() {
        // 640x480 at 260 px/rad (an ideal equidistant lens): the corner is 400 px = 88 deg
        // off the axis, a pixel 280 px left of centre 61.7 deg.
        let cam = PinholeRadtan::new(640, 480, [260.0, 260.0, 320.0, 240.0], [0.0; 5])
            .and_then(|c| c.with_lens(LensModel::Equidistant))
            .expect("valid");
        assert!(!cam.is_rectified());
        let corner = Point2::new(0.0, 0.0);
        assert!(cam.undistort_pixel(corner).is_none());
        let ray = cam.bearing_from_raw(corner).expect("imaged");
        assert!(
            (ray.z.acos().to_degrees() - 400.0 / 260.0 * 180.0 / std::f64::consts::PI).abs() < 1e-9
        );
        let raw = Point2::new(40.0, 240.0);
        let ideal = cam.undistort_pixel(raw).expect("within 80 deg");
        let expected = 320.0 - 260.0 * (280.0f64 / 260.0).tan();
        assert!(
            (ideal.x - expected).abs() < 1e-6 && (ideal.y - 240.0).abs() < 1e-9,
            "{ideal}"
        );
        let pc = cam.bearing_from_undistorted(ideal);
        let back = cam.project_raw(&pc).expect("in front");
        assert!((back - raw).norm() < 1e-6, "{back}");
        assert!(matches!(
            cam.with_lens(LensModel::DoubleSphere)
                .map(|c| PinholeRadtan {
                    distortion: [0.0, 1.5, 0.0, 0.0, 0.0],
                    ..c
                })
                .and_then(|c| c.with_lens(LensModel::DoubleSphere)),
            Err(CameraError::BadDoubleSphere { .. })
        ));
    }

    #[test]
    fn rejects_bad_calibration() {
        assert!(matches!(
            PinholeRadtan::new(640, 480, [0.0, 1.0, 0.0, 0.0], [0.0; 5]),
            Err(CameraError::BadFocal { .. })
        ));
        assert!(matches!(
            PinholeRadtan::new(0, 480, [1.0, 1.0, 0.0, 0.0], [0.0; 5]),
            Err(CameraError::BadSize { .. })
        ));
        assert!(
            PinholeRadtan::new(10, 10, [1.0, 1.0, 0.0, 0.0], [f64::NAN, 0.0, 0.0, 0.0, 0.0])
                .is_err()
        );
    }
}
