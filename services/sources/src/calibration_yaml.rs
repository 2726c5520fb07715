//! Calibration YAML as users have it:
//! - egoslam: `width`, `height`, `fx`, `fy`, `cx`, `cy`, `distortion: [...]`, optional
//!   `model: radtan | equidistant | double_sphere`;
//! - ORB-SLAM2/3 settings: `Camera.fx` ... (`Camera1.` in ORB-SLAM3), `Camera.type:
//!   PinHole | KannalaBrandt8` with `k1 k2 p1 p2 k3` or `k1 k2 k3 k4`;
//! - Kalibr camchain (`cam0:` with `camera_model`, `distortion_model`, `intrinsics`,
//!   `distortion_coeffs`, `resolution`) and EuRoC's flat `sensor.yaml`;
//! - OpenCV FileStorage: `camera_matrix` / `K` and `distortion_coefficients` / `D`, with
//!   `fisheye: 1` or `distortion_model: fisheye` for OpenCV's fisheye model.

use crate::calibration::Calibration;
use crate::SourceError;
use egoslam_geometry::LensModel;
use serde_yaml::Value;
use std::path::Path;

fn yaml_number(v: &Value) -> Option<f64> {
    match v {
        Value::Number(n) => n.as_f64(),
        Value::String(s) => s.trim().parse().ok(),
        Value::Tagged(t) => yaml_number(&t.value),
        _ => None,
    }
}

fn yaml_numbers(v: &Value) -> Option<Vec<f64>> {
    match v {
        Value::Sequence(s) => s.iter().map(yaml_number).collect(),
        Value::Tagged(t) => yaml_numbers(&t.value),
        // OpenCV matrices: {rows, cols, data: [...]}
        Value::Mapping(m) => m.get("data").and_then(yaml_numbers),
        _ => None,
    }
}

/// A size that is not a positive whole number is no size: `camera_for` then takes the
/// frames' (and the focal and centre are checked by the camera model).
fn size(w: Option<f64>, h: Option<f64>) -> (Option<u32>, Option<u32>) {
    let whole =
        |v: f64| (v >= 1.0 && v <= f64::from(u32::MAX) && v.fract() == 0.0).then_some(v as u32);
    (w.and_then(whole), h.and_then(whole))
}

/// Up to five coefficients into the model's slots, the rest zero.
fn coefficients(values: &[f64]) -> [f64; 5] {
    let mut out = [0.0; 5];
    for (slot, v) in out.iter_mut().zip(values) {
        *slot = *v;
    }
    out
}

/// The lens named by a file's model string, or an error naming the field and what it may be.
fn lens_named(path: &Path, field: &str, name: &str) -> Result<LensModel, SourceError> {
    match name.to_ascii_lowercase().as_str() {
        "radial-tangential" | "radtan" | "plumb_bob" | "none" | "pinhole" | "opencv" => {
            Ok(LensModel::RadialTangential)
        }
        "equidistant" | "equi" | "fisheye" | "kannalabrandt8" | "kannala_brandt" | "kb4" => {
            Ok(LensModel::Equidistant)
        }
        "double_sphere" | "ds" | "doublesphere" => Ok(LensModel::DoubleSphere),
        _ => Err(SourceError::parse(
            path,
            0,
            format!(
                "{field} {name:?} is not supported (expected radtan, equidistant or double_sphere)"
            ),
        )),
    }
}

pub(crate) fn parse_yaml(path: &Path, text: &str) -> Result<Calibration, SourceError> {
    // OpenCV FileStorage writes "%YAML:1.0", which is not a valid YAML directive.
    let cleaned: String = text
        .lines()
        .filter(|l| !l.starts_with('%') && l.trim() != "---")
        .collect::<Vec<_>>()
        .join("\n");
    let doc: Value = serde_yaml::from_str(&cleaned).map_err(|e| {
        SourceError::parse(path, e.location().map_or(0, |l| l.line()), e.to_string())
    })?;
    // A Kalibr camchain holds one block per camera; the first is the one filmed.
    let doc = doc.get("cam0").unwrap_or(&doc);
    if let Some(intrinsics) = doc.get("intrinsics").and_then(yaml_numbers) {
        return kalibr(path, doc, &intrinsics);
    }
    if let Some(k) = ["camera_matrix", "K", "cameraMatrix"]
        .iter()
        .find_map(|key| doc.get(*key).and_then(yaml_numbers))
    {
        return opencv_storage(path, doc, &k);
    }
    settings(path, doc)
}

