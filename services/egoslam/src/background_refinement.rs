//! The merger's global bundle adjustment on a background thread: started when the
//! cross-window reprojection error of a new window exceeds a threshold, folded back at the
//! next window boundary after it finished (or at the end of the stream), so that intake of
//! windows never waits for it. Poses it moves get a new revision when published.

use crate::stats::ServiceStats;
use egoslam_geometry::PinholeRadtan;
use egoslam_merger::{MapBuilder, RefinementOptions, RefinementOutcome};
use std::collections::BTreeSet;
use std::thread::JoinHandle;

/// The trigger and the running job, if any.
pub struct BackgroundRefiner {
    /// Start a refinement when a window's median cross-window reprojection error exceeds this.
    threshold_px: f64,
    options: RefinementOptions,
    worker: Option<JoinHandle<Option<RefinementOutcome>>>,
}

impl BackgroundRefiner {
    pub fn new(threshold_px: f64, keyframes: usize) -> Self {
        Self {
            threshold_px,
            options: RefinementOptions {
                keyframes,
                ..RefinementOptions::default()
            },
            worker: None,
        }
    }

    /// After a window was aligned: measures how well the map's earlier points reproject
    /// into the new keyframes and starts a refinement when that exceeds the threshold and
    /// none is running. Returns the measured error.
    pub fn after_window(
        &mut self,
        map: &MapBuilder,
        camera: &PinholeRadtan,
        new_keyframes: &[u64],
        new_tracks: &BTreeSet<u64>,
        stats: &mut ServiceStats,
    ) -> Option<f64> {
        let error = map.cross_window_error(camera, new_keyframes, new_tracks)?;
        let due = error > self.threshold_px && self.worker.is_none();
        tracing::debug!(cross_window_px = error, due, "cross-window error");
        if due {
            if let Some(job) = stats.time("refinement_job", || {
                map.refinement_job(camera, &self.options)
            }) {
                tracing::info!(
                    cross_window_px = error,
                    keyframes = job.keyframes(),
                    "starting a background refinement"
                );
                stats.count("refinements_started", 1);
                self.worker = Some(std::thread::spawn(move || {
                    let _span = tracing::info_span!("global_refinement").entered();
                    job.solve()
                }));
            }
        }
        Some(error)
    }

    /// Folds a finished refinement into `map`; with `wait`, waits for a running one first
    /// (end of stream). Returns whether the map changed.
    pub fn fold(&mut self, map: &mut MapBuilder, wait: bool, stats: &mut ServiceStats) -> bool {
        let finished = self.worker.as_ref().is_some_and(|w| w.is_finished());
        if !(finished || (wait && self.worker.is_some())) {
            return false;
        }
        let Some(worker) = self.worker.take() else {
            return false;
        };
        let wait_start = std::time::Instant::now();
        let outcome = match worker.join() {
            Ok(o) => o,
            Err(_) => {
                tracing::error!("the background refinement panicked; the map is unchanged");
                stats.count("refinements_failed", 1);
                return false;
            }
        };
        stats.add_time("refinement_wait", wait_start.elapsed().as_secs_f64() * 1e3);
        let Some(outcome) = outcome else {
            stats.count("refinements_failed", 1);
            return false;
        };
        let report = stats.time("refinement_fold", || map.apply_refinement(outcome));
        tracing::info!(
            keyframes = report.keyframes,
            points = report.points,
            rmse_px = report.rmse_px,
            iterations = report.iterations,
            outliers = report.outliers,
            carried_keyframes = report.carried_keyframes,
            "background refinement folded in"
        );
        stats.count("refinements_applied", 1);
        true
    }
}
