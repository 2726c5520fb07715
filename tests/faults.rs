//! Faults during a live run (issue: faults never stop the pipeline): a frontend killed
//! mid-stream continues into the same map, a frontend stalled for a moment loses no frame,
//! a second of frames lost mid-stream leaves one map, and Ctrl-C stops everything within 5 s with the results of what was processed. All
//! on a rendered 10 s, 30 fps corridor walk with ground truth, replayed in real time but
//! the lost frames' run.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A 300-frame corridor walk (10 s at 30 fps, 5 m), rendered once per build.
fn corridor_walk() -> PathBuf {
    static RENDERED: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    RENDERED
        .get_or_init(|| {
            let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("faults_corridor_300");
            let done = dir.join("rendered");
            if !done.exists() {
                let status = egoslam()
                    .args([
                        "synth", "--scene", "corridor", "--seed", "3", "--frames", "300",
                    ])
                    .arg("--out")
                    .arg(&dir)
                    .status()
                    .expect("synth");
                assert!(status.success());
                std::fs::write(&done, "").expect("mark");
            }
            dir
        })
        .clone()
}

/// Starts a real-time run of the walk and returns it once the replay is streaming. The
/// frames are read once first: from a cold page cache the replay's decoding can fall
/// behind real time, drop frames and split the map, which is not what these tests judge.
fn start_realtime(out: &Path) -> std::process::Child {
    for entry in std::fs::read_dir(corridor_walk().join("rgb")).expect("rgb") {
        let _ = std::fs::read(entry.expect("entry").path());
    }
    let run = egoslam_with_calibration_given()
        .args(["run", "--realtime", "--zenoh-listen", "none", "--input"])
        .arg(corridor_walk())
        .arg("--out")
        .arg(out)
        .spawn()
        .expect("run");
    let start = Instant::now();
    while service_pid("replay", out).is_none() {
        assert!(start.elapsed() < Duration::from_secs(30), "no replay");
        std::thread::sleep(Duration::from_millis(20));
    }
    run
}

fn trajectory_ate(r: &serde_json::Value) -> (f64, f64) {
    let t = &r["accuracy"]["trajectory"];
    (
        t["ate_rmse_m"].as_f64().expect("ATE"),
        t["gt_path_m"].as_f64().expect("path"),
    )
}

#[test]
fn a_frontend_killed_mid_stream_continues_into_the_same_map() {
    let _turn = one_test_at_a_time();
    let out = tempfile::tempdir().expect("tempdir");
    let mut run = start_realtime(out.path());
    std::thread::sleep(Duration::from_secs(4));
    sigkill("frontend", out.path());
    let status = run.wait().expect("wait");
    assert!(status.success(), "{status}");
    let r = report(out.path());
    assert_eq!(r["restarts"]["frontend"], 1, "{r}");
    assert!(r["resumed_tracks"].as_u64() > Some(100), "{r}");
    // Without the tracks continued: 2 segments, 1.0-1.1 m off.
    assert_eq!(r["segments"], 1, "{r}");
    let posed = r["posed_frames"].as_u64().expect("posed");
    assert!(posed >= 285, "{posed} of 300 frames posed: {r}");
    // Measured: 1.5-1.9 cm over 5.0 m in most runs, 10.2 cm (2 %) in one of five: where
    // the kill lands in the replay moves it. A split map is 1.0-1.1 m off.
    let (ate, path) = trajectory_ate(&r);
    assert!(ate < 0.03 * path, "ATE {ate} m over {path} m");
}

#[test]
fn a_frontend_stalled_for_300_ms_loses_no_frame_of_a_live_camera() {
    // The frontend stalls for a moment when it decides the rolling-shutter readout and
    // releases the keyframes held for it, longer while something else loads the cores
    // (egoslam_bus::FRAMES): the camera's frames wait for it on the bus instead of being
    // dropped into a gap in the tracks. Stopped here for 300 ms, 9 frames at 30 fps.
    let _turn = one_test_at_a_time();
    let out = tempfile::tempdir().expect("tempdir");
    let run = start_realtime(out.path());
    std::thread::sleep(Duration::from_secs(3));
    signal("frontend", out.path(), "-STOP");
    std::thread::sleep(Duration::from_millis(300));
    signal("frontend", out.path(), "-CONT");
    let status = run.wait_with_output().expect("wait").status;
    assert!(status.success(), "{status}");
    let r = report(out.path());
    // With 4 frames on the bus: 5 dropped.
    assert_eq!(r["dropped_frames"], 0, "{r}");
    assert_eq!(r["posed_frames"], 300, "{r}");
    assert_eq!(r["segments"], 1, "{r}");
}

