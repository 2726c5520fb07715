//! COLMAP's text model (cameras.txt, images.txt, points3D.txt), as COLMAP's
//! `model_converter` and pycolmap read it. COLMAP puts the centre of the top-left pixel at
//! (0.5, 0.5) and OpenCV at (0, 0): principal point and keypoints are shifted by half a
//! pixel.

use crate::{write_file, ExportError, ExportModel};
use egoslam_geometry::LensModel;
use std::fmt::Write;
use std::path::Path;

/// COLMAP's camera model and parameters for the calibration: PINHOLE without
/// distortion, OPENCV for k1 k2 p1 p2, FULL_OPENCV when k3 is used, OPENCV_FISHEYE for an
/// equidistant lens (COLMAP has no double sphere).
fn camera_line(model: &ExportModel) -> Result<String, ExportError> {
    let c = &model.camera;
    let [k1, k2, p1, p2, k3] = c.distortion;
    let (cx, cy) = (c.cx + 0.5, c.cy + 0.5);
    let (name, params) = if c.lens == LensModel::Equidistant {
        ("OPENCV_FISHEYE", vec![c.fx, c.fy, cx, cy, k1, k2, p1, p2])
    } else if c.lens != LensModel::RadialTangential {
        return Err(ExportError::UnsupportedLens {
            format: "COLMAP",
            lens: c.lens.name(),
        });
    } else if c.is_rectified() {
        ("PINHOLE", vec![c.fx, c.fy, cx, cy])
    } else if k3 == 0.0 {
        ("OPENCV", vec![c.fx, c.fy, cx, cy, k1, k2, p1, p2])
    } else {
        (
            "FULL_OPENCV",
            vec![c.fx, c.fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0],
        )
    };
    let params: Vec<String> = params.iter().map(|p| format!("{p}")).collect();
    Ok(format!(
        "1 {name} {} {} {}\n",
        c.width,
        c.height,
        params.join(" ")
    ))
}

/// Writes the three files into `dir` (which must exist).
pub fn write(model: &ExportModel, dir: &Path) -> Result<(), ExportError> {
    if model.images.is_empty() {
        return Err(ExportError::Empty("no posed keyframe".into()));
    }
    let cameras = format!(
        "# Camera list with one line of data per camera:\n\
         #   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n\
         # Number of cameras: 1\n{}",
        camera_line(model)?
    );
    let mut images = String::from(
        "# Image list with two lines of data per image:\n\
         #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
         #   POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    for (i, image) in model.images.iter().enumerate() {
        // COLMAP stores cam_from_world; egoslam's poses are world_from_camera.
        let rotation = image.pose.rotation.inverse();
        let translation = -(rotation * image.pose.position);
        let q = rotation.quaternion();
        let _ = writeln!(
            images,
            "{} {} {} {} {} {} {} {} 1 {}",
            i + 1,
            q.w,
            q.i,
            q.j,
            q.k,
            translation.x,
            translation.y,
            translation.z,
            image.name
        );
        let keypoints: Vec<String> = image
            .keypoints
            .iter()
            .map(|k| format!("{} {} {}", k.pixel.x + 0.5, k.pixel.y + 0.5, k.point))
            .collect();
        let _ = writeln!(images, "{}", keypoints.join(" "));
    }
    let mut points = String::from(
        "# 3D point list with one line of data per point:\n\
         #   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
    );
    for p in &model.points {
        let track: Vec<String> = p
            .track
            .iter()
            .map(|(image, keypoint)| format!("{} {keypoint}", image + 1))
            .collect();
        let [r, g, b] = p.colour;
        let _ = writeln!(
            points,
            "{} {} {} {} {r} {g} {b} {} {}",
            p.id,
            p.position.x,
            p.position.y,
            p.position.z,
            p.error,
            track.join(" ")
        );
    }
    write_file(&dir.join("cameras.txt"), &cameras)?;
    write_file(&dir.join("images.txt"), &images)?;
    write_file(&dir.join("points3D.txt"), &points)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::tests::scene;

    #[test]
    fn the_model_is_written_as_colmap_reads_it() {
        let m = scene();
        let dir = tempfile::tempdir().expect("tempdir");
        write(&m, dir.path()).expect("write");
        let cameras = std::fs::read_to_string(dir.path().join("cameras.txt")).expect("cameras");
        let line = cameras
            .lines()
            .find(|l| !l.starts_with('#'))
            .expect("camera");
        assert_eq!(
            line,
            "1 OPENCV 640 480 500 510 320.5 240.5 0.1 -0.05 0.001 0.002"
        );
        let images = std::fs::read_to_string(dir.path().join("images.txt")).expect("images");
        let rows: Vec<&str> = images.lines().filter(|l| !l.starts_with('#')).collect();
        assert_eq!(rows.len(), 6);
        // The second camera stands at x = 0.2 turned 0.05 rad about y: t = -R^T c.
        let second: Vec<f64> = rows[2]
            .split(' ')
            .take(8)
            .map(|v| v.parse().expect("number"))
            .collect();
        let (qw, qy, tx) = (second[1], second[3], second[5]);
        assert!((qw - (0.025f64).cos()).abs() < 1e-12 && (qy + (0.025f64).sin()).abs() < 1e-12);
        assert!((tx + 0.2 * (0.05f64).cos()).abs() < 1e-12, "{tx}");
        assert!(rows[2].ends_with(" 1 rgb/100.5.png"), "{}", rows[2]);
        assert_eq!(rows[3].split(' ').count(), 20 * 3);
        let points = std::fs::read_to_string(dir.path().join("points3D.txt")).expect("points");
        let rows: Vec<&str> = points.lines().filter(|l| !l.starts_with('#')).collect();
        assert_eq!(rows.len(), 20);
        // id x y z r g b error, then three (image, keypoint) pairs.
        assert_eq!(rows[0].split(' ').count(), 8 + 6);
        assert!(
            rows[0].starts_with("1000 -1 -0.75 4 128 128 128 "),
            "{}",
            rows[0]
        );
    }

    #[test]
    fn no_keyframe_is_an_error() {
        let mut m = scene();
        m.images.clear();
        let dir = tempfile::tempdir().expect("tempdir");
        assert!(matches!(write(&m, dir.path()), Err(ExportError::Empty(_))));
    }
}
