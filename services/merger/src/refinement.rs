//! Joint (global or sliding) bundle adjustment of the map, runnable off the merger's thread.
//!
//! Consecutive windows meet at their ends, where each is least constrained, so chaining
//! passes their errors on; the cross-window reprojection error (map points seen again from
//! a new window's keyframes) measures how far the chain has drifted from what the images
//! say. When it grows, the keyframes of the segment are bundle-adjusted together with every
//! stored observation, the oldest held fixed so that the settled map keeps its frame and
//! scale (paper, section 5, "global BA").
//!
//! The work is split so that it never stalls the intake of windows: [`MapBuilder::
//! refinement_job`] copies the problem out of the map (cheap), [`RefinementJob::solve`] runs
//! anywhere (a background thread), and [`MapBuilder::apply_refinement`] folds the result
//! back, carrying keyframes and points added meanwhile along by the similarity that the
//! refinement applied to the newest refined keyframes.

use crate::map::MapBuilder;
use crate::refinement_rebase::{conjugated, LoopCorrections};
use crate::window_alignment::align_shared;
use crate::window_alignment::transform_pose;
use egoslam_geometry::{PinholeRadtan, Similarity, StampedPose};
use egoslam_solver::bundle_adjustment::{
    bundle_adjust, BundleAdjustmentOptions, BundleAdjustmentResult, Observation,
};
use egoslam_solver::triangulation::CameraPose;
use egoslam_solver::unobserved_keyframes::{
    restore_unobserved_rotations, UnobservedKeyframeOptions,
};
use nalgebra::{UnitQuaternion, Vector3};
use std::collections::{BTreeMap, BTreeSet};
use tail_centres::{median_observation_distance, place_tail_centres};

mod tail_centres;

/// Options of a refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefinementOptions {
    /// Keyframes refined together, newest first (0 = every keyframe of the segment: global
    /// BA). Default 0.
    pub keyframes: usize,
    /// Oldest of those held fixed (default 5, the window overlap: they anchor frame and
    /// scale, the 7 gauge freedoms of a monocular map).
    pub fixed: usize,
    /// Newest refined keyframes whose change (a similarity) is applied to keyframes and
    /// points added while the refinement ran (default 5, one window overlap).
    pub carry_keyframes: usize,
    pub bundle_adjustment: BundleAdjustmentOptions,
}

impl Default for RefinementOptions {
    fn default() -> Self {
        Self {
            keyframes: 0,
            fixed: 5,
            carry_keyframes: 5,
            bundle_adjustment: BundleAdjustmentOptions::default(),
        }
    }
}

/// What a refinement did.
#[derive(Debug, Clone, PartialEq)]
pub struct RefinementReport {
    pub keyframes: usize,
    pub points: usize,
    pub observations: usize,
    pub outliers: usize,
    pub rmse_px: f64,
    pub iterations: usize,
    /// Keyframes added while the refinement ran, moved by the carried similarity.
    pub carried_keyframes: usize,
}

/// A refinement problem copied out of the map; owns everything, so it can be sent to a
/// worker thread.
#[derive(Debug, Clone)]
pub struct RefinementJob {
    segment: u32,
    camera: PinholeRadtan,
    options: RefinementOptions,
    /// Keyframe ids in order, with their times and poses (BA convention) when the job was
    /// made.
    ids: Vec<u64>,
    timestamps: Vec<f64>,
    poses: Vec<CameraPose>,
    tracks: Vec<u64>,
    points: Vec<Vector3<f64>>,
    observations: Vec<Observation>,
    /// `(keyframe, track)` of each observation, to remove outliers from the map.
    keys: Vec<(u64, u64)>,
    /// Keyframes and tracks of the segment when the job was made.
    known_keyframes: BTreeSet<u64>,
    known_tracks: BTreeSet<u64>,
}

