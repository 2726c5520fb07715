//! Lens models: how a ray through the camera centre lands on the normalised image plane
//! (pixel = focal * point + centre), and back.
//!
//! Radial-tangential is the pinhole model with OpenCV's polynomial distortion; the two
//! fisheye models map a ray's angle from the optical axis, so rays at and beyond 90
//! degrees have an image too. The pipeline downstream of the frontend works on "ideal"
//! pixels of the pinhole plane with the same focal and centre (bearings are exact there);
//! a fisheye ray is kept while it is within [`MAX_TANGENT_PLANE_ANGLE`] of the axis.

use nalgebra::{Point2, Vector3};

/// Which lens model the coefficients of a camera's `distortion` belong to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LensModel {
    /// OpenCV radial-tangential on the pinhole plane: `distortion` = k1, k2, p1, p2, k3.
    #[default]
    RadialTangential,
    /// Kannala-Brandt / equidistant (Kannala and Brandt, PAMI 2006; OpenCV `fisheye`,
    /// Kalibr `equidistant`, ORB-SLAM3 `KannalaBrandt8`): the image radius is
    /// `theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)` for a ray at angle
    /// `theta` from the axis; `distortion` = k1, k2, k3, k4, 0.
    Equidistant,
    /// Double sphere (Usenko, Demmel and Cremers, 3DV 2018; Basalt, TUM-VI): `distortion`
    /// = xi, alpha, 0, 0, 0.
    DoubleSphere,
}

impl LensModel {
    /// The name used in calibration files and saved maps.
    pub fn name(self) -> &'static str {
        match self {
            Self::RadialTangential => "radtan",
            Self::Equidistant => "equidistant",
            Self::DoubleSphere => "double_sphere",
        }
    }

    /// Whether rays far from the axis are imaged (the fisheye models).
    pub fn is_fisheye(self) -> bool {
        !matches!(self, Self::RadialTangential)
    }
}

/// Widest ray angle from the axis that is carried onward as an ideal pinhole pixel (80
/// degrees: tan 80 = 5.7 focal lengths off centre; nearer 90 the pinhole plane stretches a
/// pixel's noise by 1 / cos^2 of the angle, 33x at 80 degrees, so those rays weigh little
/// in any pixel-residual step anyway).
pub const MAX_TANGENT_PLANE_ANGLE: f64 = 80.0 * std::f64::consts::PI / 180.0;

/// Ray (any length, camera frame) -> normalised image point under a fisheye `lens`; `None`
/// where the model has no image of it.
pub(crate) fn fisheye_project(
    lens: LensModel,
    c: &[f64; 5],
    ray: &Vector3<f64>,
) -> Option<Point2<f64>> {
    match lens {
        LensModel::RadialTangential => None,
        LensModel::Equidistant => {
            let r = ray.x.hypot(ray.y);
            let theta = r.atan2(ray.z);
            let t2 = theta * theta;
            let theta_d = theta * (1.0 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3]))));
            if r < 1e-12 {
                // On the axis the radius' derivative at 0 is 1: the pinhole limit.
                return (ray.z > 0.0).then(|| Point2::new(ray.x / ray.z, ray.y / ray.z));
            }
            Some(Point2::new(theta_d * ray.x / r, theta_d * ray.y / r))
        }
        LensModel::DoubleSphere => {
            let (xi, alpha) = (c[0], c[1]);
            let d1 = ray.norm();
            let z1 = xi * d1 + ray.z;
            let d2 = (ray.x * ray.x + ray.y * ray.y + z1 * z1).sqrt();
            // Validity of the projection (Usenko et al., eq. 43).
            let w1 = if alpha <= 0.5 {
                alpha / (1.0 - alpha)
            } else {
                (1.0 - alpha) / alpha
            };
            let w2 = (w1 + xi) / (2.0 * w1 * xi + xi * xi + 1.0).sqrt();
            if ray.z <= -w2 * d1 {
                return None;
            }
            let denominator = alpha * d2 + (1.0 - alpha) * z1;
            (denominator > 1e-12).then(|| Point2::new(ray.x / denominator, ray.y / denominator))
        }
    }
}

