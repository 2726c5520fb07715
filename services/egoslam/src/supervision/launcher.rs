//! `egoslam run`: checks the input, starts the services, supervises them, reports.

use crate::options::RunArgs;
use crate::supervision::memory_files::RunMemoryFiles;
use crate::supervision::services::Services;
use crate::supervision::stream_calibration::{RoundSettings, StreamCalibration};
use crate::supervision::supervisor::{catch_stop_signals, supervise, Supervision};
use anyhow::Context;
use egoslam_durability::write_atomically;
use egoslam_runtime::ServiceStats;
use egoslam_sources::ground_truth::GroundTruth;
use egoslam_sources::{
    detect_layout, load_calibration, load_ground_truth, open_source, FrameSource, Layout,
};
use opencv::prelude::*;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The embedded default sequence: a 120-frame TUM fr1_rpy clip shipped in the repository.
fn default_input() -> PathBuf {
    std::env::var_os("EGOSLAM_DEFAULT_SEQUENCE")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/tum_fr1_rpy_120")
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

/// Fails, naming the option, when a zenoh TCP or TLS listen endpoint's address is taken
/// (another run's, or another program's): found before any service starts rather than when
/// the merger opens its session.
fn check_listen_endpoints(endpoints: &[String]) -> anyhow::Result<()> {
    for endpoint in endpoints {
        let Some(address) = endpoint
            .strip_prefix("tcp/")
            .or_else(|| endpoint.strip_prefix("tls/"))
        else {
            continue;
        };
        // Zenoh endpoints may carry `#` metadata or `?` configuration after the address.
        let address = address.split(['#', '?']).next().unwrap_or(address);
        let Ok(socket) = address.parse::<std::net::SocketAddr>() else {
            continue; // a host name: zenoh resolves it and reports what fails
        };
        if socket.port() == 0 {
            continue;
        }
        if let Err(e) = std::net::TcpListener::bind(socket) {
            anyhow::bail!(
                "--zenoh-listen {endpoint}: cannot listen there ({e}); another egoslam run or program has it: give another port, tcp/127.0.0.1:0 for a free one, or none"
            );
        }
    }
    Ok(())
}

/// The folder of a run's iceoryx2 files (in the temporary folder, named after the
/// launcher's process id); removed when dropped, so that a run ending in an error leaves
/// none behind.
struct BusRoot(PathBuf);

impl BusRoot {
    const PREFIX: &'static str = "egoslam-run";

    fn of_this_process() -> Self {
        Self(std::env::temp_dir().join(format!("{}{}", Self::PREFIX, std::process::id())))
    }

    /// Removes the folders of runs whose launcher is gone without removing its own (killed
    /// by SIGKILL or the OOM killer): nothing else ever would, one per such run.
    fn remove_stale() {
        let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
            return;
        };
        for entry in entries.flatten() {
            let name = entry.file_name();
            let pid = name
                .to_str()
                .and_then(|n| n.strip_prefix(Self::PREFIX))
                .and_then(|p| p.parse::<u32>().ok());
            if let Some(pid) = pid {
                if !Path::new(&format!("/proc/{pid}")).exists() {
                    tracing::debug!(folder = %entry.path().display(), "bus folder of a dead run removed");
                    let _ = std::fs::remove_dir_all(entry.path());
                }
            }
        }
    }
}

