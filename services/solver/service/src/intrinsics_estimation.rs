//! The focal and radial self-calibrations (`--calibrate-focal`, `--calibrate-radial`) made
//! from the stream the solver receives instead of a pass over the input before the start.
//!
//! `egoslam run` starts a recorded input's services with the calibration as given and asks
//! the solver for the estimates (`--estimate-intrinsics`): the solver keeps the
//! observations of the keyframes of the stream's first [`FIRST_FRAMES`] frames (those a
//! pass over the recording would track: the same tracker, frames and readout), solves
//! their first windows with the intrinsics free on a thread of its own as each is complete
//! (`egoslam_solver::focal_calibration`) while the stream goes on, and writes the estimates
//! to [`FILE_NAME`] in the state folder. A window is handed to the thread after the
//! solver's own window over the same keyframes, with the relative poses that window
//! computed ([`IntrinsicsEstimation::share_edges`]): the view graph does not depend on the
//! intrinsics left free, so the estimates skip the five-point stage the solver already ran.
//! The run goes on when none applies; when one does, `egoslam run` starts it again
//! with the corrected camera, so that every process and the saved camera use it from the
//! first frame.

use egoslam_geometry::PinholeRadtan;
use egoslam_messages::internal::v1 as internal;
pub use egoslam_solver::focal_calibration::FIRST_FRAMES;
use egoslam_solver::focal_calibration::{
    pool_focal_scales, pool_radial_terms, solve_first_window, FirstWindows,
    FocalCalibrationOptions, Intrinsic,
};
use egoslam_solver::view_graph::{EdgeCache, KeyframeObservations, ViewGraphOptions};
use egoslam_solver::window_solver::WindowSolverOptions;
use serde_json::json;
use std::path::PathBuf;
use std::sync::mpsc;
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

/// Collects the first frames' keyframes into the estimates' windows, each solved on the
/// estimation's thread once the solver has solved its window over them (so that little is
/// left to solve when the first frames end, often with the stream), and pools them at the
/// end.
pub struct IntrinsicsEstimation {
    first_frame: Option<u64>,
    keyframes: Vec<KeyframeObservations>,
    windows: Option<FirstWindows>,
    /// Complete windows waiting for the solver's relative poses.
    waiting: Vec<Vec<KeyframeObservations>>,
    /// What the estimates' view graph is built with: edges are shared only when the
    /// solver's are built with the same.
    camera: PinholeRadtan,
    view_graph: ViewGraphOptions,
    to_solve: Option<mpsc::Sender<WindowToSolve>>,
    worker: Option<JoinHandle<()>>,
}

/// A window of the estimates and the relative poses already known between its keyframes.
struct WindowToSolve {
    keyframes: Vec<KeyframeObservations>,
    edges: EdgeCache,
}

impl IntrinsicsEstimation {
    pub fn new(request: IntrinsicsRequest, state_dir: PathBuf) -> Self {
        let windows = match FirstWindows::new(&request.options) {
            Ok(w) => Some(w),
            Err(e) => {
                tracing::warn!("no intrinsics estimate: {e}");
                None
            }
        };
        let (camera, view_graph) = (request.camera, request.solver.view_graph);
        let (to_solve, solve) = mpsc::channel();
        let path = state_dir.join(FILE_NAME);
        let worker = windows
            .is_some()
            .then(|| std::thread::spawn(move || write(&path, &solve_and_pool(&request, solve))));
        Self {
            first_frame: None,
            keyframes: Vec::new(),
            windows,
            waiting: Vec::new(),
            camera,
            view_graph,
            to_solve: Some(to_solve),
            worker,
        }
    }

    /// Takes keyframe `k` (its observations as the solver takes them) while it lies in
    /// the stream's first [`FIRST_FRAMES`] frames; the first keyframe beyond ends the
    /// collection. The stream's last keyframe (made at its end, not by the tracker's rules)
    /// is not one the estimates would take from a recording's first frames, and is left
    /// out.
    pub fn observe(&mut self, k: &internal::Keyframe) {
        if self.windows.is_none() || k.reason() == internal::KeyframeReason::Last {
            return;
        }
        let first = *self.first_frame.get_or_insert(k.frame_id);
        if k.frame_id >= first + FIRST_FRAMES as u64 {
            self.end();
            return;
        }
        self.keyframes.push(crate::valid_observations(k).0);
        let window = self.windows.as_mut().and_then(FirstWindows::push);
        self.hold(window);
    }

    /// The last window, and no more.
    fn end(&mut self) {
        let window = self.windows.take().and_then(FirstWindows::finish);
        self.hold(window);
        self.keyframes = Vec::new();
    }

    fn hold(&mut self, window: Option<std::ops::RangeInclusive<usize>>) {
        if let Some(range) = window {
            self.waiting.push(self.keyframes[range].to_vec());
        }
    }

