//! Fisheye frames from a cube map: the scene is rendered by the pinhole renderer onto the
//! five faces of a cube around the camera (front, right, left, up, down: a fisheye sees
//! at most a little past 90 degrees off its axis, never behind), and each fisheye pixel
//! looks its ray up on the face it crosses, bilinearly (as test beds resample real
//! fisheye footage; the faces' texture is band-limited at their own resolution, which
//! matches the fisheye's at the image centre and is finer off it). A rolling shutter is
//! drawn from cube maps rendered at a few moments of the readout ([`ROLLING_SLICES`]):
//! each row cross-fades the two taken nearest its own exposure.

use crate::render::{add_noise, pose_at_time, render_frame, Frame, RenderOptions};
use crate::scene::Scene;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Matrix3, Point2, Rotation3, UnitQuaternion, Vector3};

/// Errors of a fisheye render.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FisheyeRenderError {
    #[error("the camera is not a fisheye ({0})")]
    NotFisheye(&'static str),
}

/// Moments of the readout a rolling-shutter fisheye frame's cube maps are rendered at (9:
/// a row is at most 1/16 of the readout from one, 1.25 ms of a 20 ms readout, a quarter
/// of a pixel at 260 px/rad for a 50 deg/s head turn, and it cross-fades the two either
/// side; each costs the five faces again).
pub const ROLLING_SLICES: usize = 9;

/// The cube's faces as rotations camera <- face (columns: the face's x, y, z axes in the
/// camera frame; y points down as in every camera frame here).
fn faces() -> [Matrix3<f64>; 5] {
    let face = |x: [f64; 3], y: [f64; 3], z: [f64; 3]| {
        Matrix3::from_columns(&[Vector3::from(x), Vector3::from(y), Vector3::from(z)])
    };
    [
        Matrix3::identity(),
        face([0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]),
        face([0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]),
        face([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]),
        face([1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]),
    ]
}

/// Renders `poses` (one, or a blurred frame's sub-poses) through the fisheye `camera`.
pub fn render_fisheye_frame(
    scene: &Scene,
    camera: &PinholeRadtan,
    poses: &[StampedPose],
    index: u64,
    options: &RenderOptions,
) -> Result<Frame, FisheyeRenderError> {
    if !camera.lens.is_fisheye() {
        return Err(FisheyeRenderError::NotFisheye(camera.lens.name()));
    }
    // A face of 90 degrees with the fisheye's pixels per radian at its centre.
    let side = (2.0 * camera.fx.max(camera.fy)).ceil().max(8.0) as u32;
    let half = f64::from(side) / 2.0;
    let face_camera =
        PinholeRadtan::new(side, side, [half, half, half - 0.5, half - 0.5], [0.0; 5])
            .map_err(|_| FisheyeRenderError::NotFisheye("face"))?;
    // Each face is a global-shutter render of its moment (one per readout slice below).
    let face_options = RenderOptions {
        noise_sigma: 0.0,
        rolling_shutter: false,
        ..*options
    };
    let rotations = faces();
    let cube = |poses: &[StampedPose]| -> Vec<Frame> {
        rotations
            .iter()
            .map(|camera_from_face| {
                let turn = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
                    *camera_from_face,
                ));
                let face_poses: Vec<StampedPose> = poses
                    .iter()
                    .map(|p| StampedPose {
                        rotation: p.rotation * turn,
                        ..*p
                    })
                    .collect();
                render_frame(scene, &face_camera, &face_poses, index, &face_options)
            })
            .collect()
    };
    // One cube map for a global shutter; for a rolling one, one per moment of the poses'
    // span, each from the single pose of that moment.
    let readout = Readout::of(options);
    let cubes: Vec<Vec<Frame>> = match (poses.first(), poses.last()) {
        (Some(first), Some(last)) if options.rolling_shutter && poses.len() > 1 => {
            let span = last.timestamp - first.timestamp;
            (0..readout.slices)
                .filter_map(|k| {
                    let t = first.timestamp + span * k as f64 / (readout.slices - 1) as f64;
                    pose_at_time(poses, t)
                })
                .map(|pose| cube(&[pose]))
                .collect()
        }
        _ => vec![cube(poses)],
    };
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut grey = vec![0f64; w * h];
    let mut depth = vec![0f32; w * h];
    let slice_of = |moment: f64| moment * (cubes.len() - 1) as f64;
    for row in 0..h {
        let row_fraction = if h > 1 {
            row as f64 / (h - 1) as f64
        } else {
            0.0
        };
        // The row's exposure: its moments, each between two of the cube maps (one map, one
        // moment for a global shutter); its depth from the map nearest its middle.
        let moments = readout.moments(row_fraction);
        let middle = (slice_of(readout.middle(row_fraction)).round() as usize).min(cubes.len() - 1);
        for col in 0..w {
            // As the pinhole renderer: pixel (col, row) shows the ray through its centre.
            let centre = Point2::new(col as f64 + 0.5, row as f64 + 0.5);
            let Some(ray) = camera.bearing_from_raw(centre) else {
                continue;
            };
            let (k, face_from_camera) = rotations
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.column(2).dot(&ray).total_cmp(&b.1.column(2).dot(&ray)))
                .map(|(k, r)| (k, r.transpose()))
                .unwrap_or((0, Matrix3::identity()));
            let d = face_from_camera * ray;
            if d.z <= 1e-9 {
                continue;
            }
            let u = half * d.x / d.z + half - 0.5;
            let v = half * d.y / d.z + half - 0.5;
            let i = row * w + col;
            grey[i] = moments
                .iter()
                .map(|m| {
                    let at = slice_of(*m);
                    let before = (at.floor() as usize).min(cubes.len() - 1);
                    let after = (before + 1).min(cubes.len() - 1);
                    let share = at - before as f64;
                    let here = bilinear(&cubes[before][k], u, v);
                    // A global shutter (one map) or a moment on a map: nothing to fade.
                    if after == before || share == 0.0 {
                        return here;
                    }
                    (1.0 - share) * here + share * bilinear(&cubes[after][k], u, v)
                })
                .sum::<f64>()
                / moments.len() as f64;
            let face = &cubes[middle][k];
            let last = f64::from(side - 1);
            let (nu, nv) = (u.round().clamp(0.0, last), v.round().clamp(0.0, last));
            let face_depth = f64::from(face.depth[nv as usize * side as usize + nu as usize]);
            // The face's z-depth along the ray, then along the fisheye's axis.
            depth[i] = (face_depth / d.z * ray.z).max(0.0) as f32;
        }
    }
    Ok(Frame {
        width: camera.width,
        height: camera.height,
        grey: add_noise(&grey, index, options.noise_sigma),
        depth,
    })
}

