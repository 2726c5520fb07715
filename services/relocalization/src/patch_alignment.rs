//! Sub-pixel placement of a map point in a query image by aligning the patch the tracker
//! saw it with (SVO's feature alignment: Forster et al. 2014, section V.A; Lucas and
//! Kanade 1981 with an affine gain and bias, Baker and Matthews 2004).
//!
//! A relocalized pose is solved from the query's own corners matched to map points, but a
//! map point is where its *track* was, not where a corner detector puts the maximum of its
//! corner response: on the rendered Aria head trajectory the two differ by 1.5 px (median)
//! while the map's own observations agree with its points within 0.44 px. Aligning each
//! inlier's saved patch, warped by the viewpoint change, to the query image finds the track's
//! position in the query; the pose solved on those positions agrees with the map. Keyframes
//! relocalized from scratch landed 2-39 mm (median 11 mm, first 20 keyframes) from their
//! own pose from the corners, and 0.5-1.2 mm (first five) with aligned patches.

use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Matrix2, Matrix4, Point2, Vector2, Vector3, Vector4};
use opencv::core::CV_8UC1;
use opencv::prelude::*;

/// Side of a saved patch, pixels: 10, SVO's 8 x 8 patch with its one-pixel border, here
/// all used as the template.
pub const PATCH_SIDE: usize = 10;

/// A square of raw-image intensities centred on a track's position (row-major, sampled
/// bilinearly at offsets -4.5 .. 4.5 px).
pub type Patch = [u8; PATCH_SIDE * PATCH_SIDE];

/// Offset of template sample `i` (row-major) from the patch centre.
fn offset(i: usize) -> Vector2<f64> {
    let half = (PATCH_SIDE as f64 - 1.0) / 2.0;
    Vector2::new(
        (i % PATCH_SIDE) as f64 - half,
        (i / PATCH_SIDE) as f64 - half,
    )
}

/// An 8-bit single-channel image borrowed for bilinear sampling.
struct Sampler<'a> {
    data: &'a [u8],
    step: usize,
    width: usize,
    height: usize,
}

impl<'a> Sampler<'a> {
    fn new(image: &'a impl MatTraitConst) -> Option<Self> {
        if image.typ() != CV_8UC1 || image.empty() {
            return None;
        }
        let step = image.step1(0).ok()?;
        Some(Self {
            data: image.data_bytes().ok()?,
            step,
            width: usize::try_from(image.cols()).ok()?,
            height: usize::try_from(image.rows()).ok()?,
        })
    }

    /// Bilinear intensity at `p`; `None` within a pixel of the border.
    fn at(&self, p: Vector2<f64>) -> Option<f64> {
        if !(p.x >= 1.0 && p.y >= 1.0) {
            return None;
        }
        let (x0, y0) = (p.x.floor() as usize, p.y.floor() as usize);
        if x0 + 2 >= self.width || y0 + 2 >= self.height {
            return None;
        }
        let (fx, fy) = (p.x - x0 as f64, p.y - y0 as f64);
        let v = |x: usize, y: usize| f64::from(self.data[y * self.step + x]);
        Some(
            (1.0 - fy) * ((1.0 - fx) * v(x0, y0) + fx * v(x0 + 1, y0))
                + fy * ((1.0 - fx) * v(x0, y0 + 1) + fx * v(x0 + 1, y0 + 1)),
        )
    }
}

/// The patch of `image` (8-bit grey) centred on the raw pixel `centre`; `None` when it
/// does not fit inside the image.
pub fn extract_patch(image: &impl MatTraitConst, centre: Point2<f64>) -> Option<Patch> {
    let sampler = Sampler::new(image)?;
    let mut patch = [0u8; PATCH_SIDE * PATCH_SIDE];
    for (i, value) in patch.iter_mut().enumerate() {
        let v = sampler.at(centre.coords + offset(i))?;
        *value = v.round().clamp(0.0, 255.0) as u8;
    }
    Some(patch)
}

