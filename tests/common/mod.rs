//! Helpers shared by the integration tests: the binary, the fixtures, unique namespaces.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// The egoslam binary; zenoh output on a free loopback port so that tests running in
/// parallel do not compete for 7447.
pub fn egoslam() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_egoslam"));
    c.env("EGOSLAM_ZENOH_LISTEN", "tcp/127.0.0.1:0");
    c
}

/// `egoslam` for tests that kill or stop a service of a run: the readout is given as 0 (a
/// global shutter, what their figures were measured with) and the focal length and
/// distortion as calibrated, so that no estimate from the stream starts the run again
/// (docs/config.md, "Calibration from the stream") after the service was hit.
pub fn egoslam_with_calibration_given() -> Command {
    let mut c = egoslam();
    c.env("EGOSLAM_ROLLING_SHUTTER_MS", "0");
    c.env("EGOSLAM_CALIBRATE_FOCAL", "false");
    c.env("EGOSLAM_CALIBRATE_RADIAL", "false");
    c
}

pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The in-repo TUM fr1_rpy clip (CC BY 4.0).
pub fn tum_fixture() -> PathBuf {
    repo().join("tests/data/tum_fr1_rpy_120")
}

/// A sequence from ../shared/data, or None (with a message) when it is absent. Under CI
/// (`CI` set, as .ci/run does) the data is always there, so its absence fails the test
/// instead of passing it unchecked.
pub fn shared(name: &str) -> Option<PathBuf> {
    let p = repo().join("../shared/data").join(name);
    if p.exists() {
        Some(p)
    } else {
        assert!(
            std::env::var_os("CI").is_none_or(|v| v.is_empty() || v == "false"),
            "{} is absent, and CI always has the shared test data",
            p.display()
        );
        eprintln!(
            "skipping: {} is absent (shared test data not on this machine)",
            p.display()
        );
        None
    }
}

/// A bus namespace no other test uses.
pub fn namespace(test: &str) -> Namespace {
    Namespace(format!("it_{test}_{}", std::process::id()))
}

/// A test's bus namespace; dropped, it removes what its services left in memory-backed
/// storage (the frontend's keyframe log and resume frame, which `egoslam run` removes for
/// its own runs), so that test runs do not fill /dev/shm.
pub struct Namespace(String);

impl std::ops::Deref for Namespace {
    type Target = String;

    fn deref(&self) -> &String {
        &self.0
    }
}

impl std::fmt::Display for Namespace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl Drop for Namespace {
    fn drop(&mut self) {
        let Some(dir) = egoslam_durability::memory_backed_dir() else {
            return;
        };
        let prefix = egoslam_durability::memory_backed_name(&self.0, "");
        for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            if entry
                .file_name()
                .to_str()
                .is_some_and(|n| n.starts_with(&prefix))
            {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
}

/// A TCP port free on loopback now (for a zenoh endpoint a test connects to).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .port()
}

/// `egoslam run --input INPUT --out OUT`, which must succeed; its report.json.
pub fn run_report(input: &Path, out: &Path) -> serde_json::Value {
    run_report_with(input, out, &[])
}

/// [`run_report`] with extra `egoslam run` arguments.
pub fn run_report_with(input: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let status = egoslam()
        .args(["run", "--input"])
        .arg(input)
        .arg("--out")
        .arg(out)
        .args(extra)
        .status()
        .expect("run");
    assert!(status.success());
    report(out)
}

/// The report.json a run wrote to `out`.
pub fn report(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report"))
        .expect("json")
}

/// Pid of the `service` process writing to `out`, once it is running.
pub fn service_pid(service: &str, out: &Path) -> Option<u32> {
    let needle = format!("--out={}", out.display());
    std::fs::read_dir("/proc").ok()?.find_map(|e| {
        let e = e.ok()?;
        let pid: u32 = e.file_name().to_str()?.parse().ok()?;
        let cmdline = std::fs::read(e.path().join("cmdline")).ok()?;
        let args: Vec<&[u8]> = cmdline.split(|b| *b == 0).collect();
        // `egoslam SERVICE ...`, or the service's lean binary `egoslam-SERVICE ...`.
        let named = egoslam_runtime::process_role::role(&cmdline) == service.as_bytes();
        let is_it = named && args.contains(&needle.as_bytes());
        is_it.then_some(pid)
    })
}

/// SIGKILLs the `service` process writing to `out`.
pub fn sigkill(service: &str, out: &Path) {
    signal(service, out, "-KILL");
}

/// Sends `signal` (`kill`'s spelling: "-KILL", "-STOP", "-CONT") to the `service` process
/// writing to `out`.
pub fn signal(service: &str, out: &Path, signal: &str) {
    // Under load the launcher may not have started the service yet: look for up to 5 s.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    let pid = loop {
        match service_pid(service, out) {
            Some(pid) => break pid,
            None if std::time::Instant::now() < deadline => {
                std::thread::sleep(std::time::Duration::from_millis(50))
            }
            None => panic!("no {service} process writing to {}", out.display()),
        }
    };
    let status = std::process::Command::new("kill")
        .args([signal, &pid.to_string()])
        .status()
        .expect("kill");
    assert!(status.success());
}

/// Serialises the tests of one test file (each file is its own binary, so each gets its own
/// lock): for tests that replay in real time or run whole pipelines, whose results measure
/// the machine's load when they share the two cores.
pub fn one_test_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}
