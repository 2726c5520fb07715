//! Developer tool: re-solves windows dumped by the solver service
//! (`EGOSLAM_DUMP_WINDOWS=DIR egoslam run ...`) and prints each window's keyframe accuracy
//! against ground truth, so estimator changes can be judged without the whole pipeline.
//!
//! `cargo run --example solve_window -- DIR GROUND_TRUTH`
//!
//! Environment knobs (estimator options): MIN_ANGLE_DEG, MIN_PARALLAX_PX, RANSAC_PX,
//! OPENCV_USAC (1: OpenCV's five-point RANSAC, 0: the own LO-RANSAC), LO_RANSAC_PX and
//! LO_RANSAC_LO (its scoring threshold and local optimisation on/off), REFINE_EDGES,
//! LOOP_CLOSURE_SPAN, RETRIANGULATION_PASSES, LUD_ITERS, REFINE_ITERS,
//! MIN_TRACK_VIEWS, REFINE_INTRINSICS.
//!
//! Input knobs (what the data contributes): FOCAL_SCALE (calibrated focal times this),
//! FY_SCALE, CX_SHIFT, CY_SHIFT (pixels), REVERSE (keyframes in reverse order: does an
//! effect follow the solver's order or the scene's?), MAX_SPAN (tracks cut into pieces of
//! that many keyframes), MAX_Y / MAX_DX (only observations above that row / within that
//! many pixels of the principal point's column), SKIP_FIRST.
//!
//! Output: EDGES (first edges' errors; EDGES=all every edge), PER_KEYFRAME (each posed
//! keyframe's error and its mean angle to the two-view directions of its edges), with TAIL
//! as well one line per window comparing its last five keyframes (the next window's
//! overlap) with the rest; SCALE (aligned over true path length and chord of each half of
//! the window and of its last five keyframes: a scale that changes along the window).

