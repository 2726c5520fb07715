//! The rolling-shutter readout of a frontend service given `auto` (`--rolling-shutter-ms`):
//! a live stream cannot be read ahead (`egoslam run` resolves `auto` for recorded inputs
//! before the services start), so the frontend estimates it from its first frames
//! (`egoslam_frontend::readout_estimation`), corrects from then on, and saves it in the
//! state folder for a restarted frontend and for the merger's saved map.

use egoslam_frontend::{
    EarlyGlobalShutter, FrameTracks, OnlineReadout, OnlineReadoutEstimator, ReadoutEstimate,
    ReadoutEstimationOptions, Tracker,
};
use std::path::Path;

/// Attempts of the online estimation (`readout_frames` each) before a global shutter is
/// assumed: at the default 150, 20 s of a still or blind start at 30 fps.
const ONLINE_ATTEMPTS: u32 = 4;

/// The readout (s) a frontend service starts with: `given_ms`, else (`auto`) the one an
/// earlier frontend of this run estimated and saved in `out`; else 0 and the online
/// estimator over the first `readout_frames` frames.
pub fn service_readout(
    given_ms: Option<f64>,
    readout_frames: u32,
    out: &Path,
) -> (f64, Option<OnlineReadoutEstimator>) {
    match given_ms.or_else(|| egoslam_durability::estimated_readout::read(out)) {
        Some(ms) => {
            if given_ms.is_none() {
                tracing::info!(
                    readout_ms = ms,
                    "rolling-shutter readout of this run, estimated before a restart"
                );
            }
            (ms / 1000.0, None)
        }
        None => {
            tracing::info!(
                frames = readout_frames,
                "rolling-shutter readout: estimated from the first frames of the stream (uncorrected until then)"
            );
            let estimator = OnlineReadoutEstimator::new(
                ReadoutEstimationOptions::default(),
                readout_frames as usize,
                ONLINE_ATTEMPTS,
            )
            .deciding_global_shutter_early(EarlyGlobalShutter::default());
            (0.0, Some(estimator))
        }
    }
}

/// Feeds the frame just tracked to the online estimator; once it decides, sets the
/// tracker's readout, saves it for a restart and returns true.
pub fn observe_online(
    online: &mut OnlineReadoutEstimator,
    tracker: &mut Tracker,
    timestamp_s: f64,
    out: &Path,
) -> anyhow::Result<bool> {
    let frame = FrameTracks {
        timestamp_s,
        tracks: tracker.sample_tracks(usize::MAX),
    };
    let readout_s = match online.push(frame, &tracker.camera()) {
        OnlineReadout::Collecting => return Ok(false),
        OnlineReadout::Estimated(e) => {
            log_estimate(&e, "online; corrected from now on");
            write_details(out, &e)?;
            e.readout_s
        }
        OnlineReadout::GaveUp(e) => {
            tracing::warn!(
                "no rolling-shutter readout estimate ({e}): a global shutter is assumed"
            );
            0.0
        }
    };
    adopt(tracker, readout_s, out)?;
    Ok(true)
}

/// File (in the state folder) with the figures of the online estimate, for the run's
/// report (JSON).
pub const DETAILS_FILE: &str = "frontend.readout_estimate.json";

/// Writes the estimate's figures to [`DETAILS_FILE`] (before the readout itself, which
/// tells the run the estimate is made).
fn write_details(out: &Path, e: &ReadoutEstimate) -> anyhow::Result<()> {
    let details = serde_json::json!({
        "best_ms": e.best_s * 1e3,
        "significant": e.significant,
        "residual_px": e.residual_px,
        "residual_at_zero_px": e.residual_at_zero_px,
        "frame_pairs": e.pairs,
    });
    let path = egoslam_durability::state_dir(out).join(DETAILS_FILE);
    egoslam_durability::write_atomically(&path, details.to_string().as_bytes())?;
    Ok(())
}

/// At the end of a stream shorter than the estimation's frames: the estimate from what
/// was collected (as reading the recording ahead would make), set on the tracker and saved.
pub fn finish_online(
    mut online: OnlineReadoutEstimator,
    tracker: &mut Tracker,
    out: &Path,
) -> anyhow::Result<f64> {
    let readout_s = match online.finish(&tracker.camera()) {
        Ok(e) => {
            log_estimate(
                &e,
                "from the whole stream, shorter than the estimation's frames",
            );
            write_details(out, &e)?;
            e.readout_s
        }
        Err(e) => {
            tracing::warn!(
                "no rolling-shutter readout estimate ({e}): a global shutter is assumed"
            );
            0.0
        }
    };
    adopt(tracker, readout_s, out)?;
    Ok(readout_s)
}

/// Corrects with `readout_s` from now on, and saves it for a restart.
fn adopt(tracker: &mut Tracker, readout_s: f64, out: &Path) -> anyhow::Result<()> {
    tracker.set_rolling_shutter_s(readout_s);
    egoslam_durability::estimated_readout::write(out, readout_s * 1e3)?;
    Ok(())
}

/// Logs an estimate with the residuals it rests on, and what to do when it found none.
pub fn log_estimate(e: &ReadoutEstimate, how: &str) {
    tracing::info!(
        readout_ms = e.readout_s * 1e3,
        best_ms = e.best_s * 1e3,
        residual_px = e.residual_px,
        residual_at_zero_px = e.residual_at_zero_px,
        pairs = e.pairs,
        "rolling-shutter readout estimated {how}"
    );
    if !e.significant {
        // Measured on a rendered walk straight ahead with head turns at a 20 ms readout:
        // no clear gain (0.8 %), taken as a global shutter, twice the error of told 20 ms
        // (docs/config.md).
        tracing::info!(
            "no clear rolling-shutter readout: taken as a global shutter; walking straight ahead can hide one, so for a rolling-shutter camera measure it on a recording of the head turning while standing still (`egoslam calibrate-readout`) and give --rolling-shutter-ms"
        );
    }
}
