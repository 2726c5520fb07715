//! ORB descriptors at tracked corners (Rublee et al., "ORB: an efficient alternative to SIFT
//! or SURF", ICCV 2011).
//!
//! Tracking stays KLT (the paper's choice); descriptors are only computed on keyframes, at
//! the corners the tracker already follows, so that every map point (a track) gets a
//! descriptor without a second detector. Query frames use the same corners (GFTT) and the
//! same descriptor, so map and query features are comparable. The orientation is ORB's
//! intensity centroid (computed here, because OpenCV's `compute` with provided keypoints
//! keeps the given angle), which makes the binary test pattern follow head roll.

use nalgebra::Point2;
use opencv::core::{KeyPoint, Mat, Ptr, ToInputArray, Vector, CV_8UC1};
use opencv::features2d::ORB;
use opencv::prelude::*;

/// A 256-bit ORB descriptor.
pub type Descriptor = [u8; 32];

/// Hamming distance between two descriptors (number of differing bits).
#[inline]
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    hamming_packed(&pack(a), &pack(b))
}

/// A descriptor as four 64-bit words, for fast distances.
pub type PackedDescriptor = [u64; 4];

/// The packed form of a descriptor.
pub fn pack(d: &Descriptor) -> PackedDescriptor {
    let mut out = [0u64; 4];
    for (i, word) in out.iter_mut().enumerate() {
        let mut bytes = [0u8; 8];
        bytes.copy_from_slice(&d[8 * i..8 * i + 8]);
        *word = u64::from_le_bytes(bytes);
    }
    out
}

#[inline(always)]
fn hamming_packed(a: &PackedDescriptor, b: &PackedDescriptor) -> u32 {
    (a[0] ^ b[0]).count_ones()
        + (a[1] ^ b[1]).count_ones()
        + (a[2] ^ b[2]).count_ones()
        + (a[3] ^ b[3]).count_ones()
}

fn hamming_all_portable(
    query: &PackedDescriptor,
    candidates: &[PackedDescriptor],
    out: &mut Vec<u32>,
) {
    out.clear();
    out.extend(candidates.iter().map(|c| hamming_packed(query, c)));
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
fn hamming_all_popcnt(
    query: &PackedDescriptor,
    candidates: &[PackedDescriptor],
    out: &mut Vec<u32>,
) {
    out.clear();
    out.extend(candidates.iter().map(|c| hamming_packed(query, c)));
}

/// Distances from `query` to every candidate, into `out`. Matching is the relocalizer's
/// hot loop: on x86-64 the POPCNT instruction (not in the baseline target, so detected at
/// run time) makes it ~3x faster than the portable bit count.
pub fn hamming_all(query: &PackedDescriptor, candidates: &[PackedDescriptor], out: &mut Vec<u32>) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("popcnt") {
        // SAFETY: the CPU supports POPCNT (checked just above).
        unsafe { hamming_all_popcnt(query, candidates, out) };
        return;
    }
    hamming_all_portable(query, candidates, out);
}

/// Why descriptors could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum DescriptorError {
    /// The image is not 8-bit single channel.
    #[error("descriptors need an 8-bit grey image, got OpenCV type {0}")]
    NotGrey(i32),
    /// An OpenCV call failed.
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// Settings of the ORB describer; defaults are ORB's own.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DescriberOptions {
    /// Side of the sampling patch, pixels (default 31, ORB's; the orientation uses the
    /// inscribed disc of radius 15).
    pub patch_size: i32,
    /// Corners closer than this to the border get no descriptor (default 16: half the patch
    /// plus one, so that the rotated pattern stays inside the image).
    pub border_px: f32,
}

impl Default for DescriberOptions {
    fn default() -> Self {
        Self {
            patch_size: 31,
            border_px: 16.0,
        }
    }
}

/// Computes ORB descriptors at given corners.
pub struct OrbDescriber {
    orb: Ptr<ORB>,
    options: DescriberOptions,
}

impl OrbDescriber {
    /// A describer with one pyramid level: the corners come from the full-resolution image.
    pub fn new(options: DescriberOptions) -> Result<Self, DescriptorError> {
        let orb = ORB::create(
            1,
            1.2,
            1,
            options.patch_size,
            0,
            2,
            opencv::features2d::ORB_ScoreType::HARRIS_SCORE,
            options.patch_size,
            20,
        )?;
        Ok(Self { orb, options })
    }

