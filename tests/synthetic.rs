//! Rendered egocentric sequences (`egoslam synth`) through the whole pipeline, against
//! their exact ground truth: the paper's egomotion profile and the head-mounted walker
//! (head scans, bob, a sharp turn). Thresholds sit a margin above what was measured
//! (docs/synth.md) so that a regression fails.

mod common;

use common::*;
use egoslam_geometry::absolute_trajectory_error;
use egoslam_sources::ground_truth::read_tum_file;
use std::path::Path;

/// Renders `path` with `frames` frames into `dir` (with `extra` arguments).
fn synth_with(dir: &Path, path: &str, frames: usize, extra: &[&str]) {
    let status = egoslam()
        .args([
            "synth",
            "--path",
            path,
            "--frames",
            &frames.to_string(),
            "--out",
        ])
        .arg(dir)
        .args(extra)
        .status()
        .expect("synth");
    assert!(status.success());
}

/// Renders `path` with `frames` frames into `dir`.
fn synth(dir: &Path, path: &str, frames: usize) {
    synth_with(dir, path, frames, &[]);
}

/// Runs the pipeline; returns the report and the keyframe ATE over the path length.
fn run(input: &Path, out: &Path) -> (serde_json::Value, f64, f64) {
    run_with(input, out, &[])
}

/// [`run`] with `extra` arguments.
fn run_with(input: &Path, out: &Path, extra: &[&str]) -> (serde_json::Value, f64, f64) {
    let report = run_report_with(input, out, extra);
    let est = read_tum_file(&out.join("keyframes.tum")).expect("keyframes");
    let gt = read_tum_file(&input.join("groundtruth.txt")).expect("ground truth");
    let ate = absolute_trajectory_error(&est, &gt, 0.001).expect("aligned");
    (report, ate.rmse, ate.gt_path_length)
}

#[test]
fn paper_egomotion_profile() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (seq, out) = (dir.path().join("seq"), dir.path().join("out"));
    synth(&seq, "egomotion", 150);
    let (report, ate, path) = run(&seq, &out);
    assert_eq!(report["posed_frames"], 150);
    assert_eq!(report["segments"], 1);
    // Measured 6.1 mm over 3.9 m (0.16 %).
    assert!(ate < 0.005 * path, "ATE {ate} m over {path} m");
    // map.ply against the rendered depth: the 332 of 3543 points known within 2 % of their
    // depth, seen by 3 keyframes and agreeing with them within 5 sigma (docs/merger.md,
    // "Published points"), measured RMSE 6.4 cm, median 2.2 cm; distance to the surface
    // RMSE 5.0 cm. Issue 5's target: under half the paper's 22.7 cm.
    let structure = &report["accuracy"]["structure"];
    assert!(structure["evaluated"].as_u64() > Some(250), "{structure}");
    let median = structure["median_m"].as_f64().expect("median");
    assert!(median < 0.04, "structure median {median} m");
    for key in ["rmse_m", "surface_rmse_m"] {
        let rmse = structure[key].as_f64().expect("rmse");
        assert!(rmse < 0.114, "structure {key} {rmse} m");
    }
    assert!(
        report["published_points"].as_u64() < Some(report["map_points"].as_u64().expect("n") / 2),
        "{report}"
    );
    let rpe = &report["accuracy"]["keyframes"]["rpe"];
    assert!(rpe["rotation_rmse_deg"].as_f64() < Some(0.5), "{rpe}");
}

#[test]
fn head_mounted_walker() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (seq, out) = (dir.path().join("seq"), dir.path().join("out"));
    synth(&seq, "walker", 150);
    let self_calibrate = ["--calibrate-focal", "true"];
    let (report, ate, path) = run_with(&seq, &out, &self_calibrate);
    assert_eq!(report["posed_frames"], 150);
    assert_eq!(report["segments"], 1);
    // Measured 8.6 mm over 3.7 m (0.23 %); 300 frames with a stop: 1.3 %.
    assert!(ate < 0.01 * path, "ATE {ate} m over {path} m");
    // The focal self-calibration (docs/config.md) leaves the exact focal length alone
    // (measured: the windows' median 0.998)...
    let focal = &report["focal_calibration"];
    assert_eq!(focal["applied_scale"].as_f64(), Some(1.0), "{focal}");
    // ...and finds the truth when told one 3 % long (515 px for the rendered 500 px:
    // measured 0.969 for 0.971, keyframe ATE 1.07 cm; 12.1 cm with the calibration as
    // given, 0.55 cm with the right one).
    let yaml = std::fs::read_to_string(seq.join("camera.yaml")).expect("camera.yaml");
    let long: String = yaml
        .lines()
        .map(|l| match l.split(':').next() {
            Some("fx") => "fx: 515".to_string(),
            Some("fy") => "fy: 515".to_string(),
            _ => l.to_string(),
        })
        .collect::<Vec<_>>()
        .join("\n");
    assert_ne!(long, yaml.trim_end(), "camera.yaml has fx and fy");
    std::fs::write(seq.join("camera.yaml"), long + "\n").expect("camera.yaml written");
    let (report, ate, path) = run_with(&seq, &dir.path().join("told_long"), &self_calibrate);
    let focal = &report["focal_calibration"];
    let scale = focal["applied_scale"].as_f64().expect("applied scale");
    assert!((scale - 500.0 / 515.0).abs() < 0.008, "{focal}");
    assert!(ate < 0.005 * path, "ATE {ate} m over {path} m told 515 px");
}

