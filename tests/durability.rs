//! Nothing is lost when the merger dies: a killed merger is restarted by the launcher,
//! resumes from its checkpoint and recovers the windows it missed from the solver's journal
//! (docs/durability.md). The final results must equal those of an undisturbed run.

mod common;

use common::*;
use std::path::Path;
use std::time::{Duration, Instant};

// One test of this file at a time (`one_test_at_a_time`). The frontend kill replays in
// real time: when the merger test's three pipeline runs share the two cores with it, the
// restarted frontend fell behind and the replay dropped 37-40 frames (69-79 of 120 posed,
// against 104-109 alone), which is a measure of the machine's load, not of the restart.

fn keyframes(out: &Path) -> String {
    std::fs::read_to_string(out.join("keyframes.tum")).expect("keyframes.tum")
}

fn run_fixture(out: &Path, fault: Option<&str>) -> std::process::Child {
    let mut c = egoslam_with_calibration_given();
    // The background refinement folds in whenever it finishes, which varies from run to
    // run; without it the results are deterministic and can be compared byte for byte.
    c.args(["run", "--global-ba-px=inf", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out);
    if let Some(f) = fault {
        c.env("EGOSLAM_FAULT", f);
    }
    c.spawn().expect("egoslam run")
}

/// Starts the clip into `out` with the environment variable `env` set (as `run_fixture`,
/// deterministic) and waits for the merger's first checkpoint.
fn run_fixture_until_checkpoint(out: &Path, env: (&str, &str)) -> std::process::Child {
    let mut c = egoslam_with_calibration_given();
    let run = c
        .args(["run", "--global-ba-px=inf", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out)
        .env(env.0, env.1)
        .spawn()
        .expect("run");
    let start = Instant::now();
    while !out.join("state/merger.checkpoint").exists() {
        assert!(start.elapsed() < Duration::from_secs(60), "no checkpoint");
        std::thread::sleep(Duration::from_millis(5));
    }
    run
}

/// The merger's stats of the run in `out`.
fn merger_stats(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("stats/merger.json")).expect("stats"))
        .expect("json")
}

fn wait_success(mut run: std::process::Child) {
    let status = run.wait().expect("wait");
    assert!(status.success(), "egoslam run failed: {status}");
}

#[test]
fn a_killed_merger_resumes_and_loses_nothing() {
    let _turn = one_test_at_a_time();
    let undisturbed = tempfile::tempdir().expect("tempdir");
    wait_success(run_fixture(undisturbed.path(), None));
    let expected = keyframes(undisturbed.path());
    let keyframe_count = report(undisturbed.path())["map_keyframes"]
        .as_u64()
        .expect("count");
    assert_eq!(expected.lines().count() as u64, keyframe_count + 1); // + header line

    // SIGKILL once the merger has checkpointed its first window.
    let killed = tempfile::tempdir().expect("tempdir");
    let run = run_fixture(killed.path(), None);
    let start = Instant::now();
    while !killed.path().join("state/merger.checkpoint").exists() {
        assert!(start.elapsed() < Duration::from_secs(60), "no checkpoint");
        std::thread::sleep(Duration::from_millis(5));
    }
    sigkill("merger", killed.path());
    wait_success(run);
    let r = report(killed.path());
    assert_eq!(r["restarts"]["merger"], 1, "{r}");
    assert_eq!(r["segments"], 1);
    assert_eq!(r["posed_frames"], 120);
    assert_eq!(keyframes(killed.path()), expected, "results differ");

    // Abort with a window in flight (received, not applied): recovered from the journal.
    let aborted = tempfile::tempdir().expect("tempdir");
    wait_success(run_fixture(
        aborted.path(),
        Some("merger-abort-at-window:3"),
    ));
    let r = report(aborted.path());
    assert_eq!(r["restarts"]["merger"], 1, "{r}");
    assert!(r["recovered_windows"].as_u64() >= Some(1), "{r}");
    assert_eq!(keyframes(aborted.path()), expected, "results differ");
}

