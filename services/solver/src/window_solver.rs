//! One temporal window solved as a global SfM problem (paper, section 4): view graph ->
//! rotation averaging -> translation averaging (with camera-point constraints) ->
//! triangulation -> bundle adjustment. Pure: keyframe tracks in, poses and points out.

use crate::bundle_adjustment::{bundle_adjust, BundleAdjustmentOptions};
use crate::detached_keyframes::{restore_detached_keyframes, DetachedKeyframeOptions};
use crate::retriangulation::{
    retriangulate_and_adjust, tracks_of, triangulate_tracks, RetriangulationOptions, Structure,
    TrackObservations,
};
use crate::rotation_averaging::{average_rotations, RelativeRotation, RotationAveragingOptions};
use crate::translation_averaging::{
    average_translations, DirectionConstraint, Endpoints, TranslationAveragingOptions,
};
use crate::triangulation::{CameraPose, TriangulationOptions};
use crate::unobserved_keyframes::{
    place_unobserved_centres, restore_unobserved_rotations, UnobservedKeyframeOptions,
};
use crate::view_graph::{
    build_view_graph, EdgeCache, KeyframeObservations, ViewEdge, ViewGraphOptions,
};
use egoslam_geometry::PinholeRadtan;
use nalgebra::{Point2, Rotation3, Vector3};
use std::collections::BTreeMap;
use std::time::Instant;

/// All estimator options of a window solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowSolverOptions {
    pub view_graph: ViewGraphOptions,
    pub rotation: RotationAveragingOptions,
    pub translation: TranslationAveragingOptions,
    pub triangulation: TriangulationOptions,
    pub bundle_adjustment: BundleAdjustmentOptions,
    /// Re-triangulation from the adjusted poses and adjustment again (retriangulation.rs).
    pub retriangulation: RetriangulationOptions,
    /// Edges whose measured rotation disagrees with the averaged one by more than this are
    /// dropped before translation averaging, degrees (default 5: the robust scale of the
    /// rotation IRLS, so only edges it already down-weighted are removed).
    pub max_edge_rotation_residual_deg: f64,
    /// Tracks used as camera-point constraints in translation averaging: those seen by at
    /// least this many keyframes (default 3: two views give a direction but no scale link).
    pub min_track_views: usize,
    /// At most this many tracks (the longest) feed translation averaging (default 800).
    pub max_averaging_tracks: usize,
    /// A window with fewer triangulated points is solved as rotation-only (default 20).
    pub min_points: usize,
    /// A window with fewer edges that carry a translation direction is solved as
    /// rotation-only (default 5, a quarter of a 20-keyframe window's consecutive edges:
    /// a rendered walk's stop had a window with 1 such edge of 98, whose centres were noise
    /// and whose scale, carried on by the merger, left the rest of the map 50x too small).
    pub min_translation_edges: usize,
    /// A window with fewer than this fraction of its edges carrying a translation
    /// direction is solved as rotation-only too (default 0.1). A head turning in place on
    /// a rolling-shutter camera with motion blur (a rendered walk at 20 ms with 9 blur
    /// sub-poses) gave a window 5 such edges of 99 (0.05),
    /// spurious parallax of the uncorrected remainder, from which 870 points were
    /// triangulated at invented depths; its motion then set the walking pace the merger
    /// resumed after the stop with, and the map after it came out 2.4x too small. Of 104
    /// windows solved with translation (of 123 solved in all) on TUM, KITTI, the Aria
    /// replay, the egomotion profile, the blackout and rendered walks with stops, none had
    /// under 0.22.
    pub min_translation_edge_fraction: f64,
    /// A window whose view graph falls into pieces is solved on its largest piece if that
    /// holds at least this fraction of the keyframes, else it fails (default 0.5: on the
    /// rendered shake, dark and Aria-replay sequences, smaller pieces each started a new
    /// map segment, 5 instead of 2 on the shake; at 0.5 the breaks stay as when the window
    /// failed whole while 4-11 % more frames get a pose).
    pub min_piece_fraction: f64,
    /// Keyframes the points barely see get their centres from the motion around them and,
    /// when bundle adjustment turned them away, their rotations from the averaging
    /// (unobserved_keyframes.rs).
    pub unobserved_keyframes: UnobservedKeyframeOptions,
    /// A group of keyframes bundle adjustment turned away with points only they see gets
    /// its rotations from the averaging (detached_keyframes.rs).
    pub detached_keyframes: DetachedKeyframeOptions,
}

