//! Camera calibration from the dataset's own files or a YAML given with `--calib`.
//!
//! Accepted formats (see docs/config.md):
//! - YAML: egoslam's own, ORB-SLAM2/3 settings, Kalibr camchain / EuRoC `sensor.yaml`,
//!   OpenCV FileStorage ([`crate::calibration_yaml`]);
//! - COLMAP `cameras.txt` ([`crate::calibration_colmap`]);
//! - KITTI `calib.txt`: the `P0:` row (or an unlabeled first row of 12 numbers), rectified.

use crate::error::{data_lines, parse_floats, read_text};
use crate::{Layout, SourceError};
use egoslam_geometry::{LensModel, PinholeRadtan};
use std::path::{Path, PathBuf};

/// Intrinsics as read from a file; the image size may be absent (KITTI calib.txt) and is
/// then taken from the first frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// fx, fy, cx, cy.
    pub focal_center: [f64; 4],
    /// The lens model's coefficients: k1, k2, p1, p2, k3 (OpenCV order) for
    /// radial-tangential ([`LensModel`] for the others).
    pub distortion: [f64; 5],
    pub lens: LensModel,
    /// Where it came from (a file, or "built-in TUM fr1" with the sequence path).
    pub origin: PathBuf,
}

impl Calibration {
    /// The camera for frames of `width` x `height`, or an error naming the calibration file
    /// when its size disagrees.
    pub fn camera_for(&self, width: u32, height: u32) -> Result<PinholeRadtan, SourceError> {
        if let (Some(cw), Some(ch)) = (self.width, self.height) {
            if (cw, ch) != (width, height) {
                return Err(SourceError::CalibrationSize {
                    path: self.origin.clone(),
                    calib_width: cw,
                    calib_height: ch,
                    width,
                    height,
                });
            }
        }
        PinholeRadtan::new(width, height, self.focal_center, self.distortion)
            .and_then(|camera| camera.with_lens(self.lens))
            .map_err(|source| SourceError::BadCalibration {
                path: self.origin.clone(),
                source,
            })
    }
}

fn parse_kitti_calib(path: &Path, text: &str) -> Result<Calibration, SourceError> {
    let (line_no, line) = data_lines(text)
        .find(|(_, l)| {
            l.starts_with("P0:")
                || l.chars()
                    .next()
                    .is_some_and(|c| c.is_ascii_digit() || c == '-')
        })
        .ok_or_else(|| SourceError::parse(path, 0, "no P0 row"))?;
    let values = parse_floats(path, line_no, line.trim_start_matches("P0:"))?;
    if values.len() < 12 {
        return Err(SourceError::parse(
            path,
            line_no,
            format!("P0 needs 12 numbers, got {}", values.len()),
        ));
    }
    Ok(Calibration {
        width: None,
        height: None,
        focal_center: [values[0], values[5], values[2], values[6]],
        distortion: [0.0; 5],
        lens: LensModel::RadialTangential,
        origin: path.into(),
    })
}

/// Reads one calibration file in any supported format (see the module doc).
pub fn read_calibration_file(path: &Path) -> Result<Calibration, SourceError> {
    let text = read_text(path)?;
    let is_yaml = path.extension().is_some_and(|e| e == "yaml" || e == "yml");
    if is_yaml {
        crate::calibration_yaml::parse_yaml(path, &text)
    } else if crate::calibration_colmap::looks_like_colmap(&text) {
        crate::calibration_colmap::parse_colmap_cameras(path, &text)
    } else {
        parse_kitti_calib(path, &text)
    }
}

/// Published intrinsics of the TUM RGB-D Kinects (vision.in.tum.de, "File Formats"), used
/// when a TUM sequence comes without a calibration file; chosen by the folder name.
fn builtin_tum(dir: &Path) -> Option<Calibration> {
    let name = dir.to_string_lossy().to_ascii_lowercase();
    let (fc, d) = if name.contains("freiburg1") || name.contains("fr1") {
        (
            [517.306408, 516.469215, 318.643040, 255.313989],
            [0.262383, -0.953104, -0.005358, 0.002628, 1.163314],
        )
    } else if name.contains("freiburg2") || name.contains("fr2") {
        (
            [520.908620, 521.007327, 325.141442, 249.701764],
            [0.231222, -0.784899, -0.003257, -0.000105, 0.917205],
        )
    } else if name.contains("freiburg3") || name.contains("fr3") {
        ([535.4, 539.2, 320.1, 247.6], [0.0; 5])
    } else {
        return None;
    };
    Some(Calibration {
        width: Some(640),
        height: Some(480),
        focal_center: fc,
        distortion: d,
        lens: LensModel::RadialTangential,
        origin: dir.join("(built-in TUM intrinsics)"),
    })
}

fn candidate_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| e.path())
                .filter(|p| p.is_file())
                .collect()
        })
        .unwrap_or_default();
    files.retain(|p| {
        let name = p
            .file_name()
            .map(|n| n.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        let ext_ok = name.ends_with(".yaml") || name.ends_with(".yml") || name.ends_with(".txt");
        ext_ok
            && (name.starts_with("calib")
                || name.starts_with("camera")
                || name.starts_with("camchain")
                || name == "sensor.yaml")
    });
    files.sort();
    files
}