/// A solved job, ready to be folded back with [`MapBuilder::apply_refinement`].
#[derive(Debug, Clone)]
pub struct RefinementOutcome {
    job: RefinementJob,
    result: BundleAdjustmentResult,
}

fn camera_pose(p: &StampedPose) -> CameraPose {
    CameraPose {
        rotation: p.rotation.inverse().to_rotation_matrix(),
        centre: p.position,
    }
}

fn stamped(timestamp: f64, p: &CameraPose) -> StampedPose {
    StampedPose {
        timestamp,
        position: p.centre,
        rotation: UnitQuaternion::from_rotation_matrix(&p.rotation.inverse()),
    }
}

impl RefinementJob {
    /// Keyframes in the problem.
    pub fn keyframes(&self) -> usize {
        self.ids.len()
    }

    /// The oldest keyframe in the problem: older ones are not in it, and the fold does not
    /// look at them.
    pub fn oldest_keyframe(&self) -> Option<u64> {
        self.ids.first().copied()
    }

    /// The newest keyframe of the segment when the job was made: keyframes after it are
    /// carried rigidly when the job is folded, so they may be changed meanwhile.
    pub fn newest_known_keyframe(&self) -> Option<u64> {
        self.known_keyframes.last().copied()
    }

    /// Runs the bundle adjustment (seconds for a thousand keyframes; call it off the
    /// merger's thread). `None` when the solver rejects the problem. A keyframe that kept
    /// too few inlier observations to hold its rotation keeps the one it had relative to its
    /// well-observed neighbours when the adjustment turned it away
    /// (`egoslam_solver::unobserved_keyframes`, as a window's): on a rendered 300 deg/s head
    /// shake, whose windows barely translate, refinements turned such keyframes up to
    /// 106 deg.
    pub fn solve(self) -> Option<RefinementOutcome> {
        let options = BundleAdjustmentOptions {
            fixed_cameras: self.options.fixed.min(self.ids.len() - 1),
            ..self.options.bundle_adjustment
        };
        let mut result = bundle_adjust(
            &self.camera,
            &self.poses,
            &self.points,
            &self.observations,
            &options,
        )
        .ok()?;
        let inliers = result.inliers_per_camera(&self.observations, self.poses.len());
        let before: Vec<_> = self.poses.iter().map(|p| p.rotation).collect();
        let restored = restore_unobserved_rotations(
            &mut result.poses,
            &self.timestamps,
            &inliers,
            &before,
            &UnobservedKeyframeOptions::default(),
        );
        let points = &result.points;
        let placed = place_tail_centres(
            &mut result.poses,
            &self.timestamps,
            &inliers,
            |poses| median_observation_distance(poses, points, &self.observations),
            &UnobservedKeyframeOptions::default(),
        );
        if restored + placed > 0 {
            tracing::debug!(
                restored,
                placed,
                "refinement: rotations and centres of unobserved keyframes kept"
            );
        }
        Some(RefinementOutcome { job: self, result })
    }
}

impl MapBuilder {
    /// Keyframe ids of a segment, in order.
    pub fn segment_keyframes(&self, segment: u32) -> Vec<u64> {
        self.keyframes
            .iter()
            .filter(|(_, (s, _))| *s == segment)
            .map(|(id, _)| *id)
            .collect()
    }

