//! The rolling-shutter readout setting (`--rolling-shutter-ms`, `frontend.rolling_shutter_ms`):
//! a time in milliseconds, or `auto`, estimated from the video
//! (`egoslam_frontend::readout_estimation`). The frontend estimates `auto` from the first
//! frames it tracks (`egoslam_frontend_service::online_readout`): on a live stream it holds
//! their keyframes until then; on a recorded input `egoslam run` starts the run again with
//! the readout when there is one (supervision/stream_calibration.rs).
//! `egoslam calibrate-readout` prints the estimate for a recording.

use crate::options::PipelineArgs;
use anyhow::{bail, Context};
use egoslam_frontend::{
    estimate_readout, FrameTracks, ReadoutEstimate, ReadoutEstimationError,
    ReadoutEstimationOptions, Tracker,
};
use egoslam_geometry::PinholeRadtan;
use egoslam_sources::{detect_layout, load_calibration, open_source, Frame, FrameSource, Layout};
use opencv::prelude::*;
use std::path::PathBuf;

/// Tracks an input's first `pipeline.readout_frames` frames (`first`, already read, then
/// the rest of `source`) with no readout correction and estimates the readout from them.
/// The source skips bad frames as the run does (FrameStream; the tracker then links the
/// frames either side and the fit uses their timestamps), so one bad file among the first
/// frames does not end the estimation; a source that gives up ends it.
pub fn estimate_from_source(
    first: Frame,
    source: &mut dyn FrameSource,
    camera: PinholeRadtan,
    pipeline: &PipelineArgs,
) -> Result<ReadoutEstimate, ReadoutEstimationError> {
    let mut tracker = Tracker::new(camera, pipeline.tracker_options(0.0));
    let mut tracked = Vec::new();
    let frames = std::iter::once(Ok(first)).chain(std::iter::from_fn(|| source.next_frame()));
    for frame in frames.take(pipeline.readout_frames as usize) {
        let frame = match frame {
            Ok(frame) => frame,
            Err(e) => {
                tracing::warn!(%e, "readout estimation stops where the source gave up");
                break;
            }
        };
        if let Err(e) = tracker.process_timed(frame.index, frame.timestamp, &frame.image) {
            tracing::warn!(%e, "readout estimation stops at a frame it cannot track");
            break;
        }
        tracked.push(FrameTracks {
            timestamp_s: frame.timestamp,
            tracks: tracker.sample_tracks(usize::MAX),
        });
    }
    estimate_tracked(&tracked, &camera)
}

/// The readout estimate of frames tracked with no correction, logged.
fn estimate_tracked(
    tracked: &[FrameTracks],
    camera: &PinholeRadtan,
) -> Result<ReadoutEstimate, ReadoutEstimationError> {
    let fit_started = std::time::Instant::now();
    let estimate = estimate_readout(tracked, camera, &ReadoutEstimationOptions::default())?;
    tracing::debug!(
        fit_ms = fit_started.elapsed().as_secs_f64() * 1e3,
        "readout fit"
    );
    egoslam_frontend_service::online_readout::log_estimate(
        &estimate,
        "from the input's first frames",
    );
    Ok(estimate)
}

/// `egoslam calibrate-readout`: estimate a recording's readout and print it.
#[derive(clap::Args, Debug)]
pub struct CalibrateReadoutArgs {
    /// The recording (any input `run` takes, not a live camera): a few seconds of turning
    /// the head, up and down as well as sideways.
    #[arg(long)]
    pub input: PathBuf,
    #[command(flatten)]
    pub rate: crate::options::FrameRateArgs,
    #[command(flatten)]
    pub calibration: crate::options::CalibrationArgs,
    #[command(flatten)]
    pub pipeline: PipelineArgs,
}

/// Prints the estimate as the configuration line to use.
pub fn calibrate(args: CalibrateReadoutArgs) -> anyhow::Result<()> {
    let input = &args.input;
    let layout = detect_layout(input)?;
    if matches!(layout, Layout::Camera { .. }) {
        bail!("calibrate-readout needs a recording, not a live camera: record a few seconds of turning the head and give that");
    }
    let mut source = open_source(input, args.rate.fps)?;
    let first = source
        .next_frame()
        .with_context(|| format!("{}: no frames", input.display()))??;
    let camera = load_calibration(&layout, args.calibration.calib.as_deref())?
        .camera_for(first.image.cols() as u32, first.image.rows() as u32)?;
    let e = estimate_from_source(first, &mut source, camera, &args.pipeline)
        .with_context(|| format!("estimating the readout of {}", input.display()))?;
    println!(
        "readout {:.0} ms ({} frame pairs; rotation-only residual {:.3} px, {:.3} px at a global shutter, best at {:.0} ms{})",
        e.readout_s * 1e3,
        e.pairs,
        e.residual_px,
        e.residual_at_zero_px,
        e.best_s * 1e3,
        if e.significant {
            ""
        } else {
            ": not a clear gain, so a global shutter; a rolling shutter can hide in a \
             recording that walks straight ahead, so for a rolling-shutter camera record \
             the head turning while standing still and run this on that"
        }
    );
    println!("[frontend]\nrolling_shutter_ms = {:.0}", e.readout_s * 1e3);
    Ok(())
}
