//! Fisheye frames from a cube map: the scene is rendered by the pinhole renderer onto the
//! five faces of a cube around the camera (front, right, left, up, down: a fisheye sees
//! at most a little past 90 degrees off its axis, never behind), and each fisheye pixel
//! looks its ray up on the face it crosses, bilinearly (as test beds resample real
//! fisheye footage; the faces' texture is band-limited at their own resolution, which
//! matches the fisheye's at the image centre and is finer off it).

use crate::render::{add_noise, render_frame, Frame, RenderOptions};
use crate::scene::Scene;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Matrix3, Point2, Rotation3, UnitQuaternion, Vector3};

/// Errors of a fisheye render.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FisheyeRenderError {
    #[error("the camera is not a fisheye ({0})")]
    NotFisheye(&'static str),
    #[error("a rolling shutter is not rendered through a fisheye")]
    RollingShutter,
}

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
    if options.rolling_shutter {
        return Err(FisheyeRenderError::RollingShutter);
    }
    // A face of 90 degrees with the fisheye's pixels per radian at its centre.
    let side = (2.0 * camera.fx.max(camera.fy)).ceil().max(8.0) as u32;
    let half = f64::from(side) / 2.0;
    let face_camera =
        PinholeRadtan::new(side, side, [half, half, half - 0.5, half - 0.5], [0.0; 5])
            .map_err(|_| FisheyeRenderError::NotFisheye("face"))?;
    let face_options = RenderOptions {
        noise_sigma: 0.0,
        ..*options
    };
    let rotations = faces();
    let rendered: Vec<Frame> = rotations
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
        .collect();
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut grey = vec![0f64; w * h];
    let mut depth = vec![0f32; w * h];
    for row in 0..h {
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
            let face = &rendered[k];
            let i = row * w + col;
            grey[i] = bilinear(face, u, v);
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
}
