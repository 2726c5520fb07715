//! What a person sees: under a terminal (a pseudo-terminal made by `script`) the run draws
//! progress bars with frames done of the total and the time left; into a pipe or a file
//! it writes plain lines, no terminal escape codes, and no error when nothing failed.

mod common;

use common::*;

#[test]
fn a_terminal_shows_progress_and_a_pipe_gets_plain_lines() {
    let dir = tempfile::tempdir().expect("tempdir");
    let command = format!(
        "{} run --input {} --out {}",
        env!("CARGO_BIN_EXE_egoslam"),
        tum_fixture().display(),
        dir.path().join("tty").display()
    );
    let seen = std::process::Command::new("script")
        .args(["-qfec", &command, "/dev/null"])
        .env("EGOSLAM_ZENOH_LISTEN", "tcp/127.0.0.1:0")
        .env_remove("EGOSLAM_LOG")
        .output()
        .expect("script (util-linux)");
    assert!(seen.status.success(), "{seen:?}");
    let screen = String::from_utf8_lossy(&seen.stdout);
    for expected in [
        "pipeline (frames posed) [",
        "/120 frames",
        " left",
        "frames 120 (posed 120)",
    ] {
        assert!(screen.contains(expected), "{expected:?} not in:\n{screen}");
    }

    let piped = egoslam()
        .args(["run", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(dir.path().join("pipe"))
        .env_remove("EGOSLAM_LOG")
        .output()
        .expect("run");
    assert!(piped.status.success());
    let log = String::from_utf8_lossy(&piped.stderr);
    assert!(log.contains("starting pipeline"), "log lines: {log}");
    assert!(
        !log.contains('\u{1b}'),
        "escape codes in a piped log:\n{log}"
    );
    assert!(!log.contains(" left"), "a bar in a piped log:\n{log}");
    assert!(
        !log.contains("error:") && !log.contains("ERROR"),
        "an error in a run that succeeded:\n{log}"
    );
}
