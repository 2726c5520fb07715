//! How accurate each temporal window is on its own, and how accurate the data allow it to
//! be. The real tracker makes keyframes from a dataset with ground truth; windows of
//! `--window` keyframes (default 20, overlap 5) are solved one by one and each window's
//! keyframe centres are Sim(3)-aligned to the ground truth. This separates errors made
//! inside windows from those added by chaining them (compare with `egoslam run`).
//!
//! With `--ba-from-truth`, each window is also bundle-adjusted from the *ground-truth*
//! poses (tracks triangulated from them, first two cameras fixed): where that settles is
//! the optimum the tracks support, so a window solve cannot be expected to beat it; the
//! gap between the two is the solver's share of the error, the rest is the data's.
//! `--window 1000` does the same for the whole sequence as one problem.
//!
//! `--rolling-shutter-ms MS` corrects the tracks for that readout as the frontend does
//! (`--extrapolated`: without centring each keyframe's correction on the next frame);
//! `--turn-prior RAD_S` then also estimates each keyframe's residual turn during the
//! readout in bundle adjustment, with that prior (`BundleAdjustmentOptions::readout_s`).
//!
//! `cargo run --release -p egoslam-solver --example window_accuracy -- DATASET [--window N] [--ba-from-truth] [--verbose]`

use egoslam_frontend::{KeyframeTracks, Tracker, TrackerOptions};
use egoslam_geometry::{umeyama, PinholeRadtan, StampedPose};
use egoslam_solver::bundle_adjustment::{bundle_adjust, Observation};
use egoslam_solver::triangulation::{triangulate_track, CameraPose};
use egoslam_solver::view_graph::{EdgeCache, KeyframeObservations};
use egoslam_solver::window_solver::{solve_window, WindowSolverOptions};
use nalgebra::{Point2, Vector3};
use std::collections::BTreeMap;
use std::error::Error;
use std::path::{Path, PathBuf};

type Result<T> = std::result::Result<T, Box<dyn Error>>;

/// Keyframes of a whole sequence from the real tracker with default options, correcting
/// for a rolling-shutter readout of `readout_s` (0: none), with `radial_k` added to the
/// calibration's k1 (what `egoslam run --calibrate-radial` applies).
fn keyframes(
    path: &Path,
    readout_s: f64,
    centred: bool,
    radial_k: f64,
) -> Result<(PinholeRadtan, Vec<KeyframeObservations>)> {
    let layout = egoslam_sources::detect_layout(path)?;
    let calib = egoslam_sources::load_calibration(&layout, None)?;
    use egoslam_sources::FrameSource;
    let mut source = egoslam_sources::open_source(path, 10.0)?;
    let mut tracker: Option<Tracker> = None;
    let mut camera = None;
    let mut keyframes = Vec::new();
    // As the frontend service: a keyframe waits for the next frame, which centres its
    // rolling-shutter correction (`Tracker::centre_keyframe`).
    let mut pending: Option<(KeyframeTracks, f64)> = None;
    let observations = |k: KeyframeTracks, timestamp: f64| {
        let tracks = k.tracks.iter().map(|p| {
            let u = p.undistorted;
            (p.track_id, Point2::new(f64::from(u.x), f64::from(u.y)))
        });
        KeyframeObservations {
            id: k.keyframe_id,
            timestamp,
            tracks: tracks.collect(),
        }
    };
    while let Some(frame) = source.next_frame() {
        let frame = frame?;
        use opencv::prelude::MatTraitConst;
        let (w, h) = (frame.image.cols() as u32, frame.image.rows() as u32);
        let cam = match camera {
            Some(c) => c,
            None => {
                let mut c = calib.camera_for(w, h)?;
                c.distortion[0] += radial_k;
                *camera.insert(c)
            }
        };
        let t = tracker.get_or_insert_with(|| {
            let options = TrackerOptions {
                rolling_shutter_s: readout_s,
                ..TrackerOptions::default()
            };
            Tracker::new(cam, options)
        });
        let outcome = t.process_timed(frame.index, frame.timestamp, &frame.image)?;
        if let Some((mut k, timestamp)) = pending.take() {
            if centred {
                t.centre_keyframe(&mut k);
            }
            keyframes.push(observations(k, timestamp));
        }
        pending = outcome.keyframe.map(|k| (k, frame.timestamp));
    }
    keyframes.extend(pending.map(|(k, timestamp)| observations(k, timestamp)));
    Ok((camera.ok_or("no frame decoded")?, keyframes))
}