/// With a horizon of 0.6 s of video the merger retires frames at every persist: their
/// rows are final in trajectory.tum's head and they leave its checkpoint. Killed after its
/// first checkpoint, the restarted merger goes on from the head that checkpoint recorded:
/// every frame is in the file exactly once, in time order, and scores as an undisturbed run.
#[test]
fn a_killed_merger_keeps_the_frames_it_retired_exactly_once() {
    let _turn = one_test_at_a_time();
    let out = tempfile::tempdir().expect("tempdir");
    let mut c = egoslam_with_calibration_given();
    let run = c
        .args([
            "run",
            "--global-ba-px=inf",
            "--frame-horizon-min=0.01",
            "--input",
        ])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path())
        .spawn()
        .expect("run");
    let start = Instant::now();
    while !out.path().join("state/merger.checkpoint").exists() {
        assert!(start.elapsed() < Duration::from_secs(60), "no checkpoint");
        std::thread::sleep(Duration::from_millis(5));
    }
    let head = std::fs::read_to_string(out.path().join("trajectory.tum")).expect("first write");
    sigkill("merger", out.path());
    wait_success(run);
    let r = report(out.path());
    assert_eq!(r["restarts"]["merger"], 1, "{r}");
    assert_eq!(r["posed_frames"], 120, "{r}");
    let text = std::fs::read_to_string(out.path().join("trajectory.tum")).expect("trajectory");
    let stamps: Vec<f64> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            l.split(' ')
                .next()
                .and_then(|t| t.parse().ok())
                .expect("stamp")
        })
        .collect();
    assert_eq!(stamps.len(), 120, "{text}");
    assert!(
        stamps.windows(2).all(|w| w[0] < w[1]),
        "not once each in time order"
    );
    assert_eq!(text.matches("# timestamp").count(), 1);
    let first_row = head.lines().nth(1).expect("a row at the first checkpoint");
    assert!(
        text.contains(first_row),
        "the first frame's row moved after it was final"
    );
    let retired = merger_stats(out.path())["counters"]["retired_frames"].as_u64();
    assert!(retired > Some(0), "the restarted merger retired nothing");
    let ate = r["accuracy"]["trajectory"]["ate_rmse_m"]
        .as_f64()
        .expect("ATE");
    // The same run undisturbed and without horizon scores 1.86 cm.
    assert!(ate < 0.0195, "ATE {ate} m");
}

/// With the checkpoint's write budget at 1 byte/s the merger checkpoints after its first
/// window and at the end only (the rewrites a growing map would make are spaced by its size
/// over the budget); killed in between, it continues from that first checkpoint (the
/// windows it had applied since come again from the solver's journal) and loses nothing.
#[test]
fn a_merger_that_checkpoints_rarely_still_loses_nothing() {
    let _turn = one_test_at_a_time();
    let undisturbed = tempfile::tempdir().expect("tempdir");
    wait_success(run_fixture(undisturbed.path(), None));
    let expected = keyframes(undisturbed.path());

    let rare = tempfile::tempdir().expect("tempdir");
    let run =
        run_fixture_until_checkpoint(rare.path(), ("EGOSLAM_PERSIST_BUDGET_BYTES_PER_S", "1"));
    // A few windows later (the clip's six take ~2 s), before the end.
    std::thread::sleep(Duration::from_millis(500));
    sigkill("merger", rare.path());
    wait_success(run);
    let r = report(rare.path());
    assert_eq!(r["restarts"]["merger"], 1, "{r}");
    assert_eq!(keyframes(rare.path()), expected, "results differ");
    let merger = merger_stats(rare.path());
    // The restarted merger's: its first window's checkpoint and the end's.
    assert_eq!(merger["counters"]["checkpoints"], 2, "{merger}");
}

#[test]
fn a_merger_behind_takes_the_windows_it_could_not_hold_from_the_journal() {
    let _turn = one_test_at_a_time();
    let undisturbed = tempfile::tempdir().expect("tempdir");
    wait_success(run_fixture(undisturbed.path(), None));
    let expected = keyframes(undisturbed.path());

    // A merger that holds one window in memory, stopped after its first window until the
    // solver has solved the rest of the clip (however long a loaded machine takes for it):
    // the windows the solver sent meanwhile wait on the bus.
    let behind = tempfile::tempdir().expect("tempdir");
    let run = run_fixture_until_checkpoint(behind.path(), ("EGOSLAM_MERGER_BACKLOG_WINDOWS", "1"));
    signal("merger", behind.path(), "-STOP");
    let stopped = Instant::now();
    while service_pid("solver", behind.path()).is_some()
        && stopped.elapsed() < Duration::from_secs(30)
    {
        std::thread::sleep(Duration::from_millis(50));
    }
    signal("merger", behind.path(), "-CONT");
    wait_success(run);
    let r = report(behind.path());
    assert_eq!(r["restarts"]["merger"], 0, "{r}");
    assert_eq!(keyframes(behind.path()), expected, "results differ");
    let merger = merger_stats(behind.path());
    let left = merger["counters"]["windows_left_in_journal"]
        .as_u64()
        .unwrap_or(0);
    assert!(left >= 1, "no window was left in the journal: {merger}");
}

/// Runs the clip (in real time with `realtime`), SIGKILLs `service` after `after`, and
/// returns the report of the run, which must complete, with the number of keyframes in
/// keyframes.tum.
fn kill_mid_run(service: &str, after: Duration, realtime: bool) -> (serde_json::Value, usize) {
    let out = tempfile::tempdir().expect("tempdir");
    let mut command = egoslam_with_calibration_given();
    command.arg("run");
    if realtime {
        command.arg("--realtime");
    }
    let run = command
        .arg("--input")
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path())
        .spawn()
        .expect("run");
    std::thread::sleep(after);
    sigkill(service, out.path());
    wait_success(run);
    let keyframes = std::fs::read_to_string(out.path().join("keyframes.tum"))
        .expect("keyframes.tum")
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .count();
    (report(out.path()), keyframes)
}