/// A walk with motion blur over the frame time, through its first sharp corner: the
/// corner's windows come out with the keyframes after the turn at another scale, which the
/// merger mends by the walking pace (docs/merger.md, "A step of the scale inside a turn").
/// Measured (540 frames, seed 13): keyframe ATE 0.027 m; 0.173 m without the mend.
#[test]
fn a_blurred_walk_keeps_its_scale_through_a_sharp_corner() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (seq, out) = (dir.path().join("seq"), dir.path().join("out"));
    synth_with(
        &seq,
        "walker",
        540,
        &["--blur-samples", "9", "--seed", "13"],
    );
    let (report, ate, path) = run(&seq, &out);
    assert_eq!(report["posed_frames"], 540);
    assert_eq!(report["segments"], 1);
    assert!(ate < 0.06, "ATE {ate} m over {path} m");
}

#[test]
fn blackout_break_is_healed_by_relocalization() {
    // The walker stops in a 2 s blackout (frames 90-149) and walks on: every track ends, the
    // map breaks, and the merger links the new segment back by relocalizing its keyframes
    // against the old one (docs/relocalization.md).
    let dir = tempfile::tempdir().expect("tempdir");
    let (seq, out) = (dir.path().join("seq"), dir.path().join("out"));
    synth(&seq, "blackout", 240);
    let (report, ate, path) = run(&seq, &out);
    assert_eq!(report["blind_frames"], 60, "{report}");
    assert_eq!(report["breaks_healed"], 1, "{report}");
    assert_eq!(report["segments"], 1, "{report}");
    // Measured 8.9 mm over 7.3 m (0.12 %): one metric map across the blackout.
    assert!(ate < 0.005 * path, "ATE {ate} m over {path} m");
}

#[test]
fn walker_in_the_corridor_and_the_street() {
    // The corridor's near walls and the street's far facades and sky, both with the
    // photographs hung in them (docs/synth.md). Measured (150 frames, 3.7 m): 2.7 mm and
    // 4.8 mm keyframe ATE (0.07 / 0.13 %), one segment each.
    for scene in ["corridor", "street"] {
        let dir = tempfile::tempdir().expect("tempdir");
        let (seq, out) = (dir.path().join("seq"), dir.path().join("out"));
        synth_with(&seq, "walker", 150, &["--scene", scene]);
        let source = std::fs::read_to_string(seq.join("SOURCE.txt")).expect("SOURCE.txt");
        assert!(source.to_lowercase().contains(scene), "{source}");
        let (report, ate, path) = run(&seq, &out);
        assert_eq!(report["posed_frames"], 150, "{scene}");
        assert_eq!(report["segments"], 1, "{scene}");
        assert!(ate < 0.005 * path, "{scene}: ATE {ate} m over {path} m");
        assert!(
            source.contains("CC BY 4.0"),
            "the photographs' licence: {source}"
        );
    }
}