    /// Descriptors at `corners` (raw pixels of `image`): `None` where a corner lies too
    /// close to the border.
    pub fn describe(
        &mut self,
        image: &(impl MatTraitConst + ToInputArray),
        corners: &[Point2<f32>],
    ) -> Result<Vec<Option<Descriptor>>, DescriptorError> {
        if image.typ() != CV_8UC1 {
            return Err(DescriptorError::NotGrey(image.typ()));
        }
        let (w, h) = (image.cols() as f32, image.rows() as f32);
        let m = self.options.border_px;
        let inside: Vec<usize> = (0..corners.len())
            .filter(|&i| {
                let p = corners[i];
                p.x >= m && p.y >= m && p.x < w - m && p.y < h - m
            })
            .collect();
        let step = image
            .mat_step()
            .first()
            .copied()
            .unwrap_or(image.cols() as usize);
        let angles = intensity_centroid_angles(image.data_bytes()?, step, corners, &inside);
        let mut keypoints = Vector::<KeyPoint>::new();
        for (&i, angle) in inside.iter().zip(angles) {
            let p = corners[i];
            keypoints.push(KeyPoint::new_coords(
                p.x,
                p.y,
                self.options.patch_size as f32,
                angle,
                0.0,
                0,
                i as i32,
            )?);
        }
        let mut out = vec![None; corners.len()];
        if keypoints.is_empty() {
            return Ok(out);
        }
        let mut descriptors = Mat::default();
        self.orb.compute(image, &mut keypoints, &mut descriptors)?;
        for (row, kp) in keypoints.iter().enumerate() {
            let bytes = descriptors.at_row::<u8>(row as i32)?;
            if let (Ok(d), Some(slot)) = (
                <Descriptor>::try_from(bytes),
                out.get_mut(kp.class_id() as usize),
            ) {
                *slot = Some(d);
            }
        }
        Ok(out)
    }
}

/// ORB's orientation: the angle (degrees, OpenCV's convention) of the vector from the corner
/// to the intensity centroid of the disc of radius 15 around it (Rosin 1999), for the
/// corners `which` (at least 16 px inside the image). Not generic over the image type, so
/// that it is compiled optimised in this crate whatever the caller's profile.
fn intensity_centroid_angles(
    data: &[u8],
    step: usize,
    corners: &[Point2<f32>],
    which: &[usize],
) -> Vec<f32> {
    const R: i32 = 15;
    let half: Vec<i32> = (-R..=R)
        .map(|dy| f64::from(R * R - dy * dy).sqrt() as i32)
        .collect();
    which
        .iter()
        .map(|&i| {
            let (cx, cy) = (corners[i].x.round() as i32, corners[i].y.round() as i32);
            // Per row: the sum of the intensities and of their offsets from the row's
            // start times them, in i32 (at most 31 * 255 * 30 per row); the moment about
            // the centre is the second minus `half` times the first. m01 takes dy times
            // the sum. A plain slice walk, which the compiler vectorises.
            let (mut m01, mut m10) = (0i64, 0i64);
            for (dy, &half) in (-R..=R).zip(&half) {
                let start = (cy + dy) as usize * step + (cx - half) as usize;
                let row = &data[start..start + 2 * half as usize + 1];
                let (mut sum, mut moment) = (0i32, 0i32);
                for (k, &v) in row.iter().enumerate() {
                    sum += i32::from(v);
                    moment += k as i32 * i32::from(v);
                }
                m10 += i64::from(moment - half * sum);
                m01 += i64::from(dy) * i64::from(sum);
            }
            let a = (m01 as f32).atan2(m10 as f32).to_degrees();
            if a < 0.0 {
                a + 360.0
            } else {
                a
            }
        })
        .collect()
}

/// Settings of corner detection on query frames (the tracker's detector, full resolution).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QueryCornerOptions {
    /// Corners per frame (default 1000: the tracker's track count, so a query sees as many
    /// features as a keyframe).
    pub max_corners: i32,
    /// GFTT quality relative to the best corner (default 0.001, the tracker's).
    pub quality: f64,
    /// Minimum distance between corners, pixels (default 10, the tracker's).
    pub min_distance_px: f64,
}

impl Default for QueryCornerOptions {
    fn default() -> Self {
        Self {
            max_corners: 1000,
            quality: 0.001,
            min_distance_px: 10.0,
        }
    }
}

