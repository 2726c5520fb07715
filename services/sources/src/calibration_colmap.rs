//! COLMAP `cameras.txt` (`CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`, colmap.github.io
//! "Output Format"): the first camera, in the models egoslam's lens models hold; the
//! principal point is moved from COLMAP's pixel convention to OpenCV's.

use crate::calibration::Calibration;
use crate::error::data_lines;
use crate::SourceError;
use egoslam_geometry::LensModel;
use std::path::Path;

/// COLMAP's camera model names with the parameters each one lists after the size.
const MODELS: &[(&str, usize)] = &[
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("FULL_OPENCV", 12),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("OPENCV_FISHEYE", 8),
];

/// Whether `text` reads as a COLMAP cameras.txt (a data line's second word is a model).
pub(crate) fn looks_like_colmap(text: &str) -> bool {
    data_lines(text).next().is_some_and(|(_, line)| {
        line.split_whitespace()
            .nth(1)
            .is_some_and(|m| MODELS.iter().any(|(name, _)| *name == m))
    })
}

pub(crate) fn parse_colmap_cameras(path: &Path, text: &str) -> Result<Calibration, SourceError> {
    let (line_no, line) = data_lines(text)
        .next()
        .ok_or_else(|| SourceError::parse(path, 0, "no camera line"))?;
    let words: Vec<&str> = line.split_whitespace().collect();
    let bad = |problem: String| SourceError::parse(path, line_no, problem);
    let model = *words
        .get(1)
        .ok_or_else(|| bad("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...".into()))?;
    let Some(&(_, count)) = MODELS.iter().find(|(name, _)| *name == model) else {
        return Err(bad(format!(
            "camera model {model:?} is not supported (expected one of {})",
            MODELS
                .iter()
                .map(|(n, _)| *n)
                .collect::<Vec<_>>()
                .join(", ")
        )));
    };
    let numbers: Vec<f64> = words[2..]
        .iter()
        .map(|w| w.parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| bad(format!("{model}: {e}")))?;
    if numbers.len() != count + 2 {
        return Err(bad(format!(
            "{model} needs WIDTH HEIGHT and {count} parameters, got {} numbers",
            numbers.len()
        )));
    }
    let whole =
        |v: f64| (v >= 1.0 && v.fract() == 0.0 && v <= f64::from(u32::MAX)).then_some(v as u32);
    let (width, height) = (whole(numbers[0]), whole(numbers[1]));
    let p = &numbers[2..];
    let (lens, focal_center, distortion) = match model {
        "SIMPLE_PINHOLE" => (
            LensModel::RadialTangential,
            [p[0], p[0], p[1], p[2]],
            [0.0; 5],
        ),
        "PINHOLE" => (
            LensModel::RadialTangential,
            [p[0], p[1], p[2], p[3]],
            [0.0; 5],
        ),
        "SIMPLE_RADIAL" => (
            LensModel::RadialTangential,
            [p[0], p[0], p[1], p[2]],
            [p[3], 0.0, 0.0, 0.0, 0.0],
        ),
        "RADIAL" => (
            LensModel::RadialTangential,
            [p[0], p[0], p[1], p[2]],
            [p[3], p[4], 0.0, 0.0, 0.0],
        ),
        "OPENCV" => (
            LensModel::RadialTangential,
            [p[0], p[1], p[2], p[3]],
            [p[4], p[5], p[6], p[7], 0.0],
        ),
        "FULL_OPENCV" => {
            // k1 k2 p1 p2 k3 k4 k5 k6: the rational terms k4..k6 are not held.
            if p[9..].iter().any(|v| *v != 0.0) {
                return Err(bad(
                    "FULL_OPENCV with k4..k6 (the rational model) is not supported".into(),
                ));
            }
            (
                LensModel::RadialTangential,
                [p[0], p[1], p[2], p[3]],
                [p[4], p[5], p[6], p[7], p[8]],
            )
        }
        // COLMAP's fisheye models are equidistant: theta_d = theta (1 + k theta^2 ...).
        "SIMPLE_RADIAL_FISHEYE" => (
            LensModel::Equidistant,
            [p[0], p[0], p[1], p[2]],
            [p[3], 0.0, 0.0, 0.0, 0.0],
        ),
        "RADIAL_FISHEYE" => (
            LensModel::Equidistant,
            [p[0], p[0], p[1], p[2]],
            [p[3], p[4], 0.0, 0.0, 0.0],
        ),
        _ => (
            LensModel::Equidistant,
            [p[0], p[1], p[2], p[3]],
            [p[4], p[5], p[6], p[7], 0.0],
        ),
    };
    // COLMAP puts a pixel's centre at (0.5, 0.5), OpenCV (and egoslam) at (0, 0).
    let [fx, fy, cx, cy] = focal_center;
    Ok(Calibration {
        width,
        height,
        focal_center: [fx, fy, cx - 0.5, cy - 0.5],
        distortion,
        lens,
        origin: path.into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "# Camera list with one line of data per camera:\n\
        #   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n";

    fn parse(line: &str) -> Result<Calibration, SourceError> {
        let text = format!("{HEADER}{line}\n");
        assert!(looks_like_colmap(&text));
        parse_colmap_cameras(Path::new("cameras.txt"), &text)
    }

    #[test]
    fn opencv_fisheye_is_equidistant_with_the_centre_in_opencv_pixels() {
        let c = parse("1 OPENCV_FISHEYE 640 480 260 261 320.5 240.5 0.01 -0.002 0.0003 -0.00004")
            .expect("fisheye");
        assert_eq!(c.lens, LensModel::Equidistant);
        assert_eq!(c.focal_center, [260.0, 261.0, 320.0, 240.0]);
        assert_eq!(c.distortion, [0.01, -0.002, 0.0003, -0.00004, 0.0]);
        assert_eq!((c.width, c.height), (Some(640), Some(480)));
        let radial = parse("2 RADIAL_FISHEYE 640 480 260 320.5 240.5 0.01 -0.002").expect("radial");
        assert_eq!(radial.lens, LensModel::Equidistant);
        assert_eq!(radial.distortion[..2], [0.01, -0.002]);
    }

    #[test]
    fn pinhole_models_keep_radial_tangential_terms_in_opencv_order() {
        let c =
            parse("1 OPENCV 640 480 500 510 320.5 240.5 0.1 -0.05 0.001 0.002").expect("opencv");
        assert_eq!(c.lens, LensModel::RadialTangential);
        assert_eq!(c.focal_center, [500.0, 510.0, 320.0, 240.0]);
        assert_eq!(c.distortion, [0.1, -0.05, 0.001, 0.002, 0.0]);
        let full =
            parse("1 FULL_OPENCV 640 480 500 510 320.5 240.5 0.1 -0.05 0.001 0.002 0.3 0 0 0")
                .expect("full");
        assert_eq!(full.distortion[4], 0.3);
        let err =
            parse("1 FULL_OPENCV 640 480 500 510 320.5 240.5 0.1 -0.05 0.001 0.002 0.3 0.1 0 0")
                .expect_err("rational");
        assert!(err.to_string().contains("k4..k6"), "{err}");
        let err = parse("1 OPENCV 640 480 500 510 320.5").expect_err("short");
        assert!(
            err.to_string().contains("cameras.txt") && err.to_string().contains("8 parameters"),
            "{err}"
        );
        assert!(!looks_like_colmap(
            "P0: 718.8 0 607.1 0 0 718.8 185.2 0 0 0 1 0\n"
        ));
    }
}
