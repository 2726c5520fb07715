//! The rolling-shutter readout setting (`--rolling-shutter-ms`, `frontend.rolling_shutter_ms`):
//! a time in milliseconds, or `auto`, estimated from the video
//! (`egoslam_frontend::readout_estimation`). `egoslam run` resolves it before the services
//! start by tracking the first frames of a recorded input; a frontend service given `auto`
//! (a live stream, which cannot be read ahead) estimates it from its first frames and
//! corrects from then on (`egoslam_frontend_service::online_readout`). `egoslam calibrate-readout` prints the estimate for a recording.

use crate::cli::PipelineArgs;
use anyhow::{bail, Context};
use egoslam_frontend::{
    estimate_readout, FrameTracks, KeyframePolicy, ReadoutEstimate, ReadoutEstimationError,
    ReadoutEstimationOptions, Tracker, TrackerOptions,
};
use egoslam_geometry::PinholeRadtan;
use egoslam_sources::{detect_layout, load_calibration, open_source, Frame, FrameSource, Layout};
use opencv::prelude::*;
use std::path::PathBuf;

pub use egoslam_durability::estimated_readout::MAX_READOUT_MS;

/// Frames `auto` tracks before the run (150: 5 s at 30 fps, ~1.3 s of tracking, which is
/// most of the pre-pass). 300 gave the same estimates on every sequence here (rendered
/// 30 ms walks 29-30 ms, the 15 ms shake 16 ms, tum_fr1_rpy's 120 frames 22 ms, 0 on the
/// global-shutter ones) at twice the cost.
pub const AUTO_FRAMES: u32 = 150;

/// The readout the frontend corrects for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Readout {
    /// Estimated from the video (recorded inputs; see the module doc).
    Auto,
    /// Given, ms from the first row to the last (0: a global shutter).
    Millis(f64),
}

impl Readout {
    /// The readout given, ms (None: `auto`).
    pub fn given_ms(self) -> Option<f64> {
        match self {
            Readout::Millis(ms) => Some(ms),
            Readout::Auto => None,
        }
    }
}

impl std::str::FromStr for Readout {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        if text.eq_ignore_ascii_case("auto") {
            return Ok(Readout::Auto);
        }
        let v: f64 = text
            .parse()
            .map_err(|e| format!("{text}: {e} (a time in ms, or auto)"))?;
        millis(v)
    }
}

fn millis(v: f64) -> Result<Readout, String> {
    if (0.0..=MAX_READOUT_MS).contains(&v) {
        Ok(Readout::Millis(v))
    } else {
        Err(format!(
            "{v}: must be between 0 and {MAX_READOUT_MS} ms, or auto"
        ))
    }
}

impl std::fmt::Display for Readout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Readout::Auto => write!(f, "auto"),
            Readout::Millis(ms) => write!(f, "{ms}"),
        }
    }
}

impl<'de> serde::Deserialize<'de> for Readout {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Value {
            Number(f64),
            Word(String),
        }
        match Value::deserialize(d)? {
            Value::Number(v) => millis(v),
            Value::Word(w) => w.parse(),
        }
        .map_err(|e| serde::de::Error::custom(format!("rolling_shutter_ms = {e}")))
    }
}

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
    let mut tracker = Tracker::new(camera, tracker_options(pipeline, 0.0));
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

/// The tracker's options from the pipeline's, with the readout given in seconds.
pub fn tracker_options(pipeline: &PipelineArgs, rolling_shutter_s: f64) -> TrackerOptions {
    TrackerOptions {
        target_tracks: pipeline.tracks,
        lk_window_px: pipeline.lk_window,
        predict_motion: pipeline.predict_motion,
        rolling_shutter_s,
        keyframes: KeyframePolicy {
            max_frames_between: pipeline.keyframe_every,
            max_mean_flow_px: pipeline.keyframe_flow_px,
            ..KeyframePolicy::default()
        },
        ..TrackerOptions::default()
    }
}

/// `egoslam calibrate-readout`: estimate a recording's readout and print it.
#[derive(clap::Args, Debug)]
pub struct CalibrateReadoutArgs {
    /// The recording (any input `run` takes, not a live camera): a few seconds of turning
    /// the head, up and down as well as sideways.
    #[arg(long)]
    pub input: PathBuf,
    /// Frame rate of image folders and videos without one.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Calibration file (default: found next to the input, docs/config.md).
    #[arg(long)]
    pub calib: Option<PathBuf>,
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
    let mut source = open_source(input, args.fps)?;
    let first = source
        .next_frame()
        .with_context(|| format!("{}: no frames", input.display()))??;
    let camera = load_calibration(&layout, args.calib.as_deref())?
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_times_and_auto_and_refuses_the_rest() {
        assert_eq!("auto".parse::<Readout>(), Ok(Readout::Auto));
        assert_eq!("AUTO".parse::<Readout>(), Ok(Readout::Auto));
        assert_eq!("25".parse::<Readout>(), Ok(Readout::Millis(25.0)));
        assert!("-1".parse::<Readout>().is_err());
        assert!("101".parse::<Readout>().is_err());
        assert!("fast".parse::<Readout>().is_err());
        assert_eq!(Readout::Millis(12.5).to_string(), "12.5");
        #[derive(serde::Deserialize)]
        struct Section {
            rolling_shutter_ms: Readout,
        }
        let s: Section = toml::from_str("rolling_shutter_ms = 20").expect("number");
        assert_eq!(s.rolling_shutter_ms, Readout::Millis(20.0));
        let s: Section = toml::from_str("rolling_shutter_ms = \"auto\"").expect("auto");
        assert_eq!(s.rolling_shutter_ms, Readout::Auto);
        assert!(toml::from_str::<Section>("rolling_shutter_ms = 500").is_err());
    }
}
