//! `egoslam export` of a real run (the embedded TUM clip): the COLMAP model's cameras stand
//! where the ground truth puts them and its keypoints are where its camera model projects
//! its points; nerfstudio's transforms.json names images that exist.

mod common;

use common::*;
use egoslam_geometry::{absolute_trajectory_error, StampedPose};
use egoslam_sources::ground_truth::read_tum_file;
use nalgebra::{Point2, Quaternion, UnitQuaternion, Vector3};
use std::collections::BTreeMap;
use std::path::Path;

fn numbers(line: &str) -> Vec<f64> {
    line.split_whitespace()
        .map(|v| v.parse().expect("number"))
        .collect()
}

/// (timestamp, cam_from_world rotation, translation, keypoints (x, y, point id)) per image.
type Image = (
    f64,
    UnitQuaternion<f64>,
    Vector3<f64>,
    Vec<(Point2<f64>, u64)>,
);

fn images(dir: &Path) -> Vec<Image> {
    let text = std::fs::read_to_string(dir.join("images.txt")).expect("images.txt");
    let rows: Vec<&str> = text.lines().filter(|l| !l.starts_with('#')).collect();
    rows.chunks(2)
        .map(|pair| {
            let head: Vec<&str> = pair[0].split(' ').collect();
            let v: Vec<f64> = head[1..8]
                .iter()
                .map(|x| x.parse().expect("number"))
                .collect();
            let name = head[9];
            assert!(
                name.starts_with("rgb/"),
                "the input's own image name: {name}"
            );
            let stem = Path::new(name)
                .file_stem()
                .and_then(|s| s.to_str())
                .expect("stem");
            let keypoints = numbers(pair[1])
                .chunks(3)
                .map(|k| (Point2::new(k[0], k[1]), k[2] as u64))
                .collect();
            (
                stem.parse().expect("timestamp name"),
                UnitQuaternion::from_quaternion(Quaternion::new(v[0], v[1], v[2], v[3])),
                Vector3::new(v[4], v[5], v[6]),
                keypoints,
            )
        })
        .collect()
}

#[test]
fn a_run_exports_to_colmap_and_nerfstudio() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out");
    let report = run_report(&tum_fixture(), &out);
    let colmap = dir.path().join("colmap");
    let status = egoslam()
        .args(["export", "--format", "colmap", "--run"])
        .arg(&out)
        .arg("--out")
        .arg(&colmap)
        .status()
        .expect("export");
    assert!(status.success());

    let images = images(&colmap);
    assert_eq!(
        images.len() as u64,
        report["map_keyframes"].as_u64().expect("keyframes")
    );
    // Image centres against the ground truth: as accurate as the run's keyframes.
    let centres: Vec<StampedPose> = images
        .iter()
        .map(|(t, q, tr, _)| StampedPose {
            timestamp: *t,
            position: -(q.inverse() * tr),
            rotation: q.inverse(),
        })
        .collect();
    let gt = read_tum_file(&tum_fixture().join("groundtruth.txt")).expect("ground truth");
    let ate = absolute_trajectory_error(&centres, &gt, 0.02).expect("ate");
    let keyframes = read_tum_file(&out.join("keyframes.tum")).expect("keyframes.tum");
    let keyframe_ate = absolute_trajectory_error(&keyframes, &gt, 0.02).expect("ate");
    assert_eq!(ate.matched, images.len());
    assert!(
        (ate.rmse - keyframe_ate.rmse).abs() < 0.1 * keyframe_ate.rmse,
        "export {:.4} m vs keyframes.tum {:.4} m",
        ate.rmse,
        keyframe_ate.rmse
    );

    // Keypoints where COLMAP's camera model projects the points (pixel centres at 0.5).
    let cameras = std::fs::read_to_string(colmap.join("cameras.txt")).expect("cameras");
    let camera = cameras
        .lines()
        .find(|l| !l.starts_with('#'))
        .expect("camera");
    let fields: Vec<&str> = camera.split(' ').collect();
    assert_eq!(fields[1], "FULL_OPENCV", "TUM fr1 has k3: {camera}");
    let c = numbers(&fields[4..].join(" "));
    let points_text = std::fs::read_to_string(colmap.join("points3D.txt")).expect("points");
    let points: BTreeMap<u64, Vector3<f64>> = points_text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            let v = numbers(l);
            (v[0] as u64, Vector3::new(v[1], v[2], v[3]))
        })
        .collect();
    assert!(points.len() > 500, "{} points", points.len());
    let mut errors = Vec::new();
    for (_, q, t, keypoints) in &images {
        for (pixel, id) in keypoints {
            let p = q * points[id] + t;
            let (x, y) = (p.x / p.z, p.y / p.z);
            let r2 = x * x + y * y;
            let radial = 1.0 + c[4] * r2 + c[5] * r2 * r2 + c[8] * r2 * r2 * r2;
            let xd = x * radial + 2.0 * c[6] * x * y + c[7] * (r2 + 2.0 * x * x);
            let yd = y * radial + c[6] * (r2 + 2.0 * y * y) + 2.0 * c[7] * x * y;
            let projected = Point2::new(c[0] * xd + c[2], c[1] * yd + c[3]);
            errors.push((projected - pixel).norm());
        }
    }
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    assert!(median < 1.5, "median reprojection {median:.2} px");

    let nerfstudio = dir.path().join("nerfstudio");
    let status = egoslam()
        .args(["export", "--format", "nerfstudio", "--run"])
        .arg(&out)
        .arg("--out")
        .arg(&nerfstudio)
        .status()
        .expect("export");
    assert!(status.success());
    let transforms: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(nerfstudio.join("transforms.json")).expect("transforms"),
    )
    .expect("json");
    let frames = transforms["frames"].as_array().expect("frames");
    assert_eq!(frames.len(), images.len());
    for f in frames {
        let path = f["file_path"].as_str().expect("file_path");
        assert!(nerfstudio.join(path).is_file(), "{path}");
    }
    assert!(nerfstudio.join("sparse_pc.ply").is_file());
}