/// Kalibr camchain `cam0` or EuRoC `sensor.yaml`.
fn kalibr(path: &Path, doc: &Value, intrinsics: &[f64]) -> Result<Calibration, SourceError> {
    let model = doc
        .get("camera_model")
        .and_then(Value::as_str)
        .unwrap_or("pinhole");
    let distortion_model = doc.get("distortion_model").and_then(Value::as_str);
    let coeffs = doc
        .get("distortion_coeffs")
        .or_else(|| doc.get("distortion_coefficients"))
        .and_then(yaml_numbers)
        .unwrap_or_default();
    let (lens, focal_center, distortion) = match model {
        "pinhole" => {
            let [fu, fv, cu, cv] = <[f64; 4]>::try_from(intrinsics).map_err(|_| {
                SourceError::parse(path, 0, "intrinsics must be [fu, fv, cu, cv] for pinhole")
            })?;
            let lens = match distortion_model {
                Some(name) => lens_named(path, "distortion_model", name)?,
                None => LensModel::RadialTangential,
            };
            if lens == LensModel::DoubleSphere {
                return Err(SourceError::parse(
                    path,
                    0,
                    "distortion_model double_sphere belongs to camera_model ds",
                ));
            }
            (lens, [fu, fv, cu, cv], coefficients(&coeffs))
        }
        "ds" => {
            let [xi, alpha, fu, fv, cu, cv] = <[f64; 6]>::try_from(intrinsics).map_err(|_| {
                SourceError::parse(
                    path,
                    0,
                    "intrinsics must be [xi, alpha, fu, fv, cu, cv] for ds",
                )
            })?;
            (
                LensModel::DoubleSphere,
                [fu, fv, cu, cv],
                [xi, alpha, 0.0, 0.0, 0.0],
            )
        }
        "omni" => {
            // Mei's unified model is the double sphere with xi 0 and alpha = xi / (1 + xi),
            // focal / (1 + xi) (Usenko et al. 2018, section 3); its extra radtan terms are
            // not.
            let [xi, fu, fv, cu, cv] = <[f64; 5]>::try_from(intrinsics).map_err(|_| {
                SourceError::parse(path, 0, "intrinsics must be [xi, fu, fv, cu, cv] for omni")
            })?;
            if coeffs.iter().any(|c| *c != 0.0) {
                return Err(SourceError::parse(
                    path,
                    0,
                    "camera_model omni with distortion_coeffs is not supported (omni without distortion, ds or pinhole-equidistant are)",
                ));
            }
            let s = 1.0 + xi;
            (
                LensModel::DoubleSphere,
                [fu / s, fv / s, cu, cv],
                [0.0, xi / s, 0.0, 0.0, 0.0],
            )
        }
        other => {
            return Err(SourceError::parse(
                path,
                0,
                format!("camera_model {other:?} is not supported (expected pinhole, ds or omni)"),
            ))
        }
    };
    let (width, height) = match doc.get("resolution") {
        None => (None, None),
        Some(v) => match yaml_numbers(v).as_deref() {
            Some(&[w, h]) => size(Some(w), Some(h)),
            _ => {
                return Err(SourceError::parse(
                    path,
                    0,
                    "resolution must be [width, height] (two positive integers)",
                ))
            }
        },
    };
    Ok(Calibration {
        width,
        height,
        focal_center,
        distortion,
        lens,
        origin: path.into(),
    })
}

/// OpenCV FileStorage: a 3x3 camera matrix, its distortion vector and a fisheye flag.
fn opencv_storage(path: &Path, doc: &Value, k: &[f64]) -> Result<Calibration, SourceError> {
    if k.len() != 9 {
        return Err(SourceError::parse(
            path,
            0,
            format!("camera_matrix must be 3x3 (9 numbers), got {}", k.len()),
        ));
    }
    let d = ["distortion_coefficients", "D", "dist_coeffs", "distCoeffs"]
        .iter()
        .find_map(|key| doc.get(*key).and_then(yaml_numbers))
        .unwrap_or_default();
    let fisheye = doc
        .get("fisheye")
        .and_then(yaml_number)
        .is_some_and(|v| v != 0.0)
        || doc.get("fisheye").and_then(Value::as_bool) == Some(true);
    let lens = match doc.get("distortion_model").and_then(Value::as_str) {
        Some(name) => lens_named(path, "distortion_model", name)?,
        None if fisheye => LensModel::Equidistant,
        None => LensModel::RadialTangential,
    };
    if lens == LensModel::RadialTangential && d.len() > 5 && d[5..].iter().any(|v| *v != 0.0) {
        return Err(SourceError::parse(
            path,
            0,
            "distortion_coefficients beyond k1 k2 p1 p2 k3 (the rational or thin-prism model) are not supported",
        ));
    }
    let number = |keys: &[&str]| {
        keys.iter()
            .find_map(|key| doc.get(*key).and_then(yaml_number))
    };
    let (width, height) = size(
        number(&["image_width", "width"]),
        number(&["image_height", "height"]),
    );
    Ok(Calibration {
        width,
        height,
        focal_center: [k[0], k[4], k[2], k[5]],
        distortion: coefficients(&d),
        lens,
        origin: path.into(),
    })
}