/// The calibration for a sequence: `explicit` when given, else the dataset's own file
/// (EuRoC `sensor.yaml`, KITTI `calib.txt`, a `calib*`/`camera*` file in the sequence folder
/// or up to three folders above), else TUM's published values for TUM folders.
pub fn load_calibration(
    layout: &Layout,
    explicit: Option<&Path>,
) -> Result<Calibration, SourceError> {
    if let Some(path) = explicit {
        return read_calibration_file(path);
    }
    let root = layout.root();
    if let Layout::Euroc { cam_dir } = layout {
        let sensor = cam_dir.join("sensor.yaml");
        if sensor.is_file() {
            return read_calibration_file(&sensor);
        }
    }
    for dir in root.ancestors().take(4) {
        for file in candidate_files(dir) {
            match read_calibration_file(&file) {
                Ok(c) => {
                    tracing::info!(file = %file.display(), "calibration found next to the sequence");
                    return Ok(c);
                }
                Err(e) => tracing::debug!(%e, "not a calibration file"),
            }
        }
    }
    if let Layout::Tum { dir } = layout {
        if let Some(c) = builtin_tum(dir) {
            return Ok(c);
        }
    }
    Err(SourceError::MissingCalibration { path: root.into() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect_layout;

    use crate::shared_test_data as shared;

    #[test]
    fn reads_each_datasets_own_calibration() {
        if let Some(d) = shared("tum_fr1_rpy") {
            let c = load_calibration(&detect_layout(&d).expect("tum"), None).expect("calib");
            assert_eq!(c.focal_center[0], 517.306408);
            assert_eq!(c.distortion[4], 1.163314);
            assert_eq!((c.width, c.height), (Some(640), Some(480)));
        }
        if let Some(d) = shared("euroc_v1_01") {
            let c = load_calibration(&detect_layout(&d).expect("euroc"), None).expect("calib");
            assert_eq!(c.focal_center, [458.654, 457.296, 367.215, 248.375]);
            assert_eq!(c.distortion[0], -0.28340811);
            assert_eq!((c.width, c.height), (Some(752), Some(480)));
        }
        if let Some(d) = shared("kitti_odometry_00") {
            let c = load_calibration(&detect_layout(&d).expect("kitti"), None).expect("calib");
            assert_eq!(c.focal_center, [718.856, 718.856, 607.1928, 185.2157]);
            let txt = d.join("calib_P0_P1_unlabeled_from_niconielsen32.txt");
            let c2 = read_calibration_file(&txt).expect("P0 row");
            assert_eq!(c2.focal_center, c.focal_center);
        }
    }

    #[test]
    fn own_format_and_size_check() {
        let dir = tempfile::tempdir().expect("tempdir");
        let f = dir.path().join("cam.yaml");
        std::fs::write(&f, "width: 640\nheight: 480\nfx: 500\nfy: 501\ncx: 320\ncy: 240\ndistortion: [0.1, -0.2, 0, 0, 0]\n")
            .expect("write");
        let c = read_calibration_file(&f).expect("parse");
        assert_eq!(c.distortion[1], -0.2);
        assert!(c.camera_for(640, 480).is_ok());
        let err = c.camera_for(1241, 376).expect_err("size mismatch");
        assert!(
            err.to_string().contains("cam.yaml") && err.to_string().contains("640x480"),
            "{err}"
        );
        std::fs::write(&f, "fy: 1\n").expect("write");
        assert!(read_calibration_file(&f).is_err());
        let zero = dir.path().join("zero.yaml");
        std::fs::write(&zero, "fx: 0\nfy: 1\ncx: 1\ncy: 1\n").expect("write");
        let err = read_calibration_file(&zero)
            .expect("parses")
            .camera_for(10, 10)
            .expect_err("bad focal");
        let cause = std::error::Error::source(&err)
            .map(|c| c.to_string())
            .unwrap_or_default();
        assert!(
            err.to_string().contains("zero.yaml") && cause.contains("focal"),
            "{err}: {cause}"
        );
    }

    #[test]
    fn a_resolution_that_is_not_two_numbers_is_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        let f = dir.path().join("sensor.yaml");
        for res in ["[]", "[640]", "[640, 480, 3]", "nope"] {
            std::fs::write(
                &f,
                format!("intrinsics: [500, 500, 320, 240]\nresolution: {res}\n"),
            )
            .expect("write");
            let err = read_calibration_file(&f).expect_err(res);
            assert!(
                err.to_string().contains("sensor.yaml") && err.to_string().contains("resolution"),
                "{res}: {err}"
            );
        }
        std::fs::write(
            &f,
            "intrinsics: [500, 500, 320, 240]\nresolution: [640, 480]\n",
        )
        .expect("write");
        let c = read_calibration_file(&f).expect("parses");
        assert_eq!((c.width, c.height), (Some(640), Some(480)));
    }
}
