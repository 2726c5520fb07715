//! `egoslam run`: checks the input, starts the services, supervises them, reports.

use crate::cli::{PipelineArgs, RunArgs};
use crate::output::{camera_yaml, write_atomically};
use crate::stats::ServiceStats;
use anyhow::{bail, Context};
use egoslam_geometry::PinholeRadtan;
use egoslam_sources::ground_truth::GroundTruth;
use egoslam_sources::{
    detect_layout, load_calibration, load_ground_truth, open_source, Frame, FrameSource, Layout,
};
use opencv::prelude::*;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// The embedded default sequence: a 120-frame TUM fr1_rpy clip shipped in the repository.
fn default_input() -> PathBuf {
    std::env::var_os("EGOSLAM_DEFAULT_SEQUENCE")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/tum_fr1_rpy_120")
        })
}

fn pipeline_flags(p: &PipelineArgs) -> Vec<String> {
    let flags = vec![
        format!("--keyframe-every={}", p.keyframe_every),
        format!("--keyframe-flow-px={}", p.keyframe_flow_px),
        format!("--tracks={}", p.tracks),
        format!("--lk-window={}", p.lk_window),
        format!("--window={}", p.window),
        format!("--overlap={}", p.overlap),
        format!("--loop-closures={}", p.loop_closures),
        format!("--refine-keyframes={}", p.refine_keyframes),
        format!("--refinement-lag={}", p.refinement_lag),
        format!("--loop-closure={}", p.loop_closure),
        format!("--global-ba-px={}", p.global_ba_px),
        format!("--max-point-std={}", p.max_point_std),
        format!("--predict-motion={}", p.predict_motion),
        format!("--rolling-shutter-ms={}", p.rolling_shutter_ms),
        format!("--readout-frames={}", p.readout_frames),
    ];
    flags
}

/// Replaces `--rolling-shutter-ms auto` by the readout estimated from the input's first
/// frames (`first`, then the rest of `source`; 0 when no estimate can be made: too short or
/// too still an input), and says what was used, for the report.
fn resolve_readout(
    args: &mut RunArgs,
    input: &Path,
    layout: &Layout,
    first: Frame,
    source: &mut dyn FrameSource,
    camera: PinholeRadtan,
) -> serde_json::Value {
    use crate::readout::{estimate_from_source, Readout};
    let given = args.pipeline.rolling_shutter_ms;
    if let Readout::Millis(ms) = given {
        return json!({ "setting": given.to_string(), "readout_ms": ms });
    }
    if matches!(layout, Layout::Camera { .. }) {
        // A live camera cannot be read ahead: the frontend estimates it from its first
        // frames (readout.rs) and logs the value.
        return json!({ "setting": "auto", "estimated_by": "the frontend, online" });
    }
    let started = Instant::now();
    let estimate = estimate_from_source(first, source, camera, &args.pipeline);
    let (readout_ms, details) = match estimate {
        Ok(e) => (
            e.readout_s * 1e3,
            json!({
                "best_ms": e.best_s * 1e3,
                "significant": e.significant,
                "residual_px": e.residual_px,
                "residual_at_zero_px": e.residual_at_zero_px,
                "frame_pairs": e.pairs,
            }),
        ),
        Err(e) => {
            let e = format!("estimating the readout of {}: {e}", input.display());
            tracing::warn!(
                "no rolling-shutter readout estimate ({e}): a global shutter is assumed"
            );
            (0.0, json!({ "error": e }))
        }
    };
    args.pipeline.rolling_shutter_ms = Readout::Millis(readout_ms);
    json!({
        "setting": "auto",
        "readout_ms": readout_ms,
        "estimate": details,
        "estimation_ms": started.elapsed().as_secs_f64() * 1e3,
    })
}

/// Ground truth next to the input, if any (TUM groundtruth.txt, KITTI poses/NN.txt, EuRoC).
/// Image folders and videos carry no clock of their own (their timestamps are frame index /
/// fps), so nothing found near them could be associated: they need `--gt` and real stamps.
fn find_ground_truth(layout: &Layout) -> Option<GroundTruth> {
    if matches!(
        layout,
        Layout::ImageFolder { .. } | Layout::Video { .. } | Layout::Camera { .. }
    ) {
        return None;
    }
    let root = layout.root();
    if let Layout::Kitti { dir } = layout {
        let name = dir.file_name()?.to_string_lossy().into_owned();
        let poses = dir
            .parent()?
            .parent()?
            .join("poses")
            .join(format!("{name}.txt"));
        if poses.is_file() {
            return load_ground_truth(&poses).ok();
        }
    }
    root.ancestors()
        .take(3)
        .find_map(|d| load_ground_truth(d).ok())
}