/// When a rolling-shutter frame's rows are exposed, as fractions of the span of the poses
/// it is given (0: the first row's exposure starts, 1: the last row's ends), and how many
/// cube maps over that span render it.
struct Readout {
    /// [`RenderOptions::rolling_exposure`]: the share of the span one row's exposure takes.
    exposure: f64,
    /// Moments averaged over a row's exposure (1 without blur).
    samples: usize,
    slices: usize,
}

impl Readout {
    fn of(options: &RenderOptions) -> Self {
        let exposure = options.rolling_exposure.clamp(0.0, 1.0);
        let samples = if exposure > 0.0 {
            options.blur_samples.max(1)
        } else {
            1
        };
        // With blur, enough maps that a row's exposure spans one per moment it averages
        // (`samples` over `exposure` of the span), so blurring costs maps, not renders per
        // moment (a 20 ms readout and 9 blur moments: 19 maps, not 9 x 9).
        let for_blur = if samples > 1 {
            ((samples - 1) as f64 / exposure).ceil() as usize + 1
        } else {
            0
        };
        Self {
            exposure,
            samples,
            slices: ROLLING_SLICES.max(for_blur.min(4 * ROLLING_SLICES)),
        }
    }

    /// The moments the row at `fraction` (0: first row, 1: last) averages over its
    /// exposure.
    fn moments(&self, fraction: f64) -> Vec<f64> {
        let start = fraction * (1.0 - self.exposure);
        (0..self.samples)
            .map(|j| {
                let within = if self.samples > 1 {
                    j as f64 / (self.samples - 1) as f64
                } else {
                    0.0
                };
                start + self.exposure * within
            })
            .collect()
    }

    /// The middle of that row's exposure (its depth is drawn from there).
    fn middle(&self, fraction: f64) -> f64 {
        fraction * (1.0 - self.exposure) + 0.5 * self.exposure
    }
}