/// Normalised image point -> unit ray under a fisheye `lens`; `None` outside the model's
/// image.
pub(crate) fn fisheye_unproject(
    lens: LensModel,
    c: &[f64; 5],
    m: Point2<f64>,
) -> Option<Vector3<f64>> {
    match lens {
        LensModel::RadialTangential => None,
        LensModel::Equidistant => {
            let theta_d = m.coords.norm();
            if theta_d < 1e-12 {
                return Some(Vector3::z());
            }
            // Newton on theta (OpenCV's fisheye::undistortPoints does the same iteration).
            let mut theta = theta_d;
            for _ in 0..20 {
                let t2 = theta * theta;
                let f =
                    theta * (1.0 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3])))) - theta_d;
                let df = 1.0
                    + t2 * (3.0 * c[0] + t2 * (5.0 * c[1] + t2 * (7.0 * c[2] + t2 * 9.0 * c[3])));
                if df.abs() < 1e-12 {
                    return None;
                }
                let step = f / df;
                theta -= step;
                if step.abs() < 1e-14 {
                    break;
                }
            }
            if !(0.0..std::f64::consts::PI).contains(&theta) {
                return None;
            }
            let s = theta.sin() / theta_d;
            Some(Vector3::new(m.x * s, m.y * s, theta.cos()))
        }
        LensModel::DoubleSphere => {
            let (xi, alpha) = (c[0], c[1]);
            let r2 = m.x * m.x + m.y * m.y;
            if alpha > 0.5 && r2 > 1.0 / (2.0 * alpha - 1.0) {
                return None;
            }
            let root = 1.0 - (2.0 * alpha - 1.0) * r2;
            let mz = (1.0 - alpha * alpha * r2) / (alpha * root.max(0.0).sqrt() + 1.0 - alpha);
            let mz2 = mz * mz;
            let k = (mz * xi + (mz2 + (1.0 - xi * xi) * r2).max(0.0).sqrt()) / (mz2 + r2);
            let ray = Vector3::new(k * m.x, k * m.y, k * mz - xi);
            let n = ray.norm();
            (n > 1e-12 && n.is_finite()).then(|| ray / n)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rays from the axis to `max_deg`, all around.
    fn rays(max_deg: f64) -> impl Iterator<Item = Vector3<f64>> {
        (0..=36).flat_map(move |a| {
            (0..12).map(move |b| {
                let theta = (a as f64 / 36.0 * max_deg).to_radians();
                let phi = b as f64 / 12.0 * std::f64::consts::TAU;
                Vector3::new(
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                )
            })
        })
    }

    #[test]
    fn fisheye_models_round_trip_rays_to_95_degrees() {
        let models = [
            (LensModel::Equidistant, [0.02, -0.01, 0.003, -0.0005, 0.0]),
            (LensModel::Equidistant, [0.0; 5]),
            // TUM-VI's 512x512 camera in Usenko et al. (xi -0.18, alpha 0.59).
            (LensModel::DoubleSphere, [-0.18, 0.59, 0.0, 0.0, 0.0]),
        ];
        for (lens, c) in models {
            for ray in rays(95.0) {
                let m = fisheye_project(lens, &c, &ray).expect("imaged");
                let back = fisheye_unproject(lens, &c, m).expect("unprojected");
                assert!((back - ray).norm() < 1e-9, "{lens:?} {ray:?} -> {back:?}");
            }
        }
    }

    #[test]
    fn an_ideal_equidistant_lens_puts_the_angle_on_the_radius() {
        // theta_d = theta: 90 degrees lands pi/2 focal lengths off centre, where a
        // pinhole has no image at all.
        let c = [0.0; 5];
        let m = fisheye_project(LensModel::Equidistant, &c, &Vector3::new(1.0, 0.0, 0.0))
            .expect("imaged");
        assert!((m.x - std::f64::consts::FRAC_PI_2).abs() < 1e-12 && m.y.abs() < 1e-12);
        let m = fisheye_project(LensModel::Equidistant, &c, &Vector3::new(0.0, 1.0, 1.0))
            .expect("imaged");
        assert!((m.y - std::f64::consts::FRAC_PI_4).abs() < 1e-12);
    }

    #[test]
    fn double_sphere_with_zero_xi_and_alpha_is_the_pinhole() {
        let c = [0.0; 5];
        let m = fisheye_project(LensModel::DoubleSphere, &c, &Vector3::new(0.3, -0.2, 1.0))
            .expect("imaged");
        assert!((m - Point2::new(0.3, -0.2)).norm() < 1e-12);
        assert!(
            fisheye_project(LensModel::DoubleSphere, &c, &Vector3::new(1.0, 0.0, -0.1)).is_none()
        );
    }
}