/// Services the supervisor restarts when they die by a signal: the merger resumes exactly
/// (checkpoint + journal); a restarted frontend continues its ids and a restarted solver
/// starts a new stream, which the merger continues as a new map segment (the keyframes in
/// flight are lost: docs/durability.md). The replay (camera) is not restarted.
const RESTARTABLE: &[&str] = &["merger", "solver", "frontend"];

/// Restarts allowed per service within [`RESTART_INTERVAL`] (as systemd's StartLimitBurst
/// and StartLimitIntervalSec): a service that keeps dying has a real problem, but one killed
/// now and then on a long run is restarted every time.
const RESTART_BURST: usize = 3;
const RESTART_INTERVAL: Duration = Duration::from_secs(60);

struct Supervised {
    name: &'static str,
    args: Vec<String>,
    child: Child,
    restarts: u32,
    /// When the restarts within the last [`RESTART_INTERVAL`] happened.
    recent_restarts: std::collections::VecDeque<Instant>,
}

impl Supervised {
    /// Whether one more restart stays within the burst limit (forgets older restarts).
    fn may_restart(&mut self, now: Instant) -> bool {
        while self
            .recent_restarts
            .front()
            .is_some_and(|t| now.duration_since(*t) > RESTART_INTERVAL)
        {
            self.recent_restarts.pop_front();
        }
        self.recent_restarts.len() < RESTART_BURST
    }
}

