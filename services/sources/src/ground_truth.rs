//! Ground-truth trajectories in the layouts of TUM, KITTI and EuRoC, as camera poses.
//!
//! - TUM: `timestamp tx ty tz qx qy qz qw` (camera poses).
//! - KITTI: rows of a 3x4 `[R|t]` (world_from_cam0), times from `sequences/NN/times.txt`.
//! - EuRoC: body (IMU) poses, either the ASL `data.csv` (ns, p, q as w x y z) or a TUM-format
//!   export; the camera pose is `T_WB * T_BS` with `T_BS` from `cam0/sensor.yaml`.

use crate::error::{data_lines, parse_floats, read_text};
use crate::SourceError;
use egoslam_geometry::StampedPose;
use nalgebra::{
    Isometry3, Matrix3, Matrix4, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use serde_yaml::Value;
use std::path::{Path, PathBuf};

/// Camera poses with a note on how they were obtained.
#[derive(Debug, Clone)]
pub struct GroundTruth {
    pub poses: Vec<StampedPose>,
    /// e.g. "KITTI poses .../00.txt with times .../times.txt".
    pub description: String,
}

/// Reads a TUM trajectory file (`timestamp tx ty tz qx qy qz qw`).
pub fn read_tum_file(path: &Path) -> Result<Vec<StampedPose>, SourceError> {
    let text = read_text(path)?;
    data_lines(&text)
        .map(|(n, line)| {
            let v = parse_floats(path, n, line)?;
            if v.len() != 8 {
                return Err(SourceError::parse(
                    path,
                    n,
                    format!("expected 8 numbers (TUM), got {}", v.len()),
                ));
            }
            Ok(StampedPose {
                timestamp: v[0],
                position: Vector3::new(v[1], v[2], v[3]),
                rotation: UnitQuaternion::from_quaternion(Quaternion::new(v[7], v[4], v[5], v[6])),
            })
        })
        .collect()
}

/// The rotation nearest to `m`, in a bounded number of iterations: nalgebra's
/// `Rotation3::from_matrix` iterates until convergence, which a NaN (or a matrix far from
/// any rotation) never reaches.
fn nearest_rotation(m: &Matrix3<f64>) -> Rotation3<f64> {
    if !m.iter().all(|v| v.is_finite()) {
        return Rotation3::from_matrix_unchecked(Matrix3::from_element(f64::NAN));
    }
    Rotation3::from_matrix_eps(m, 1e-12, 100, Rotation3::identity())
}

fn read_kitti(path: &Path, times: &Path) -> Result<Vec<StampedPose>, SourceError> {
    let stamps: Vec<f64> = {
        let text = read_text(times)?;
        data_lines(&text)
            .map(|(n, l)| parse_floats(times, n, l).map(|v| v.first().copied().unwrap_or(f64::NAN)))
            .collect::<Result<_, _>>()?
    };
    let text = read_text(path)?;
    // The pose file may be longer than the image sequence: keep the stamped prefix.
    data_lines(&text)
        .zip(stamps)
        .map(|((n, line), t)| {
            let v = parse_floats(path, n, line)?;
            if v.len() != 12 {
                return Err(SourceError::parse(
                    path,
                    n,
                    format!("expected 12 numbers (KITTI 3x4), got {}", v.len()),
                ));
            }
            let r = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
            Ok(StampedPose {
                timestamp: t,
                position: Vector3::new(v[3], v[7], v[11]),
                rotation: UnitQuaternion::from_rotation_matrix(&nearest_rotation(&r)),
            })
        })
        .collect()
}

fn read_euroc_csv(path: &Path) -> Result<Vec<StampedPose>, SourceError> {
    let text = read_text(path)?;
    data_lines(&text)
        .map(|(n, line)| {
            let v = parse_floats(path, n, line)?;
            if v.len() < 8 {
                return Err(SourceError::parse(
                    path,
                    n,
                    "expected 'ns, px, py, pz, qw, qx, qy, qz, ...'",
                ));
            }
            Ok(StampedPose {
                timestamp: v[0] * 1e-9,
                position: Vector3::new(v[1], v[2], v[3]),
                rotation: UnitQuaternion::from_quaternion(Quaternion::new(v[4], v[5], v[6], v[7])),
            })
        })
        .collect()
}

/// `T_BS` (camera to body) from a Kalibr/EuRoC `sensor.yaml`.
pub fn read_body_from_sensor(path: &Path) -> Result<Isometry3<f64>, SourceError> {
    let text = read_text(path)?;
    let cleaned: String = text
        .lines()
        .filter(|l| !l.starts_with('%'))
        .collect::<Vec<_>>()
        .join("\n");
    let doc: Value =
        serde_yaml::from_str(&cleaned).map_err(|e| SourceError::parse(path, 0, e.to_string()))?;
    let data: Vec<f64> = doc
        .get("T_BS")
        .and_then(|t| t.get("data"))
        .and_then(Value::as_sequence)
        .map(|s| s.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default();
    if data.len() != 16 {
        return Err(SourceError::parse(
            path,
            0,
            "T_BS must be a 4x4 matrix (data: 16 numbers)",
        ));
    }
    let m = Matrix4::from_row_slice(&data);
    let r = nearest_rotation(&m.fixed_view::<3, 3>(0, 0).into_owned());
    Ok(Isometry3::from_parts(
        Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
        UnitQuaternion::from_rotation_matrix(&r),
    ))
}

fn body_to_camera(poses: &mut [StampedPose], t_bs: &Isometry3<f64>) {
    for p in poses {
        let t_wb = Isometry3::from_parts(Translation3::from(p.position), p.rotation);
        let t_wc = t_wb * t_bs;
        p.position = t_wc.translation.vector;
        p.rotation = t_wc.rotation;
    }
}

/// The EuRoC `sensor.yaml` of cam0 in `dir` or one of its ancestors, if any.
fn find_euroc_sensor(start: &Path) -> Option<PathBuf> {
    start
        .ancestors()
        .take(4)
        .map(|d| d.join("mav0/cam0/sensor.yaml"))
        .find(|p| p.is_file())
}

fn kitti_times_for(poses: &Path) -> Option<PathBuf> {
    let stem = poses.file_stem()?.to_string_lossy().into_owned();
    let dataset = poses.parent()?.parent()?;
    [
        dataset.join("sequences").join(&stem).join("times.txt"),
        poses.with_file_name(format!("{stem}_times.txt")),
    ]
    .into_iter()
    .find(|p| p.is_file())
}

fn first_data_columns(path: &Path) -> Result<usize, SourceError> {
    let text = read_text(path)?;
    let (n, line) = data_lines(&text)
        .next()
        .ok_or_else(|| SourceError::Empty { path: path.into() })?;
    Ok(parse_floats(path, n, line)?.len())
}

/// Loads camera ground truth from a file or a dataset folder (see the module doc).
pub fn load_ground_truth(path: &Path) -> Result<GroundTruth, SourceError> {
    let meta = std::fs::metadata(path).map_err(|e| SourceError::io(path, e))?;
    if meta.is_dir() {
        let candidates = [
            path.join("groundtruth.txt"),
            path.join("mav0/state_groundtruth_estimate0/data.csv"),
        ];
        if let Some(f) = candidates.iter().find(|p| p.is_file()) {
            return load_ground_truth(f);
        }
        // Any *groundtruth*/*gt* file or KITTI dataset/poses/NN.txt, one level down at most.
        let mut files: Vec<PathBuf> = Vec::new();
        for dir in [
            path.to_path_buf(),
            path.join("dataset/poses"),
            path.join("poses"),
        ] {
            if let Ok(rd) = std::fs::read_dir(&dir) {
                files.extend(
                    rd.filter_map(|e| e.ok())
                        .map(|e| e.path())
                        .filter(|p| p.is_file()),
                );
            }
        }
        files.sort();
        let pick = files.iter().find(|p| {
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().to_ascii_lowercase())
                .unwrap_or_default();
            name.contains("groundtruth")
                || (name.ends_with(".txt") && p.parent().is_some_and(|d| d.ends_with("poses")))
        });
        if let Some(f) = pick {
            return load_ground_truth(f);
        }
        // A TUM sequence in a subfolder.
        if let Ok(rd) = std::fs::read_dir(path) {
            let mut subdirs: Vec<PathBuf> = rd
                .filter_map(|e| e.ok())
                .map(|e| e.path())
                .filter(|p| p.is_dir())
                .collect();
            subdirs.sort();
            if let Some(f) = subdirs
                .iter()
                .map(|d| d.join("groundtruth.txt"))
                .find(|f| f.is_file())
            {
                return load_ground_truth(&f);
            }
        }
        return Err(SourceError::UnknownLayout { path: path.into() });
    }
    let columns = first_data_columns(path)?;
    let is_csv = path.extension().is_some_and(|e| e == "csv");
    let (mut poses, mut description) = match columns {
        12 => {
            let times = kitti_times_for(path).ok_or_else(|| {
                SourceError::parse(
                    path,
                    0,
                    "KITTI poses need times.txt (looked in ../sequences/NN/ and NN_times.txt)",
                )
            })?;
            let d = format!(
                "KITTI poses {} with times {}",
                path.display(),
                times.display()
            );
            (read_kitti(path, &times)?, d)
        }
        8 if !is_csv => (
            read_tum_file(path)?,
            format!("TUM trajectory {}", path.display()),
        ),
        n if is_csv && n >= 8 => (
            read_euroc_csv(path)?,
            format!("EuRoC body poses {}", path.display()),
        ),
        n => {
            return Err(SourceError::parse(
                path,
                0,
                format!("unrecognised ground truth: {n} columns"),
            ));
        }
    };
    // EuRoC ground truth is of the body (IMU), not the camera.
    if let Some(sensor) = path.parent().and_then(find_euroc_sensor) {
        let t_bs = read_body_from_sensor(&sensor)?;
        body_to_camera(&mut poses, &t_bs);
        description.push_str(&format!(", body poses x T_BS from {}", sensor.display()));
    }
    // A pose with a NaN or infinity cannot be aligned (an SVD of it need not converge): it
    // is left out, and said.
    let listed = poses.len();
    poses.retain(|p| {
        p.timestamp.is_finite()
            && p.position.iter().all(|v| v.is_finite())
            && p.rotation.coords.iter().all(|v| v.is_finite())
    });
    if poses.len() < listed {
        tracing::warn!(
            path = %path.display(),
            "{} of {listed} ground-truth poses are not finite and are left out",
            listed - poses.len()
        );
        description.push_str(&format!(
            ", {} non-finite poses left out",
            listed - poses.len()
        ));
    }
    if poses.is_empty() {
        return Err(SourceError::Empty { path: path.into() });
    }
    Ok(GroundTruth { poses, description })
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::shared_test_data as shared;

    #[test]
    fn tum_ground_truth() {
        let Some(d) = shared("tum_fr1_rpy") else {
            return;
        };
        let gt = load_ground_truth(&d).expect("gt");
        assert_eq!(gt.poses.len(), 2742);
        assert!((gt.poses[0].timestamp - 1305031225.93).abs() < 0.01);
    }

    #[test]
    fn kitti_ground_truth_has_stamped_prefix_in_metres() {
        let Some(d) = shared("kitti_odometry_00") else {
            return;
        };
        let gt = load_ground_truth(&d).expect("gt");
        assert_eq!(gt.poses.len(), 150);
        assert!(gt.poses[0].position.norm() < 1e-6);
        let path: f64 = gt
            .poses
            .windows(2)
            .map(|w| (w[1].position - w[0].position).norm())
            .sum();
        assert!((path - 108.0).abs() < 5.0, "path {path} m");
    }

    #[test]
    fn euroc_ground_truth_is_camera_not_body() {
        let Some(d) = shared("euroc_v1_01") else {
            return;
        };
        let gt = load_ground_truth(&d.join("groundtruth_V101_tum_from_evo.txt")).expect("gt");
        assert!(gt.description.contains("T_BS"));
        // First row body position 0.878895 2.183400 0.948427; the camera sits a few cm away.
        let offset = (gt.poses[0].position - Vector3::new(0.878895, 2.183400, 0.948427)).norm();
        assert!(offset > 0.03 && offset < 0.1, "offset {offset}");
        // The camera looks along its z axis; at the start the MAV's body x is up, cam0 is
        // mounted facing forward: the camera z axis must be near horizontal.
        let z = gt.poses[0].rotation * Vector3::z();
        assert!(z.z.abs() < 0.5, "camera z {z:?}");
    }

    #[test]
    fn bad_ground_truth_is_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        let f = dir.path().join("gt.txt");
        std::fs::write(&f, "1 2 3\n").expect("write");
        let err = load_ground_truth(&f).expect_err("3 columns");
        assert!(err.to_string().contains("gt.txt"), "{err}");
    }

    #[test]
    fn non_finite_poses_are_left_out_and_a_bad_rotation_does_not_hang() {
        let dir = tempfile::tempdir().expect("tempdir");
        let seq = dir.path().join("sequences/00");
        std::fs::create_dir_all(&seq).expect("mkdir");
        std::fs::write(seq.join("times.txt"), "0.0\n0.1\n0.2\n").expect("times");
        let poses = dir.path().join("poses");
        std::fs::create_dir_all(&poses).expect("mkdir");
        let f = poses.join("00.txt");
        std::fs::write(
            &f,
            "1 0 0 0 0 1 0 0 0 0 1 0\n\
             nan 0 0 1 0 1 0 0 0 0 1 0\n\
             0 0 0 2 0 0 0 0 0 0 0 0\n",
        )
        .expect("poses");
        let gt = load_ground_truth(&f).expect("loads");
        assert_eq!(gt.poses.len(), 2, "{}", gt.description);
        assert!(
            gt.description.contains("1 non-finite"),
            "{}",
            gt.description
        );
        let tum = dir.path().join("gt_tum.txt");
        std::fs::write(
            &tum,
            "1 0 0 0 0 0 0 1\n2 nan 0 0 0 0 0 1\n3 inf 0 0 0 0 0 1\n",
        )
        .expect("tum");
        assert_eq!(load_ground_truth(&tum).expect("loads").poses.len(), 1);
    }
}