/// How a patch seen from a reference keyframe looks from the query pose: the derivative of
/// the query pixel with respect to the reference pixel, for a surface through `point`
/// facing the reference camera (SVO's affine warp). Pixels are the ideal pinhole's.
/// `None` when the point is behind either camera.
pub fn viewpoint_warp(
    camera: &PinholeRadtan,
    reference: &StampedPose,
    reference_pixel: Point2<f64>,
    point: &Vector3<f64>,
    query: &StampedPose,
) -> Option<Matrix2<f64>> {
    let depth = (reference.rotation.inverse() * (point - reference.position)).z;
    if depth <= 1e-9 {
        return None;
    }
    let in_query = |pixel: Point2<f64>| {
        let ray = Vector3::new(
            (pixel.x - camera.cx) / camera.fx,
            (pixel.y - camera.cy) / camera.fy,
            1.0,
        );
        let world = reference.position + reference.rotation * (ray * depth);
        camera.project_undistorted(&(query.rotation.inverse() * (world - query.position)))
    };
    let centre = in_query(reference_pixel)?;
    let along_x = in_query(reference_pixel + Vector2::new(1.0, 0.0))? - centre;
    let along_y = in_query(reference_pixel + Vector2::new(0.0, 1.0))? - centre;
    Some(Matrix2::from_columns(&[along_x, along_y]))
}

/// Settings of one alignment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlignmentOptions {
    /// Gauss-Newton iterations at most (default 15: from within 3 px it converges in 3-6).
    pub max_iterations: usize,
    /// Step below which it has converged, pixels (default 0.01).
    pub converged_px: f64,
    /// Farthest the result may be from the prediction, pixels (default 3: the relocalizer's
    /// refinement inlier threshold; further, the prediction was not this point).
    pub max_shift_px: f64,
    /// Smallest normalised cross-correlation of the patch with the image at the result
    /// (default 0.8: an occluded or mismatched point correlates far less).
    pub min_correlation: f64,
    /// Largest area change of the viewpoint warp (default 2: beyond, the reference patch
    /// is too far from what the query sees).
    pub max_area_ratio: f64,
}

impl Default for AlignmentOptions {
    fn default() -> Self {
        Self {
            max_iterations: 15,
            converged_px: 0.01,
            max_shift_px: 3.0,
            min_correlation: 0.8,
            max_area_ratio: 2.0,
        }
    }
}

/// Where `patch` lies in `image` (raw pixels), starting from `predicted` and seen through
/// `warp` ([`viewpoint_warp`]); intensities may differ by a gain and an offset (exposure).
/// `None` when it leaves the image, does not converge within `options.max_shift_px`, or
/// correlates less than `options.min_correlation` there.
pub fn align_patch(
    image: &impl MatTraitConst,
    patch: &Patch,
    predicted: Point2<f64>,
    warp: &Matrix2<f64>,
    options: &AlignmentOptions,
) -> Option<Point2<f64>> {
    let area = warp.determinant();
    if !(area > 1.0 / options.max_area_ratio && area < options.max_area_ratio) {
        return None;
    }
    let sampler = Sampler::new(image)?;
    let offsets: Vec<Vector2<f64>> = (0..patch.len()).map(|i| warp * offset(i)).collect();
    let template: Vec<f64> = patch.iter().map(|&v| f64::from(v)).collect();
    // Inverse compositional (Baker and Matthews 2004): the Jacobian comes from the
    // template's gradient, carried into the query by the warp, so it and the normal
    // matrix are computed once and each iteration samples the image only. Parameters:
    // position (2), gain, bias; the residual is image - (gain * patch + bias).
    let to_query = warp.try_inverse()?.transpose();
    let jacobians: Vec<Vector4<f64>> = (0..patch.len())
        .map(|i| {
            let g = to_query * template_gradient(&template, i);
            Vector4::new(g.x, g.y, -template[i], -1.0)
        })
        .collect();
    let normal: Matrix4<f64> = jacobians.iter().map(|j| j * j.transpose()).sum();
    let normal = normal.try_inverse()?;
    let (mut position, mut gain, mut bias) = (predicted.coords, 1.0, 0.0);
    let mut converged = false;
    for _ in 0..options.max_iterations {
        let mut b = Vector4::<f64>::zeros();
        for ((d, t), jacobian) in offsets.iter().zip(&template).zip(&jacobians) {
            let residual = sampler.at(position + d)? - (gain * t + bias);
            b += jacobian * residual;
        }
        let step = -(normal * b);
        // The position's Jacobian assumed unit gain: scale its step back.
        position += Vector2::new(step[0], step[1]) / gain.max(0.1);
        gain += step[2];
        bias += step[3];
        if (position - predicted.coords).norm() > options.max_shift_px {
            return None;
        }
        if Vector2::new(step[0], step[1]).norm() < options.converged_px {
            converged = true;
            break;
        }
    }
    if !converged {
        return None;
    }
    let seen: Option<Vec<f64>> = offsets.iter().map(|d| sampler.at(position + d)).collect();
    (correlation(&template, &seen?) >= options.min_correlation).then_some(Point2::from(position))
}