use egoslam_geometry::{absolute_trajectory_error, PinholeRadtan, StampedPose};
use egoslam_messages::internal::v1 as internal;
use egoslam_solver::view_graph::{EdgeCache, KeyframeObservations};
use egoslam_solver::window_solver::{solve_window, WindowSolverOptions};
use nalgebra::{Point2, UnitQuaternion};
use prost::Message;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(args.len() == 3, "usage: solve_window DUMP_DIR GROUND_TRUTH");
    let gt = egoslam_sources::load_ground_truth(std::path::Path::new(&args[2]))?;
    let mut files: Vec<_> = std::fs::read_dir(&args[1])?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .collect();
    files.sort();
    let mut cache = EdgeCache::new();
    // The ground-truth pose nearest in time to `t`.
    let near = |t: f64| {
        gt.poses
            .iter()
            .min_by(|a, b| (a.timestamp - t).abs().total_cmp(&(b.timestamp - t).abs()))
            .copied()
    };
    // Tuning knobs (environment), so estimator defaults can be compared on dumped windows.
    let env = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<f64>().ok());
    let mut options = WindowSolverOptions::default();
    if let Some(v) = env("MIN_ANGLE_DEG") {
        options.triangulation.min_angle_deg = v;
    }
    if let Some(v) = env("MIN_PARALLAX_PX") {
        options.view_graph.relative_pose.min_parallax_px = v;
    }
    if let Some(v) = env("RANSAC_PX") {
        options.view_graph.relative_pose.ransac_threshold_px = v;
    }
    if let Some(v) = env("OPENCV_USAC") {
        options.view_graph.relative_pose.estimator = if v != 0.0 {
            egoslam_solver::relative_pose::EssentialEstimator::OpenCvUsac
        } else {
            egoslam_solver::relative_pose::EssentialEstimator::LoRansac
        };
    }
    if let Some(v) = env("LO_RANSAC_PX") {
        options.view_graph.relative_pose.lo_ransac_threshold_px = v;
    }
    if let Some(v) = env("LO_RANSAC_LO") {
        options
            .view_graph
            .relative_pose
            .lo_ransac_local_optimization = v != 0.0;
    }
    if let Some(v) = env("REFINE_EDGES") {
        options.view_graph.relative_pose.refine = v != 0.0;
    }
    if let Some(v) = env("LOOP_CLOSURE_SPAN") {
        options.view_graph.loop_closure_span = v as usize;
    }
    if let Some(v) = env("RETRIANGULATION_PASSES") {
        options.retriangulation.max_passes = v as usize;
    }
    if let Some(v) = env("LUD_ITERS") {
        options.translation.lud_iterations = v as usize;
    }
    if let Some(v) = env("REFINE_ITERS") {
        options.translation.refine_iterations = v as usize;
    }
    if let Some(v) = env("REFINE_INTRINSICS") {
        options.bundle_adjustment.refine_intrinsics = v != 0.0;
    }
    if let Some(v) = env("MIN_TRACK_VIEWS") {
        options.min_track_views = v as usize;
    }
    for file in files {
        let bytes = std::fs::read(&file)?;
        let mut buf = bytes.as_slice();
        let mut kfs = Vec::new();
        while !buf.is_empty() {
            kfs.push(internal::Keyframe::decode_length_delimited(&mut buf)?);
        }
        if std::env::var_os("SKIP_FIRST").is_some() {
            kfs.remove(0);
        }
        if std::env::var_os("REVERSE").is_some() {
            kfs.reverse();
        }
        let i = kfs[0].intrinsics.clone().unwrap_or_default();
        let fs = env("FOCAL_SCALE").unwrap_or(1.0);
        let camera = PinholeRadtan::new(
            i.width,
            i.height,
            [
                i.fx * fs,
                i.fy * fs * env("FY_SCALE").unwrap_or(1.0),
                i.cx + env("CX_SHIFT").unwrap_or(0.0),
                i.cy + env("CY_SHIFT").unwrap_or(0.0),
            ],
            [0.0; 5],
        )?;
        let span = env("MAX_SPAN").map(|v| v as u64);
        let obs: Vec<KeyframeObservations> = kfs
            .iter()
            .enumerate()
            .map(|(n, k)| KeyframeObservations {
                id: k.keyframe_id,
                timestamp: k.timestamp_s,
                tracks: k
                    .tracks
                    .iter()
                    .filter(|t| env("MAX_Y").is_none_or(|m| f64::from(t.y) < m))
                    .filter(|t| env("MAX_DX").is_none_or(|m| (f64::from(t.x) - i.cx).abs() < m))
                    .map(|t| {
                        // MAX_SPAN: cut each track into pieces of that many keyframes
                        // (staggered by track id), to see what long tracks contribute.
                        let id = span.map_or(t.track_id, |s| {
                            t.track_id * 1000 + (n as u64 + t.track_id % s) / s
                        });
                        (id, Point2::new(f64::from(t.x), f64::from(t.y)))
                    })
                    .collect(),
            })
            .collect();
        if std::env::var_os("EDGES").is_some() {
            let (edges, _) = egoslam_solver::view_graph::build_view_graph(
                &camera,
                &obs,
                &options.view_graph,
                &mut EdgeCache::new(),
            );
            let all = std::env::var_os("EDGES").is_some_and(|v| v == "all");
            for e in edges.iter().filter(|e| all || e.i < 3) {
                let (Some(gi), Some(gj)) = (near(obs[e.i].timestamp), near(obs[e.j].timestamp))
                else {
                    continue;
                };
                let (ri, rj) = (gi.rotation.inverse(), gj.rotation.inverse());
                let r_gt = rj * ri.inverse();
                let t_gt = (rj * (gi.position - gj.position)).normalize();
                let r_err = UnitQuaternion::from_rotation_matrix(&e.pose.rotation)
                    .angle_to(&r_gt)
                    .to_degrees();
                let t_err = e
                    .pose
                    .translation
                    .dot(&t_gt)
                    .clamp(-1.0, 1.0)
                    .acos()
                    .to_degrees();
                println!("  edge {}-{}: rot err {r_err:.3} deg, dir err {t_err:.2} deg, inliers {}/{}, parallax {:.1}px", e.i, e.j, e.pose.inliers, e.pose.matches, e.pose.parallax_px);
            }
        }
        let s = solve_window(&camera, &obs, &options, &mut cache);
        let finite = s.poses.iter().all(|p| {
            p.centre
                .iter()
                .chain(p.rotation.matrix().iter())
                .all(|v| v.is_finite())
        });
        if !finite {
            println!("{}: non-finite poses", file.display());
        }
        // A partial window poses only its largest connected piece: `s.keyframes` says which.
        let est: Vec<StampedPose> = s
            .keyframes
            .iter()
            .map(|k| &kfs[*k])
            .zip(&s.poses)
            .map(|(k, p)| StampedPose {
                timestamp: k.timestamp_s,
                position: p.centre,
                rotation: UnitQuaternion::from_rotation_matrix(&p.rotation.inverse()),
            })
            .collect();
        let ate = absolute_trajectory_error(&est, &gt.poses, 0.02);
        let timings: Vec<String> = s
            .timings_ms
            .iter()
            .map(|(st, ms)| format!("{st} {ms:.0}"))
            .collect();
        if std::env::var_os("DEPTHS").is_some() {
            // Per posed keyframe: how many of the window's points it sees and their median
            // depth, against the window's median (points at invented depths show here).
            let positions: std::collections::HashMap<u64, nalgebra::Vector3<f64>> =
                s.points.iter().map(|p| (p.track_id, p.position)).collect();
            // Each posed keyframe's point depths, in `s.keyframes` order.
            let depths: Vec<Vec<f64>> = s
                .keyframes
                .iter()
                .zip(&s.poses)
                .map(|(&k, pose)| {
                    s.observations
                        .iter()
                        .filter(|(o, _, _)| *o == k)
                        .filter_map(|(_, t, _)| positions.get(t))
                        .map(|x| pose.to_camera(x).z)
                        .collect()
                })
                .collect();
            let window_median = egoslam_geometry::median(depths.concat());
            for (&k, d) in s.keyframes.iter().zip(depths) {
                let n = d.len();
                let m = egoslam_geometry::median(d);
                println!(
                    "  kf {} t {:.2} points {n} median depth {m:.4} ({:.3} of the window's)",
                    kfs[k].keyframe_id,
                    kfs[k].timestamp_s,
                    m / window_median
                );
            }
        }
        if std::env::var_os("PER_KEYFRAME").is_some() {
            // Per keyframe: the mean angle between the solution's direction to each
            // view-graph neighbour and the two-view direction of that edge.
            let (edges, _) = egoslam_solver::view_graph::build_view_graph(
                &camera,
                &obs,
                &options.view_graph,
                &mut EdgeCache::new(),
            );
            let mut by_window = vec![None; kfs.len()];
            for (k, p) in s.keyframes.iter().zip(&s.poses) {
                by_window[*k] = Some(*p);
            }
            let disagreement = |k: usize| {
                let poses: Option<Vec<_>> = by_window.iter().copied().collect();
                let poses = poses?;
                let angles: Vec<f64> = edges
                    .iter()
                    .filter(|e| e.i == k || e.j == k)
                    .filter_map(|e| e.direction_disagreement_deg(&poses))
                    .collect();
                (!angles.is_empty()).then(|| angles.iter().sum::<f64>() / angles.len() as f64)
            };
            let mut tail_rows: Vec<(f64, f64)> = Vec::new();
            if let Ok(r) = &ate {
                for (k, e) in est.iter().enumerate() {
                    if let Some(g) = near(e.timestamp) {
                        let err = (r.alignment.apply(&e.position) - g.position).norm();
                        if std::env::var_os("TAIL").is_some() {
                            tail_rows.push((err, disagreement(s.keyframes[k]).unwrap_or(f64::NAN)));
                            continue;
                        }
                        let kf = &kfs[s.keyframes[k]];
                        println!(
                            "  kf {} t {:.2} tracks {} err {:.3} disagreement {:.1} deg",
                            kf.keyframe_id,
                            kf.timestamp_s,
                            kf.tracks.len(),
                            err,
                            disagreement(s.keyframes[k]).unwrap_or(f64::NAN)
                        );
                    }
                }
            }
            if tail_rows.len() > 10 {
                let o = 5;
                let (interior, tail) = tail_rows.split_at(tail_rows.len() - o);
                let mut d: Vec<f64> = interior
                    .iter()
                    .map(|r| r.1)
                    .filter(|v| v.is_finite())
                    .collect();
                d.sort_by(f64::total_cmp);
                let med = d.get(d.len() / 2).copied().unwrap_or(f64::NAN);
                let td: Vec<f64> = tail.iter().map(|r| r.1).filter(|v| v.is_finite()).collect();
                let tmean = td.iter().sum::<f64>() / td.len().max(1) as f64;
                let ie = interior.iter().map(|r| r.0).sum::<f64>() / interior.len() as f64;
                let te = tail.iter().map(|r| r.0).sum::<f64>() / tail.len() as f64;
                // Tracks tying the last five keyframes to the rest: seen twice on each side.
                let cut_strength = |c: usize| {
                    let mut views: std::collections::HashMap<u64, (usize, usize)> =
                        Default::default();
                    for (k, kf) in obs.iter().enumerate() {
                        for id in kf.tracks.keys() {
                            let e = views.entry(*id).or_default();
                            if k < c {
                                e.0 += 1
                            } else {
                                e.1 += 1
                            }
                        }
                    }
                    views.values().filter(|(a, b)| *a >= 2 && *b >= 2).count()
                };
                let n = obs.len();
                let tail_cut = cut_strength(n - o);
                let mut cuts: Vec<usize> = (2..n - 1).map(cut_strength).collect();
                cuts.sort_unstable();
                let median_cut = cuts.get(cuts.len() / 2).copied().unwrap_or(0);
                println!("TAIL {} interior_d {med:.1} tail_d {tmean:.1} ratio {:.2} interior_err {ie:.4} tail_err {te:.4} err_ratio {:.2} tail_cut {tail_cut} median_cut {median_cut}", file.display(), tmean / med, te / ie.max(1e-9));
            }
        }
        if let (Some(_), Ok(r)) = (std::env::var_os("SCALE"), &ate) {
            // Scale along the window: aligned path length over true path length, per half.
            let pairs: Vec<_> = est
                .iter()
                .filter_map(|e| {
                    near(e.timestamp).map(|g| (r.alignment.apply(&e.position), g.position))
                })
                .collect();
            let ratio = |range: std::ops::Range<usize>| {
                let (mut a, mut b) = (0.0, 0.0);
                for k in range.start + 1..range.end {
                    a += (pairs[k].0 - pairs[k - 1].0).norm();
                    b += (pairs[k].1 - pairs[k - 1].1).norm();
                }
                let (s, e) = (range.start, range.end - 1);
                let chord = (pairs[e].0 - pairs[s].0).norm()
                    / f64::max((pairs[e].1 - pairs[s].1).norm(), 1e-12);
                format!("{:.4} (chord {chord:.4})", a / f64::max(b, 1e-12))
            };
            let n = pairs.len();
            if n > 4 {
                println!(
                    "SCALE {} first {} second {} tail5 {}",
                    file.display(),
                    ratio(0..n / 2 + 1),
                    ratio(n / 2..n),
                    ratio(n.saturating_sub(5)..n)
                );
            }
        }
        match ate {
            Ok(r) => println!(
                "{}: {:?} edges {} (t {}) points {} rmse {:.2}px | ATE {:.4} m of {:.3} m path ({:.1}%) | {}",
                file.display(),
                s.status,
                s.edges,
                s.translation_edges,
                s.points.len(),
                s.rmse_px,
                r.rmse,
                r.gt_path_length,
                100.0 * r.rmse / r.gt_path_length.max(1e-9),
                timings.join(", ")
            ),
            Err(e) => println!("{}: {:?} ({e})", file.display(), s.status),
        }
    }
    Ok(())
}