#[test]
fn a_rolling_shutter_walk_holds_with_the_readout_given() {
    // The walker rendered with a 30 ms rolling-shutter readout (docs/synth.md). Measured
    // (150 frames, 3.7 m; renderer revision 2, exactly 30 ms): 0.84 m keyframe ATE when
    // the pipeline assumes a global shutter, 1.08 cm (0.29 %) with --rolling-shutter-ms
    // 30 (docs/config.md), 1.25 cm (0.34 %) with the readout estimated (the default,
    // `auto`: 31 ms). The bound, 0.35 %, failed the earlier correction with the velocity
    // of half a frame before (0.39 %, on the earlier render's 29.2 ms readout).
    let dir = tempfile::tempdir().expect("tempdir");
    let seq = dir.path().join("seq");
    synth_with(&seq, "walker", 150, &["--rolling-shutter-ms", "30"]);
    let ate_with = |extra: &[&str], out: &Path| {
        let (report, ate, path) = run_with(&seq, out, extra);
        assert_eq!(report["posed_frames"], 150);
        (ate, path, report)
    };
    let (corrected, path, _) = ate_with(&["--rolling-shutter-ms", "30"], &dir.path().join("a"));
    assert!(
        corrected < 0.0035 * path,
        "corrected: {corrected} m over {path} m"
    );
    let (assumed_global, _, _) = ate_with(&["--rolling-shutter-ms", "0"], &dir.path().join("b"));
    assert!(
        assumed_global > 5.0 * corrected,
        "the rendered shutter must matter: {assumed_global} vs {corrected} m"
    );
    // The default, `auto`: the readout estimated from the frames (31 ms measured).
    let (estimated, _, report) = ate_with(&[], &dir.path().join("c"));
    let readout = report["rolling_shutter"]["readout_ms"]
        .as_f64()
        .expect("readout");
    assert!((25.0..=35.0).contains(&readout), "estimated {readout} ms");
    assert!(
        estimated < 0.0035 * path,
        "estimated readout: {estimated} m over {path} m"
    );
}

#[test]
fn loops_close_while_the_map_is_refined_in_the_background() {
    // The bench's 1500-frame walk (seed 7) returns to where it started and closes two
    // loops with the defaults (0.0555 m keyframe ATE over 51.4 m). With a background
    // refinement started after every window (`--global-ba-px 0.01`: a cross-window error
    // that stays high), every loop attempt used to fall while one ran and none was made:
    // 0 loops, 0.239 m (0.244 m with loop closure off). Measured with attempts made
    // before a refinement starts and owed past one: 1 loop, 0.071 m (0.14 %).
    let dir = tempfile::tempdir().expect("tempdir");
    let (seq, out) = (dir.path().join("seq"), dir.path().join("out"));
    synth_with(&seq, "walker", 1500, &["--seed", "7"]);
    let (report, ate, path) = run_with(&seq, &out, &["--global-ba-px", "0.01"]);
    assert_eq!(report["posed_frames"], 1500);
    assert!(
        report["loops_closed"].as_u64().is_some_and(|n| n >= 1),
        "{report}"
    );
    // The loop's sightings of the old points stay in the map as observations (3,882 on
    // this walk; a loop needs at least 30 shared points).
    assert!(
        report["loop_sightings"].as_u64().is_some_and(|n| n >= 30),
        "{report}"
    );
    assert!(ate < 0.0025 * path, "ATE {ate} m over {path} m");
}

/// The endurance benchmark's short form (CI): two back-and-forth passes of a 150-frame
/// corridor walk through the real processes, sampled. Measured: every one of 596 frames
/// posed in one segment, 0.8 cm ATE over 14.8 m (0.3 cm for one pass), 536 MiB peak over
/// all processes, 72 MiB written.
#[test]
fn the_endurance_benchmark_samples_a_looped_walk() {
    let data = tempfile::tempdir().expect("tempdir");
    let out = tempfile::tempdir().expect("tempdir");
    let markdown = out.path().join("benchmarks.md");
    let status = egoslam()
        .args([
            "bench",
            "--suite",
            "endurance",
            "--cycles",
            "2",
            "--walk-frames",
            "150",
        ])
        .arg("--data")
        .arg(data.path())
        .arg("--out")
        .arg(out.path())
        .arg("--markdown")
        .arg(&markdown)
        .status()
        .expect("bench");
    assert!(status.success());
    let work = out.path().join("endurance_synth_corridor_150_x2");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(work.join("summary.json")).expect("summary"))
            .expect("json");
    assert_eq!(summary["frames"], 596, "{summary}");
    assert_eq!(summary["posed_frames"], 596, "{summary}");
    assert_eq!(summary["segments"], 1, "{summary}");
    let ate = summary["ate_m"].as_f64().expect("ATE");
    assert!(ate < 0.02, "whole-loop ATE {ate} m: {summary}");
    let peak = summary["rss_peak_mib"].as_f64().expect("peak");
    assert!(peak < 1024.0, "peak {peak} MiB: {summary}");
    // Every service was sampled, and the disk as it grew.
    let csv = std::fs::read_to_string(work.join("samples.csv")).expect("samples");
    let header: Vec<&str> = csv.lines().next().expect("header").split(',').collect();
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|v| v.parse().expect("number")).collect())
        .collect();
    assert!(rows.len() >= 4, "{csv}");
    for service in ["launcher", "replay", "frontend", "solver", "merger"] {
        let column = header
            .iter()
            .position(|h| *h == format!("rss_{service}_mib"))
            .expect("column");
        assert!(rows.iter().any(|r| r[column] > 10.0), "{service}: {csv}");
    }
    assert!(std::fs::read_to_string(work.join("endurance.svg"))
        .expect("plot")
        .contains("<svg"));
    assert!(std::fs::read_to_string(&markdown)
        .expect("markdown")
        .contains("egoslam bench endurance: begin"));
}

