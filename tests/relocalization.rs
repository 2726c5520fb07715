//! Relocalization and saved maps through the real binary (docs/relocalization.md): the
//! paper's protocol (build the map from a sequence's keyframes, relocalize every frame
//! from scratch, compare with ground truth in the map's Sim(3) alignment) and damaged map
//! files. Thresholds sit a margin above the figures measured in docs/benchmarks.md.

mod common;

use common::*;
use egoslam_sources::ground_truth::read_tum_file;
use std::path::Path;
use std::process::Output;

fn localize(map: &Path, input: &Path, out: &Path, extra: &[&str]) -> Output {
    egoslam()
        .arg("localize")
        .arg("--map")
        .arg(map)
        .arg("--input")
        .arg(input)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .expect("localize")
}

/// Builds a map of `input` with `egoslam run --map-out`, localizes the same frames, and
/// returns the localization report. The map is built assuming a global shutter: the
/// queries are single frames, which relocalization cannot correct for a rolling shutter,
/// and against a map corrected for one (`auto` finds 21 ms on the TUM clip) fewer of
/// them relocalize (docs/relocalization.md: 114 of 120, 19 of 25 non-keyframes, against
/// 118 and 23). The other sequences here are global-shutter, where `auto` gives 0.
fn map_then_localize(input: &Path, dir: &Path) -> serde_json::Value {
    map_then_localize_with(input, dir, &[])
}