    /// Copies the refinement problem of the current segment (its last `options.keyframes`,
    /// or all) out of the map; `None` when there is too little to refine (fewer keyframes
    /// than `fixed + 2`, or no point seen twice).
    pub fn refinement_job(
        &self,
        camera: &PinholeRadtan,
        options: &RefinementOptions,
    ) -> Option<RefinementJob> {
        let segment = self.current_segment?;
        let all = self.segment_keyframes(segment);
        if all.len() < options.fixed + 2 {
            return None;
        }
        let mut ids = all.clone();
        if options.keyframes > 0 {
            ids.drain(..ids.len().saturating_sub(options.keyframes));
        }
        let index: BTreeMap<u64, usize> = ids.iter().enumerate().map(|(i, id)| (*id, i)).collect();
        let poses: Vec<CameraPose> = ids
            .iter()
            .map(|id| camera_pose(&self.keyframes[id].1))
            .collect();
        let timestamps = ids
            .iter()
            .map(|id| self.keyframes[id].1.timestamp)
            .collect();
        let (first, last) = (ids[0], ids[ids.len() - 1]);
        let mut by_track: BTreeMap<u64, Vec<(usize, nalgebra::Point2<f64>)>> = BTreeMap::new();
        let sightings = self
            .observations
            .range((first, 0)..=(last, u64::MAX))
            .chain(self.seen_again.range((first, 0)..=(last, u64::MAX)));
        for ((kf, track), px) in sightings {
            if let Some(&cam) = index.get(kf) {
                by_track.entry(*track).or_default().push((cam, *px));
            }
        }
        let (mut tracks, mut points, mut observations, mut keys) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (track, obs) in &by_track {
            let Some((s, x)) = self.points.get(track) else {
                continue;
            };
            if *s != segment || obs.len() < 2 {
                continue;
            }
            let point = points.len();
            points.push(*x);
            tracks.push(*track);
            for (cam, px) in obs {
                observations.push(Observation {
                    camera: *cam,
                    point,
                    pixel: *px,
                });
                keys.push((ids[*cam], *track));
            }
        }
        if points.is_empty() {
            return None;
        }
        let known_tracks = self
            .points
            .iter()
            .filter(|(_, (s, _))| *s == segment)
            .map(|(t, _)| *t)
            .collect();
        Some(RefinementJob {
            segment,
            camera: *camera,
            options: *options,
            ids,
            timestamps,
            poses,
            tracks,
            points,
            observations,
            keys,
            known_keyframes: all.into_iter().collect(),
            known_tracks,
        })
    }

    /// Folds a solved job back into the map: refined keyframes and points take their new
    /// values; keyframes and points of the segment added since the job was made move with
    /// the similarity that maps the newest refined keyframes' old poses onto their new ones
    /// (so the map stays continuous at the join); outlier observations are dropped. A job
    /// whose segment is no longer current still updates that segment's own keyframes.
    /// `loops`: the loops closed since the job was made, replayed onto its result
    /// ([`crate::refinement_rebase`]).
    pub fn apply_refinement(
        &mut self,
        outcome: RefinementOutcome,
        loops: &LoopCorrections,
    ) -> RefinementReport {
        let RefinementOutcome { job, result } = outcome;
        let carry = job.options.carry_keyframes.clamp(2, job.ids.len());
        let tail = job.ids.len() - carry;
        // The job's keyframes must still be this segment's (a map reset meanwhile, e.g. a
        // new solver stream, makes the result stale: it is dropped).
        let current = job
            .ids
            .iter()
            .all(|id| matches!(self.keyframes.get(id), Some((s, _)) if *s == job.segment));
        if !current {
            return RefinementReport {
                keyframes: 0,
                points: 0,
                observations: 0,
                outliers: 0,
                rmse_px: result.rmse_px,
                iterations: result.iterations,
                carried_keyframes: 0,
            };
        }
        let stamp = |id: &u64| self.keyframes.get(id).map_or(0.0, |(_, p)| p.timestamp);
        let before: Vec<StampedPose> = job.ids[tail..]
            .iter()
            .zip(&job.poses[tail..])
            .map(|(id, p)| stamped(stamp(id), p))
            .collect();
        let after: Vec<StampedPose> = job.ids[tail..]
            .iter()
            .zip(&result.poses[tail..])
            .map(|(id, p)| stamped(stamp(id), p))
            .collect();
        let moved_points: Vec<(Vector3<f64>, Vector3<f64>)> = job
            .points
            .iter()
            .zip(&result.points)
            .map(|(a, b)| (*a, *b))
            .collect();
        let (carried, _) = align_shared(&before, &after, &moved_points);
        for (id, pose) in job.ids.iter().zip(&result.poses) {
            if let Some((_, p)) = self.keyframes.get_mut(id) {
                *p = transform_pose(&loops.of_keyframe(*id), &stamped(p.timestamp, pose));
            }
        }
        for (track, x) in job.tracks.iter().zip(&result.points) {
            let x = loops.of_known_point(*track).apply(x);
            self.points.insert(*track, (job.segment, x));
        }
        let carried_keyframes = self.carry_new(&job, &carried, loops);
        for o in &result.outliers {
            self.observations.remove(&job.keys[*o]);
            self.seen_again.remove(&job.keys[*o]);
        }
        RefinementReport {
            keyframes: job.ids.len(),
            points: job.points.len(),
            observations: job.observations.len(),
            outliers: result.outliers.len(),
            rmse_px: result.rmse_px,
            iterations: result.iterations,
            carried_keyframes,
        }
    }

