//! The focal and radial self-calibrations (`--calibrate-focal`, `--calibrate-radial`) made
//! from the stream the solver receives instead of a pass over the input before the start.
//!
//! `egoslam run` starts a recorded input's services with the calibration as given and asks
//! the solver for the estimates (`--estimate-intrinsics`): the solver keeps the
//! observations of the keyframes of the stream's first [`FIRST_FRAMES`] frames (what the
//! pre-pass tracked: the same tracker, frames and readout), solves their first windows
//! with the intrinsics free on a thread of its own (`egoslam_solver::focal_calibration`)
//! while the stream goes on, and writes the estimates to [`FILE_NAME`] in the state
//! folder. The run goes on when none applies; when one does, `egoslam run` starts it again
//! with the corrected camera, so that every process and the saved camera use it from the
//! first frame.

use egoslam_geometry::PinholeRadtan;
use egoslam_messages::internal::v1 as internal;
pub use egoslam_solver::focal_calibration::FIRST_FRAMES;
use egoslam_solver::focal_calibration::{
    estimate_focal_scale, estimate_radial_term, FocalCalibrationOptions,
};
use egoslam_solver::view_graph::KeyframeObservations;
use egoslam_solver::window_solver::WindowSolverOptions;
use serde_json::json;
use std::path::PathBuf;
use std::thread::JoinHandle;

/// The estimates' file in the state folder (JSON; written once, atomically).
pub const FILE_NAME: &str = "intrinsics_estimate.json";

/// What to estimate, with what.
#[derive(Debug, Clone)]
pub struct IntrinsicsRequest {
    /// The calibration as given (the lens model and distortion the estimates refine).
    pub camera: PinholeRadtan,
    pub radial: bool,
    pub focal: bool,
    /// The windows the estimates solve: the run's window size and overlap.
    pub options: FocalCalibrationOptions,
    pub solver: WindowSolverOptions,
}

/// Collects the first frames' keyframes and estimates from them once they are in.
pub struct IntrinsicsEstimation {
    request: IntrinsicsRequest,
    state_dir: PathBuf,
    first_frame: Option<u64>,
    keyframes: Vec<KeyframeObservations>,
    worker: Option<JoinHandle<()>>,
}

impl IntrinsicsEstimation {
    pub fn new(request: IntrinsicsRequest, state_dir: PathBuf) -> Self {
        Self {
            request,
            state_dir,
            first_frame: None,
            keyframes: Vec::new(),
            worker: None,
        }
    }

    /// Takes keyframe `k` (its observations as the solver takes them): kept while it lies
    /// in the stream's first [`FIRST_FRAMES`] frames; the first keyframe beyond starts the
    /// estimation. The stream's last keyframe (made at its end, not by the tracker's rules)
    /// is not one the pre-pass saw, and is left out.
    pub fn observe(&mut self, k: &internal::Keyframe) {
        if self.worker.is_some() {
            return;
        }
        let first = *self.first_frame.get_or_insert(k.frame_id);
        if k.frame_id >= first + FIRST_FRAMES as u64 {
            self.start();
        } else if k.reason() != internal::KeyframeReason::Last {
            self.keyframes.push(crate::valid_observations(k).0);
        }
    }

    /// At the end of the stream: estimates from what came, if not begun already; then
    /// waits for the estimates to be written.
    pub fn finish(mut self) {
        if self.worker.is_none() {
            self.start();
        }
        if let Some(worker) = self.worker.take() {
            if worker.join().is_err() {
                tracing::error!("the intrinsics estimation panicked: no estimate");
            }
        }
    }

    fn start(&mut self) {
        let keyframes = std::mem::take(&mut self.keyframes);
        let request = self.request.clone();
        let path = self.state_dir.join(FILE_NAME);
        self.worker = Some(std::thread::spawn(move || {
            let _span =
                tracing::info_span!("estimate_intrinsics", keyframes = keyframes.len()).entered();
            let estimates = estimate(&request, &keyframes);
            if let Err(e) =
                egoslam_durability::write_atomically(&path, estimates.to_string().as_bytes())
            {
                tracing::error!(
                    "{}: {e}; the run keeps the calibration as given",
                    path.display()
                );
            }
        }));
    }
}

/// The requested estimates of `keyframes` as JSON: for each, the estimate's figures and
/// whether it applies, or why there is none.
fn estimate(request: &IntrinsicsRequest, keyframes: &[KeyframeObservations]) -> serde_json::Value {
    let (camera, options, solver) = (&request.camera, &request.options, &request.solver);
    let radial = request.radial.then(|| {
        match estimate_radial_term(camera, keyframes, options, solver) {
            Ok(e) => {
                tracing::info!(k = e.k, standard_error = e.standard_error, windows = e.per_window.len(), applied = e.significant, "radial distortion estimated from the stream's first windows");
                json!({ "k": e.k, "applied_k": e.applied(), "standard_error": e.standard_error, "per_window": e.per_window })
            }
            Err(e) => json!({ "error": format!("{e} ({} keyframes)", keyframes.len()) }),
        }
    });
    let focal = request.focal.then(|| {
        match estimate_focal_scale(camera, keyframes, options, solver) {
            Ok(e) => {
                tracing::info!(scale = e.scale, standard_error = e.standard_error, windows = e.per_window.len(), applied = e.significant, "focal length estimated from the stream's first windows");
                json!({ "scale": e.scale, "applied_scale": e.applied(), "standard_error": e.standard_error, "per_window": e.per_window })
            }
            Err(e) => json!({ "error": format!("{e} ({} keyframes)", keyframes.len()) }),
        }
    });
    json!({ "keyframes": keyframes.len(), "radial": radial, "focal": focal })
}