/// [`map_then_localize`] with `run_args` added to the map's run.
fn map_then_localize_with(input: &Path, dir: &Path, run_args: &[&str]) -> serde_json::Value {
    let map = map_by(egoslam_with_calibration_given(), input, dir, run_args);
    let out = localize(&map, input, &dir.join("localized"), &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    report(&dir.join("localized"))
}

/// The map of `input` by a plain `egoslam run --map-out` (the rolling-shutter readout and
/// the calibration estimated from the stream), in `dir/map.egomap`.
fn default_map(input: &Path, dir: &Path) -> std::path::PathBuf {
    map_by(egoslam(), input, dir, &[])
}

/// The map of `input` by `egoslam` (`command`) `run --map-out` with `run_args`, in
/// `dir/map.egomap` (the run's output in `dir/run`).
fn map_by(
    mut command: std::process::Command,
    input: &Path,
    dir: &Path,
    run_args: &[&str],
) -> std::path::PathBuf {
    let map = dir.join("map.egomap");
    let status = command
        .args(["run", "--input"])
        .arg(input)
        .args(run_args)
        .arg("--out")
        .arg(dir.join("run"))
        .arg("--map-out")
        .arg(&map)
        .status()
        .expect("run");
    assert!(status.success());
    map
}

fn f(v: &serde_json::Value) -> f64 {
    v.as_f64().expect("number")
}

fn expect_refused(output: &Output, reason: &str) {
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(stderr.contains(reason), "expected {reason:?} in: {stderr}");
}

#[test]
fn tum_every_frame_relocalized_from_scratch_and_damaged_maps_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let r = map_then_localize(&tum_fixture(), dir.path());
    // Measured: 118 of 120 frames, 23 of the 25 that are not keyframes (114 before weak
    // appearance poses confirmed by projection were accepted).
    assert_eq!(r["frames"], 120);
    assert!(f(&r["localized"]) >= 115.0, "{r}");
    assert!(
        f(&r["non_keyframes_localized"]) >= 0.85 * f(&r["non_keyframes"]),
        "{r}"
    );
    // Measured 2.5-2.8 cm and 1.5-1.7 deg: the map's own keyframes are 2.4 cm and 1.3 deg
    // off (median) in the same alignment, and relocalization cannot be better than its map.
    let acc = &r["accuracy"];
    assert!(f(&acc["median_position_m"]) < 0.035, "{acc}");
    assert!(
        f(&acc["median_position_m"]) < 1.3 * f(&acc["map_keyframe_median_position_m"]),
        "{acc}"
    );
    assert!(f(&acc["median_rotation_deg"]) < 2.5, "{acc}");
    // Measured: 19 % of the path (the first frames, where the map is weakest; 880 % before
    // the refinement by projection was bounded: a frame 2.9 m off). fr1_rpy's path is
    // mostly rotation, 0.35 m in all.
    let worst = worst_off_the_run(dir.path());
    assert!(
        worst < 0.3,
        "a frame {worst} of the path off the run's pose"
    );

    // Damaged map files: a named reason, exit code 1, never a panic.
    let map = std::fs::read(dir.path().join("map.egomap")).expect("map");
    let input = tum_fixture();
    let damaged = dir.path().join("damaged.egomap");
    let out = dir.path().join("refused");
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (map[..map.len() / 3].to_vec(), "truncated"),
        (
            {
                let mut m = map.clone();
                let i = m.len() - 100;
                m[i] ^= 0x04;
                m
            },
            "checksum mismatch",
        ),
        (
            {
                let mut m = map.clone();
                m[8] = 7;
                m
            },
            "map format version 7",
        ),
        (
            b"\x89PNG\r\n\x1a\n not a map".to_vec(),
            "not an egoslam map",
        ),
        (Vec::new(), "not an egoslam map"),
    ];
    for (bytes, reason) in cases {
        std::fs::write(&damaged, bytes).expect("write");
        expect_refused(&localize(&damaged, &input, &out, &[]), reason);
    }
    expect_refused(
        &localize(&dir.path().join("absent.egomap"), &input, &out, &[]),
        "cannot be read",
    );
    // A map used with another vocabulary than the one it was built with.
    let vocabulary = dir.path().join("other.vocab");
    let status = egoslam()
        .args(["vocab", "train", "--depth", "2", "--out"])
        .arg(&vocabulary)
        .arg(input.join("rgb"))
        .status()
        .expect("vocab train");
    assert!(status.success());
    let with_other = ["--vocabulary", vocabulary.to_str().expect("utf-8 path")];
    expect_refused(
        &localize(&dir.path().join("map.egomap"), &input, &out, &with_other),
        "was built for vocabulary",
    );

    // A localization killed on the way keeps what it had localized: the trajectory is
    // written every 100 frames, before the progress line that says so (it had been written
    // only at the end).
    let partial = dir.path().join("partial");
    let mut child = egoslam()
        .arg("localize")
        .arg("--map")
        .arg(dir.path().join("map.egomap"))
        .arg("--input")
        .arg(&input)
        .arg("--out")
        .arg(&partial)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("localize");
    let stderr = child.stderr.take().expect("stderr");
    let progressed = std::io::BufRead::lines(std::io::BufReader::new(stderr))
        .map_while(Result::ok)
        .any(|line| line.contains("localizing"));
    child.kill().expect("kill");
    child.wait().expect("wait");
    assert!(progressed, "no progress line");
    let text = std::fs::read_to_string(partial.join("trajectory.tum")).expect("partial trajectory");
    let poses = text.lines().filter(|l| !l.starts_with('#')).count();
    // Of the first 100 frames ~90 relocalize; the 20 after them were not reached.
    assert!((80..=100).contains(&poses), "{poses} poses");
    assert!(!partial.join("report.json").exists());

    // A frame of another size is skipped and counted (it had been localized with the
    // first frame's camera).
    use opencv::{core, imgcodecs, imgproc};
    let folder = dir.path().join("images");
    std::fs::create_dir_all(&folder).expect("mkdir");
    let mut images: Vec<_> = std::fs::read_dir(input.join("rgb"))
        .expect("rgb")
        .map(|e| e.expect("entry").path())
        .collect();
    images.sort();
    for image in &images[..30] {
        std::fs::copy(image, folder.join(image.file_name().expect("name"))).expect("copy");
    }
    std::fs::copy(input.join("camera.yaml"), folder.join("camera.yaml")).expect("calib");
    let victim = folder.join(images[15].file_name().expect("name"));
    let victim = victim.to_str().expect("utf-8");
    let image = imgcodecs::imread(victim, imgcodecs::IMREAD_UNCHANGED).expect("read");
    let mut small = core::Mat::default();
    let size = core::Size::new(320, 240);
    imgproc::resize(&image, &mut small, size, 0.0, 0.0, imgproc::INTER_AREA).expect("resize");
    imgcodecs::imwrite(victim, &small, &core::Vector::new()).expect("write");
    let out = dir.path().join("sizes");
    let o = localize(&dir.path().join("map.egomap"), &folder, &out, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    assert_eq!(r["frames"], 29, "{r}");
    assert_eq!(r["failures"]["frame skipped (size)"], 1, "{r}");
}

#[test]
fn kitti_every_frame_relocalized_from_scratch() {
    let Some(input) = shared("kitti_odometry_00") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    // The map as `egoslam run` builds it by default, with the radial term its rectified
    // calibration leaves self-calibrated (docs/config.md, `calibrate_radial`).
    let r = map_then_localize_with(
        &input.join("dataset/sequences/00"),
        dir.path(),
        &["--calibrate-radial", "auto"],
    );
    // Measured: 147 of 150 (56 of 59 non-keyframes), median 0.302 m / 0.685 deg with the
    // queries undistorted by the map's camera (0.38 m / 0.69 deg in a map built without the
    // radial term; 0.281 m with the queries undistorted without it). Issue 7's >= 95 % is
    // held; its 0.3 m is missed by 2 mm.
    assert!(f(&r["localized"]) >= 143.0, "{r}");
    let acc = &r["accuracy"];
    assert!(f(&acc["median_position_m"]) < 0.33, "{acc}");
    assert!(f(&acc["median_rotation_deg"]) < 1.0, "{acc}");
}

