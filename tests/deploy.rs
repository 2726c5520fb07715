//! The systemd deployment (deploy/): the units pass `systemd-analyze verify` without a
//! warning, and a real service process speaks sd_notify (READY, then watchdog pings) to
//! the socket systemd would give it.

mod common;

use common::*;
use std::os::unix::net::UnixDatagram;
use std::time::{Duration, Instant};

#[test]
fn units_verify_cleanly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let units = repo().join("deploy/systemd");
    let mut names = Vec::new();
    for entry in std::fs::read_dir(&units).expect("deploy/systemd") {
        let path = entry.expect("entry").path();
        let name = path.file_name().expect("name").to_owned();
        // verify checks that ExecStart exists: point it at the binary under test.
        let text = std::fs::read_to_string(&path)
            .expect("unit")
            .replace("/usr/local/bin/egoslam", env!("CARGO_BIN_EXE_egoslam"));
        std::fs::write(dir.path().join(&name), text).expect("copy");
        names.push(dir.path().join(name));
    }
    assert_eq!(names.len(), 5, "four services and the target");
    let out = std::process::Command::new("systemd-analyze")
        .arg("verify")
        .args(&names)
        .output()
        .expect("systemd-analyze (package systemd, installed by deploy/install-deps.sh)");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && stderr.trim().is_empty(), "{stderr}");
}

#[test]
fn a_service_reports_ready_and_pings_the_watchdog() {
    let dir = tempfile::tempdir().expect("tempdir");
    let socket_path = dir.path().join("notify");
    let socket = UnixDatagram::bind(&socket_path).expect("bind");
    socket
        .set_read_timeout(Some(Duration::from_secs(20)))
        .expect("timeout");
    // As its unit starts it: the lean binary (deploy/systemd/egoslam-merger.service).
    let mut merger = std::process::Command::new(env!("CARGO_BIN_EXE_egoslam-merger"))
        .env("EGOSLAM_ZENOH_LISTEN", "tcp/127.0.0.1:0")
        .arg(format!("--namespace={}", namespace("notify")))
        .arg(format!("--out={}", dir.path().display()))
        .env("NOTIFY_SOCKET", &socket_path)
        .env("WATCHDOG_USEC", "400000")
        .spawn()
        .expect("merger");
    let mut seen = Vec::new();
    let start = Instant::now();
    let mut buf = [0u8; 256];
    while !(seen.iter().any(|m: &String| m.starts_with("READY=1"))
        && seen.iter().filter(|m| *m == "WATCHDOG=1").count() >= 2)
    {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "got only {seen:?}"
        );
        let n = socket.recv(&mut buf).expect("notification");
        seen.push(String::from_utf8_lossy(&buf[..n]).into_owned());
    }
    merger.kill().expect("kill");
    merger.wait().expect("reaped");
    assert!(seen[0].starts_with("READY=1"), "{seen:?}");
}

/// The units run the lean service binaries because they leave out OpenCV's video and image
/// decoding (~250 shared libraries loaded at every start, docs/deploy.md): a service that
/// comes to call into either would bring them back without a word.
#[test]
fn the_lean_service_binaries_do_not_link_the_decoders() {
    let binaries = [
        env!("CARGO_BIN_EXE_egoslam-frontend"),
        env!("CARGO_BIN_EXE_egoslam-solver"),
        env!("CARGO_BIN_EXE_egoslam-merger"),
    ];
    for binary in binaries {
        let out = std::process::Command::new("readelf")
            .args(["-d", binary])
            .output()
            .expect("readelf (binutils, with the C toolchain)");
        assert!(out.status.success(), "readelf {binary}");
        let dynamic = String::from_utf8_lossy(&out.stdout);
        let needed: Vec<&str> = dynamic.lines().filter(|l| l.contains("(NEEDED)")).collect();
        assert!(
            needed.iter().any(|l| l.contains("libopencv_core")),
            "{binary}: not linked as expected: {needed:?}"
        );
        for decoder in ["libopencv_videoio", "libopencv_imgcodecs"] {
            assert!(
                !needed.iter().any(|l| l.contains(decoder)),
                "{binary} links {decoder}: {needed:?}"
            );
        }
    }
    // And the multi-call binary does, which is what the lean ones are for.
    let out = std::process::Command::new("readelf")
        .args(["-d", env!("CARGO_BIN_EXE_egoslam")])
        .output()
        .expect("readelf");
    assert!(String::from_utf8_lossy(&out.stdout).contains("libopencv_videoio"));
}

/// A lean binary's help and usage errors name it as it is run (`egoslam-solver [OPTIONS]`),
/// not as the multi-call subcommand it parses (`egoslam-solver solver`), and it takes the
/// subcommand's flags.
#[test]
fn a_lean_binary_names_itself_in_its_usage() {
    for (service, binary) in [
        ("frontend", env!("CARGO_BIN_EXE_egoslam-frontend")),
        ("solver", env!("CARGO_BIN_EXE_egoslam-solver")),
        ("merger", env!("CARGO_BIN_EXE_egoslam-merger")),
    ] {
        let help = std::process::Command::new(binary)
            .arg("--help")
            .output()
            .expect("help");
        assert!(help.status.success(), "{binary} --help");
        let text = String::from_utf8_lossy(&help.stdout);
        assert!(
            text.contains(&format!("Usage: egoslam-{service} [OPTIONS]")),
            "{text}"
        );
        assert!(text.contains("--namespace"), "{text}");
        let wrong = std::process::Command::new(binary)
            .arg("--no-such-flag")
            .output()
            .expect("usage error");
        assert_eq!(wrong.status.code(), Some(2));
        let text = String::from_utf8_lossy(&wrong.stderr);
        assert!(
            text.contains(&format!("Usage: egoslam-{service} [OPTIONS]")),
            "{text}"
        );
    }
}
