//! Starting one round of `egoslam run`'s services on a fresh output folder: the camera file,
//! the flags each service is given, and the processes, consumers first.

use crate::options::{PipelineArgs, RunArgs};
use crate::supervision::live_view::LiveView;
use crate::supervision::supervisor::{spawn, stop_all, Supervised};
use egoslam_durability::write_atomically;
use egoslam_export::camera_yaml::camera_yaml;
use egoslam_geometry::PinholeRadtan;
use std::path::{Path, PathBuf};

/// What a round of services is started with.
pub struct Services<'a> {
    pub input: &'a Path,
    pub args: &'a RunArgs,
    /// Where the calibration came from (named in camera.yaml).
    pub origin: &'a Path,
    /// The camera of this round (the calibration, corrected by the estimates so far).
    pub camera: &'a PinholeRadtan,
    /// The calibration as given.
    pub calibrated: &'a PinholeRadtan,
    pub namespace: &'a str,
    /// Flags for every service beyond the run's (stream_calibration.rs).
    pub flags: Vec<String>,
}

fn pipeline_flags(p: &PipelineArgs) -> Vec<String> {
    let mut flags = vec![
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
        format!("--cull-keyframes={}", p.cull_keyframes),
        format!("--max-map-keyframes={}", p.max_map_keyframes),
        format!("--global-ba-px={}", p.global_ba_px),
        format!("--max-point-std={}", p.max_point_std),
        format!("--predict-motion={}", p.predict_motion),
        format!("--rolling-shutter-ms={}", p.rolling_shutter_ms),
        format!("--readout-frames={}", p.readout_frames),
        format!("--patch-retention-min={}", p.patch_retention_min),
        format!("--frame-horizon-min={}", p.frame_horizon_min),
    ];
    if p.map_all_points {
        flags.push("--map-all-points".into());
    }
    flags
}

impl Services<'_> {
    /// Clears what an earlier run or round left in `out`, writes the round's camera.yaml
    /// and starts the services, consumers first (every producer also waits for its
    /// consumer to connect).
    pub fn start(
        &self,
        out: &Path,
        live_view: Option<&LiveView>,
    ) -> anyhow::Result<Vec<Supervised>> {
        let args = self.args;
        for stale in [
            "trajectory.tum",
            "keyframes.tum",
            "map.ply",
            "map_all.ply",
            "report.json",
        ] {
            let _ = std::fs::remove_file(out.join(stale));
        }
        // A new run starts from no state: a checkpoint or journal left there would be resumed.
        let _ = std::fs::remove_dir_all(egoslam_durability::state_dir(out));
        let _ = std::fs::remove_dir_all(out.join("stats"));
        let mut origin = self.origin.display().to_string();
        if self.camera != self.calibrated {
            origin += ", self-calibrated from the stream (report.json)";
        }
        let camera_file = out.join("camera.yaml");
        write_atomically(
            &camera_file,
            camera_yaml(self.camera, &PathBuf::from(origin)).as_bytes(),
        )?;
        let mut common = vec![
            format!("--namespace={}", self.namespace),
            format!("--out={}", out.display()),
            format!("--camera={}", camera_file.display()),
        ];
        common.extend(pipeline_flags(&args.pipeline));
        common.extend(self.flags.iter().cloned());
        let mut replay_args = vec![
            format!("--input={}", self.input.display()),
            format!("--fps={}", args.sequence.rate.fps),
        ];
        if args.sequence.realtime {
            replay_args.push("--realtime".into());
        }
        replay_args.extend(common.iter().cloned());
        let mut merger_args = common.clone();
        merger_args.extend(args.egress.to_flags());
        if let Some(view) = live_view {
            merger_args.push(view.merger_flag());
        }
        if let Some(path) = &args.map.map_out {
            merger_args.push(format!("--map-out={}", path.display()));
        }
        if let Some(path) = &args.map.vocabulary {
            merger_args.push(format!("--vocabulary={}", path.display()));
        }
        let mut frontend_args = common.clone();
        if let Some(path) = &args.map.map_in {
            merger_args.push(format!("--map-in={}", path.display()));
            frontend_args.push(format!("--map-in={}", path.display()));
        }
        let mut children = Vec::new();
        for (name, service_args) in [
            ("merger", &merger_args),
            ("solver", &common),
            ("frontend", &frontend_args),
            ("replay", &replay_args),
        ] {
            match spawn(name, service_args) {
                Ok(c) => children.push(c),
                Err(e) => {
                    stop_all(&mut children);
                    return Err(e);
                }
            }
        }
        Ok(children)
    }
}
