//! A client in another language: the Python subscriber (clients/python, eclipse-zenoh and
//! protobuf code generated from proto/) follows a real replayed run and saves the
//! trajectory; it must equal the run's own trajectory.tum. The Python environment is
//! target/python, made by deploy/install-deps.sh (the README's test command runs it first).

mod common;

use common::*;
use std::time::Duration;

#[path = "../services/egress/tests/support/pki.rs"]
mod pki;

/// Runs the Python client against `egoslam run` on the fixture and checks that it saved
/// the run's own trajectory. `client_args` and `run_args` carry the TLS options.
/// The replay is lossless: in real time (`--realtime`) a loaded CI machine dropped 1 and
/// 3 of the 120 frames in two runs, and the run itself then posed 119 and 117, which the
/// client matched but the frame count below did not. One run at a time all the same.
fn python_follows_a_run(endpoint: &str, device: &str, client_args: &[String], run_args: &[String]) {
    let _turn = one_test_at_a_time();
    let python = repo().join("target/python/bin/python");
    assert!(
        python.exists(),
        "{} missing: run ./deploy/install-deps.sh",
        python.display()
    );
    let out = tempfile::tempdir().expect("tempdir");
    let saved = out.path().join("python.tum");
    // The client's own temporary files (generated message modules) go here, so the test
    // can see that it leaves none behind.
    let client_tmp = tempfile::tempdir().expect("tempdir");
    let mut client = std::process::Command::new(&python)
        .arg(repo().join("clients/python/egoslam_subscriber.py"))
        .args(["--connect", endpoint, "--device", device])
        .args(["--quiet", "--until-finished", "--timeout", "120", "--out"])
        .arg(&saved)
        .args(client_args)
        .env("TMPDIR", client_tmp.path())
        .spawn()
        .expect("python client");
    std::thread::sleep(Duration::from_millis(300));
    let results = out.path().join("run");
    let status = egoslam()
        .args(["run", "--device", device, "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(&results)
        .args(run_args)
        .env("EGOSLAM_ZENOH_LISTEN", endpoint)
        .status()
        .expect("run");
    assert!(status.success());
    let client_status = client.wait().expect("client exit");
    assert!(client_status.success(), "python client failed");
    let left: Vec<_> = std::fs::read_dir(client_tmp.path())
        .expect("client tmp")
        .filter_map(|e| e.ok().map(|e| e.file_name()))
        .collect();
    assert!(left.is_empty(), "the client left {left:?} behind");
    let from_python = std::fs::read_to_string(&saved).expect("python trajectory");
    let from_run = std::fs::read_to_string(results.join("trajectory.tum")).expect("run trajectory");
    assert_eq!(from_python.lines().count(), 121, "120 frames and a header");
    assert_eq!(
        from_python, from_run,
        "latest revision of every frame, as in the file"
    );
}

#[test]
fn python_subscriber_saves_the_same_trajectory_as_the_run() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    python_follows_a_run(&endpoint, "py", &[], &[]);
}

/// The documented remote set-up (docs/egress.md): mutual TLS, one allowed client name, the
/// read-only policy; the Python client presents its certificate.
#[test]
fn python_subscriber_follows_a_run_over_mutual_tls() {
    let pki = pki::Pki::new();
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let path = |name: &str| pki.path(name).display().to_string();
    let run_args = [
        format!("--zenoh-tls-root-ca={}", path("ca.pem")),
        format!("--zenoh-tls-certificate={}", path("server.pem")),
        format!("--zenoh-tls-private-key={}", path("server.key")),
        "--zenoh-tls-mutual".to_string(),
        "--zenoh-allow-common-name=viewer".to_string(),
    ];
    let client_args = [
        format!("--tls-root-ca={}", path("ca.pem")),
        format!("--tls-certificate={}", path("viewer.pem")),
        format!("--tls-private-key={}", path("viewer.key")),
    ];
    python_follows_a_run(&endpoint, "pytls", &client_args, &run_args);
}