fn spawn(name: &'static str, args: &[String]) -> anyhow::Result<Supervised> {
    use std::os::unix::process::CommandExt;
    let exe = std::env::current_exe().context("locating the egoslam executable")?;
    let mut command = Command::new(exe);
    command.arg(name).args(args);
    // A launcher that is killed (SIGKILL, or SIGTERM, which it does not catch) must not
    // leave its services running on: each gets SIGTERM when the launcher dies, and stops
    // as on any SIGTERM. Found when two killed runs kept writing into one output folder.
    // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
    unsafe {
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let child = command
        .spawn()
        .with_context(|| format!("starting the {name} service"))?;
    Ok(Supervised {
        name,
        args: args.to_vec(),
        child,
        restarts: 0,
        recent_restarts: Default::default(),
    })
}

fn stop_all(children: &mut [Supervised]) {
    for c in children.iter_mut() {
        // SIGTERM first: services finish their current item and release shared memory.
        // Only to those still running: a service that has exited was reaped by `try_wait`,
        // its process id may already be another process's (and `kill(1)` printed "No such
        // process" for it under the service's own error).
        if matches!(c.child.try_wait(), Ok(None)) {
            if let Ok(pid) = libc::pid_t::try_from(c.child.id()) {
                // SAFETY: kill(2) touches no memory; `pid` is our unreaped child.
                unsafe { libc::kill(pid, libc::SIGTERM) };
            }
        }
    }
    let deadline = Instant::now() + Duration::from_secs(3);
    for c in children.iter_mut() {
        while Instant::now() < deadline && matches!(c.child.try_wait(), Ok(None)) {
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = c.child.kill();
        let _ = c.child.wait();
    }
}

/// Waits for every service. A restartable service killed by a signal (SIGKILL, a crash) is
/// started again; any other failure stops the others and is reported. Returns the restarts
/// per service.
fn supervise(mut children: Vec<Supervised>) -> anyhow::Result<Vec<(&'static str, u32)>> {
    use std::os::unix::process::ExitStatusExt;
    loop {
        let mut running = 0;
        for i in 0..children.len() {
            match children[i].child.try_wait()? {
                Some(status)
                    if status.signal().is_some()
                        && RESTARTABLE.contains(&children[i].name)
                        && children[i].may_restart(Instant::now()) =>
                {
                    let c = &mut children[i];
                    tracing::warn!(service = c.name, %status, "service died; restarting it");
                    let again = spawn(c.name, &c.args)?;
                    c.child = again.child;
                    c.restarts += 1;
                    c.recent_restarts.push_back(Instant::now());
                    running += 1;
                }
                Some(status) if !status.success() => {
                    let name = children[i].name;
                    stop_all(&mut children);
                    bail!("the {name} service failed ({status}); the pipeline was stopped");
                }
                Some(_) => {}
                None => running += 1,
            }
        }
        if running == 0 {
            return Ok(children.iter().map(|c| (c.name, c.restarts)).collect());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Peak resident memory per process and their sum (an upper bound of the pipeline's peak:
/// the processes need not peak at the same moment), MiB.
fn peak_memory(stats: &[ServiceStats]) -> serde_json::Value {
    let mib = |kib: u64| (kib as f64 / 1024.0 * 10.0).round() / 10.0;
    let launcher = crate::stats::peak_rss_kib();
    let mut m = serde_json::Map::new();
    m.insert("launcher".into(), json!(mib(launcher)));
    for s in stats {
        m.insert(s.service.clone(), json!(mib(s.peak_rss_kib)));
    }
    let sum = launcher + stats.iter().map(|s| s.peak_rss_kib).sum::<u64>();
    m.insert("sum".into(), json!(mib(sum)));
    serde_json::Value::Object(m)
}

pub fn run(mut args: RunArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let input = args.input.clone().unwrap_or_else(default_input);
    let layout = detect_layout(&input)?;
    // Open the sequence and decode the first frame now: a bad path, an empty sequence, an
    // unreadable image or a wrong calibration size fails here, before any process starts.
    let mut source = open_source(&input, args.fps)?;
    let total_frames = source.len_hint();
    let first = source
        .next_frame()
        .with_context(|| format!("{}: no frames", input.display()))??;
    let calibration = load_calibration(&layout, args.calib.as_deref())?;
    let camera = calibration.camera_for(first.image.cols() as u32, first.image.rows() as u32)?;
    // An output folder that cannot be made fails before the readout pre-pass, not after.
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let readout_report =
        resolve_readout(&mut args, &input, &layout, first, source.as_mut(), camera);
    drop(source);
    let (camera, focal_report) =
        crate::self_calibration::resolve_focal(&args, &input, &layout, camera);
    let (camera, radial_report) =
        crate::self_calibration::resolve_radial(&args, &input, &layout, camera);
    let mut origin = calibration.origin.display().to_string();
    if let Some(scale) = focal_report["applied_scale"].as_f64().filter(|s| *s != 1.0) {
        origin += &format!(", focal lengths x{scale:.4} (self-calibrated, report.json)");
    }
    if let Some(k) = radial_report["applied_k"].as_f64().filter(|k| *k != 0.0) {
        origin += &format!(", k1 {k:+.4} (self-calibrated, report.json)");
    }
    let origin = PathBuf::from(origin);

    let out = &args.out;
    for stale in [
        "trajectory.tum",
        "keyframes.tum",
        "map.ply",
        "report.json",
        crate::checkpoint::FILE_NAME,
        crate::window_journal::FILE_NAME,
        crate::features_log::FILE_NAME,
        crate::frontend_service::KEYFRAME_LOG,
        crate::frontend_service::ID_STATE_FILE,
        crate::readout::READOUT_STATE_FILE,
        crate::log_compaction::MERGER_MARK,
        crate::log_compaction::SOLVER_MARK,
    ] {
        let _ = std::fs::remove_file(out.join(stale));
    }
    let _ = std::fs::remove_dir_all(out.join("stats"));
    let camera_file = out.join("camera.yaml");
    write_atomically(&camera_file, camera_yaml(&camera, &origin).as_bytes())?;
    tracing::info!(input = %input.display(), ?layout, frames = ?total_frames, calibration = %calibration.origin.display(), "starting pipeline");

    let namespace = format!("run{}", std::process::id());
    let mut common = vec![
        format!("--namespace={namespace}"),
        format!("--out={}", out.display()),
        format!("--camera={}", camera_file.display()),
    ];
    common.extend(pipeline_flags(&args.pipeline));
    let mut replay_args = vec![
        format!("--input={}", input.display()),
        format!("--fps={}", args.fps),
    ];
    if args.realtime {
        replay_args.push("--realtime".into());
    }
    replay_args.extend(common.iter().cloned());
    // Consumers first; every producer also waits for its consumer to connect.
    let mut children = Vec::new();
    let mut merger_args = common.clone();
    merger_args.extend(args.egress.to_flags());
    if let Some(path) = &args.map.map_out {
        merger_args.push(format!("--map-out={}", path.display()));
    }
    if let Some(path) = &args.map.vocabulary {
        merger_args.push(format!("--vocabulary={}", path.display()));
    }
    for (name, service_args) in [
        ("merger", &merger_args),
        ("solver", &common),
        ("frontend", &common),
    ] {
        match spawn(name, service_args) {
            Ok(c) => children.push(c),
            Err(e) => {
                stop_all(&mut children);
                return Err(e);
            }
        }
    }
    match spawn("replay", &replay_args) {
        Ok(c) => children.push(c),
        Err(e) => {
            stop_all(&mut children);
            return Err(e);
        }
    }
    let restarts = supervise(children)?;

    let stats: Vec<ServiceStats> = ["replay", "frontend", "solver", "merger"]
        .iter()
        .map(|s| ServiceStats::read(out, s))
        .collect::<anyhow::Result<_>>()?;
    let (replay, frontend, solver, merger) = (&stats[0], &stats[1], &stats[2], &stats[3]);
    let mut timings = serde_json::Map::new();
    for s in &stats {
        for (stage, ms) in &s.timings_ms {
            timings.insert(format!("{}.{stage}", s.service), json!(ms));
        }
    }
    timings.insert("total".into(), json!(started.elapsed().as_secs_f64() * 1e3));
    let counter = |s: &ServiceStats, k: &str| s.counters.get(k).copied().unwrap_or(0);

    let ground_truth = match &args.gt {
        Some(p) => Some(load_ground_truth(p)?),
        None => find_ground_truth(&layout),
    };
    let mut accuracy = serde_json::Value::Null;
    if let Some(gt) = &ground_truth {
        accuracy = crate::eval::accuracy(out, layout.root(), &camera, gt)?;
    }
    let report = json!({
        "input": input.display().to_string(),
        "layout": format!("{layout:?}"),
        "calibration": calibration.origin.display().to_string(),
        "frames": replay.frames,
        "dropped_frames": counter(replay, "dropped_frames"),
        "corrupt_frames": counter(replay, "corrupt_frames"),
        "wrong_size_frames": counter(replay, "wrong_size_frames"),
        "posed_frames": counter(merger, "posed_frames"),
        "keyframes": frontend.keyframes,
        "windows": solver.windows,
        "unsolved_windows": counter(merger, "unsolved_windows"),
        "segments": counter(merger, "segments"),
        // Breaks (segments started) that relocalization linked back (docs/relocalization.md):
        // breaks left = segments - 1.
        "breaks_healed": counter(merger, "breaks_healed"),
        // Loops closed inside a segment (docs/merger.md, "Loop closure").
        "loops_closed": counter(merger, "loops_closed"),
        // The closed loops' sightings of old points kept as observations (the loop's
        // constraint in later refinements; docs/merger.md, "Loop closure").
        "loop_sightings": counter(merger, "loop_sightings"),
        "blind_frames": counter(frontend, "blind_frames"),
        "window_translations": solver.window_translations,
        "map_points": counter(merger, "map_points"),
        "published_points": counter(merger, "published_points"),
        "peak_rss_mib": peak_memory(&stats),
        "restarts": restarts.iter().map(|(name, n)| (name.to_string(), json!(n))).collect::<serde_json::Map<_, _>>(),
        "recovered_windows": counter(merger, "recovered_windows"),
        "localized_frames": counter(merger, "localized_frames"),
        "interpolated_frames": counter(merger, "interpolated_frames"),
        "timings_ms": timings,
        "rolling_shutter": readout_report,
        "focal_calibration": focal_report,
        "radial_calibration": radial_report,
        "accuracy": accuracy,
    });
    write_atomically(
        &out.join("report.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    println!(
        "frames {} (posed {}), keyframes {}, windows {}, segments {} ({} breaks healed), {} loops closed; results in {}",
        replay.frames,
        counter(merger, "posed_frames"),
        frontend.keyframes,
        solver.windows,
        counter(merger, "segments"),
        counter(merger, "breaks_healed"),
        counter(merger, "loops_closed"),
        out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn restarts_are_limited_per_interval_not_per_run() {
        let child = Command::new("true").spawn().expect("spawn true");
        let mut s = Supervised {
            name: "solver",
            args: Vec::new(),
            child,
            restarts: 0,
            recent_restarts: Default::default(),
        };
        let t0 = Instant::now();
        for k in 0..RESTART_BURST {
            assert!(s.may_restart(t0 + Duration::from_secs(k as u64)));
            s.recent_restarts
                .push_back(t0 + Duration::from_secs(k as u64));
        }
        assert!(!s.may_restart(t0 + Duration::from_secs(10)), "burst spent");
        // A minute after the first restart, one more is allowed; a kill every 60 s never
        // runs out.
        assert!(s.may_restart(t0 + RESTART_INTERVAL + Duration::from_secs(1)));
        let _ = s.child.wait();
    }
}