impl Default for WindowSolverOptions {
    fn default() -> Self {
        Self {
            view_graph: ViewGraphOptions::default(),
            rotation: RotationAveragingOptions::default(),
            translation: TranslationAveragingOptions::default(),
            triangulation: TriangulationOptions::default(),
            bundle_adjustment: BundleAdjustmentOptions::default(),
            retriangulation: RetriangulationOptions::default(),
            max_edge_rotation_residual_deg: 5.0,
            min_track_views: 3,
            max_averaging_tracks: 800,
            min_points: 20,
            min_translation_edges: 5,
            min_translation_edge_fraction: 0.1,
            min_piece_fraction: 0.5,
            unobserved_keyframes: UnobservedKeyframeOptions::default(),
            detached_keyframes: DetachedKeyframeOptions::default(),
        }
    }
}

/// Outcome class of a window.
#[derive(Debug, Clone, PartialEq)]
pub enum WindowStatus {
    /// Full solve: poses, points, bundle adjustment.
    Solved,
    /// Too little parallax to trust any translation: rotations are solved, all centres
    /// coincide (the head turned in place), no points. Poses are still valid; the reason
    /// says which test decided.
    RotationOnly(String),
    /// The window could not be solved; the reason says why.
    Failed(String),
}

/// A triangulated, adjusted point.
#[derive(Debug, Clone, PartialEq)]
pub struct SolvedPoint {
    pub track_id: u64,
    pub position: Vector3<f64>,
    pub observations: u32,
}

