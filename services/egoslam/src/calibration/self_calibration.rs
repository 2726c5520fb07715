//! `egoslam run`'s intrinsics self-calibration before the services start
//! (`--calibrate-focal`, `--calibrate-radial`; focal.rs estimates): each estimates from the
//! input's first keyframes, those the readout pre-pass tracked on its way when it found no
//! readout (the same frames, tracker and camera), else read again from the input's start,
//! and reports what it did for report.json.

use crate::calibration::focal::{first_keyframes, FOCAL_FRAMES};
use crate::calibration::readout::{FirstKeyframes, Readout};
use crate::cli::RunArgs;
use egoslam_geometry::PinholeRadtan;
use egoslam_solver::view_graph::KeyframeObservations;
use egoslam_sources::{open_source, Layout};
use serde_json::json;
use std::path::Path;
use std::time::Instant;

/// Runs `estimate` on the input's first keyframes (`tracked`, when they were tracked with
/// this camera and the run's readout is 0; else tracked again from the input's start with
/// the run's readout), and times it; `Err` is the report of why nothing was estimated
/// (`setting` off, a live camera, or the estimate's error).
fn read_ahead<T>(
    args: &RunArgs,
    (input, layout, camera): (&Path, &Layout, PinholeRadtan),
    tracked: Option<&FirstKeyframes>,
    (setting, what): (bool, &str),
    estimate: impl FnOnce(&[KeyframeObservations]) -> anyhow::Result<T>,
) -> Result<(T, f64), serde_json::Value> {
    if !setting {
        return Err(json!({ "setting": false }));
    }
    if matches!(layout, Layout::Camera { .. }) {
        tracing::info!("{what} self-calibration needs a recorded input: the live camera runs with its calibration as given");
        return Err(json!({ "setting": true, "error": "a live camera cannot be read ahead" }));
    }
    let started = Instant::now();
    let readout_s = match args.pipeline.rolling_shutter_ms {
        Readout::Millis(ms) => ms / 1000.0,
        Readout::Auto => 0.0,
    };
    // The readout pre-pass tracked these frames already, with no readout and this camera.
    let result = match tracked.filter(|t| readout_s == 0.0 && t.camera == camera) {
        Some(tracked) => estimate(&tracked.keyframes),
        None => open_source(input, args.fps)
            .map_err(anyhow::Error::from)
            .and_then(|source| {
                let step = format!("{what} calibration");
                crate::supervision::progress::reading_frames(
                    &step,
                    &mut source.quiet(),
                    FOCAL_FRAMES,
                    0,
                    |s| first_keyframes(s, camera, &args.pipeline, readout_s),
                )
            })
            .and_then(|keyframes| estimate(&keyframes)),
    };
    let elapsed_ms = started.elapsed().as_secs_f64() * 1e3;
    result.map(|e| (e, elapsed_ms)).map_err(|e| {
        tracing::info!("no {what} estimate ({e:#}): the calibration is used as given");
        json!({ "setting": true, "error": format!("{e:#}"), "estimation_ms": elapsed_ms })
    })
}

/// Under `--calibrate-focal true` the camera with the focal length of the input's first
/// windows (focal.rs) when they clearly disagree with the calibration, else `camera`; and
/// what was done, for the report.
pub fn resolve_focal(
    args: &RunArgs,
    (input, layout): (&Path, &Layout),
    camera: PinholeRadtan,
    tracked: Option<&FirstKeyframes>,
) -> (PinholeRadtan, serde_json::Value) {
    let setting = (args.pipeline.calibrate_focal, "focal");
    let recording = (input, layout, camera);
    match read_ahead(args, recording, tracked, setting, |keyframes| {
        crate::calibration::focal::estimate_from_keyframes(keyframes, camera, &args.pipeline)
    }) {
        Ok((e, elapsed_ms)) => {
            let applied = e.applied();
            (
                crate::calibration::focal::scaled(&camera, applied),
                json!({
                    "setting": true,
                    "scale": e.scale,
                    "applied_scale": applied,
                    "standard_error": e.standard_error,
                    "per_window": e.per_window,
                    "estimation_ms": elapsed_ms,
                }),
            )
        }
        Err(report) => (camera, report),
    }
}

