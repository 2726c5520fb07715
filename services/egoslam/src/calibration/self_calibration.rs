//! `egoslam run`'s intrinsics self-calibration before the services start
//! (`--calibrate-focal`, `--calibrate-radial`; focal.rs estimates): each estimates from the
//! input's first keyframes, those the readout pre-pass tracked on its way when it found no
//! readout (the same frames, tracker and camera), else read again from the input's start,
//! and reports what it did for report.json.

use crate::calibration::focal::{first_keyframes, FOCAL_FRAMES};
use crate::calibration::readout::FirstKeyframes;
use crate::calibration::settings::{RadialSetting, Readout};
use crate::options::RunArgs;
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
        None => open_source(input, args.sequence.rate.fps)
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
