//! End to end `egoslam run` (all four processes, lossless replay as fast as the frontend
//! takes frames): real-time factor = sequence duration / wall time, and peak memory, median
//! of `EGOSLAM_BENCH_RUNS` (default 3) runs per sequence. zenoh output is off (no
//! subscriber is measured). Sequences: the in-repo clip, those of ../shared/data present
//! on the machine, and the rendered 300-frame walk when `egoslam bench` has rendered it
//! (target/bench-data). A run started again with a calibration estimated from the stream
//! (a rolling-shutter readout, a radial term: docs/config.md) is counted apart: its wall
//! time includes the frames processed before the estimate. `cargo bench -p egoslam
//! --bench end_to_end`; method in docs/benchmarks.md.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Duration of the sequence as the trajectory covers it: last - first stamp + one frame.
fn sequence_seconds(trajectory: &Path) -> Option<f64> {
    let text = std::fs::read_to_string(trajectory).ok()?;
    let stamps: Vec<f64> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| l.split_whitespace().next()?.parse().ok())
        .collect();
    let (first, last) = (stamps.first()?, stamps.last()?);
    let frame = (last - first) / (stamps.len().max(2) - 1) as f64;
    Some(last - first + frame)
}

fn main() {
    let runs: usize = std::env::var("EGOSLAM_BENCH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let shared = repo().join("../shared/data");
    let sequences = [
        (
            "tum_fr1_rpy_120 (repo)",
            repo().join("tests/data/tum_fr1_rpy_120"),
        ),
        ("tum_fr1_rpy", shared.join("tum_fr1_rpy")),
        ("kitti_odometry_00", shared.join("kitti_odometry_00")),
        ("euroc_v1_01", shared.join("euroc_v1_01")),
        (
            "synth_walker_300 (rendered, 640x480)",
            repo().join("target/bench-data/synth_walker_300"),
        ),
    ];
    println!("| sequence | frames | duration s | wall s (median of {runs}) | started again | real-time factor | peak RSS sum MiB (frontend / solver / merger) |");
    println!("|---|---|---|---|---|---|---|");
    for (name, input) in sequences {
        if !input.exists() {
            eprintln!("{name}: {} absent, skipped", input.display());
            continue;
        }
        let out = std::env::temp_dir().join(format!("egoslam_e2e_{}", std::process::id()));
        let (mut walls, mut rtfs, mut mems) = (Vec::new(), Vec::new(), Vec::new());
        let mut restarts = Vec::new();
        let mut last_report = serde_json::Value::Null;
        let mut duration = 0.0;
        for _ in 0..runs {
            let start = Instant::now();
            let status = Command::new(env!("CARGO_BIN_EXE_egoslam"))
                .args(["run", "--input"])
                .arg(&input)
                .arg("--out")
                .arg(&out)
                .env("EGOSLAM_ZENOH_LISTEN", "none")
                .env("EGOSLAM_LOG", "warn")
                .stdout(std::process::Stdio::null())
                .status()
                .expect("egoslam run");
            let wall = start.elapsed().as_secs_f64();
            assert!(status.success(), "{name}: egoslam run failed");
            duration = sequence_seconds(&out.join("trajectory.tum")).expect("trajectory");
            let report: serde_json::Value = serde_json::from_str(
                &std::fs::read_to_string(out.join("report.json")).expect("report"),
            )
            .expect("json");
            walls.push(wall);
            rtfs.push(duration / wall);
            mems.push(report["peak_rss_mib"]["sum"].as_f64().unwrap_or(0.0));
            restarts.push(report["calibration_restarts"].as_f64().unwrap_or(0.0));
            last_report = report;
        }
        let mem = &last_report["peak_rss_mib"];
        println!(
            "| {name} | {} | {duration:.1} | {:.2} | {:.0} | {:.2} | {:.0} ({} / {} / {}) |",
            last_report["frames"],
            median(&mut walls),
            median(&mut restarts),
            median(&mut rtfs),
            median(&mut mems),
            mem["frontend"],
            mem["solver"],
            mem["merger"],
        );
        let _ = std::fs::remove_dir_all(&out);
    }
}