/// GFTT corners of a query frame (raw pixels).
pub fn detect_corners(
    image: &Mat,
    options: &QueryCornerOptions,
) -> Result<Vec<Point2<f32>>, DescriptorError> {
    if image.typ() != CV_8UC1 {
        return Err(DescriptorError::NotGrey(image.typ()));
    }
    let mut corners = Vector::<opencv::core::Point2f>::new();
    opencv::imgproc::good_features_to_track(
        image,
        &mut corners,
        options.max_corners,
        options.quality,
        options.min_distance_px,
        &opencv::core::no_array(),
        3,
        false,
        0.04,
    )?;
    Ok(corners.iter().map(|c| Point2::new(c.x, c.y)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Point2f, Scalar};

    fn textured(w: i32, h: i32, seed: u64) -> Mat {
        let mut state = seed;
        let mut img =
            Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).expect("image");
        // Blocks of random grey: corners everywhere, deterministic.
        for by in 0..h / 8 {
            for bx in 0..w / 8 {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let v = (state >> 56) as f64;
                opencv::imgproc::rectangle(
                    &mut img,
                    opencv::core::Rect::new(bx * 8, by * 8, 8, 8),
                    Scalar::all(v),
                    -1,
                    opencv::imgproc::LINE_8,
                    0,
                )
                .expect("draw");
            }
        }
        let mut blurred = Mat::default();
        opencv::imgproc::gaussian_blur_def(&img, &mut blurred, opencv::core::Size::new(5, 5), 1.0)
            .expect("blur");
        blurred
    }

    #[test]
    fn orientation_row_sums_equal_the_per_pixel_moments() {
        let img = textured(96, 80, 5);
        let step = img.cols() as usize;
        let data = img.data_bytes().expect("bytes");
        let corners: Vec<Point2<f32>> = (0..40)
            .map(|k| {
                Point2::new(
                    16.0 + (k * 7 % 60) as f32 + 0.4,
                    16.0 + (k * 11 % 46) as f32,
                )
            })
            .collect();
        let which: Vec<usize> = (0..corners.len()).collect();
        let fast = intensity_centroid_angles(data, step, &corners, &which);
        for (c, angle) in corners.iter().zip(fast) {
            let (cx, cy) = (c.x.round() as i64, c.y.round() as i64);
            let (mut m01, mut m10) = (0i64, 0i64);
            for dy in -15i64..=15 {
                let half = ((225 - dy * dy) as f64).sqrt() as i64;
                for dx in -half..=half {
                    let v = i64::from(data[((cy + dy) * step as i64 + cx + dx) as usize]);
                    m10 += dx * v;
                    m01 += dy * v;
                }
            }
            let a = (m01 as f32).atan2(m10 as f32).to_degrees();
            assert_eq!(angle, if a < 0.0 { a + 360.0 } else { a });
        }
    }

    #[test]
    fn descriptors_follow_the_corner_under_rotation_and_refuse_the_border() {
        let img = textured(320, 240, 3);
        let corners = detect_corners(&img, &QueryCornerOptions::default()).expect("corners");
        assert!(corners.len() > 200, "{}", corners.len());
        let mut describer = OrbDescriber::new(DescriberOptions::default()).expect("orb");
        let mut probe = corners.clone();
        probe.push(Point2::new(3.0, 3.0));
        let d = describer.describe(&img, &probe).expect("describe");
        assert!(
            d.last().expect("probe").is_none(),
            "border corner described"
        );
        // Rotate the image 20 deg about its centre: the same corner keeps a close descriptor
        // thanks to the orientation, while other corners are far.
        let centre = Point2f::new(160.0, 120.0);
        let rot = opencv::imgproc::get_rotation_matrix_2d(centre, 20.0, 1.0).expect("rot");
        let mut rotated = Mat::default();
        opencv::imgproc::warp_affine_def(&img, &mut rotated, &rot, img.size().expect("size"))
            .expect("warp");
        let (a, b) = (20.0f32.to_radians().cos(), 20.0f32.to_radians().sin());
        let mut close = 0;
        let mut tried = 0;
        for (c, desc) in corners.iter().zip(&d) {
            let (dx, dy) = (c.x - 160.0, c.y - 120.0);
            if dx * dx + dy * dy > 70.0 * 70.0 {
                continue;
            }
            let Some(desc) = desc else { continue };
            // warpAffine with a positive angle turns the image counter-clockwise.
            let moved = Point2::new(160.0 + a * dx + b * dy, 120.0 - b * dx + a * dy);
            let Some(Some(other)) = describer.describe(&rotated, &[moved]).expect("d").pop() else {
                continue;
            };
            tried += 1;
            if hamming(desc, &other) < 64 {
                close += 1;
            }
        }
        assert!(tried > 30, "{tried}");
        assert!(close * 10 >= tried * 7, "{close} of {tried} within 64 bits");
        assert_eq!(hamming(&[0xff; 32], &[0; 32]), 256);
        let described: Vec<Descriptor> = d.iter().flatten().copied().collect();
        let (a, b) = (described[0], described[1]);
        let mut all = Vec::new();
        hamming_all(&pack(&a), &[pack(&b), pack(&a)], &mut all);
        assert_eq!(all, vec![hamming(&a, &b), 0]);
    }
}
