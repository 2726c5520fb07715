//! Accuracy of the whole pipeline (`egoslam run`) against ground truth. Thresholds sit a
//! margin above what was measured (docs/benchmarks.md) so that a regression fails; the
//! targets of the window-solver issue are lower still and are tracked in that document.

mod common;

use common::*;
use egoslam_geometry::{absolute_trajectory_error, associate};
use egoslam_sources::ground_truth::read_tum_file;
use egoslam_sources::load_ground_truth;
use std::path::Path;

/// Keyframe ATE (m) and its ground-truth path length.
fn keyframe_ate(out: &Path, gt: &Path) -> (f64, f64) {
    let est = read_tum_file(&out.join("keyframes.tum")).expect("keyframes");
    let gt = load_ground_truth(gt).expect("gt");
    let r = absolute_trajectory_error(&est, &gt.poses, 0.02).expect("aligned");
    (r.rmse, r.gt_path_length)
}

/// The ATE any trajectory, even one collapsed to a point, reaches under a free Sim(3)
/// alignment: the RMS distance of the ground-truth positions at the keyframes from their
/// mean (the constant-position baseline).
fn constant_position_ate(out: &Path, gt: &Path) -> f64 {
    let est = read_tum_file(&out.join("keyframes.tum")).expect("keyframes");
    let gt = load_ground_truth(gt).expect("gt");
    let positions: Vec<_> = associate(&est, &gt.poses, 0.02)
        .into_iter()
        .map(|(_, g)| gt.poses[g].position)
        .collect();
    let mean = positions.iter().sum::<nalgebra::Vector3<f64>>() / positions.len() as f64;
    let sum: f64 = positions.iter().map(|p| (p - mean).norm_squared()).sum();
    (sum / positions.len() as f64).sqrt()
}

#[test]
fn tum_fixture_every_frame_posed_one_segment() {
    let out = tempfile::tempdir().expect("tempdir");
    let report = run_report(&tum_fixture(), out.path());
    assert_eq!(report["posed_frames"], 120);
    assert_eq!(report["segments"], 1);
    let (ate, path) = keyframe_ate(out.path(), &tum_fixture());
    // fr1_rpy mostly turns in place: under a free scale a collapsed trajectory would score
    // the ground truth's own spread (3.76 cm at the keyframes). Measured 0.0147 m, 0.39 of
    // that baseline (JPEG clip; ORB-SLAM3 mono: 0.0149 m on the PNG originals).
    let baseline = constant_position_ate(out.path(), &tum_fixture());
    assert!(
        ate < 0.6 * baseline,
        "keyframe ATE {ate} m over {path} m, constant-position baseline {baseline} m"
    );
}

/// The merger's background refinement is folded at a fixed window lag
/// (`--refinement-lag`), so a run is reproducible: the same input gives the same map byte
/// for byte, refinement included (folded "whenever finished", two runs of the TUM clip
/// differed by up to 40 % in keyframe ATE).
#[test]
fn same_input_same_map_with_a_background_refinement() {
    let (a, b) = (
        tempfile::tempdir().expect("tempdir"),
        tempfile::tempdir().expect("tempdir"),
    );
    run_report(&tum_fixture(), a.path());
    run_report(&tum_fixture(), b.path());
    let stats: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(a.path().join("stats/merger.json")).expect("merger stats"),
    )
    .expect("json");
    let applied = stats["counters"]["refinements_applied"]
        .as_u64()
        .unwrap_or(0);
    assert!(applied >= 1, "no refinement to test the fold with: {stats}");
    for file in ["keyframes.tum", "trajectory.tum", "map.ply"] {
        let read = |d: &Path| std::fs::read(d.join(file)).expect("output");
        assert!(
            read(a.path()) == read(b.path()),
            "{file} differs between runs"
        );
    }
}

#[test]
fn kitti_every_frame_posed_one_segment() {
    let Some(input) = shared("kitti_odometry_00") else {
        return;
    };
    let out = tempfile::tempdir().expect("tempdir");
    // A car at 10 fps: the motion prediction for head turns is off, as docs/config.md
    // advises for vehicle footage (with it: 0.486 m keyframe, 0.515 m frame ATE). The
    // radial self-calibration (on by default, docs/config.md) finds the pincushion the
    // rectified calibration leaves.
    let report = run_report_with(&input, out.path(), &["--predict-motion", "false"]);
    assert_eq!(report["posed_frames"], 150);
    assert_eq!(report["segments"], 1);
    let (ate, _) = keyframe_ate(out.path(), &input.join("dataset/poses/00.txt"));
    // Measured 0.270 m over 109 m (0.418 m with the calibration as given, 0.327 m with the
    // focal length self-calibrated instead).
    assert!(ate < 0.31, "keyframe ATE {ate} m");
    let radial = &report["radial_calibration"];
    let k = radial["applied_k"].as_f64().expect("radial term applied");
    // Measured 0.0103; the ground-truth poses fit the tracks best at 0.02-0.03.
    assert!((0.005..0.03).contains(&k), "radial calibration {radial}");
    // The 63 frames between keyframes are localized by PnP on the map (measured: all 63),
    // and the whole trajectory is about as good as the keyframes (measured 0.292 m; 0.41 m
    // with the calibration as given).
    let localized = report["localized_frames"].as_u64().expect("count");
    assert!(localized >= 55, "{localized} frames localized by PnP");
    let frames = read_tum_file(&out.path().join("trajectory.tum")).expect("trajectory");
    let gt = load_ground_truth(&input.join("dataset/poses/00.txt")).expect("gt");
    let all = absolute_trajectory_error(&frames, &gt.poses, 0.02).expect("aligned");
    assert!(all.rmse < 0.33, "frame ATE {} m", all.rmse);
}

#[test]
fn euroc_standing_still_invents_no_motion_and_gets_rotations_right() {
    let Some(input) = shared("euroc_v1_01") else {
        return;
    };
    let out = tempfile::tempdir().expect("tempdir");
    let report = run_report(&input, out.path());
    assert_eq!(report["posed_frames"], 95);
    assert_eq!(report["segments"], 1);
    let est = read_tum_file(&out.path().join("keyframes.tum")).expect("keyframes");
    let path: f64 = est
        .windows(2)
        .map(|w| (w[1].position - w[0].position).norm())
        .sum();
    let reach = est
        .iter()
        .map(|p| (p.position - est[0].position).norm())
        .fold(0.0, f64::max);
    // Scale is free, so compare the path with the farthest excursion: no back-and-forth
    // jitter bigger than the motion itself (measured: both exactly 0, rotation-only windows).
    assert!(path <= 3.0 * reach + 1e-9, "path {path} vs reach {reach}");
    // Relative rotations to the first keyframe against ground truth (camera = body x T_BS).
    let gt = load_ground_truth(&input.join("groundtruth_V101_tum_from_evo.txt")).expect("gt");
    let pairs = associate(&est, &gt.poses, 0.02);
    assert!(pairs.len() >= 4);
    let (e0, g0) = (est[pairs[0].0].rotation, gt.poses[pairs[0].1].rotation);
    for &(e, g) in &pairs {
        let rel_est = e0.inverse() * est[e].rotation;
        let rel_gt = g0.inverse() * gt.poses[g].rotation;
        let err = rel_est.angle_to(&rel_gt).to_degrees();
        assert!(err < 1.0, "keyframe rotation error {err} deg");
    }
}