/// Ground-truth pose nearest in time (within 20 ms).
fn nearest(truth: &[StampedPose], t: f64) -> Option<&StampedPose> {
    truth
        .iter()
        .min_by(|a, b| (a.timestamp - t).abs().total_cmp(&(b.timestamp - t).abs()))
        .filter(|g| (g.timestamp - t).abs() < 0.02)
}

/// Sim(3)-aligned RMSE of `centres` against `truth` (None when they cannot be aligned).
fn aligned_rmse(centres: &[Vector3<f64>], truth: &[Vector3<f64>]) -> Option<f64> {
    let sim = umeyama(centres, truth).ok()?;
    let sq: f64 = centres
        .iter()
        .zip(truth)
        .map(|(a, b)| (sim.apply(a) - b).norm_squared())
        .sum();
    Some((sq / centres.len() as f64).sqrt())
}

/// Bundle adjustment of `window` started from the ground-truth poses; returns the
/// Sim(3)-aligned keyframe RMSE where it settles and its reprojection RMSE.
fn ba_from_truth(
    camera: &PinholeRadtan,
    window: &[KeyframeObservations],
    truth: &[Vector3<f64>],
    truth_poses: &[CameraPose],
    options: &WindowSolverOptions,
) -> Option<(f64, f64)> {
    let mut tracks: BTreeMap<u64, Vec<(usize, Point2<f64>)>> = BTreeMap::new();
    for (k, kf) in window.iter().enumerate() {
        for (id, p) in &kf.tracks {
            tracks.entry(*id).or_default().push((k, *p));
        }
    }
    let (mut points, mut observations) = (Vec::new(), Vec::new());
    for obs in tracks.values() {
        if let Ok(p) = triangulate_track(camera, truth_poses, obs, &options.triangulation) {
            for i in p.inliers {
                observations.push(Observation {
                    camera: obs[i].0,
                    point: points.len(),
                    pixel: obs[i].1,
                });
            }
            points.push(p.position);
        }
    }
    let mut ba = options.bundle_adjustment;
    ba.fixed_cameras = 2;
    let r = bundle_adjust(camera, truth_poses, &points, &observations, &ba).ok()?;
    let centres: Vec<_> = r.poses.iter().map(|p| p.centre).collect();
    Some((aligned_rmse(&centres, truth)?, r.rmse_px))
}

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let (mut path, mut size, mut from_truth, mut verbose) = (None, 20usize, false, false);
    let mut readout_ms = 0.0;
    let mut start_from: Option<PathBuf> = None;
    let mut turn_prior: Option<f64> = None;
    let mut extrapolated = false;
    let mut radial_k = 0.0;
    while let Some(a) = args.next() {
        match a.as_str() {
            "--window" => size = args.next().ok_or("--window N")?.parse()?,
            "--ba-from-truth" => from_truth = true,
            "--verbose" => verbose = true,
            "--ba-from" => start_from = Some(args.next().ok_or("--ba-from POSES.tum")?.into()),
            "--extrapolated" => extrapolated = true,
            "--radial" => radial_k = args.next().ok_or("--radial K")?.parse()?,
            "--turn-prior" => turn_prior = Some(args.next().ok_or("--turn-prior RAD_S")?.parse()?),
            "--rolling-shutter-ms" => {
                readout_ms = args.next().ok_or("--rolling-shutter-ms MS")?.parse()?
            }
            _ => path = Some(PathBuf::from(a)),
        }
    }
    let path =
        path.ok_or("usage: window_accuracy DATASET [--window N] [--ba-from-truth] [--verbose] [--rolling-shutter-ms MS [--extrapolated] [--turn-prior RAD_S]] [--ba-from POSES.tum] [--radial K]")?;
    opencv::core::set_num_threads(1)?;
    let truth = egoslam_sources::load_ground_truth(&path)?.poses;
    let start_poses = match &start_from {
        Some(file) => Some(egoslam_sources::ground_truth::read_tum_file(file)?),
        None => None,
    };
    let (camera, keyframes) = keyframes(&path, readout_ms / 1000.0, !extrapolated, radial_k)?;
    let mut options = WindowSolverOptions::default();
    if let Some(prior) = turn_prior {
        options.bundle_adjustment.readout_s = readout_ms / 1000.0;
        options.bundle_adjustment.turn_prior_rad_s = prior;
    }
    let overlap = 5.min(size / 2);
    let mut cache = EdgeCache::new();
    let (mut start, mut sq, mut n) = (0usize, 0.0, 0usize);
    while start + 2 <= keyframes.len() {
        let end = (start + size).min(keyframes.len());
        let window = &keyframes[start..end];
        let s = solve_window(&camera, window, &options, &mut cache);
        let (mut centres, mut gt) = (Vec::new(), Vec::new());
        for (pose, k) in s.poses.iter().zip(&s.keyframes) {
            if let Some(g) = nearest(&truth, window[*k].timestamp) {
                centres.push(pose.centre);
                gt.push(g.position);
            }
        }
        let path_m: f64 = gt.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
        let time: f64 = s.timings_ms.iter().map(|t| t.1).sum();
        let mut obs_by_track: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
        for (k, kf) in window.iter().enumerate() {
            for id in kf.tracks.keys() {
                obs_by_track.entry(*id).or_default().push(k);
            }
        }
        let weakest_cut = (2..window.len().saturating_sub(1))
            .map(|c| {
                obs_by_track
                    .values()
                    .filter(|ks| {
                        ks.iter().filter(|k| **k < c).count() >= 2
                            && ks.iter().filter(|k| **k >= c).count() >= 2
                    })
                    .count()
            })
            .min()
            .unwrap_or(0);
        let mut line = format!(
            "window {start:4}-{end:4} {:?}: posed {}/{}, {} edges ({} with direction), weakest cut {weakest_cut} tracks, {:.3} px, {time:.0} ms",
            s.status,
            s.poses.len(),
            window.len(),
            s.edges,
            s.translation_edges,
            s.rmse_px
        );
        if verbose {
            if let Ok(sim) = umeyama(&centres, &gt) {
                for (k, (c, g)) in centres.iter().zip(&gt).enumerate() {
                    let e = (sim.apply(c) - g).norm();
                    println!("    keyframe {:4}: error {e:.4} m", start + s.keyframes[k]);
                }
            }
        }
        if let Some(e) = aligned_rmse(&centres, &gt) {
            sq += e * e * centres.len() as f64;
            n += centres.len();
            line += &format!(
                "; ATE {e:.4} m ({:.2} % of {path_m:.2} m)",
                100.0 * e / path_m.max(1e-12)
            );
        }
        if from_truth {
            let found: Option<Vec<&StampedPose>> = window
                .iter()
                .map(|k| nearest(&truth, k.timestamp))
                .collect();
            if let Some(found) = found {
                let gt_all: Vec<_> = found.iter().map(|g| g.position).collect();
                let poses: Vec<CameraPose> = found
                    .iter()
                    .map(|g| CameraPose {
                        rotation: g.rotation.to_rotation_matrix().inverse(),
                        centre: g.position,
                    })
                    .collect();
                if let Some((e, px)) = ba_from_truth(&camera, window, &gt_all, &poses, &options) {
                    line += &format!("; BA from truth settles at {e:.4} m ({px:.3} px)");
                }
                let given: Option<Vec<CameraPose>> = start_poses.as_ref().and_then(|list| {
                    window
                        .iter()
                        .map(|k| {
                            nearest(list, k.timestamp).map(|g| CameraPose {
                                rotation: g.rotation.to_rotation_matrix().inverse(),
                                centre: g.position,
                            })
                        })
                        .collect()
                });
                if let Some(given) = given {
                    let centres: Vec<_> = given.iter().map(|p| p.centre).collect();
                    let before = aligned_rmse(&centres, &gt_all).unwrap_or(f64::NAN);
                    if let Some((e, px)) = ba_from_truth(&camera, window, &gt_all, &given, &options)
                    {
                        line += &format!(
                            "; from the given poses ({before:.4} m) BA settles at {e:.4} m ({px:.3} px)"
                        );
                    }
                }
            }
        }
        println!("{line}");
        if end == keyframes.len() {
            break;
        }
        start = end - overlap;
    }
    println!(
        "all windows, each aligned on its own: keyframe ATE RMSE {:.4} m over {n}",
        (sq / n.max(1) as f64).sqrt()
    );
    Ok(())
}
