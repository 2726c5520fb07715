//! nerfstudio's transforms.json (the format `ns-process-data` writes and `ns-train`
//! reads): one camera's intrinsics, and per frame its image path relative to the json and
//! its camera-to-world matrix in OpenGL axes (x right, y up, z backwards); beside it
//! sparse_pc.ply, the coloured points splatfacto starts from.

use crate::{write_file, ExportError, ExportModel};
use egoslam_geometry::LensModel;
use serde_json::json;
use std::fmt::Write;
use std::path::Path;

/// File name of the point cloud referenced by `ply_file_path`.
pub const POINT_CLOUD: &str = "sparse_pc.ply";

/// The camera-to-world matrix in OpenGL axes: egoslam's camera looks down +z with y down
/// (OpenCV), so the y and z columns change sign.
fn transform_matrix(image: &crate::ExportImage) -> Vec<Vec<f64>> {
    let r = image.pose.rotation.to_rotation_matrix();
    let c = image.pose.position;
    (0..3)
        .map(|i| vec![r[(i, 0)], -r[(i, 1)], -r[(i, 2)], c[i]])
        .chain(std::iter::once(vec![0.0, 0.0, 0.0, 1.0]))
        .collect()
}

/// Writes transforms.json and sparse_pc.ply into `dir`; `file_path(i)` is image i's path
/// relative to `dir` (the caller puts the image there).
pub fn write(
    model: &ExportModel,
    dir: &Path,
    file_path: impl Fn(usize) -> String,
) -> Result<(), ExportError> {
    if model.images.is_empty() {
        return Err(ExportError::Empty("no posed keyframe".into()));
    }
    let c = &model.camera;
    let [k1, k2, p1, p2, k3] = c.distortion;
    // nerfstudio's OPENCV_FISHEYE reads k1..k4 (its `k4` key): the equidistant lens.
    let (camera_model, k3, k4, p1, p2) = match c.lens {
        LensModel::RadialTangential => ("OPENCV", k3, 0.0, p1, p2),
        LensModel::Equidistant => ("OPENCV_FISHEYE", p1, p2, 0.0, 0.0),
        LensModel::DoubleSphere => {
            return Err(ExportError::UnsupportedLens {
                format: "nerfstudio",
                lens: c.lens.name(),
            })
        }
    };
    let frames: Vec<serde_json::Value> = model
        .images
        .iter()
        .enumerate()
        .map(|(i, image)| {
            json!({
                "file_path": file_path(i),
                "transform_matrix": transform_matrix(image),
                "colmap_im_id": i + 1,
            })
        })
        .collect();
    let transforms = json!({
        "camera_model": camera_model,
        "w": c.width,
        "h": c.height,
        "fl_x": c.fx,
        "fl_y": c.fy,
        "cx": c.cx,
        "cy": c.cy,
        "k1": k1,
        "k2": k2,
        "k3": k3,
        "k4": k4,
        "p1": p1,
        "p2": p2,
        "ply_file_path": POINT_CLOUD,
        "frames": frames,
    });
    let text = serde_json::to_string_pretty(&transforms).unwrap_or_default();
    write_file(&dir.join("transforms.json"), &text)?;
    let mut ply = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\n\
         property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
         end_header\n",
        model.points.len()
    );
    for p in &model.points {
        let [r, g, b] = p.colour;
        let _ = writeln!(
            ply,
            "{} {} {} {r} {g} {b}",
            p.position.x as f32, p.position.y as f32, p.position.z as f32
        );
    }
    write_file(&dir.join(POINT_CLOUD), &ply)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::tests::scene;

    #[test]
    fn frames_carry_opengl_camera_to_world_matrices_and_their_paths() {
        let m = scene();
        let dir = tempfile::tempdir().expect("tempdir");
        write(&m, dir.path(), |i| format!("images/{i}.png")).expect("write");
        let t: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("transforms.json")).expect("json"),
        )
        .expect("valid json");
        assert_eq!(t["camera_model"], "OPENCV");
        assert_eq!(
            (t["w"].as_u64(), t["fl_y"].as_f64()),
            (Some(640), Some(510.0))
        );
        assert_eq!(t["k2"].as_f64(), Some(-0.05));
        let frames = t["frames"].as_array().expect("frames");
        assert_eq!(frames.len(), 3);
        assert_eq!(frames[1]["file_path"], "images/1.png");
        let m1: Vec<Vec<f64>> =
            serde_json::from_value(frames[1]["transform_matrix"].clone()).expect("4x4");
        // Centre in the last column; the camera's viewing direction (+z in OpenCV) is
        // minus the third column.
        assert!((m1[0][3] - 0.2).abs() < 1e-12);
        let forward = m.images[1].pose.rotation * nalgebra::Vector3::z();
        for (i, row) in m1.iter().take(3).enumerate() {
            assert!((row[2] + forward[i]).abs() < 1e-12);
        }
        assert_eq!(m1[3], vec![0.0, 0.0, 0.0, 1.0]);
        let ply = std::fs::read_to_string(dir.path().join(POINT_CLOUD)).expect("ply");
        assert!(ply.contains("element vertex 20\n"));
        assert_eq!(ply.lines().count(), 10 + 20);
    }
}
