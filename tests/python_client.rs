//! A client in another language: the Python subscriber (clients/python, eclipse-zenoh and
//! protobuf code generated from proto/) follows a real replayed run and saves the
//! trajectory; it must equal the run's own trajectory.tum. The Python environment is
//! target/python, made by deploy/install-deps.sh (the README's test command runs it first).

mod common;

use common::*;
use std::time::Duration;

#[test]
fn python_subscriber_saves_the_same_trajectory_as_the_run() {
    let python = repo().join("target/python/bin/python");
    assert!(
        python.exists(),
        "{} missing: run ./deploy/install-deps.sh",
        python.display()
    );
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let out = tempfile::tempdir().expect("tempdir");
    let saved = out.path().join("python.tum");
    let mut client = std::process::Command::new(&python)
        .arg(repo().join("clients/python/egoslam_subscriber.py"))
        .args([
            "--connect",
            &endpoint,
            "--device",
            "py",
            "--quiet",
            "--until-finished",
        ])
        .args(["--timeout", "120", "--out"])
        .arg(&saved)
        .spawn()
        .expect("python client");
    std::thread::sleep(Duration::from_millis(300));
    let results = out.path().join("run");
    let status = egoslam()
        .args(["run", "--realtime", "--device", "py", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(&results)
        .env("EGOSLAM_ZENOH_LISTEN", &endpoint)
        .status()
        .expect("run");
    assert!(status.success());
    let client_status = client.wait().expect("client exit");
    assert!(client_status.success(), "python client failed");
    let from_python = std::fs::read_to_string(&saved).expect("python trajectory");
    let from_run = std::fs::read_to_string(results.join("trajectory.tum")).expect("run trajectory");
    assert_eq!(from_python.lines().count(), 121, "120 frames and a header");
    assert_eq!(
        from_python, from_run,
        "latest revision of every frame, as in the file"
    );
}