/// egoslam's own keys, or ORB-SLAM's `Camera.` / `Camera1.` settings.
fn settings(path: &Path, doc: &Value) -> Result<Calibration, SourceError> {
    let get = |key: &str| doc.get(key).and_then(yaml_number);
    let missing = |what: &str| SourceError::parse(path, 0, format!("calibration lacks {what}"));
    for prefix in ["", "Camera.", "Camera1."] {
        let key = |k: &str| format!("{prefix}{k}");
        let Some(fx) = get(&key("fx")) else {
            continue;
        };
        let fy = get(&key("fy")).ok_or_else(|| missing(&key("fy")))?;
        let cx = get(&key("cx")).ok_or_else(|| missing(&key("cx")))?;
        let cy = get(&key("cy")).ok_or_else(|| missing(&key("cy")))?;
        let model_field = ["model", "Camera.type", "Camera1.type"]
            .into_iter()
            .find(|k| doc.get(*k).is_some());
        let lens =
            match model_field.and_then(|k| doc.get(k).and_then(Value::as_str).map(|v| (k, v))) {
                Some((field, name)) => lens_named(path, field, name)?,
                None => LensModel::RadialTangential,
            };
        let names: &[&str] = match lens {
            LensModel::RadialTangential => &["k1", "k2", "p1", "p2", "k3"],
            LensModel::Equidistant => &["k1", "k2", "k3", "k4"],
            LensModel::DoubleSphere => &["xi", "alpha"],
        };
        let distortion = match doc.get("distortion").and_then(yaml_numbers) {
            Some(d) => coefficients(&d),
            None => coefficients(
                &names
                    .iter()
                    .map(|k| get(&key(k)).unwrap_or(0.0))
                    .collect::<Vec<_>>(),
            ),
        };
        let (width, height) = size(get(&key("width")), get(&key("height")));
        return Ok(Calibration {
            width,
            height,
            focal_center: [fx, fy, cx, cy],
            distortion,
            lens,
            origin: path.into(),
        });
    }
    Err(missing(
        "fx/fy/cx/cy (or Camera.fx..., intrinsics, a cam0 block, or camera_matrix)",
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Calibration, SourceError> {
        parse_yaml(Path::new("calib.yaml"), text)
    }

    #[test]
    fn a_kalibr_camchain_gives_its_model_intrinsics_and_size() {
        let c = parse(
            "cam0:\n  camera_model: pinhole\n  distortion_model: equidistant\n  \
             distortion_coeffs: [0.01, -0.002, 0.0003, -0.00004]\n  \
             intrinsics: [260.5, 261.0, 319.5, 239.5]\n  resolution: [640, 480]\n  \
             rostopic: /cam0/image_raw\n",
        )
        .expect("camchain");
        assert_eq!(c.lens, LensModel::Equidistant);
        assert_eq!(c.focal_center, [260.5, 261.0, 319.5, 239.5]);
        assert_eq!(c.distortion, [0.01, -0.002, 0.0003, -0.00004, 0.0]);
        assert_eq!((c.width, c.height), (Some(640), Some(480)));
        let radtan = parse(
            "cam0:\n  camera_model: pinhole\n  distortion_model: radtan\n  \
             distortion_coeffs: [-0.28, 0.07, 0.0002, 0.00002]\n  \
             intrinsics: [458.6, 457.3, 367.2, 248.4]\n  resolution: [752, 480]\n",
        )
        .expect("radtan camchain");
        assert_eq!(radtan.lens, LensModel::RadialTangential);
        assert_eq!(radtan.distortion, [-0.28, 0.07, 0.0002, 0.00002, 0.0]);
        let ds = parse(
            "cam0:\n  camera_model: ds\n  intrinsics: [-0.18, 0.59, 156.0, 155.9, 254.9, 256.9]\n  \
             resolution: [512, 512]\n",
        )
        .expect("double sphere");
        assert_eq!(ds.lens, LensModel::DoubleSphere);
        assert_eq!(ds.focal_center, [156.0, 155.9, 254.9, 256.9]);
        assert_eq!(ds.distortion[..2], [-0.18, 0.59]);
    }

    #[test]
    fn mei_omni_without_distortion_becomes_the_double_sphere_it_is() {
        let c = parse(
            "cam0:\n  camera_model: omni\n  distortion_model: none\n  distortion_coeffs: [0, 0, 0, 0]\n  \
             intrinsics: [1.0, 500.0, 500.0, 320.0, 240.0]\n",
        )
        .expect("omni");
        assert_eq!(c.lens, LensModel::DoubleSphere);
        assert_eq!(c.focal_center, [250.0, 250.0, 320.0, 240.0]);
        assert_eq!(c.distortion[..2], [0.0, 0.5]);
        let err = parse(
            "cam0:\n  camera_model: omni\n  distortion_coeffs: [0.1, 0, 0, 0]\n  \
             intrinsics: [1.0, 500.0, 500.0, 320.0, 240.0]\n",
        )
        .expect_err("omni with radtan terms");
        assert!(
            err.to_string().contains("calib.yaml") && err.to_string().contains("omni"),
            "{err}"
        );
    }

    #[test]
    fn an_unknown_model_names_the_file_the_field_and_what_is_expected() {
        let err = parse(
            "cam0:\n  camera_model: pinhole\n  distortion_model: fov\n  intrinsics: [1, 1, 1, 1]\n",
        )
        .expect_err("fov");
        let text = err.to_string();
        assert!(
            text.contains("calib.yaml")
                && text.contains("distortion_model")
                && text.contains("\"fov\"")
                && text.contains("equidistant"),
            "{text}"
        );
        let err =
            parse("cam0:\n  camera_model: pinhole\n  intrinsics: [1, 1, 1]\n").expect_err("3");
        assert!(err.to_string().contains("[fu, fv, cu, cv]"), "{err}");
    }

    #[test]
    fn opencv_storage_with_a_fisheye_flag_is_equidistant() {
        let c = parse(
            "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   \
             rows: 3\n   cols: 3\n   dt: d\n   data: [ 262., 0., 320.5, 0., 263., 240.5, 0., 0., 1. ]\n\
             distortion_coefficients: !!opencv-matrix\n   rows: 4\n   cols: 1\n   dt: d\n   \
             data: [ 0.02, -0.01, 0.003, -0.0004 ]\nfisheye: 1\n",
        )
        .expect("FileStorage");
        assert_eq!(c.lens, LensModel::Equidistant);
        assert_eq!(c.focal_center, [262.0, 263.0, 320.5, 240.5]);
        assert_eq!(c.distortion[3], -0.0004);
        assert_eq!((c.width, c.height), (Some(640), Some(480)));
        let plain =
            parse("K: [500, 0, 320, 0, 501, 240, 0, 0, 1]\nD: [0.1, -0.2, 0.001, 0.002, 0.05]\n")
                .expect("K D");
        assert_eq!(plain.lens, LensModel::RadialTangential);
        assert_eq!(plain.distortion, [0.1, -0.2, 0.001, 0.002, 0.05]);
        let err = parse("K: [500, 0, 320, 0, 501, 240]\n").expect_err("not 3x3");
        assert!(err.to_string().contains("3x3"), "{err}");
    }

    #[test]
    fn orb_slam3_kannala_brandt_settings_read_k1_to_k4() {
        let c = parse(
            "Camera.type: \"KannalaBrandt8\"\nCamera1.fx: 190.97\nCamera1.fy: 190.97\n\
             Camera1.cx: 254.93\nCamera1.cy: 256.89\nCamera1.k1: 0.0034\nCamera1.k2: 0.0007\n\
             Camera1.k3: -0.0020\nCamera1.k4: 0.0002\nCamera.width: 512\nCamera.height: 512\n",
        )
        .expect("ORB-SLAM3");
        assert_eq!(c.lens, LensModel::Equidistant);
        assert_eq!(c.focal_center, [190.97, 190.97, 254.93, 256.89]);
        assert_eq!(c.distortion, [0.0034, 0.0007, -0.0020, 0.0002, 0.0]);
        let pinhole = parse(
            "Camera.type: \"PinHole\"\nCamera.fx: 517.3\nCamera.fy: 516.5\nCamera.cx: 318.6\n\
             Camera.cy: 255.3\nCamera.k1: 0.26\nCamera.k2: -0.95\nCamera.p1: -0.005\n\
             Camera.p2: 0.002\nCamera.k3: 1.16\n",
        )
        .expect("ORB-SLAM2 pinhole");
        assert_eq!(pinhole.lens, LensModel::RadialTangential);
        assert_eq!(pinhole.distortion, [0.26, -0.95, -0.005, 0.002, 1.16]);
    }
}