/// Renders a sequence with `egoslam synth ARGS` into `dir/sequence`.
fn rendered(dir: &Path, args: &[&str]) -> std::path::PathBuf {
    let sequence = dir.join("sequence");
    let status = egoslam()
        .arg("synth")
        .args(args)
        .arg("--out")
        .arg(&sequence)
        .status()
        .expect("synth");
    assert!(status.success());
    sequence
}

/// Issue 7's rendered head-mounted case: the Project Aria head trajectory replayed through
/// the rendered room (as `egoslam bench` does), mapped by the pipeline, every frame
/// relocalized from scratch with patch alignment.
#[test]
fn aria_head_trajectory_every_frame_relocalized_from_scratch() {
    let Some(trajectories) = shared("trajectories") else {
        return;
    };
    let trajectory = trajectories
        .join("aria_head_mounted/projectaria_tools_mps_sample_closed_loop_trajectory.csv");
    let dir = tempfile::tempdir().expect("tempdir");
    let trajectory = trajectory.to_str().expect("UTF-8 path");
    let sequence = rendered(
        dir.path(),
        &[
            "--path",
            "replay",
            "--frames",
            "300",
            "--trajectory",
            trajectory,
        ],
    );
    let r = map_then_localize(&sequence, dir.path());
    // Measured: 300 of 300, median 1.00 cm / 0.156 deg against a map whose keyframes are
    // 0.78 cm / 0.098 deg off (1.29x). Judged relative to the map (the ratio below); the
    // absolute bound is issue 7's 1 cm with 5 % for the map's gauge (the same map in the
    // solver's scale, 9.2 m per unit instead of 0.83, gave 0.95 cm).
    assert!(f(&r["localized"]) >= 285.0, "{r}");
    let acc = &r["accuracy"];
    assert!(f(&acc["median_position_m"]) <= 0.0105, "{acc}");
    assert!(f(&acc["median_rotation_deg"]) <= 0.2, "{acc}");
    assert!(
        f(&acc["median_position_m"]) < 1.35 * f(&acc["map_keyframe_median_position_m"]),
        "{acc}"
    );
    // Measured: 0.4 % of the path (57 % before three frames, 2.6-4.3 m off, were kept at
    // the pose their refinement by projection had started from).
    let worst = worst_off_the_run(dir.path());
    assert!(
        worst < 0.05,
        "a frame {worst} of the path off the run's pose"
    );
}

/// Issue 7's targets on a rendered head-mounted walk whose last second turns the head in
/// place (a stretch with no map points, placed by rotation): >= 95 % of the frames,
/// median <= 1.0 cm and <= 0.2 deg.
#[test]
fn rendered_walk_meets_the_relocalization_targets() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sequence = rendered(dir.path(), &["--path", "walker", "--frames", "150"]);
    let r = map_then_localize(&sequence, dir.path());
    // Measured: 150 of 150 (118 before frames were placed by rotation), median 0.67 cm /
    // 0.091 deg against a map whose keyframes are 0.49 cm / 0.085 deg off.
    assert!(f(&r["localized"]) >= 143.0, "{r}");
    let acc = &r["accuracy"];
    assert!(f(&acc["median_position_m"]) <= 0.01, "{acc}");
    assert!(f(&acc["median_rotation_deg"]) <= 0.2, "{acc}");
}