/// The face's grey level at `(u, v)`, bilinear, clamped at its border.
fn bilinear(face: &Frame, u: f64, v: f64) -> f64 {
    let (w, h) = (face.width as usize, face.height as usize);
    let u = u.clamp(0.0, (w - 1) as f64);
    let v = v.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (u.floor() as usize, v.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (u - x0 as f64, v - y0 as f64);
    let at = |x: usize, y: usize| f64::from(face.grey[y * w + x]);
    let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
    let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
    top * (1.0 - fy) + bottom * fy
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_geometry::LensModel;

    #[test]
    fn the_faces_are_rotations_looking_along_their_axes() {
        let axes = [
            Vector3::z(),
            Vector3::x(),
            -Vector3::x(),
            -Vector3::y(),
            Vector3::y(),
        ];
        for (r, axis) in faces().iter().zip(axes) {
            assert!((r.determinant() - 1.0).abs() < 1e-12);
            assert!((r * r.transpose() - Matrix3::identity()).norm() < 1e-12);
            assert!((r.column(2) - axis).norm() < 1e-12);
        }
    }

    #[test]
    fn a_fisheye_frame_sees_the_scene_where_the_lens_puts_it() {
        // The room seen through an ideal equidistant lens and through a pinhole of the
        // same focal: near the centre both images agree (the lens is nearly a pinhole
        // there), and the fisheye sees the whole wide field the pinhole cannot.
        let scene = Scene::room(3);
        let pose = StampedPose {
            timestamp: 0.0,
            position: Vector3::new(0.0, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        };
        let options = RenderOptions {
            noise_sigma: 0.0,
            threads: 2,
            ..RenderOptions::default()
        };
        let pinhole =
            PinholeRadtan::new(160, 120, [65.0, 65.0, 79.5, 59.5], [0.0; 5]).expect("camera");
        let fisheye = pinhole.with_lens(LensModel::Equidistant).expect("fisheye");
        let flat = render_frame(&scene, &pinhole, &[pose], 0, &options);
        let wide = render_fisheye_frame(&scene, &fisheye, &[pose], 0, &options).expect("fisheye");
        let (mut diff, mut n) = (0.0, 0);
        for row in 50..70 {
            for col in 70..90 {
                let i = row * 160 + col;
                diff += (f64::from(flat.grey[i]) - f64::from(wide.grey[i])).abs();
                n += 1;
            }
        }
        assert!(
            diff / (n as f64) < 12.0,
            "mean grey difference at the centre {}",
            diff / n as f64
        );
        let seen = wide.depth.iter().filter(|d| **d > 0.0).count();
        assert!(seen > 160 * 120 * 9 / 10, "{seen} pixels with depth");
        assert!(render_fisheye_frame(&scene, &pinhole, &[pose], 0, &options).is_err());
    }

    #[test]
    fn a_rolling_shutter_fisheye_shows_each_row_from_its_own_moment() {
        // The head turns 8 deg about the vertical axis during the readout: the first rows
        // must look as the first pose sees them, the last rows as the last pose does.
        let scene = Scene::room(3);
        let turn = |deg: f64| StampedPose {
            timestamp: deg / 400.0,
            position: Vector3::zeros(),
            rotation: UnitQuaternion::from_euler_angles(0.0, deg.to_radians(), 0.0),
        };
        let readout: Vec<StampedPose> = (0..=8).map(|d| turn(f64::from(d))).collect();
        let options = RenderOptions {
            noise_sigma: 0.0,
            threads: 2,
            rolling_shutter: true,
            ..RenderOptions::default()
        };
        let global = RenderOptions {
            rolling_shutter: false,
            ..options
        };
        let camera = PinholeRadtan::new(160, 120, [65.0, 65.0, 79.5, 59.5], [0.0; 5])
            .expect("camera")
            .with_lens(LensModel::Equidistant)
            .expect("fisheye");
        let rolling = render_fisheye_frame(&scene, &camera, &readout, 0, &options).expect("rs");
        let at = |pose: StampedPose| {
            render_fisheye_frame(&scene, &camera, &[pose], 0, &global).expect("global")
        };
        let (first, last) = (at(turn(0.0)), at(turn(8.0)));
        let difference = |a: &Frame, b: &Frame, rows: std::ops::Range<usize>| {
            let mut sum = 0.0;
            let mut n = 0.0;
            for row in rows {
                for col in 30..130 {
                    let i = row * 160 + col;
                    sum += (f64::from(a.grey[i]) - f64::from(b.grey[i])).abs();
                    n += 1.0;
                }
            }
            sum / n
        };
        let (top, bottom) = (0..3, 117..120);
        assert!(difference(&rolling, &first, top.clone()) < 1.5);
        assert!(difference(&rolling, &last, bottom.clone()) < 1.5);
        // And the turn is visible there: each pose alone differs in the other's rows.
        assert!(difference(&rolling, &last, top.clone()) > 3.0);
        assert!(difference(&rolling, &first, bottom.clone()) > 3.0);
        // With blur, each row exposed over half the span: the first rows average the first
        // half's poses, the last rows the second half's.
        let blurred = RenderOptions {
            rolling_exposure: 0.5,
            blur_samples: 5,
            ..options
        };
        let rolling = render_fisheye_frame(&scene, &camera, &readout, 0, &blurred).expect("rs");
        let over = |degrees: [f64; 5]| {
            let poses: Vec<StampedPose> = degrees.iter().map(|d| turn(*d)).collect();
            render_fisheye_frame(&scene, &camera, &poses, 0, &global).expect("blurred")
        };
        let (early, late) = (
            over([0.0, 1.0, 2.0, 3.0, 4.0]),
            over([4.0, 5.0, 6.0, 7.0, 8.0]),
        );
        assert!(difference(&rolling, &early, top.clone()) < 1.0);
        assert!(difference(&rolling, &late, bottom.clone()) < 1.0);
        assert!(difference(&rolling, &late, top) > 3.0);
        assert!(difference(&rolling, &early, bottom) > 3.0);
    }
}