#[test]
fn a_second_of_frames_lost_mid_stream_leaves_one_map_with_every_frame_posed() {
    // Frames 100-129 never arrive (a camera stall; a real-time frontend that fell behind
    // drops them the same way): every track ends there. The input lists the walk's other
    // frames, with their timestamps. One test at a time: a run beside the real-time ones
    // would make them drop frames.
    let _turn = one_test_at_a_time();
    let walk = corridor_walk();
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("input");
    std::fs::create_dir(&input).expect("input");
    for file in ["camera.yaml", "groundtruth.txt"] {
        std::fs::copy(walk.join(file), input.join(file)).expect("copy");
    }
    std::os::unix::fs::symlink(walk.join("rgb"), input.join("rgb")).expect("symlink");
    let listed = std::fs::read_to_string(walk.join("rgb.txt")).expect("rgb.txt");
    let kept: Vec<&str> = listed
        .lines()
        .filter(|l| l.starts_with('#'))
        .chain(
            listed
                .lines()
                .filter(|l| !l.starts_with('#'))
                .enumerate()
                .filter(|(i, _)| !(100..130).contains(i))
                .map(|(_, l)| l),
        )
        .collect();
    std::fs::write(input.join("rgb.txt"), kept.join("\n")).expect("rgb.txt");
    let r = run_report(&input, &dir.path().join("out"));
    assert_eq!(r["frames"], 270, "{r}");
    assert_eq!(r["posed_frames"], 270, "{r}");
    assert_eq!(r["segments"], 1, "{r}");
    // Measured 0.46 deg; 3.2 deg when the window across the gap fell into pieces and the
    // keyframes after it were posed only by interpolation across the gap.
    let orientation = r["accuracy"]["trajectory"]["orientation_rmse_deg"]
        .as_f64()
        .expect("orientation");
    assert!(orientation < 1.0, "orientation error {orientation} deg");
    // Measured 2.8 cm over 5.0 m.
    let (ate, path) = trajectory_ate(&r);
    assert!(ate < 0.01 * path, "ATE {ate} m over {path} m");
}

#[test]
fn ctrl_c_stops_every_process_within_5_s_and_keeps_what_was_processed() {
    let _turn = one_test_at_a_time();
    let out = tempfile::tempdir().expect("tempdir");
    let mut run = start_realtime(out.path());
    std::thread::sleep(Duration::from_secs(4));
    let pid = run.id().to_string();
    let signalled = Instant::now();
    let status = std::process::Command::new("kill")
        .args(["-INT", &pid])
        .status()
        .expect("kill");
    assert!(status.success());
    let status = run.wait().expect("wait");
    let stopped = signalled.elapsed();
    assert!(
        stopped < Duration::from_secs(5),
        "stopped after {stopped:?}"
    );
    assert_eq!(status.code(), Some(130), "{status}");
    for service in ["replay", "frontend", "solver", "merger"] {
        assert_eq!(
            service_pid(service, out.path()),
            None,
            "{service} left running"
        );
    }
    let r = report(out.path());
    assert_eq!(r["interrupted_by_signal"], 2, "{r}");
    let frames = r["frames"].as_u64().expect("frames");
    let posed = r["posed_frames"].as_u64().expect("posed");
    // About 4 s of the 10 s were streamed (start-up takes some of them).
    assert!((60..250).contains(&frames), "{frames} frames streamed");
    assert!(posed + 5 >= frames, "{posed} of {frames} posed");
    let trajectory = std::fs::read_to_string(out.path().join("trajectory.tum")).expect("tum");
    assert_eq!(
        trajectory.lines().filter(|l| !l.starts_with('#')).count() as u64,
        posed
    );
    let (ate, path) = trajectory_ate(&r);
    assert!(ate < 0.01 * path.max(0.5), "ATE {ate} m over {path} m");
}
