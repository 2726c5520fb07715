//! The view graph of a window: edges between consecutive keyframes plus local loop closures.
//!
//! Paper, section 4 ("Local Loop Closures"): besides each keyframe's predecessor, edges to
//! the last L keyframes that still share enough tracks tie the window together, so that a
//! single bad pairwise estimate cannot bend the whole window.

use crate::relative_pose::{
    estimate_relative_pose, RelativePose, RelativePoseError, RelativePoseOptions,
};
use crate::triangulation::CameraPose;
use egoslam_geometry::PinholeRadtan;
use nalgebra::Point2;
use std::collections::{BTreeMap, HashMap};

/// The tracks of one keyframe: track id -> undistorted pixel (ordered, so that RANSAC sees
/// the same correspondences in the same order on every run).
#[derive(Debug, Clone, PartialEq)]
pub struct KeyframeObservations {
    pub id: u64,
    pub timestamp: f64,
    pub tracks: BTreeMap<u64, Point2<f64>>,
}

/// Options of the graph.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewGraphOptions {
    /// L: loop-closure edges reach back this many keyframes (default 6, as the issue and
    /// the paper's "last few keyframes").
    pub loop_closure_span: usize,
    /// Shared tracks needed for a loop-closure edge (default 50; consecutive keyframes are
    /// always attempted).
    pub min_shared_tracks: usize,
    pub relative_pose: RelativePoseOptions,
}

impl Default for ViewGraphOptions {
    fn default() -> Self {
        Self {
            loop_closure_span: 6,
            min_shared_tracks: 50,
            relative_pose: RelativePoseOptions::default(),
        }
    }
}

/// A measured edge between window keyframes `i < j` (indices into the window).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewEdge {
    pub i: usize,
    pub j: usize,
    pub pose: RelativePose,
}

impl ViewEdge {
    /// Angle, degrees, between the edge's measured translation direction and the one the
    /// camera `poses` give (`R_j (c_i - c_j)`); `None` for an edge without a direction or
    /// coinciding centres. How far a solution strays from the two-view evidence, which no
    /// triangulation or adjustment has touched.
    pub fn direction_disagreement_deg(&self, poses: &[CameraPose]) -> Option<f64> {
        if !self.pose.has_translation {
            return None;
        }
        let (pi, pj) = (poses.get(self.i)?, poses.get(self.j)?);
        let t = pj.rotation * (pi.centre - pj.centre);
        let norm = t.norm();
        (norm > 0.0 && norm.is_finite()).then(|| {
            (t / norm)
                .dot(&self.pose.translation)
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees()
        })
    }
}

/// Relative poses already computed, by keyframe id pair: overlapping windows share them.
pub type EdgeCache = HashMap<(u64, u64), Result<RelativePose, RelativePoseError>>;

/// Builds the graph; failed pairs are returned with their reason.
pub fn build_view_graph(
    camera: &PinholeRadtan,
    keyframes: &[KeyframeObservations],
    options: &ViewGraphOptions,
    cache: &mut EdgeCache,
) -> (Vec<ViewEdge>, Vec<(usize, usize, RelativePoseError)>) {
    let mut edges = Vec::new();
    let mut failures = Vec::new();
    let focal = 0.5 * (camera.fx + camera.fy);
    for j in 1..keyframes.len() {
        for i in j.saturating_sub(options.loop_closure_span)..j {
            let (a, b) = (&keyframes[i], &keyframes[j]);
            let key = (a.id, b.id);
            let result = match cache.get(&key) {
                Some(r) => r.clone(),
                None => {
                    let mut pi = Vec::new();
                    let mut pj = Vec::new();
                    for (track, p) in &a.tracks {
                        if let Some(q) = b.tracks.get(track) {
                            pi.push(((p.x - camera.cx) / camera.fx, (p.y - camera.cy) / camera.fy));
                            pj.push(((q.x - camera.cx) / camera.fx, (q.y - camera.cy) / camera.fy));
                        }
                    }
                    let consecutive = i + 1 == j;
                    let r = if !consecutive && pi.len() < options.min_shared_tracks {
                        Err(RelativePoseError::TooFewMatches(pi.len()))
                    } else {
                        estimate_relative_pose(&pi, &pj, focal, &options.relative_pose)
                    };
                    cache.insert(key, r.clone());
                    r
                }
            };
            match result {
                Ok(pose) => edges.push(ViewEdge { i, j, pose }),
                Err(e) => failures.push((i, j, e)),
            }
        }
    }
    (edges, failures)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::relative_pose::RelativePose;
    use nalgebra::{Rotation3, Vector3};

    #[test]
    fn direction_disagreement_is_the_angle_to_the_poses_own_direction() {
        let poses = [
            CameraPose {
                rotation: Rotation3::identity(),
                centre: Vector3::zeros(),
            },
            CameraPose {
                rotation: Rotation3::from_euler_angles(0.0, 0.3, 0.0),
                centre: Vector3::new(0.0, 0.0, 1.0),
            },
        ];
        // x_j = R_j (x - c_j): the first centre seen from the second camera.
        let truth = (poses[1].rotation * (poses[0].centre - poses[1].centre)).normalize();
        let edge = |translation: Vector3<f64>, has_translation: bool| ViewEdge {
            i: 0,
            j: 1,
            pose: RelativePose {
                rotation: poses[1].rotation,
                translation,
                has_translation,
                inliers: 100,
                matches: 100,
                parallax_px: 10.0,
            },
        };
        let same = edge(truth, true).direction_disagreement_deg(&poses);
        assert!(same.is_some_and(|a| a < 1e-6), "{same:?}");
        let opposite = edge(-truth, true).direction_disagreement_deg(&poses);
        assert!(
            opposite.is_some_and(|a| (a - 180.0).abs() < 1e-6),
            "{opposite:?}"
        );
        let side = truth.cross(&Vector3::y()).normalize();
        let right = edge(side, true).direction_disagreement_deg(&poses);
        assert!(right.is_some_and(|a| (a - 90.0).abs() < 1e-6), "{right:?}");
        assert_eq!(edge(truth, false).direction_disagreement_deg(&poses), None);
        let together = [poses[0], poses[0]];
        assert_eq!(
            edge(truth, true).direction_disagreement_deg(&together),
            None
        );
    }
}