/// Writes a Kalibr camchain `cam0` at `path` for a 640x480 equidistant lens of `focal`
/// px/rad with first term `k1`, as users have their calibration; returns the path.
fn equidistant_camchain(path: &Path, focal: f64, k1: f64) -> String {
    std::fs::write(
        path,
        format!(
            "cam0:\n  camera_model: pinhole\n  distortion_model: equidistant\n  \
             distortion_coeffs: [{k1:?}, 0.0, 0.0, 0.0]\n  \
             intrinsics: [{focal:?}, {focal:?}, 320.0, 240.0]\n  resolution: [640, 480]\n"
        ),
    )
    .expect("camchain written");
    path.to_string_lossy().into_owned()
}

#[test]
fn a_fisheye_walk_is_posed_as_well_as_through_a_pinhole() {
    // The walker seen through an ideal equidistant fisheye (260 px/rad: 141 deg across the
    // 640 px, 176 deg across the diagonal; rendered from a cube map, docs/synth.md) and
    // through the default 500 px pinhole, the same path and scene. The calibration reaches
    // the run as a Kalibr camchain, as users have it.
    let dir = tempfile::tempdir().expect("tempdir");
    let (fisheye, pinhole) = (dir.path().join("fisheye"), dir.path().join("pinhole"));
    synth_with(
        &fisheye,
        "walker",
        150,
        &["--lens", "equidistant", "--focal", "260"],
    );
    synth(&pinhole, "walker", 150);
    std::fs::remove_file(fisheye.join("camera.yaml")).expect("own camera.yaml removed");
    let calib = equidistant_camchain(&dir.path().join("camchain.yaml"), 260.0, 0.0);
    let (report, ate, path) = run_with(&fisheye, &dir.path().join("a"), &["--calib", &calib]);
    assert_eq!(report["posed_frames"], 150, "{report}");
    assert_eq!(report["segments"], 1, "{report}");
    let yaml = std::fs::read_to_string(dir.path().join("a/camera.yaml")).expect("camera.yaml");
    assert!(yaml.contains("model: equidistant"), "{yaml}");
    let (_, pinhole_ate, _) = run_with(&pinhole, &dir.path().join("b"), &[]);
    // Measured (keyframes): fisheye 2.6 mm (52 keyframes), pinhole 5.5 mm (109) over 3.7 m.
    assert!(ate < 0.01 * path, "fisheye ATE {ate} m over {path} m");
    assert!(
        ate < 1.25 * pinhole_ate.max(0.002 * path),
        "fisheye {ate} m, pinhole {pinhole_ate} m"
    );

    // A nominal calibration of the make (focal 270 px/rad, 4 % long; k1 0.03 where the
    // lens has none), self-calibrated: both found on the fisheye's own image.
    let nominal = equidistant_camchain(&dir.path().join("nominal.yaml"), 270.0, 0.03);
    let self_calibrated = [
        "--calib",
        &nominal,
        "--calibrate-focal",
        "true",
        "--calibrate-radial",
        "true",
    ];
    let (report, nominal_ate, _) = run_with(&fisheye, &dir.path().join("c"), &self_calibrated);
    let scale = report["focal_calibration"]["applied_scale"]
        .as_f64()
        .expect("scale");
    let k = report["radial_calibration"]["applied_k"]
        .as_f64()
        .expect("k");
    // Measured on 300 frames of the walk: scale 0.9614 (truth 0.9630), k -0.0283 (-0.03);
    // keyframe ATE 1.9 cm, against 1.1 cm with the lens as it is and 17.7 cm with the
    // nominal k1 taken as given.
    assert!(
        (scale - 260.0 / 270.0).abs() < 0.006,
        "focal scale {scale}: {report}"
    );
    assert!((k + 0.03).abs() < 0.005, "first term {k}: {report}");
    assert_eq!(report["posed_frames"], 150, "{report}");
    assert!(
        nominal_ate < 2.0 * ate.max(0.002 * path),
        "self-calibrated {nominal_ate} m, calibrated {ate} m"
    );
}
