//! Joint refinement of the most recent keyframes of the map.
//!
//! Consecutive windows meet at their ends, where each is least constrained (in forward
//! motion, scale drifts towards a window's ends), so aligning them there passes that error
//! on. After each window is chained, the last keyframes of the segment (the new window and
//! the one before) are bundle-adjusted together with every stored observation, the oldest
//! ones held fixed so that the settled map keeps its frame and scale: a sliding global
//! bundle adjustment (paper, section 5, "global BA").

use crate::chaining::MapBuilder;
use egoslam_geometry::PinholeRadtan;
use egoslam_solver::bundle_adjustment::{bundle_adjust, BundleAdjustmentOptions, Observation};
use egoslam_solver::triangulation::CameraPose;
use nalgebra::{UnitQuaternion, Vector3};
use std::collections::BTreeMap;

/// Options of the sliding refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefinementOptions {
    /// Keyframes refined together, newest first (default 40: two windows of 20).
    pub keyframes: usize,
    /// Oldest of those held fixed (default 5, the window overlap: they anchor frame and scale).
    pub fixed: usize,
    pub bundle_adjustment: BundleAdjustmentOptions,
}

impl Default for RefinementOptions {
    fn default() -> Self {
        Self {
            keyframes: 40,
            fixed: 5,
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
}

impl MapBuilder {
    /// Refines the last keyframes of the current segment; `None` when there is too little
    /// to refine (fewer keyframes than `fixed + 2`, or no shared points).
    pub fn refine_recent(
        &mut self,
        camera: &PinholeRadtan,
        options: &RefinementOptions,
    ) -> Option<RefinementReport> {
        let segment = self.current_segment?;
        let mut ids: Vec<u64> = self
            .keyframes
            .iter()
            .filter(|(_, (s, _))| *s == segment)
            .map(|(id, _)| *id)
            .collect();
        if ids.len() < options.fixed + 2 {
            return None;
        }
        ids.drain(..ids.len().saturating_sub(options.keyframes));
        let index: BTreeMap<u64, usize> = ids.iter().enumerate().map(|(i, id)| (*id, i)).collect();
        let poses: Vec<CameraPose> = ids
            .iter()
            .map(|id| {
                let p = &self.keyframes[id].1;
                CameraPose {
                    rotation: p.rotation.inverse().to_rotation_matrix(),
                    centre: p.position,
                }
            })
            .collect();
        // Points of the segment seen by at least two of these keyframes.
        let (first, last) = (ids[0], ids[ids.len() - 1]);
        let mut by_track: BTreeMap<u64, Vec<(usize, nalgebra::Point2<f64>)>> = BTreeMap::new();
        for ((kf, track), px) in self.observations.range((first, 0)..=(last, u64::MAX)) {
            if let Some(&cam) = index.get(kf) {
                by_track.entry(*track).or_default().push((cam, *px));
            }
        }
        let mut tracks = Vec::new();
        let mut points: Vec<Vector3<f64>> = Vec::new();
        let mut observations = Vec::new();
        let mut keys = Vec::new();
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
        let ba = BundleAdjustmentOptions {
            fixed_cameras: options.fixed.min(ids.len() - 1),
            ..options.bundle_adjustment
        };
        let result = bundle_adjust(camera, &poses, &points, &observations, &ba).ok()?;
        for (id, pose) in ids.iter().zip(&result.poses) {
            if let Some((_, p)) = self.keyframes.get_mut(id) {
                p.position = pose.centre;
                p.rotation = UnitQuaternion::from_rotation_matrix(&pose.rotation.inverse());
            }
        }
        for (track, x) in tracks.iter().zip(&result.points) {
            self.points.insert(*track, (segment, *x));
        }
        for o in &result.outliers {
            self.observations.remove(&keys[*o]);
        }
        Some(RefinementReport {
            keyframes: ids.len(),
            points: points.len(),
            observations: observations.len(),
            outliers: result.outliers.len(),
            rmse_px: result.rmse_px,
        })
    }
}