/// The window's result, in the frame of its first keyframe (identity rotation, origin).
#[derive(Debug, Clone, PartialEq)]
pub struct WindowSolution {
    pub status: WindowStatus,
    /// Indices of the window's keyframes that `poses` (and the observations' keyframe
    /// indices) refer to: all of them, or the largest connected piece of the view graph.
    pub keyframes: Vec<usize>,
    /// One per keyframe, in window order (empty when failed).
    pub poses: Vec<CameraPose>,
    pub points: Vec<SolvedPoint>,
    /// Inlier observations kept by bundle adjustment: (keyframe index, track id, pixel).
    pub observations: Vec<(usize, u64, Point2<f64>)>,
    pub outlier_observations: usize,
    /// Observations (keyframe index, track id, pixel) of tracks seen twice or more whose
    /// rays met at too small an angle to triangulate in this window: the merger
    /// re-triangulates them once other windows add views (paper, section 5).
    pub weak_observations: Vec<(usize, u64, Point2<f64>)>,
    pub rmse_px: f64,
    /// The focal length over the calibrated one that bundle adjustment settled on when it
    /// refined the intrinsics (`BundleAdjustmentOptions::refine_intrinsics`, used by
    /// [`crate::focal_calibration`]); 1 otherwise.
    pub focal_scale: f64,
    /// The radial term bundle adjustment settled on with the intrinsics refined (in the
    /// ideal camera's normalized coordinates, as `k1` of the calibration; used by
    /// [`crate::focal_calibration`]); 0 otherwise.
    pub radial_k: f64,
    pub edges: usize,
    pub translation_edges: usize,
    /// (stage, milliseconds) in execution order.
    pub timings_ms: Vec<(&'static str, f64)>,
}

impl WindowSolution {
    /// Rotations only, every centre at the origin (the first keyframe's).
    fn rotation_only(
        reason: String,
        rotations: &[Rotation3<f64>],
        edges: usize,
        translation_edges: usize,
        timings_ms: Vec<(&'static str, f64)>,
    ) -> Self {
        Self {
            status: WindowStatus::RotationOnly(reason),
            keyframes: (0..rotations.len()).collect(),
            poses: rotations
                .iter()
                .map(|r| CameraPose {
                    rotation: *r,
                    centre: Vector3::zeros(),
                })
                .collect(),
            points: Vec::new(),
            observations: Vec::new(),
            outlier_observations: 0,
            weak_observations: Vec::new(),
            rmse_px: 0.0,
            focal_scale: 1.0,
            radial_k: 0.0,
            edges,
            translation_edges,
            timings_ms,
        }
    }

    fn failed(reason: String, timings_ms: Vec<(&'static str, f64)>, edges: usize) -> Self {
        Self {
            status: WindowStatus::Failed(reason),
            keyframes: Vec::new(),
            poses: Vec::new(),
            points: Vec::new(),
            observations: Vec::new(),
            outlier_observations: 0,
            weak_observations: Vec::new(),
            rmse_px: 0.0,
            focal_scale: 1.0,
            radial_k: 0.0,
            edges,
            translation_edges: 0,
            timings_ms,
        }
    }
}

fn timed<T>(
    timings: &mut Vec<(&'static str, f64)>,
    stage: &'static str,
    f: impl FnOnce() -> T,
) -> T {
    let _span = tracing::debug_span!("window_stage", stage).entered();
    let start = Instant::now();
    let out = f();
    timings.push((stage, start.elapsed().as_secs_f64() * 1e3));
    out
}

/// Tracks for translation averaging: the longest first, but every keyframe gets at least a
/// share of its own (a keyframe no selected track reaches would be left unconstrained).
fn select_averaging_tracks<'t>(
    tracks: &'t BTreeMap<u64, TrackObservations>,
    keyframes: usize,
    options: &WindowSolverOptions,
) -> Vec<(&'t u64, &'t TrackObservations)> {
    let mut long: Vec<(&u64, &TrackObservations)> = tracks
        .iter()
        .filter(|(_, o)| o.len() >= options.min_track_views)
        .collect();
    long.sort_by(|a, b| b.1.len().cmp(&a.1.len()).then(a.0.cmp(b.0)));
    let per_keyframe = options.max_averaging_tracks / keyframes.max(1) / 2;
    let mut coverage = vec![0usize; keyframes];
    let mut chosen = Vec::new();
    let mut rest = Vec::new();
    for t in long {
        if chosen.len() < options.max_averaging_tracks / 2
            || t.1.iter().any(|(k, _)| coverage[*k] < per_keyframe)
        {
            for (k, _) in t.1 {
                coverage[*k] += 1;
            }
            chosen.push(t);
        } else {
            rest.push(t);
        }
    }
    let room = options.max_averaging_tracks.saturating_sub(chosen.len());
    chosen.extend(rest.into_iter().take(room));
    chosen
}

fn bearing(camera: &PinholeRadtan, p: &Point2<f64>) -> Vector3<f64> {
    camera.bearing_from_undistorted(*p)
}

/// Solves one window; never panics on data, reports failure in the status instead.
pub fn solve_window(
    camera: &PinholeRadtan,
    keyframes: &[KeyframeObservations],
    options: &WindowSolverOptions,
    cache: &mut EdgeCache,
) -> WindowSolution {
    let mut timings = Vec::new();
    let n = keyframes.len();
    if n < 2 {
        return WindowSolution::failed(format!("{n} keyframe(s): nothing to solve"), timings, 0);
    }
    let (edges, failures) = timed(&mut timings, "relative_poses", || {
        build_view_graph(camera, keyframes, &options.view_graph, cache)
    });
    for (i, j, e) in &failures {
        tracing::debug!(i, j, %e, "no edge");
    }
    // A view graph in pieces (a dark second, a whip pan) is solved on its largest piece:
    // the rest of the window is left unposed instead of failing the whole window, so the
    // map continues wherever the piece still shares keyframes with the previous window.
    let component = largest_component(n, &edges);
    if component.len() < 2 || (component.len() as f64) < options.min_piece_fraction * n as f64 {
        return WindowSolution::failed(
            format!(
                "view graph in pieces: the largest holds {} of {n} keyframes",
                component.len()
            ),
            timings,
            edges.len(),
        );
    }
    if component.len() == n {
        return solve_connected(camera, keyframes, &edges, options, timings);
    }
    let mut index = vec![usize::MAX; n];
    for (new, old) in component.iter().enumerate() {
        index[*old] = new;
    }
    let sub_keyframes: Vec<KeyframeObservations> =
        component.iter().map(|k| keyframes[*k].clone()).collect();
    let sub_edges: Vec<ViewEdge> = edges
        .iter()
        .filter(|e| index[e.i] != usize::MAX && index[e.j] != usize::MAX)
        .map(|e| ViewEdge {
            i: index[e.i],
            j: index[e.j],
            ..*e
        })
        .collect();
    tracing::info!(
        solved = component.len(),
        keyframes = n,
        "view graph disconnected: solving its largest piece"
    );
    let mut solution = solve_connected(camera, &sub_keyframes, &sub_edges, options, timings);
    let back = |k: &mut usize| *k = component[*k];
    solution
        .observations
        .iter_mut()
        .for_each(|o| back(&mut o.0));
    solution
        .weak_observations
        .iter_mut()
        .for_each(|o| back(&mut o.0));
    solution.keyframes = component;
    solution
}

/// Keyframe indices of the largest connected piece of the view graph, in order (ties: the
/// piece with the earliest keyframe, which continues the previous window).
fn largest_component(n: usize, edges: &[ViewEdge]) -> Vec<usize> {
    let mut parent: Vec<usize> = (0..n).collect();
    fn root(parent: &mut [usize], mut k: usize) -> usize {
        while parent[k] != k {
            parent[k] = parent[parent[k]];
            k = parent[k];
        }
        k
    }
    for e in edges {
        let (a, b) = (root(&mut parent, e.i), root(&mut parent, e.j));
        if a != b {
            parent[a.max(b)] = a.min(b);
        }
    }
    let mut size = vec![0usize; n];
    let roots: Vec<usize> = (0..n).map(|k| root(&mut parent, k)).collect();
    for r in &roots {
        size[*r] += 1;
    }
    let best = (0..n)
        .max_by(|a, b| size[*a].cmp(&size[*b]).then(b.cmp(a)))
        .unwrap_or(0);
    (0..n).filter(|k| roots[*k] == best).collect()
}

/// Solves a window whose view graph is connected.
fn solve_connected(
    camera: &PinholeRadtan,
    keyframes: &[KeyframeObservations],
    edges: &[ViewEdge],
    options: &WindowSolverOptions,
    mut timings: Vec<(&'static str, f64)>,
) -> WindowSolution {
    let n = keyframes.len();
    let rel: Vec<RelativeRotation> = edges
        .iter()
        .map(|e| RelativeRotation {
            i: e.i,
            j: e.j,
            rotation: e.pose.rotation,
            weight: e.pose.inliers as f64,
        })
        .collect();
    let rotations = match timed(&mut timings, "rotation_averaging", || {
        average_rotations(n, &rel, &options.rotation)
    }) {
        Ok(r) => r,
        Err(e) => {
            return WindowSolution::failed(format!("rotation averaging: {e}"), timings, edges.len())
        }
    };
    let max_residual = options.max_edge_rotation_residual_deg.to_radians();
    let translation_edges: Vec<_> = edges
        .iter()
        .zip(&rotations.edge_residuals)
        .filter(|(e, r)| e.pose.has_translation && **r < max_residual)
        .map(|(e, _)| e)
        .collect();
    let rot = &rotations.rotations;
    let needed = options
        .min_translation_edges
        .max((options.min_translation_edge_fraction * edges.len() as f64).ceil() as usize);
    if translation_edges.len() < needed {
        let reason = format!(
            "{} of {} edges have parallax (fewer than {needed})",
            translation_edges.len(),
            edges.len(),
        );
        return WindowSolution::rotation_only(
            reason,
            rot,
            edges.len(),
            translation_edges.len(),
            timings,
        );
    }

    // Tracks of the window: track id -> [(keyframe index, pixel)].
    let tracks = tracks_of(keyframes);
    let long = select_averaging_tracks(&tracks, n, options);

    let mut constraints: Vec<DirectionConstraint> = translation_edges
        .iter()
        .map(|e| DirectionConstraint {
            endpoints: Endpoints::Cameras { i: e.i, j: e.j },
            direction: -(rot[e.j].inverse() * e.pose.translation),
            weight: 1.0,
        })
        .collect();
    for (point, (_, obs)) in long.iter().enumerate() {
        for (k, p) in obs.iter() {
            constraints.push(DirectionConstraint {
                endpoints: Endpoints::CameraPoint { i: *k, point },
                direction: rot[*k].inverse() * bearing(camera, p),
                weight: 1.0,
            });
        }
    }
    let averaged = match timed(&mut timings, "translation_averaging", || {
        average_translations(n, long.len(), &constraints, &options.translation)
    }) {
        Ok(r) => r,
        Err(e) => {
            // The rotations are still good: keep them rather than break the map.
            tracing::warn!(%e, "translation averaging failed; window kept as rotation only");
            return WindowSolution::rotation_only(
                format!("translation averaging failed: {e}"),
                rot,
                edges.len(),
                translation_edges.len(),
                timings,
            );
        }
    };
    let poses: Vec<CameraPose> = rot
        .iter()
        .zip(&averaged.centres)
        .map(|(r, c)| CameraPose {
            rotation: *r,
            centre: *c,
        })
        .collect();

    // Triangulate every track seen twice or more.
    let mut ids: Vec<u64> = tracks
        .iter()
        .filter(|(_, o)| o.len() >= 2)
        .map(|(id, _)| *id)
        .collect();
    ids.sort_unstable();
    let structure = timed(&mut timings, "triangulation", || {
        triangulate_tracks(camera, &poses, &tracks, &ids, &options.triangulation)
    });
    if structure.points.len() < options.min_points {
        // Centres that no point confirms are set by a handful of directions and the rays of
        // tracks too short to triangulate; on rendered walks such windows put centres metres
        // off and handed the merger a scale 50x wrong. The rotations stand.
        let reason = format!(
            "{} points triangulated (fewer than {})",
            structure.points.len(),
            options.min_points
        );
        let mut solution = WindowSolution::rotation_only(
            reason,
            rot,
            edges.len(),
            translation_edges.len(),
            timings,
        );
        solution.weak_observations = structure.weak;
        return solution;
    }
    let adjusted = match timed(&mut timings, "bundle_adjustment", || {
        bundle_adjust(
            camera,
            &poses,
            &structure.positions(),
            &structure.observations,
            &options.bundle_adjustment,
        )
    }) {
        Ok(r) => r,
        Err(e) => {
            return WindowSolution::failed(format!("bundle adjustment: {e}"), timings, edges.len())
        }
    };
    let readjusted = timed(&mut timings, "retriangulation", || {
        retriangulate_and_adjust(
            camera,
            &tracks,
            &ids,
            &translation_edges,
            structure,
            adjusted,
            &options.retriangulation,
            &options.triangulation,
            &options.bundle_adjustment,
        )
    });
    if readjusted.passes > 0 {
        tracing::debug!(
            passes = readjusted.passes,
            observations = readjusted.structure.observations.len(),
            "re-triangulated and adjusted again"
        );
    }
    let Structure {
        points,
        observations,
        weak,
    } = readjusted.structure;
    let adjusted = readjusted.adjusted;
    let mut outlier = vec![false; observations.len()];
    for &n in &adjusted.outliers {
        outlier[n] = true;
    }
    // Inlier observations per keyframe, for the unobserved keyframes' poses.
    let mut seen = adjusted.inliers_per_camera(&observations, n);
    let mut adjusted_poses = adjusted.poses;
    let detached = restore_detached_keyframes(
        &mut adjusted_poses,
        rot,
        &observations,
        &outlier,
        &options.detached_keyframes,
    );
    if !detached.is_empty() {
        tracing::debug!(
            ?detached,
            "keyframes turned away with points only they see: rotations from the averaging"
        );
    }
    // A detached keyframe's points were placed for its turned pose: its observations leave
    // the solution, and its centre is placed from the motion as an unobserved one's.
    for &k in &detached {
        seen[k] = 0;
    }
    let mut counts = vec![0u32; points.len()];
    let mut kept = Vec::with_capacity(observations.len());
    for (o, _) in observations
        .iter()
        .zip(&outlier)
        .filter(|(o, out)| !**out && detached.binary_search(&o.camera).is_err())
    {
        counts[o.point] += 1;
        kept.push((o.camera, points[o.point].0, o.pixel));
    }
    let timestamps: Vec<f64> = keyframes.iter().map(|k| k.timestamp).collect();
    let restored = restore_unobserved_rotations(
        &mut adjusted_poses,
        &timestamps,
        &seen,
        rot,
        &options.unobserved_keyframes,
    );
    let placed = place_unobserved_centres(
        &mut adjusted_poses,
        &timestamps,
        &seen,
        &options.unobserved_keyframes,
    );
    if placed > 0 || restored > 0 {
        tracing::debug!(
            placed,
            restored,
            "unobserved keyframes: centres placed from the motion, rotations from the averaging"
        );
    }
    let solved_points = points
        .iter()
        .zip(&adjusted.points)
        .zip(&counts)
        .filter(|(_, c)| **c >= 2)
        .map(|(((id, _), x), c)| SolvedPoint {
            track_id: *id,
            position: *x,
            observations: *c,
        })
        .collect();
    WindowSolution {
        status: WindowStatus::Solved,
        keyframes: (0..n).collect(),
        poses: adjusted_poses,
        points: solved_points,
        observations: kept,
        outlier_observations: adjusted.outliers.len(),
        weak_observations: weak,
        rmse_px: adjusted.rmse_px,
        focal_scale: adjusted.focal_scale,
        radial_k: adjusted.radial_k,
        edges: edges.len(),
        translation_edges: translation_edges.len(),
        timings_ms: timings,
    }
}

#[cfg(test)]
mod tests;
