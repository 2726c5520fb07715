//! `egoslam run`'s intrinsics self-calibration before the services start
//! (`--calibrate-focal`, `--calibrate-radial`; focal.rs estimates): each reads the input
//! again from its start, and reports what it did for report.json.

use crate::cli::RunArgs;
use crate::readout::Readout;
use egoslam_geometry::PinholeRadtan;
use egoslam_sources::{open_source, FrameSource, Layout};
use serde_json::json;
use std::path::Path;
use std::time::Instant;

/// Runs `estimate` on the input read again from its start, with the run's readout, and
/// times it; `Err` is the report of why nothing was estimated (`setting` off, a live
/// camera, or the estimate's error).
fn read_ahead<T>(
    args: &RunArgs,
    input: &Path,
    layout: &Layout,
    (setting, what): (bool, &str),
    estimate: impl FnOnce(&mut dyn FrameSource, f64) -> anyhow::Result<T>,
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
    let result = open_source(input, args.fps)
        .map_err(anyhow::Error::from)
        .and_then(|mut source| estimate(source.as_mut(), readout_s));
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
    input: &Path,
    layout: &Layout,
    camera: PinholeRadtan,
) -> (PinholeRadtan, serde_json::Value) {
    let setting = (args.pipeline.calibrate_focal, "focal");
    match read_ahead(args, input, layout, setting, |source, readout_s| {
        crate::focal::estimate_from_source(source, camera, &args.pipeline, readout_s)
    }) {
        Ok((e, elapsed_ms)) => {
            let applied = e.applied();
            (
                crate::focal::scaled(&camera, applied),
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

/// Under `--calibrate-radial true` the camera with the radial term of the input's first
/// windows added to its k1 (focal.rs) when they agree on a clear one, else `camera`; and
/// what was done, for the report.
pub fn resolve_radial(
    args: &RunArgs,
    input: &Path,
    layout: &Layout,
    camera: PinholeRadtan,
) -> (PinholeRadtan, serde_json::Value) {
    let setting = (args.pipeline.calibrate_radial, "radial");
    match read_ahead(args, input, layout, setting, |source, readout_s| {
        crate::focal::radial_from_source(source, camera, &args.pipeline, readout_s)
    }) {
        Ok((e, elapsed_ms)) => {
            let applied = e.applied();
            (
                crate::focal::with_radial(&camera, applied),
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