    /// Applies `t` to the segment's keyframes and points that the job did not know, in the
    /// frame the loops closed since corrected each into.
    fn carry_new(&mut self, job: &RefinementJob, t: &Similarity, loops: &LoopCorrections) -> usize {
        let mut moved = 0;
        for (id, (s, p)) in self.keyframes.iter_mut() {
            if *s == job.segment && !job.known_keyframes.contains(id) {
                let carry = conjugated(t, &loops.of_keyframe(*id));
                *p = transform_pose(&carry, p);
                moved += 1;
            }
        }
        let carry = conjugated(t, &loops.newest());
        for (track, (s, x)) in self.points.iter_mut() {
            if *s == job.segment && !job.known_tracks.contains(track) {
                *x = carry.apply(x);
            }
        }
        moved
    }

    /// Refines in place (job, solve and fold on this thread).
    pub fn refine_recent(
        &mut self,
        camera: &PinholeRadtan,
        options: &RefinementOptions,
    ) -> Option<RefinementReport> {
        let outcome = self.refinement_job(camera, options)?.solve()?;
        Some(self.apply_refinement(outcome, &LoopCorrections::default()))
    }

    /// Cross-window reprojection error: the median pixel error of the observations made
    /// from `keyframes` of points that were already in the map before them (all but
    /// `new_tracks`, the points the latest window brought), with the map's current poses
    /// and points. Within a window BA fits its observations to ~1 px; what
    /// exceeds that here is disagreement between windows (drift). The median, because a
    /// few points near a camera's plane reproject hundreds of pixels off and would make an
    /// RMS say "drift" on a sound map. `None` without such observations.
    pub fn cross_window_error(
        &self,
        camera: &PinholeRadtan,
        keyframes: &[u64],
        new_tracks: &BTreeSet<u64>,
    ) -> Option<f64> {
        let mut errors = Vec::new();
        for id in keyframes {
            let Some((segment, pose)) = self.keyframes.get(id) else {
                continue;
            };
            let cam = camera_pose(pose);
            for ((_, track), px) in self.observations.range((*id, 0)..=(*id, u64::MAX)) {
                if new_tracks.contains(track) {
                    continue;
                }
                let Some((s, x)) = self.points.get(track) else {
                    continue;
                };
                let pc = cam.to_camera(x);
                if *s != *segment || pc.z <= 1e-9 {
                    continue;
                }
                let Some(projected) = camera.project_undistorted(&pc) else {
                    continue;
                };
                errors.push((projected - px).norm());
            }
        }
        crate::median(errors)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::MapParts;
    use nalgebra::Rotation3;

    fn camera() -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    /// Keyframe `i` of a walk along x, looking down +z with a slow yaw sway.
    fn truth(i: usize) -> StampedPose {
        let cam = CameraPose {
            rotation: Rotation3::from_euler_angles(0.0, 0.05 * (0.3 * i as f64).sin(), 0.0),
            centre: Vector3::new(0.1 * i as f64, 0.0, 0.0),
        };
        stamped(i as f64, &cam)
    }

    /// Truth moved by a drift growing with the keyframe index (the chaining error).
    fn drifted(i: usize) -> StampedPose {
        let d = i.saturating_sub(5) as f64;
        let mut p = truth(i);
        p.position += Vector3::new(0.002 * d, -0.001 * d, 0.003 * d);
        p.rotation = UnitQuaternion::from_euler_angles(0.0005 * d, -0.0004 * d, 0.0) * p.rotation;
        p
    }

    #[test]
    fn a_job_whose_map_was_reset_meanwhile_changes_nothing() {
        let camera = camera();
        let mut parts = MapParts {
            current_segment: Some(0),
            segments: 1,
            ..MapParts::default()
        };
        for i in 0..10u64 {
            parts.keyframes.insert(i, (0, truth(i as usize)));
            let x = Vector3::new(0.1 * i as f64, 0.0, 4.0);
            parts.points.insert(i, (0, x));
            for k in 0..10u64 {
                let cam = camera_pose(&truth(k as usize));
                if let Some(px) = camera.project_undistorted(&cam.to_camera(&x)) {
                    parts.observations.insert((k, i), px);
                }
            }
        }
        let map = MapBuilder::from_parts(parts);
        let job = map
            .refinement_job(&camera, &RefinementOptions::default())
            .expect("job");
        let outcome = job.solve().expect("solved");
        let mut reset = MapBuilder::new();
        let report = reset.apply_refinement(outcome, &LoopCorrections::default());
        assert_eq!(report.keyframes, 0);
        assert_eq!(reset.keyframes().count(), 0);
    }

    /// A map of keyframes 0..25 at their `drifted` poses and points on a wall 4 m ahead
    /// (`columns` of 6, 5 cm apart), each observed by keyframes `0..observers` within 0.6 m
    /// of it, where `seen_from(i)` sees it.
    fn wall_map(
        camera: &PinholeRadtan,
        columns: usize,
        observers: usize,
        seen_from: fn(usize) -> StampedPose,
    ) -> MapBuilder {
        let mut parts = MapParts {
            current_segment: Some(0),
            segments: 1,
            ..MapParts::default()
        };
        let mut track = 0u64;
        for gx in 0..columns {
            for gy in 0..6 {
                let x = Vector3::new(-0.5 + 0.05 * gx as f64, -0.6 + 0.25 * gy as f64, 4.0);
                for i in 0..observers {
                    let cam = camera_pose(&seen_from(i));
                    if (cam.centre.x - x.x).abs() > 0.6 {
                        continue;
                    }
                    if let Some(px) = camera.project_undistorted(&cam.to_camera(&x)) {
                        parts.observations.insert((i as u64, track), px);
                    }
                }
                parts.points.insert(track, (0, x));
                track += 1;
            }
        }
        for i in 0..25 {
            parts.keyframes.insert(i as u64, (0, drifted(i)));
        }
        MapBuilder::from_parts(parts)
    }

    #[test]
    fn a_background_job_corrects_drift_and_carries_what_came_meanwhile() {
        let camera = camera();
        // The points are where the true keyframes see them; the keyframes drifted.
        let mut map = wall_map(&camera, 60, 26, truth);
        let job = map
            .refinement_job(&camera, &RefinementOptions::default())
            .expect("job");
        // A keyframe arrives while the job runs, chained onto the drifted map.
        map.keyframes.insert(25, (0, drifted(25)));
        let error = |map: &MapBuilder, i: usize| {
            (map.keyframes[&(i as u64)].1.position - truth(i).position).norm()
        };
        let before: Vec<f64> = (0..26).map(|i| error(&map, i)).collect();
        let report =
            map.apply_refinement(job.solve().expect("solved"), &LoopCorrections::default());
        assert_eq!(report.keyframes, 25);
        assert_eq!(report.carried_keyframes, 1);
        assert!(report.rmse_px < 0.05, "{report:?}");
        for (i, was) in before.iter().enumerate().take(25).skip(5) {
            let now = error(&map, i);
            assert!(now < 0.1 * was.max(1e-3), "kf {i}: {now} was {was}");
        }
        assert!(
            error(&map, 25) < 0.2 * before[25],
            "carried kf: {} was {}",
            error(&map, 25),
            before[25]
        );
    }

    /// The map's reprojection error over every observation (px, RMS).
    fn reprojection_rmse(map: &MapBuilder, camera: &PinholeRadtan) -> f64 {
        let mut sum = 0.0;
        let mut n = 0;
        for ((kf, track), px) in &map.observations {
            let (Some((_, pose)), Some((_, x))) = (map.keyframes.get(kf), map.points.get(track))
            else {
                continue;
            };
            let pc = camera_pose(pose).to_camera(x);
            if let Some(p) = camera.project_undistorted(&pc) {
                sum += (p - px).norm_squared();
                n += 1;
            }
        }
        (sum / n as f64).sqrt()
    }

    #[test]
    fn points_seen_again_join_the_refinement() {
        let camera = camera();
        let mut map = wall_map(&camera, 20, 25, truth);
        let count = |map: &MapBuilder| {
            map.refinement_job(&camera, &RefinementOptions::default())
                .expect("job")
                .observations
                .len()
        };
        let before = count(&map);
        // Keyframe 24 sees point 0 again (the wall's first column, 0.6 m beyond its reach).
        let x = map.points[&0].1;
        let px = camera
            .project_undistorted(&camera_pose(&truth(24)).to_camera(&x))
            .expect("in view");
        assert!(!map.observations.contains_key(&(24, 0)));
        map.seen_again.insert((24, 0), px);
        assert_eq!(count(&map), before + 1);
    }

    #[test]
    fn a_loop_closed_while_the_job_runs_survives_the_fold() {
        use crate::loop_closure::{LoopClosure, LoopOptions};
        let camera = camera();
        // Consistent with its observations (the drifted poses see the points).
        let mut map = wall_map(&camera, 80, 32, drifted);
        let job = map
            .refinement_job(&camera, &RefinementOptions::default())
            .expect("job");
        for i in 25..32 {
            map.keyframes.insert(i as u64, (0, drifted(i)));
        }
        // A loop from keyframe 12 on, with a scale, a turn and a shift (the map is
        // consistent with its observations before and after it: points follow keyframes).
        let closure = LoopClosure {
            segment: 0,
            anchor_keyframe: 12,
            transform: Similarity {
                scale: 0.8,
                rotation: nalgebra::Rotation3::from_euler_angles(0.0, 0.05, 0.02),
                translation: Vector3::new(0.1, -0.05, 0.2),
            },
            keyframes: 3,
            shared_points: 100,
            scale_steps: Vec::new(),
            sightings: Vec::new(),
        };
        let options = LoopOptions {
            max_correction_fraction: 10.0,
            ..LoopOptions::default()
        };
        let before_loop = reprojection_rmse(&map, &camera);
        let report = map.close_loop(&closure, &options).expect("loop");
        let after_loop = reprojection_rmse(&map, &camera);
        let mut loops = LoopCorrections::default();
        loops.record(&report.keyframe_moves, &report.point_owners);
        let outcome = job.solve().expect("solved");
        let folded = map.apply_refinement(outcome, &loops);
        let after_fold = reprojection_rmse(&map, &camera);
        assert_eq!(folded.carried_keyframes, 7);
        assert!(
            after_fold < 1.5 * after_loop.max(0.5),
            "before the loop {before_loop} px, after it {after_loop} px, after the fold {after_fold} px"
        );
        // The loop's move of the newest keyframe is kept.
        let newest = map.keyframes[&31].1.position;
        let target = closure.transform.apply(&drifted(31).position);
        assert!((newest - target).norm() < 0.05, "{newest} vs {target}");
    }
}
