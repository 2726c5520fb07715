//! The merger's global bundle adjustment on a background thread: started when the
//! cross-window reprojection error of a new window exceeds a threshold and folded back at
//! a window boundary (or at the end of the stream). Poses it moves get a new revision when
//! published.
//!
//! *When* it is folded decides which later windows are chained onto the refined map, and
//! so the result. Folded "whenever it happens to have finished", two runs of the same input
//! differed by up to 40 % in keyframe ATE (TUM clip 2.43 vs 3.38 cm), which made single
//! runs useless for comparing changes. So by default it is folded a fixed number of windows
//! after it started, waiting for it if need be: the same input gives the same map. That
//! number is `fold_lag`, or more for a large job ([`KEYFRAMES_PER_LAG_WINDOW`]), so that
//! the intake seldom waits.

use super::tally::Tally;
use crate::refinement_rebase::LoopCorrections;
use crate::{LoopReport, MapBuilder, RefinementOptions, RefinementOutcome};
use egoslam_geometry::PinholeRadtan;
use std::collections::BTreeSet;
use std::thread::JoinHandle;

/// A refinement of N keyframes is folded no earlier than N / this windows after its start
/// (default 50). Measured on the rendered 12,000-frame walk: a 1500-keyframe job takes
/// ~30 s, while windows reach the merger every ~0.6 s in a lossless replay; with a lag of
/// 3 the merger finished about 4 minutes after the solver, with N / 50 (30 windows) it
/// waited 5 s in all for 9 refinements. Deterministic: the lag depends on the job, not
/// on the clock.
pub const KEYFRAMES_PER_LAG_WINDOW: usize = 50;

/// The fold lag of a job of `keyframes` keyframes (0 stays 0: fold whenever finished).
fn job_lag(fold_lag: u32, keyframes: usize) -> u32 {
    if fold_lag == 0 {
        return 0;
    }
    let by_size = u32::try_from(keyframes.div_ceil(KEYFRAMES_PER_LAG_WINDOW)).unwrap_or(u32::MAX);
    fold_lag.max(by_size)
}

/// The trigger and the running job, if any.
pub struct BackgroundRefiner {
    /// Start a refinement when a window's median cross-window reprojection error exceeds this.
    threshold_px: f64,
    options: RefinementOptions,
    /// Fold the refinement before the `fold_lag`-th window after the one that started it,
    /// waiting if it is still running; 0: whenever it has finished (no waiting, not
    /// reproducible).
    fold_lag: u32,
    /// Windows that arrived since the running refinement started.
    windows_since_start: u32,
    /// The lag of the running refinement (`fold_lag`, or more for a large job).
    job_lag: u32,
    worker: Option<JoinHandle<Option<RefinementOutcome>>>,
    /// The newest keyframe the running job knows (`None` when none runs).
    running_newest: Option<u64>,
    /// The oldest keyframe the running job holds (`None` when none runs).
    running_oldest: Option<u64>,
    /// Loops closed since the running job was made, replayed onto its result.
    loops_since_start: LoopCorrections,
}

impl BackgroundRefiner {
    /// `fold_lag`: see [`BackgroundRefiner::fold`].
    pub fn new(threshold_px: f64, keyframes: usize, fold_lag: u32) -> Self {
        Self {
            threshold_px,
            options: RefinementOptions {
                keyframes,
                ..RefinementOptions::default()
            },
            fold_lag,
            windows_since_start: 0,
            job_lag: fold_lag,
            worker: None,
            running_newest: None,
            running_oldest: None,
            loops_since_start: LoopCorrections::default(),
        }
    }

    /// Records a loop closed while a refinement runs, to replay onto its result at the fold
    /// (crate::refinement_rebase); nothing when none runs.
    pub fn record_loop(&mut self, report: &LoopReport) {
        if self.worker.is_some() {
            self.loops_since_start
                .record(&report.keyframe_moves, &report.point_owners);
        }
    }

    /// Whether the next window would have to wait for the running refinement (it is due
    /// before that window and still running). The merger keeps taking windows off the bus
    /// meanwhile and applies them once it finished.
    pub fn holds_next_window(&self) -> bool {
        self.fold_lag > 0
            && self.windows_since_start + 1 >= self.job_lag
            && self.worker.as_ref().is_some_and(|w| !w.is_finished())
    }

    /// Keyframes older than this are in no running refinement and may be removed (all of
    /// them when none runs).
    pub fn free_before(&self) -> u64 {
        match (&self.worker, self.running_oldest) {
            (None, _) => u64::MAX,
            (Some(_), Some(oldest)) => oldest,
            (Some(_), None) => 0,
        }
    }

    /// Whether a refinement is running (started, not folded yet).
    pub fn is_running(&self) -> bool {
        self.worker.is_some()
    }

    /// Whether a running refinement holds a copy of `keyframe` (or of a later one): its fold
    /// would then overwrite a change made to that keyframe meanwhile. Keyframes newer than
    /// everything the job knows are carried rigidly at the fold and may be changed.
    pub fn holds_keyframes_from(&self, keyframe: u64) -> bool {
        self.worker.is_some() && self.running_newest.is_none_or(|newest| newest >= keyframe)
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
        stats: &mut Tally,
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
                self.windows_since_start = 0;
                self.job_lag = job_lag(self.fold_lag, job.keyframes());
                self.running_newest = job.newest_known_keyframe();
                self.running_oldest = job.oldest_keyframe();
                self.loops_since_start = LoopCorrections::default();
                self.worker = Some(std::thread::spawn(move || {
                    let _span = tracing::info_span!("global_refinement").entered();
                    job.solve()
                }));
            }
        }
        Some(error)
    }

    /// Called once before each window is added (and at the end of the stream, with
    /// `end_of_stream`, when a running refinement is always waited for). With a `fold_lag`
    /// of N the refinement is folded before the N-th window after its start (more for a
    /// large job, [`KEYFRAMES_PER_LAG_WINDOW`]), waited for if still running, never
    /// earlier; with 0, whenever it has finished. Returns whether the map changed.
    pub fn fold(&mut self, map: &mut MapBuilder, end_of_stream: bool, stats: &mut Tally) -> bool {
        if self.worker.is_none() {
            return false;
        }
        self.windows_since_start += 1;
        let due = if self.fold_lag == 0 {
            self.worker.as_ref().is_some_and(|w| w.is_finished())
        } else {
            self.windows_since_start >= self.job_lag
        };
        if !(due || end_of_stream) {
            return false;
        }
        let Some(worker) = self.worker.take() else {
            return false;
        };
        self.running_newest = None;
        self.running_oldest = None;
        let loops = std::mem::take(&mut self.loops_since_start);
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
        let report = stats.time("refinement_fold", || map.apply_refinement(outcome, &loops));
        tracing::info!(
            keyframes = report.keyframes,
            points = report.points,
            rmse_px = report.rmse_px,
            iterations = report.iterations,
            outliers = report.outliers,
            carried_keyframes = report.carried_keyframes,
            loops_replayed = !loops.is_empty(),
            "background refinement folded in"
        );
        stats.count("refinements_applied", 1);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn large_jobs_get_a_longer_lag_and_zero_stays_zero() {
        assert_eq!(job_lag(3, 95), 3, "the TUM clip's refinement");
        assert_eq!(job_lag(3, 1500), 30);
        assert_eq!(job_lag(40, 1500), 40);
        assert_eq!(job_lag(0, 1500), 0, "fold whenever finished");
    }
}