    /// Hands the complete windows to the estimation's thread with the relative poses the
    /// solver computed between their keyframes (`cache`, after the solver's window; built
    /// on `camera` with `view_graph`: none are taken when either differs from the
    /// estimates'). Called after each of the solver's windows.
    pub fn share_edges(
        &mut self,
        cache: &EdgeCache,
        camera: &PinholeRadtan,
        view_graph: &ViewGraphOptions,
    ) {
        let same_graph = (camera.fx, camera.fy, camera.cx, camera.cy)
            == (
                self.camera.fx,
                self.camera.fy,
                self.camera.cx,
                self.camera.cy,
            )
            && *view_graph == self.view_graph;
        self.hand_over(|keyframes| {
            if !same_graph {
                return EdgeCache::new();
            }
            let ids: std::collections::HashSet<u64> = keyframes.iter().map(|k| k.id).collect();
            cache
                .iter()
                .filter(|((a, b), _)| ids.contains(a) && ids.contains(b))
                .map(|(key, edge)| (*key, edge.clone()))
                .collect()
        });
        if self.windows.is_none() {
            self.to_solve = None;
        }
    }

    /// Sends the waiting windows to the estimation's thread, each with `edges_of` it.
    fn hand_over(&mut self, edges_of: impl Fn(&[KeyframeObservations]) -> EdgeCache) {
        for keyframes in std::mem::take(&mut self.waiting) {
            if let Some(to_solve) = &self.to_solve {
                let edges = edges_of(&keyframes);
                // The worker is gone only after a panic, which `finish` reports.
                let _ = to_solve.send(WindowToSolve { keyframes, edges });
            }
        }
    }

    /// The stream ended (before the solver's last window): the last window, if the first
    /// frames lasted that long, waits for that window's relative poses.
    pub fn stream_ended(&mut self) {
        if self.windows.is_some() {
            self.end();
        }
    }

    /// After the solver's last window: hands over what still waits (without relative
    /// poses) and waits until the estimates are written.
    pub fn finish(mut self) {
        self.stream_ended();
        self.hand_over(|_| EdgeCache::new());
        self.to_solve = None;
        if self.worker.take().is_some_and(|w| w.join().is_err()) {
            tracing::error!("the intrinsics estimation panicked: no estimate");
        }
    }
}

/// Writes the estimates to `path` (the thread's last step: once the first frames' windows
/// are solved, while the stream goes on, so that the run can start again early).
fn write(path: &std::path::Path, estimates: &serde_json::Value) {
    if let Err(e) = egoslam_durability::write_atomically(path, estimates.to_string().as_bytes()) {
        tracing::error!(
            "{}: {e}; the run keeps the calibration as given",
            path.display()
        );
    }
}

/// The estimation's thread: solves each window as it comes, for each intrinsic asked
/// (one edge cache each, as `focal_calibration::first_window_terms`), then pools them.
fn solve_and_pool(
    request: &IntrinsicsRequest,
    windows: mpsc::Receiver<WindowToSolve>,
) -> serde_json::Value {
    let asked: Vec<Intrinsic> = [
        (request.focal, Intrinsic::Focal),
        (request.radial, Intrinsic::Radial),
    ]
    .into_iter()
    .filter_map(|(on, what)| on.then_some(what))
    .collect();
    let mut solvers: Vec<(Intrinsic, WindowSolverOptions, EdgeCache, Vec<f64>)> = asked
        .iter()
        .map(|&what| {
            (
                what,
                what.solver(&request.solver),
                EdgeCache::new(),
                Vec::new(),
            )
        })
        .collect();
    let mut keyframes = 0;
    for WindowToSolve {
        keyframes: window,
        edges,
    } in windows
    {
        let _span = tracing::info_span!("estimate_intrinsics", keyframes = window.len()).entered();
        keyframes += window.len();
        for (what, solver, cache, terms) in &mut solvers {
            cache.extend(edges.iter().map(|(key, edge)| (*key, edge.clone())));
            let solved = solve_first_window(&request.camera, &window, solver, cache);
            terms.extend(solved.as_ref().and_then(|s| what.term(s)));
        }
    }
    let options = &request.options;
    let mut estimates = json!({ "radial": null, "focal": null });
    for (what, _, _, terms) in solvers {
        let estimate = match what {
            Intrinsic::Focal => pool_focal_scales(terms, options).map(|e| {
                tracing::info!(scale = e.scale, standard_error = e.standard_error, windows = e.per_window.len(), applied = e.significant, "focal length estimated from the stream's first windows");
                json!({ "scale": e.scale, "applied_scale": e.applied(), "standard_error": e.standard_error, "per_window": e.per_window })
            }),
            Intrinsic::Radial => pool_radial_terms(terms, options).map(|e| {
                tracing::info!(k = e.k, standard_error = e.standard_error, windows = e.per_window.len(), applied = e.significant, "radial distortion estimated from the stream's first windows");
                json!({ "k": e.k, "applied_k": e.applied(), "standard_error": e.standard_error, "per_window": e.per_window })
            }),
        };
        let key = if what == Intrinsic::Focal {
            "focal"
        } else {
            "radial"
        };
        estimates[key] = estimate.unwrap_or_else(
            |e| json!({ "error": format!("{e} (windows of {keyframes} keyframes)") }),
        );
    }
    estimates
}