/// Gradient of the template at sample `i`: central differences inside the patch, one-sided
/// on its border.
fn template_gradient(template: &[f64], i: usize) -> Vector2<f64> {
    let (x, y) = (i % PATCH_SIDE, i / PATCH_SIDE);
    let at = |x: usize, y: usize| template[y * PATCH_SIDE + x];
    let along = |lo: usize, hi: usize, value: &dyn Fn(usize) -> f64| {
        (value(hi) - value(lo)) / (hi - lo) as f64
    };
    let last = PATCH_SIDE - 1;
    let gx = along(x.saturating_sub(1), (x + 1).min(last), &|x| at(x, y));
    let gy = along(y.saturating_sub(1), (y + 1).min(last), &|y| at(x, y));
    Vector2::new(gx, gy)
}

/// Zero-mean normalised cross-correlation of two equally long samples.
fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        ab += (x - ma) * (y - mb);
        aa += (x - ma) * (x - ma);
        bb += (y - mb) * (y - mb);
    }
    if aa <= 0.0 || bb <= 0.0 {
        return 0.0;
    }
    ab / (aa * bb).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;
    use opencv::core::{Mat, Scalar};

    /// A smooth blob texture: intensity varies within a patch in both directions.
    fn image(shift: Vector2<f64>, gain: f64, bias: f64) -> Mat {
        let mut img =
            Mat::new_rows_cols_with_default(120, 160, CV_8UC1, Scalar::all(0.0)).expect("image");
        for y in 0..120 {
            for x in 0..160 {
                let (u, v) = (x as f64 - shift.x, y as f64 - shift.y);
                let value = 128.0
                    + 60.0 * (u / 7.0).sin() * (v / 5.0).cos()
                    + 30.0 * ((u + v) / 11.0).sin();
                *img.at_2d_mut::<u8>(y, x).expect("pixel") =
                    (gain * value + bias).round().clamp(0.0, 255.0) as u8;
            }
        }
        img
    }

    #[test]
    fn a_patch_is_found_to_a_fraction_of_a_pixel_under_a_shift_and_an_exposure_change() {
        let reference = image(Vector2::zeros(), 1.0, 0.0);
        let centre = Point2::new(60.3, 50.7);
        let patch = extract_patch(&reference, centre).expect("inside");
        let shift = Vector2::new(1.73, -1.21);
        let query = image(shift, 0.8, 20.0);
        let found = align_patch(
            &query,
            &patch,
            centre,
            &Matrix2::identity(),
            &AlignmentOptions::default(),
        )
        .expect("aligned");
        let error = (found - (centre + shift)).norm();
        assert!(error < 0.05, "{found} {error}");
        // Outside the image, and too far from the prediction: refused.
        assert!(extract_patch(&reference, Point2::new(2.0, 50.0)).is_none());
        let far = AlignmentOptions {
            max_shift_px: 1.0,
            ..AlignmentOptions::default()
        };
        assert!(align_patch(&query, &patch, centre, &Matrix2::identity(), &far).is_none());
    }

    #[test]
    fn the_viewpoint_warp_of_a_step_towards_a_wall_magnifies() {
        let camera =
            PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
        let pose = |z: f64| StampedPose {
            timestamp: 0.0,
            position: Vector3::new(0.0, 0.0, z),
            rotation: UnitQuaternion::identity(),
        };
        let point = Vector3::new(0.4, -0.2, 4.0);
        let pixel = camera.project_undistorted(&point).expect("in front");
        // 1 m closer to a point 4 m away: everything around it looks 4/3 as large.
        let warp = viewpoint_warp(&camera, &pose(0.0), pixel, &point, &pose(1.0)).expect("warp");
        assert!(
            (warp - Matrix2::identity() * (4.0 / 3.0)).norm() < 1e-9,
            "{warp}"
        );
        assert!(viewpoint_warp(&camera, &pose(0.0), pixel, &point, &pose(5.0)).is_none());
    }
}