/// Under `--calibrate-radial` (true, or auto for a calibration without distortion terms)
/// the camera with the radial term of the input's first windows added to its k1
/// (focal.rs) when they agree on a clear one, else `camera`; and what was done, for the
/// report.
pub fn resolve_radial(
    args: &RunArgs,
    (input, layout): (&Path, &Layout),
    camera: PinholeRadtan,
    tracked: Option<&FirstKeyframes>,
) -> (PinholeRadtan, serde_json::Value) {
    let setting = args.pipeline.calibrate_radial;
    if setting == RadialSetting::Auto && !setting.applies_to(&camera) {
        return (
            camera,
            json!({ "setting": "auto", "skipped": "the calibration has distortion terms: trusted" }),
        );
    }
    let setting = (setting.applies_to(&camera), "radial");
    let recording = (input, layout, camera);
    match read_ahead(args, recording, tracked, setting, |keyframes| {
        crate::calibration::focal::radial_from_keyframes(keyframes, camera, &args.pipeline)
    }) {
        Ok((e, elapsed_ms)) => {
            let applied = e.applied();
            (
                crate::calibration::focal::with_radial(&camera, applied),
                json!({
                    "setting": true,
                    "k": e.k,
                    "applied_k": applied,
                    "standard_error": e.standard_error,
                    "per_window": e.per_window,
                    "estimation_ms": elapsed_ms,
                }),
            )
        }
        Err(report) => (camera, report),
    }
}

/// When the radial term is self-calibrated (`--calibrate-radial`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RadialSetting {
    /// Only for a calibration without distortion terms (rectified images, or a pinhole
    /// from a datasheet): the residual of a rectification is what one radial term
    /// captures. A calibration that models its lens is trusted: on tum_fr1_rpy's
    /// in-repo JPEG clip (five distortion terms given) the windows agreed on k = -0.014,
    /// which made the map worse (keyframe ATE 1.47 -> 1.64 cm), and the same frames as
    /// PNG gave -0.008.
    Auto,
    /// Always estimated (applied when clear).
    On,
    /// Never.
    Off,
}

impl RadialSetting {
    /// Whether to estimate for `camera`: the first term of its lens model (radial-tangential
    /// k1, equidistant k1, double sphere xi), a fisheye's measured on its own image.
    pub fn applies_to(self, camera: &PinholeRadtan) -> bool {
        match self {
            RadialSetting::Auto => camera.distortion.iter().all(|d| *d == 0.0),
            RadialSetting::On => true,
            RadialSetting::Off => false,
        }
    }
}

impl std::str::FromStr for RadialSetting {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        match text.to_ascii_lowercase().as_str() {
            "auto" => Ok(RadialSetting::Auto),
            "true" => Ok(RadialSetting::On),
            "false" => Ok(RadialSetting::Off),
            _ => Err(format!("{text}: auto, true or false")),
        }
    }
}

impl std::fmt::Display for RadialSetting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            RadialSetting::Auto => "auto",
            RadialSetting::On => "true",
            RadialSetting::Off => "false",
        })
    }
}

impl<'de> serde::Deserialize<'de> for RadialSetting {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Value {
            Bool(bool),
            Word(String),
        }
        match Value::deserialize(d)? {
            Value::Bool(true) => Ok(RadialSetting::On),
            Value::Bool(false) => Ok(RadialSetting::Off),
            Value::Word(w) => w.parse(),
        }
        .map_err(|e| serde::de::Error::custom(format!("calibrate_radial = {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_estimates_the_radial_term_only_where_the_calibration_models_no_lens() {
        let pinhole =
            PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
        let lens = PinholeRadtan {
            distortion: [0.26, -0.95, 0.0, 0.0, 1.16],
            ..pinhole
        };
        assert!(RadialSetting::Auto.applies_to(&pinhole));
        assert!(!RadialSetting::Auto.applies_to(&lens));
        assert!(RadialSetting::On.applies_to(&lens));
        assert!(!RadialSetting::Off.applies_to(&pinhole));
        // A fisheye as well: its first term when nominal, trusted when calibrated.
        let nominal_fisheye = pinhole
            .with_lens(egoslam_geometry::LensModel::Equidistant)
            .expect("camera");
        assert!(RadialSetting::Auto.applies_to(&nominal_fisheye));
        let calibrated_fisheye = PinholeRadtan {
            distortion: [0.02, -0.003, 0.0, 0.0, 0.0],
            ..nominal_fisheye
        };
        assert!(!RadialSetting::Auto.applies_to(&calibrated_fisheye));
        for (text, setting) in [
            ("auto", RadialSetting::Auto),
            ("TRUE", RadialSetting::On),
            ("false", RadialSetting::Off),
        ] {
            assert_eq!(text.parse::<RadialSetting>(), Ok(setting));
            assert_eq!(
                setting.to_string().parse::<RadialSetting>(),
                Ok(setting),
                "round trip"
            );
        }
        assert!("yes".parse::<RadialSetting>().is_err());
        #[derive(serde::Deserialize)]
        struct Section {
            calibrate_radial: RadialSetting,
        }
        for (toml_text, setting) in [
            ("calibrate_radial = \"auto\"", RadialSetting::Auto),
            ("calibrate_radial = true", RadialSetting::On),
            ("calibrate_radial = false", RadialSetting::Off),
        ] {
            let s: Section = toml::from_str(toml_text).expect("parses");
            assert_eq!(s.calibrate_radial, setting);
        }
        assert!(toml::from_str::<Section>("calibrate_radial = 3").is_err());
    }
}
