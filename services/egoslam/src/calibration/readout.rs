//! The rolling-shutter readout setting (`--rolling-shutter-ms`, `frontend.rolling_shutter_ms`):
//! a time in milliseconds, or `auto`, estimated from the video
//! (`egoslam_frontend::readout_estimation`). `egoslam run` resolves it before the services
//! start by tracking the first frames of a recorded input; a frontend service given `auto`
//! (a live stream, which cannot be read ahead) estimates it from its first frames and
//! corrects from then on (`egoslam_frontend_service::online_readout`). `egoslam calibrate-readout` prints the estimate for a recording.

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
    estimate_and_track(first, source, camera, pipeline, 0).0
}

/// The first keyframes of a recording as the focal and radial self-calibrations take them
/// (`focal::first_keyframes`, tracked with no readout through `camera`).
pub struct FirstKeyframes {
    pub camera: PinholeRadtan,
    pub keyframes: Vec<egoslam_solver::view_graph::KeyframeObservations>,
}

/// [`estimate_from_source`], tracking on to the first `keyframe_frames` frames for
/// [`FirstKeyframes`] when that is more: the self-calibrations then need not read and track
/// them again when the readout comes out 0. `None` when a frame up to there could not be
/// read or tracked (the self-calibration reads them again and reports why).
pub fn estimate_and_track(
    first: Frame,
    source: &mut dyn FrameSource,
    camera: PinholeRadtan,
    pipeline: &PipelineArgs,
    keyframe_frames: usize,
) -> (
    Result<ReadoutEstimate, ReadoutEstimationError>,
    Option<FirstKeyframes>,
) {
    let mut tracker = Tracker::new(camera, pipeline.tracker_options(0.0));
    let mut tracked = Vec::new();
    let mut keyframes = crate::calibration::focal::KeyframeCollector::default();
    let mut complete = true;
    let readout_frames = pipeline.readout_frames as usize;
    let frames = std::iter::once(Ok(first)).chain(std::iter::from_fn(|| source.next_frame()));
    for (k, frame) in frames.take(readout_frames.max(keyframe_frames)).enumerate() {
        let frame = match frame {
            Ok(frame) => frame,
            Err(e) => {
                tracing::warn!(%e, "readout estimation stops where the source gave up");
                complete = false;
                break;
            }
        };
        let outcome = match tracker.process_timed(frame.index, frame.timestamp, &frame.image) {
            Ok(outcome) => outcome,
            Err(e) => {
                tracing::warn!(%e, "readout estimation stops at a frame it cannot track");
                complete = false;
                break;
            }
        };
        if k < readout_frames {
            tracked.push(FrameTracks {
                timestamp_s: frame.timestamp,
                tracks: tracker.sample_tracks(usize::MAX),
            });
        }
        // Exactly the frames the self-calibrations would track themselves.
        if k < keyframe_frames {
            keyframes.push(&tracker, outcome, frame.timestamp);
        }
    }
    let keyframes = (complete && keyframe_frames > 0).then(|| FirstKeyframes {
        camera,
        keyframes: keyframes.finish(),
    });
    (estimate_tracked(&tracked, &camera), keyframes)
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
