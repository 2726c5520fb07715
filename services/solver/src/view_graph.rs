//! The view graph of a window: edges between consecutive keyframes plus local loop closures.
//!
//! Paper, section 4 ("Local Loop Closures"): besides each keyframe's predecessor, edges to
//! the last L keyframes that still share enough tracks tie the window together, so that a
//! single bad pairwise estimate cannot bend the whole window.

use crate::relative_pose::{
    estimate_relative_pose, RelativePose, RelativePoseError, RelativePoseOptions,
};
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