/// A walk rendered with a 30 ms rolling-shutter readout, mapped with the readout estimated
/// (the default), every frame relocalized from scratch with and without the query's turn
/// during the readout refined: by default with the readout the map records, with
/// `--rolling-shutter-ms 0` without.
#[test]
fn rolling_shutter_queries_are_posed_with_their_turn() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sequence = rendered(
        dir.path(),
        &[
            "--path",
            "walker",
            "--frames",
            "150",
            "--rolling-shutter-ms",
            "30",
        ],
    );
    let map = default_map(&sequence, dir.path());
    let localized = |extra: &[&str]| {
        let out = dir.path().join(format!("localized_{}", extra.len()));
        let output = localize(&map, &sequence, &out, extra);
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        report(&out)
    };
    let (plain, turned) = (localized(&["--rolling-shutter-ms", "0"]), localized(&[]));
    // The map's run estimated the readout (30 ms rendered) and the map kept it.
    let readout = f(&turned["rolling_shutter_ms"]);
    assert!((25.0..=35.0).contains(&readout), "{turned}");
    // Measured: 126 of 150 frames, median 10.4 cm and 1.07 deg without the turn; with it
    // 150 (the turn in place at the end placed by rotation too), 1.2 cm and 0.12 deg, and
    // an ATE of 2.0x the map keyframes' (2.6 cm and 0.29 deg, 3.9x, when only the final
    // refinement knew the turn, not the search by projection and the aligned solve).
    assert!(f(&turned["localized"]) >= 145.0, "{turned}");
    assert!(
        f(&turned["localized"]) > f(&plain["localized"]),
        "{plain} {turned}"
    );
    let (p, t) = (&plain["accuracy"], &turned["accuracy"]);
    assert!(
        f(&t["median_position_m"]) < 0.5 * f(&p["median_position_m"]),
        "{p} {t}"
    );
    assert!(f(&t["median_position_m"]) < 0.018, "{t}");
    assert!(f(&t["median_rotation_deg"]) < 0.2, "{t}");
    assert!(f(&t["ate_m"]) < 2.6 * f(&t["map_keyframe_ate_m"]), "{t}");
    // A readout no camera has is refused before anything is read.
    let refused = localize(
        &map,
        &sequence,
        &dir.path().join("x"),
        &["--rolling-shutter-ms", "200"],
    );
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("must be between 0 and 100 ms"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
}

/// The relocalization protocol on the TUM clip: the map of a plain `egoslam run`
/// (the rolling-shutter readout estimated, 21-22 ms), every frame relocalized from scratch
/// with the readout the map records, scored as a trajectory.
#[test]
fn tum_relocalized_within_a_quarter_of_its_maps_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let map = default_map(&tum_fixture(), dir.path());
    let out = dir.path().join("localized");
    let output = localize(&map, &tum_fixture(), &out, &[]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let r = report(&out);
    // Measured: 113 of 120 frames, ATE 1.72 cm against the map keyframes' 1.44 cm (1.19x;
    // 1.39x when the search by projection and the aligned solve ignored the turn during
    // the readout, and frames of the turn in place were placed by a few points).
    assert!(f(&r["localized"]) >= 110.0, "{r}");
    let acc = &r["accuracy"];
    assert!(
        f(&acc["ate_m"]) <= 1.3 * f(&acc["map_keyframe_ate_m"]),
        "{acc}"
    );
}

/// After [`map_then_localize`] in `dir`: the largest distance from a relocalized frame to
/// where the run itself posed it (both in the map's frame), over the run's path length.
/// A median hides a wrong pose; this does not.
fn worst_off_the_run(dir: &Path) -> f64 {
    let read = |file: &str| read_tum_file(&dir.join(file)).expect("trajectory");
    let (run, localized) = (read("run/trajectory.tum"), read("localized/trajectory.tum"));
    // Both files write the same timestamps (microseconds).
    let key = |t: f64| (t * 1e6).round() as i64;
    let posed: std::collections::HashMap<i64, _> =
        run.iter().map(|p| (key(p.timestamp), p.position)).collect();
    let path: f64 = run
        .windows(2)
        .map(|w| (w[1].position - w[0].position).norm())
        .sum();
    let off: Vec<f64> = localized
        .iter()
        .filter_map(|p| Some((p.position - posed.get(&key(p.timestamp))?).norm()))
        .collect();
    // The run posed every frame: a frame not found would make the check vacuous.
    assert_eq!(
        off.len(),
        localized.len(),
        "relocalized frames the run did not pose"
    );
    off.into_iter().fold(0.0, f64::max) / path
}

/// The rendered egomotion profile (forward motion past planes at several depths), every
/// frame relocalized from scratch: each relocalized frame must land where the run itself
/// posed it (same map frame), so that a wrong pose cannot hide behind a good median. Two
/// frames had been relocalized metres off (the refinement by projection had turned their
/// poses 57 and 176 deg); frames whose appearance matches are too few alone are placed
/// by the tentative pose's confirmation.
#[test]
fn egomotion_profile_relocalizes_without_a_wrong_pose() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sequence = rendered(dir.path(), &["--path", "egomotion", "--frames", "150"]);
    let r = map_then_localize(&sequence, dir.path());
    // Measured: 143 of 150 (139 before the tentative poses), median 0.75 cm / 0.166 deg.
    assert!(f(&r["localized"]) >= 142.0, "{r}");
    let acc = &r["accuracy"];
    assert!(f(&acc["median_position_m"]) <= 0.01, "{acc}");
    // Measured: 0.9 % of the path (104 % before: a frame 4 m off).
    let worst = worst_off_the_run(dir.path());
    assert!(
        worst < 0.05,
        "a frame {worst} of the path off the run's pose"
    );
}