#[test]
fn a_killed_frontend_or_solver_is_restarted_and_the_run_completes() {
    let _turn = one_test_at_a_time();
    // The frontend continues its ids; what the killed frontend held is lost (its few
    // frames in flight). The map goes on, in a new segment when the restart broke the
    // tracks, which relocalization may link back. The replay is real-time, so frames it
    // could not hand over meanwhile are dropped, and how many depends on the machine's
    // load: measured 115 posed + 1 dropped on an idle machine, 105 + 10 beside three busy
    // loops, 63 posed once in CI beside a parallel test run. What the restart may lose is
    // the rest: 4-5 frames in those runs.
    let (r, _) = kill_mid_run("frontend", Duration::from_millis(1800), true);
    assert_eq!(r["restarts"]["frontend"], 1, "{r}");
    let posed = r["posed_frames"].as_u64().expect("posed");
    let dropped = r["dropped_frames"].as_u64().expect("dropped");
    assert!(
        posed + dropped >= 105 && posed >= 40,
        "frontend: {posed} of 120 frames posed, {dropped} dropped by the replay: {r}"
    );
    // A killed solver loses nothing: the restarted one continues its stream from its
    // journal and replays the frontend's keyframe log, so every keyframe the frontend made
    // (95: lossless replay, no frame dropped) is in the map, in one segment, every frame is
    // posed, and the keyframe ATE is that of an undisturbed run (0.0211 m). One of 8
    // killed runs beside a parallel test gave 0.026 m: the merger's background refinement
    // runs on its own thread and folds in at whichever window it finishes by, which load
    // moves; a resume that lost or doubled windows would be far off either.
    let (r, keyframes) = kill_mid_run("solver", Duration::from_millis(1500), false);
    assert_eq!(r["restarts"]["solver"], 1, "{r}");
    // Every keyframe the frontend made reached the map, and a map this small is kept
    // whole (KeyframeCullingOptions::min_map_keyframes): all are in keyframes.tum.
    assert_eq!(r["keyframes"], 95, "{r}");
    assert_eq!(r["map_keyframes"], keyframes, "{r}");
    assert_eq!(keyframes, 95, "{r}");
    assert_eq!(r["segments"], 1, "{r}");
    assert_eq!(r["posed_frames"], 120, "{r}");
    let ate = r["accuracy"]["keyframes"]["ate_rmse_m"]
        .as_f64()
        .expect("ate");
    assert!(
        (0.95 * 0.0211..1.3 * 0.0211).contains(&ate),
        "keyframe ATE {ate} m"
    );
}

/// Bounded disk use (docs/durability.md, "Disk use"): with compaction forced past 100 KB
/// the solver drops the windows the merger has checkpointed (and the frontend the
/// keyframes the solver no longer needs, when the solver keeps up), yet a merger and then a
/// solver killed mid-run lose nothing: the same keyframes and frames as an undisturbed run.
#[test]
fn compacted_logs_still_recover_a_killed_merger_and_solver() {
    let _turn = one_test_at_a_time();
    let out = tempfile::tempdir().expect("tempdir");
    let run = egoslam_with_calibration_given()
        .args(["run", "--global-ba-px=inf", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path())
        .env("EGOSLAM_COMPACT_ABOVE_BYTES", "100000")
        .spawn()
        .expect("run");
    // The merger is killed once it has checkpointed (its mark lets the journal shrink),
    // the solver half a second later.
    let start = Instant::now();
    while !out.path().join("state/merger.applied").exists() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "no merger checkpoint"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    // The frontend's keyframe log is kept in memory-backed storage, off the flash.
    let namespace = format!("run{}", run.id());
    let in_memory = egoslam_durability::keyframe_log_path(out.path(), &namespace);
    let in_state = out.path().join("state/keyframes.log");
    assert!(
        in_memory.exists() && !in_state.exists(),
        "keyframe log at {}",
        in_memory.display()
    );
    sigkill("merger", out.path());
    std::thread::sleep(Duration::from_millis(500));
    sigkill("solver", out.path());
    wait_success(run);
    // At the end it joins the rest of the state, and the run leaves no file in memory.
    assert!(!in_memory.exists(), "{} left behind", in_memory.display());
    assert!(
        in_state.metadata().is_ok_and(|m| m.len() > 0),
        "no keyframe log kept"
    );
    let r = report(out.path());
    assert_eq!(r["restarts"]["merger"], 1, "{r}");
    assert_eq!(r["restarts"]["solver"], 1, "{r}");
    assert_eq!(r["segments"], 1, "{r}");
    // A lossless replay makes 95 keyframes: all of them are in the map (a map this small
    // is kept whole), every frame is posed.
    let in_map = keyframes(out.path())
        .lines()
        .filter(|l| !l.starts_with('#'))
        .count();
    assert_eq!(r["keyframes"], 95, "{r}");
    assert_eq!(r["map_keyframes"], in_map, "{r}");
    assert_eq!(in_map, 95, "{r}");
    assert_eq!(r["posed_frames"], 120, "{r}");
    // The journal was compacted: it starts after window 0.
    let journal = std::fs::read(out.path().join("state/windows.journal")).expect("journal");
    let first = u64::from_le_bytes(journal[20..28].try_into().expect("header"));
    assert!(first > 0, "journal not compacted");
}
