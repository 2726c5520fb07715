//! A service that dies is noticed: its consumer fails instead of hanging, and the launcher
//! stops the whole pipeline with an error naming the service; a killed launcher's bus
//! folder is removed by the next run.

mod common;

use common::*;
use std::time::{Duration, Instant};

#[test]
fn consumer_notices_a_killed_producer() {
    let ns = namespace("death");
    let out = tempfile::tempdir().expect("tempdir");
    let camera = tum_fixture().join("camera.yaml");
    let args = [
        format!("--namespace={ns}"),
        format!("--out={}", out.path().display()),
        format!("--camera={}", camera.display()),
    ];
    let mut merger = egoslam_with_calibration_given()
        .arg("merger")
        .args(&args)
        .spawn()
        .expect("merger");
    let mut solver = egoslam_with_calibration_given()
        .arg("solver")
        .args(&args)
        .spawn()
        .expect("solver");
    let mut frontend = egoslam_with_calibration_given()
        .arg("frontend")
        .args(&args)
        .spawn()
        .expect("frontend");
    let mut replay = egoslam_with_calibration_given()
        .arg("replay")
        .arg(format!("--input={}", tum_fixture().display()))
        .arg("--realtime")
        .args(&args)
        .spawn()
        .expect("replay");
    std::thread::sleep(Duration::from_millis(1500));
    replay.kill().expect("SIGKILL replay");
    replay.wait().expect("reaped");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = frontend.try_wait().expect("poll") {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "frontend hangs after its producer died"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(
        !status.success(),
        "frontend must fail when its producer dies mid-stream"
    );
    // The failure travels down the pipeline: each consumer sees its producer vanish.
    for (name, child) in [("solver", &mut solver), ("merger", &mut merger)] {
        let start = Instant::now();
        let status = loop {
            if let Some(s) = child.try_wait().expect("poll") {
                break s;
            }
            assert!(
                start.elapsed() < Duration::from_secs(20),
                "{name} hangs after its producer died"
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        assert!(!status.success(), "{name} must report the broken stream");
    }
}

#[test]
fn launcher_stops_everything_when_a_service_dies() {
    let out = tempfile::tempdir().expect("tempdir");
    let mut run = egoslam_with_calibration_given()
        .args(["run", "--realtime", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run");
    // Find the replay child (the one service that is not restarted) and kill it.
    std::thread::sleep(Duration::from_millis(1500));
    let children = std::process::Command::new("pgrep")
        .args(["-P", &run.id().to_string(), "-f", "egoslam replay"])
        .output()
        .expect("pgrep");
    let pid = String::from_utf8_lossy(&children.stdout).trim().to_string();
    assert!(!pid.is_empty(), "replay child not found");
    std::process::Command::new("kill")
        .args(["-9", &pid])
        .status()
        .expect("kill");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = run.try_wait().expect("poll") {
            break s;
        }
        assert!(start.elapsed() < Duration::from_secs(20), "launcher hangs");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(!status.success());
    let mut stderr = String::new();
    use std::io::Read;
    run.stderr
        .take()
        .expect("pipe")
        .read_to_string(&mut stderr)
        .expect("read");
    assert!(stderr.contains("replay service failed"), "{stderr}");
    // No orphans: the other services were stopped.
    assert_eq!(services_writing_to(out.path()), 0, "services left running");
}

/// The launcher killed, its services stop; the bus folder it could not remove is removed
/// by the next run (its process is gone), which leaves none of its own.
#[test]
fn services_stop_when_the_launcher_is_killed() {
    let out = tempfile::tempdir().expect("tempdir");
    // The runs' temporary folder: their iceoryx2 folders go there.
    let tmp = tempfile::tempdir().expect("tempdir");
    // The clip's images as a folder replayed at 1 frame/s: two minutes of run, so services
    // still running after 15 s are orphans, not a run that ended by itself.
    let mut run = egoslam_with_calibration_given()
        .args(["run", "--realtime", "--fps", "1", "--input"])
        .arg(tum_fixture().join("rgb"))
        .arg("--calib")
        .arg(tum_fixture().join("camera.yaml"))
        .arg("--out")
        .arg(out.path())
        .env("TMPDIR", tmp.path())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("run");
    let bus_folder = tmp.path().join(format!("egoslam-run{}", run.id()));
    let services = || services_writing_to(out.path());
    let start = Instant::now();
    while services() < 4 {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "services not started"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    run.kill().expect("SIGKILL the launcher");
    run.wait().expect("reaped");
    let start = Instant::now();
    while services() > 0 {
        assert!(
            start.elapsed() < Duration::from_secs(15),
            "{} services left running after the launcher was killed",
            services()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(bus_folder.is_dir(), "the killed run's bus folder");
    let next = tempfile::tempdir().expect("tempdir");
    let status = egoslam()
        .args(["run", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(next.path())
        .env("TMPDIR", tmp.path())
        .stderr(std::process::Stdio::null())
        .status()
        .expect("next run");
    assert!(status.success());
    let left: Vec<_> = std::fs::read_dir(tmp.path())
        .expect("tmp")
        .flatten()
        .map(|e| e.file_name())
        .filter(|n| n.to_string_lossy().starts_with("egoslam-run"))
        .collect();
    assert!(left.is_empty(), "bus folders left: {left:?}");
}

/// Processes whose command line has `--out=<out>`: the services of one run. (`--` before
/// the pattern: without it pgrep takes `--out=...` for an option of its own, fails, and
/// prints nothing, so "none left" held whatever was running.)
fn services_writing_to(out: &std::path::Path) -> usize {
    let found = std::process::Command::new("pgrep")
        .args(["-f", "--", &format!("--out={}", out.display())])
        .output()
        .expect("pgrep");
    assert!(
        matches!(found.status.code(), Some(0 | 1)),
        "pgrep failed: {}",
        String::from_utf8_lossy(&found.stderr)
    );
    String::from_utf8_lossy(&found.stdout)
        .split_whitespace()
        .count()
}