impl Drop for BusRoot {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Writes the iceoryx2 configuration of this run (egoslam's, with its root `dir`) into
/// `dir` and returns its path. The root is kept short (in the temporary folder, not under
/// the output): iceoryx2 names Unix sockets after it, whose paths may not pass 108 bytes.
fn per_run_bus_config(dir: &Path) -> anyhow::Result<PathBuf> {
    let shared = egoslam_bus::config_path();
    let text = std::fs::read_to_string(&shared)
        .with_context(|| format!("reading the iceoryx2 configuration {}", shared.display()))?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let root = format!("root-path = {:?}", format!("{}/", dir.display()));
    let mut replaced = false;
    let lines: Vec<String> = text
        .lines()
        .map(|l| {
            if l.trim_start().starts_with("root-path") && !replaced {
                replaced = true;
                root.clone()
            } else {
                l.to_string()
            }
        })
        .collect();
    if !replaced {
        anyhow::bail!("{}: no root-path to replace", shared.display());
    }
    let path = dir.join("iceoryx2.toml");
    write_atomically(&path, (lines.join("\n") + "\n").as_bytes())?;
    Ok(path)
}

/// One figure per process (the launcher's, then each service's from its stats) and their
/// sum, each rounded to `decimals`.
fn per_process(
    launcher: f64,
    stats: &[ServiceStats],
    figure: impl Fn(&ServiceStats) -> f64,
    decimals: i32,
) -> serde_json::Value {
    let unit = 10f64.powi(decimals);
    let round = |v: f64| (v * unit).round() / unit;
    let mut m = serde_json::Map::new();
    m.insert("launcher".into(), json!(round(launcher)));
    for s in stats {
        m.insert(s.service.clone(), json!(round(figure(s))));
    }
    let sum = launcher + stats.iter().map(&figure).sum::<f64>();
    m.insert("sum".into(), json!(round(sum)));
    serde_json::Value::Object(m)
}

/// Peak resident memory per process and their sum (an upper bound of the pipeline's peak:
/// the processes need not peak at the same moment), MiB.
fn peak_memory(stats: &[ServiceStats]) -> serde_json::Value {
    let mib = |kib: u64| kib as f64 / 1024.0;
    let launcher = mib(egoslam_runtime::peak_rss_kib());
    per_process(launcher, stats, |s| mib(s.peak_rss_kib), 1)
}

/// CPU time per process and their sum, seconds: the launcher's own (the first frame's
/// check, supervision, evaluation), each service's its own threads (of the last round, when
/// the run started again for a calibration estimate).
fn cpu_time(stats: &[ServiceStats]) -> serde_json::Value {
    per_process(egoslam_runtime::cpu_seconds(), stats, |s| s.cpu_s, 2)
}

pub fn run(mut args: RunArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let live_view = crate::supervision::live_view::LiveView::start(&args.view, &args.egress)?;
    let input = args.sequence.input.clone().unwrap_or_else(default_input);
    let layout = detect_layout(&input)?;
    // Open the sequence and decode the first frame now: a bad path, an empty sequence, an
    // unreadable image or a wrong calibration size fails here, before any process starts.
    // Quiet: the replay reads these frames again and warns about each bad one then.
    let mut source = open_source(&input, args.sequence.rate.fps)?.quiet();
    let total_frames = source.len_hint();
    let first = source
        .next_frame()
        .with_context(|| format!("{}: no frames", input.display()))??;
    let calibration = load_calibration(&layout, args.calibration.calib.as_deref())?;
    let camera = calibration.camera_for(first.image.cols() as u32, first.image.rows() as u32)?;
    check_listen_endpoints(&args.egress.zenoh_listen)?;
    std::fs::create_dir_all(&args.output.out)
        .with_context(|| format!("creating {}", args.output.out.display()))?;
    drop(source);
    drop(first);
    if let Some(path) = &args.map.map_in {
        // Read once here, so that a map this egoslam cannot use stops the run before it
        // starts, with the reason.
        let vocabulary =
            egoslam_durability::map_file::load_vocabulary(args.map.vocabulary.as_deref())?;
        egoslam_durability::map_file::read_map(path, &vocabulary)?;
    }
    // The self-calibrations come from the stream (stream_calibration.rs): the services
    // start with the calibration as given.
    let mut calibrations = if matches!(layout, Layout::Camera { .. }) {
        StreamCalibration::live(args.pipeline.rolling_shutter_ms)
    } else {
        StreamCalibration::new(
            args.pipeline.rolling_shutter_ms,
            args.pipeline.calibrate_focal,
            args.pipeline.calibrate_radial.applies_to(&camera),
        )
    };
    let mut round = RoundSettings {
        readout: args.pipeline.rolling_shutter_ms,
        camera,
    };
    let out = args.output.out.clone();
    let out = &out;
    let namespace = format!("run{}", std::process::id());
    // The services' iceoryx2 files in a folder of this run's, not the shared /tmp/iceoryx2:
    // runs never see each other's services or clean up each other's nodes.
    BusRoot::remove_stale();
    RunMemoryFiles::remove_stale();
    let bus_root = BusRoot::of_this_process();
    let mut memory_files = RunMemoryFiles::new(out, &namespace);
    let bus_config = per_run_bus_config(&bus_root.0)?;
    std::env::set_var("EGOSLAM_ICEORYX2_CONFIG", &bus_config);
    // From here on a Ctrl-C stops the services in order and keeps what they processed.
    catch_stop_signals()?;
    if crate::supervision::progress::on_terminal() && std::env::var_os("EGOSLAM_LOG").is_none() {
        // The bar shows the progress; the services only say what needs attention.
        std::env::set_var("EGOSLAM_LOG", format!("warn,{}", crate::QUIET_TARGETS));
    }
    let (supervision, run_id) = loop {
        args.pipeline.rolling_shutter_ms = round.readout;
        // Each round on its own bus names: nothing of a stopped round's is met again.
        let round_namespace = match calibrations.restarts {
            0 => namespace.clone(),
            n => format!("{namespace}r{n}"),
        };
        memory_files.follow(&round_namespace);
        // A round started again is a new run to a client (Status.run_id changes): its
        // poses start again from the first frame.
        let run_id = format!(
            "{round_namespace}-{}",
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_millis())
        );
        std::env::set_var("EGOSLAM_RUN_ID", &run_id);
        let services = Services {
            input: &input,
            args: &args,
            origin: &calibration.origin,
            camera: &round.camera,
            calibrated: &camera,
            namespace: &round_namespace,
            flags: calibrations.flags(),
        };
        let children = services.start(out, live_view.as_ref())?;
        if calibrations.restarts == 0 {
            tracing::info!(input = %input.display(), ?layout, frames = ?total_frames, calibration = %calibration.origin.display(), "starting pipeline");
            if let Some(view) = &live_view {
                let total = total_frames.map(|n| n as u64);
                view.follow_with(crate::supervision::progress::frames_bar(
                    "pipeline (frames posed)",
                    total,
                ));
            }
        }
        let mut next = None;
        let supervision = supervise(children, || {
            next = calibrations.check(out, &round);
            next.is_some()
        });
        // A run that ended before its last estimate was read (a short input).
        let next = match &supervision {
            Ok(s) if !s.started_again && s.interrupted_by.is_none() => {
                next.or_else(|| calibrations.check(out, &round))
            }
            _ => next,
        };
        match next {
            Some(settings) => {
                // A killed frontend leaves the tracks it would have resumed from.
                memory_files.discard();
                calibrations.start_again();
                tracing::info!("the run starts again from the first frame with the calibration estimated from the stream");
                round = settings;
            }
            None => break (supervision, run_id),
        }
    };
    let camera = round.camera;
    // Every service has ended (or was stopped): their bus files are of no further use.
    drop(bus_root);
    drop(memory_files);
    let Supervision {
        restarts,
        interrupted_by,
        ..
    } = supervision?;
    let [readout_report, focal_report, radial_report] = calibrations.reports();
    let calibration_restarts = calibrations.restarts;
    let interrupted = interrupted_by.is_some();
    if let Some(view) = live_view {
        // The recording must be closed whatever the rest of the report does.
        if let Err(e) = view.finish(interrupted) {
            tracing::error!("the live view: {e:#}");
        }
    }

    // A service stopped before it wrote its statistics left none: counted as nothing.
    let stats: Vec<ServiceStats> = ["replay", "frontend", "solver", "merger"]
        .iter()
        .map(|s| match ServiceStats::read(out, s) {
            Err(e) if interrupted => {
                tracing::warn!("{e:#}: the service was stopped before it wrote them");
                Ok(ServiceStats::new(s))
            }
            read => read,
        })
        .collect::<Result<_, _>>()?;
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
        accuracy = match egoslam_evaluation::accuracy(out, layout.root(), &camera, gt) {
            Ok(a) => a,
            Err(e) if interrupted => json!({ "error": format!("{e:#}") }),
            Err(e) => return Err(e),
        };
    }
    let report = json!({
        // Raised when a field changes meaning or goes (docs/config.md, "report.json").
        "schema_version": REPORT_SCHEMA_VERSION,
        // Stopped early by this signal (SIGINT 2, SIGTERM 15): the results cover the frames
        // processed until then.
        "interrupted_by_signal": interrupted_by,
        // The id every status message over zenoh carries.
        "run_id": run_id,
        "input": input.display().to_string(),
        // The rate image folders were stamped with (`egoslam export` names their images).
        "fps": args.sequence.rate.fps,
        "layout": {
            "kind": layout.kind(),
            "path": layout.path().display().to_string(),
        },
        "calibration": calibration.origin.display().to_string(),
        "frames": replay.frames,
        "dropped_frames": counter(replay, "dropped_frames"),
        // Frames skipped by reason (missing, unreadable, decode, timestamp, size).
        "skipped_frames": replay
            .counters
            .iter()
            .filter_map(|(k, n)| Some((k.strip_prefix(crate::replay::SKIPPED_PREFIX)?.to_string(), json!(n))))
            .collect::<serde_json::Map<_, _>>(),
        // Bus messages dropped as invalid (undecodable, sequence going back, a frame whose
        // header does not match its pixels), per receiving service.
        "dropped_messages": stats
            .iter()
            .map(|s| (s.service.clone(), json!(counter(s, "dropped_messages"))))
            .collect::<serde_json::Map<_, _>>(),
        "posed_frames": counter(merger, "posed_frames"),
        "keyframes": frontend.keyframes,
        // Those the map keeps (keyframes.tum); the others were culled as redundant
        // (docs/merger.md, "Keyframe culling") and stay in the trajectory as frames.
        "map_keyframes": merger.keyframes,
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
        "cpu_s": cpu_time(&stats),
        // Tracks a restarted frontend continued from its predecessor's last frame.
        "resumed_tracks": counter(frontend, "resumed_tracks"),
        "restarts": restarts.iter().map(|(name, n)| (name.to_string(), json!(n))).collect::<serde_json::Map<_, _>>(),
        "recovered_windows": counter(merger, "recovered_windows"),
        "localized_frames": counter(merger, "localized_frames"),
        "interpolated_frames": counter(merger, "interpolated_frames"),
        "timings_ms": timings,
        // Each frame's time from its capture (the replay's send) to each hop, over the
        // frames that reached it (docs/benchmarks.md, "Pose latency"): the live pose is
        // on zenoh at `live_published`.
        "latency_ms": stats
            .iter()
            .flat_map(|s| s.latency.iter())
            .filter_map(|(hop, h)| Some((hop.clone(), json!(h.summary()?))))
            .collect::<serde_json::Map<_, _>>(),
        // How the live tracker posed the frames (revision 0; docs/merger.md, "Live poses").
        "live_poses": {
            "tracking": counter(merger, "live_tracking"),
            "rotation": counter(merger, "live_rotation"),
            "predicted": counter(merger, "live_predicted"),
            "lost": counter(merger, "live_lost"),
            "before_the_first_window": counter(merger, "live_before_map"),
            "missed": counter(merger, "live_frames_missed"),
        },
        // Times the run started again from the first frame with a calibration estimated
        // from the stream (docs/config.md, "Calibration from the stream").
        "calibration_restarts": calibration_restarts,
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
    match interrupted_by {
        Some(signal) => Err(Interrupted { signal }.into()),
        None => Ok(()),
    }
}

/// Version of report.json's layout: 2 since skipped frames are counted by reason
/// (`skipped_frames`, replacing `corrupt_frames` and `wrong_size_frames`).
const REPORT_SCHEMA_VERSION: u32 = 3;

/// The run was stopped by a signal after writing its results (exit status 128 + signal).
#[derive(Debug, thiserror::Error)]
#[error("stopped by signal {signal}; the results cover the frames processed until then")]
pub struct Interrupted {
    pub signal: i32,
}
