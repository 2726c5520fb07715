//! The option groups of the commands and services (`egoslam run`, `replay`, `frontend`,
//! `solver`, `merger`): each option defined once, as a clap flag whose help heading and id
//! are its configuration-file section and key (config.rs) and whose value parser is its
//! range check (option_checks.rs); each service's options struct is built from them here.

use crate::option_checks as checks;
use clap::builder::RangedU64ValueParser;
use clap::Args;
use egoslam_frontend::{KeyframePolicy, TrackerOptions};
use std::path::PathBuf;

/// Options of the tracking and solving stages, shared by `run` and the services.
#[derive(Args, Debug, Clone)]
pub struct PipelineArgs {
    /// P: a keyframe at least every P frames (1-1000).
    #[arg(long, help_heading = "frontend", default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub keyframe_every: u32,
    /// m: a keyframe when the mean flow since the last one exceeds m pixels (0.1-1000).
    #[arg(long, help_heading = "frontend", default_value_t = 20.0, value_parser = checks::flow_px)]
    pub keyframe_flow_px: f64,
    /// Tracks kept alive by the frontend (50-20000).
    #[arg(long, help_heading = "frontend", default_value_t = 1000, value_parser = RangedU64ValueParser::<usize>::new().range(50..=20_000))]
    pub tracks: usize,
    /// Lucas-Kanade window side, pixels (odd, 3-51; larger is slower and smoother).
    #[arg(long, help_heading = "frontend", default_value_t = 9, value_parser = checks::lk_window)]
    pub lk_window: i32,
    /// Retry tracks LK lost from where their last motion predicts them (fast head turns;
    /// on by default, `--predict-motion false` turns it off: docs/config.md has the
    /// trade-off measured).
    #[arg(long, help_heading = "frontend", default_value_t = true, action = clap::ArgAction::Set)]
    pub predict_motion: bool,
    /// Rolling-shutter readout of the camera, ms from the first row to the last (0: a
    /// global shutter), or `auto`: estimated by the frontend from the first frames, whose
    /// keyframes wait for it (a global shutter is decided after 75 when they clearly show
    /// one); observations are moved to the middle row's time (docs/config.md).
    #[arg(
        long,
        help_heading = "frontend",
        default_value = "auto",
        env = "EGOSLAM_ROLLING_SHUTTER_MS"
    )]
    pub rolling_shutter_ms: crate::calibration::settings::Readout,
    /// Frames `--rolling-shutter-ms auto` estimates the readout from (23-10000): the
    /// stream's first (their keyframes wait for the estimate: the first window comes that
    /// much later).
    #[arg(long, help_heading = "frontend", default_value_t = crate::calibration::settings::AUTO_FRAMES, value_parser = clap::value_parser!(u32).range(23..=10_000))]
    pub readout_frames: u32,
    /// Self-calibrate the focal length: the solver solves the first windows of a recorded
    /// input with the intrinsics free and, when they agree on a clearly different focal
    /// length, the run starts again with the calibration's fx and fy scaled (docs/config.md;
    /// a live camera runs with the calibration as given). Off by default: on TUM and KITTI it improves the
    /// positions and worsens the rotations (docs/config.md has the figures).
    #[arg(long, help_heading = "frontend", default_value_t = false, action = clap::ArgAction::Set, env = "EGOSLAM_CALIBRATE_FOCAL")]
    pub calibrate_focal: bool,
    /// Self-calibrate a radial distortion the calibration leaves: the solver solves the
    /// first windows of a recorded input with one radial term free (the focal held) and,
    /// when they agree on a clear one, the run starts again with it added to the
    /// calibration's k1 (docs/config.md; a live camera runs with the calibration as given). `auto` (the default): only for a
    /// calibration without distortion terms (rectified images, a datasheet's pinhole, a
    /// fisheye's nominal lens, whose first term is measured on its own image);
    /// kitti_odometry_00 0.479 -> 0.246 m.
    #[arg(long, help_heading = "frontend", default_value_t = crate::calibration::settings::RadialSetting::Auto, env = "EGOSLAM_CALIBRATE_RADIAL")]
    pub calibrate_radial: crate::calibration::settings::RadialSetting,
    /// K: keyframes per window (10-30, the paper's range).
    #[arg(long, help_heading = "solver", default_value_t = 20, value_parser = clap::value_parser!(u16).range(10..=30))]
    pub window: u16,
    /// L: loop-closure edges from each keyframe reach back this many keyframes (1-29).
    #[arg(long, help_heading = "solver", default_value_t = 6, value_parser = clap::value_parser!(u16).range(1..=29))]
    pub loop_closures: u16,
    /// O: keyframes shared by consecutive windows (3 to K - 1).
    #[arg(long, help_heading = "solver", default_value_t = 5, value_parser = RangedU64ValueParser::<usize>::new().range(3..=29))]
    pub overlap: usize,
    /// Merger: start a background bundle adjustment of the map when a new window's
    /// median cross-window reprojection error exceeds this many pixels ("inf" disables
    /// it). Default 1.5: inside a window BA leaves ~0.8 px; measured between windows 0.5-1.2
    /// px on KITTI and TUM, and 2.6 px where the TUM clip's chain drifts (docs/solver.md).
    #[arg(long, help_heading = "merger", default_value_t = 1.5, value_parser = checks::positive_or_inf)]
    pub global_ba_px: f64,
    /// Merger: keyframes in that bundle adjustment, newest first (0: the whole segment).
    /// Default 1500: its cost grows faster than the segment (800 keyframes 13 s, 2405 83 s,
    /// 5330 188 s); on the rendered 12,000-frame walk the bound took the run from 344 s to
    /// 218 s and the merger from 2.4 to 1.6 GB with the same keyframe ATE (5.62 m).
    #[arg(long, help_heading = "merger", default_value_t = 1500)]
    pub refine_keyframes: usize,
    /// Merger: fold that bundle adjustment into the map exactly this many windows after it
    /// started, waiting for it if need be, so that the same input always gives the same map
    /// (0: whenever it has finished, never waiting; two runs then differ; at most 1000).
    /// Default 3.
    #[arg(long, help_heading = "merger", default_value_t = 3, value_parser = clap::value_parser!(u32).range(0..=1000))]
    pub refinement_lag: u32,
    /// Merger: close loops inside a map segment when the newest keyframes relocalize into
    /// a part of it mapped long before (docs/merger.md, "Loop closure"); `false` turns it
    /// off.
    #[arg(long, help_heading = "merger", default_value_t = true, action = clap::ArgAction::Set)]
    pub loop_closure: bool,
    /// Merger: match each new keyframe's corners to the points of older keyframes (up to
    /// 300 before) that viewed the same place, and keep them as sightings of those points,
    /// which the background refinement then adjusts across the revisit (docs/merger.md,
    /// "Points seen again"); `false` turns it off.
    #[arg(long, help_heading = "merger", default_value_t = true, action = clap::ArgAction::Set)]
    pub reassociate_points: bool,
    /// Merger: take out of the map the keyframes whose points nearly all (90 %) are seen
    /// by three other keyframes, once no window can bring them again (docs/merger.md,
    /// "Keyframe culling"); their frames stay in the trajectory. `false` keeps every
    /// keyframe (memory then grows with the time walked).
    #[arg(long, help_heading = "merger", default_value_t = true, action = clap::ArgAction::Set)]
    pub cull_keyframes: bool,
    /// Merger: keyframes the map aims to keep at most (keyframes that see no point and
    /// those the spine needs stay beyond it); over it, those whose place another
    /// keyframe covers most closely are culled first (docs/merger.md, "Keyframe culling").
    /// Limits the merger's memory (~0.3-0.4 MB per keyframe); soft, so a long run can pass
    /// it (docs/benchmarks.md, "Endurance"). 0: no ceiling. Default 3000.
    #[arg(long, help_heading = "merger", default_value_t = 3000)]
    pub max_map_keyframes: usize,
    /// Merger: map.ply holds only the map points whose standard deviation, from the
    /// keyframes that saw them at 1 px noise, is at most this fraction of their distance to
    /// the nearest of those keyframes ("inf": every point). Default 0.02 (6 cm at 3 m).
    /// Zenoh carries every point with that figure; the saved map and the pipeline keep
    /// every point (docs/merger.md, "Published points").
    #[arg(long, help_heading = "merger", default_value_t = 0.02, value_parser = checks::positive_or_inf)]
    pub max_point_std: f64,
    /// Merger: also write map_all.ply, every triangulated point with its views and
    /// relative standard deviation (NaN where the views do not fix it).
    #[arg(long, help_heading = "merger")]
    pub map_all_points: bool,
    /// Merger: minutes of video a keyframe's image patches (pixels of the wearer's
    /// surroundings, kept for relocalization and map.ply's colours) are kept in the state
    /// folder; older ones leave at the features log's next compaction, descriptors stay
    /// while the map holds the keyframe (docs/durability.md, "Retention"). 0: as long as the
    /// map needs them.
    #[arg(long, help_heading = "merger", default_value_t = 0.0, value_parser = checks::non_negative_minutes)]
    pub patch_retention_min: f64,
    /// Merger: minutes of video after which a frame's pose is final: it leaves memory and
    /// the checkpoint, and its row joins trajectory.tum's head, which is not rewritten
    /// (docs/merger.md, "Frame horizon"). Keyframes and the map are not affected; a loop
    /// closed later moves only the frames within the horizon (and the keyframes). Bounds
    /// the merger's per-frame state (~250 B a frame) over a day. 0: keep every frame.
    #[arg(long, help_heading = "merger", default_value_t = 10.0, value_parser = checks::non_negative_minutes)]
    pub frame_horizon_min: f64,
}

/// Where results go over zenoh (docs/egress.md).
#[derive(Args, Debug, Clone)]
pub struct EgressArgs {
    /// Device name: key expressions are egoslam/<device>/...
    #[arg(long, help_heading = "zenoh", default_value = "default")]
    pub device: String,
    /// zenoh endpoints to listen on (repeatable; loopback only by default; "none" disables
    /// zenoh output; "tcp/127.0.0.1:0" picks a free port).
    #[arg(
        id = "listen",
        long = "zenoh-listen",
        value_name = "ENDPOINT",
        help_heading = "zenoh",
        env = "EGOSLAM_ZENOH_LISTEN",
        default_value = "tcp/127.0.0.1:7447",
        value_parser = checks::zenoh_endpoint
    )]
    pub zenoh_listen: Vec<String>,
    /// zenoh router or peer endpoints to connect to (repeatable).
    #[arg(
        id = "connect",
        long = "zenoh-connect",
        value_name = "ENDPOINT",
        help_heading = "zenoh",
        value_parser = checks::zenoh_endpoint
    )]
    pub zenoh_connect: Vec<String>,
    /// Remote sessions may only subscribe and query; `--zenoh-remote-writable` (file:
    /// `remote_read_only = false`) lets them publish and declare queryables on egoslam/**.
    #[arg(
        id = "remote_read_only",
        long = "zenoh-remote-writable",
        help_heading = "zenoh",
        action = clap::ArgAction::SetFalse
    )]
    pub remote_read_only: bool,
    /// TLS: CA certificate (PEM) that verifies client certificates (mutual TLS) or the
    /// router connected to.
    #[arg(
        id = "root_ca",
        long = "zenoh-tls-root-ca",
        value_name = "FILE.pem",
        help_heading = "zenoh.tls"
    )]
    pub zenoh_tls_root_ca: Option<PathBuf>,
    /// TLS: this side's certificate chain (PEM); needed by a tls/ listen endpoint.
    #[arg(
        id = "certificate",
        long = "zenoh-tls-certificate",
        value_name = "FILE.pem",
        help_heading = "zenoh.tls"
    )]
    pub zenoh_tls_certificate: Option<PathBuf>,
    /// TLS: the private key of --zenoh-tls-certificate (PEM).
    #[arg(
        id = "private_key",
        long = "zenoh-tls-private-key",
        value_name = "FILE.pem",
        help_heading = "zenoh.tls"
    )]
    pub zenoh_tls_private_key: Option<PathBuf>,
    /// TLS: require client certificates signed by --zenoh-tls-root-ca.
    #[arg(id = "mutual", long = "zenoh-tls-mutual", help_heading = "zenoh.tls")]
    pub zenoh_tls_mutual: bool,
    /// Mutual TLS: only clients with this certificate common name get results (repeatable;
    /// none: every client the CA vouches for).
    #[arg(
        id = "allowed_common_names",
        long = "zenoh-allow-common-name",
        value_name = "NAME",
        help_heading = "zenoh.tls"
    )]
    pub zenoh_allow_common_name: Vec<String>,
}

impl EgressArgs {
    /// The zenoh network options these flags describe.
    pub fn network(&self) -> egoslam_egress::NetworkOptions {
        let tls = [
            &self.zenoh_tls_root_ca,
            &self.zenoh_tls_certificate,
            &self.zenoh_tls_private_key,
        ]
        .iter()
        .any(|p| p.is_some())
        .then(|| egoslam_egress::TlsOptions {
            root_ca: self.zenoh_tls_root_ca.clone(),
            certificate: self.zenoh_tls_certificate.clone(),
            private_key: self.zenoh_tls_private_key.clone(),
            mutual: self.zenoh_tls_mutual,
            allowed_common_names: self.zenoh_allow_common_name.clone(),
        });
        egoslam_egress::NetworkOptions {
            listen: self.zenoh_listen.clone(),
            connect: self.zenoh_connect.clone(),
            tls,
            remote_read_only: self.remote_read_only,
        }
    }

    /// The same options as flags, for a child process (the launcher's merger).
    pub fn to_flags(&self) -> Vec<String> {
        let mut flags = vec![format!("--device={}", self.device)];
        let path = |flag: &str, p: &Option<PathBuf>| {
            p.as_ref().map(|p| format!("--{flag}={}", p.display()))
        };
        flags.extend(
            self.zenoh_listen
                .iter()
                .map(|e| format!("--zenoh-listen={e}")),
        );
        flags.extend(
            self.zenoh_connect
                .iter()
                .map(|e| format!("--zenoh-connect={e}")),
        );
        flags.extend(path("zenoh-tls-root-ca", &self.zenoh_tls_root_ca));
        flags.extend(path("zenoh-tls-certificate", &self.zenoh_tls_certificate));
        flags.extend(path("zenoh-tls-private-key", &self.zenoh_tls_private_key));
        flags.extend(
            self.zenoh_allow_common_name
                .iter()
                .map(|n| format!("--zenoh-allow-common-name={n}")),
        );
        if self.zenoh_tls_mutual {
            flags.push("--zenoh-tls-mutual".into());
        }
        if !self.remote_read_only {
            flags.push("--zenoh-remote-writable".into());
        }
        flags
    }
}

/// The input sequence of `egoslam run` and `egoslam replay`.
#[derive(Args, Debug, Clone)]
pub struct SequenceArgs {
    /// Sequence: TUM/KITTI/EuRoC folder, video file, image folder or camera device.
    /// `egoslam run` without one plays the embedded TUM fr1_rpy clip
    /// (tests/data/tum_fr1_rpy_120), evaluated against its ground truth; `egoslam replay`
    /// needs one (here or in the configuration file).
    #[arg(
        id = "path",
        long = "input",
        value_name = "INPUT",
        help_heading = "input"
    )]
    pub input: Option<PathBuf>,
    /// Replay at the recorded rate (frames dropped if the frontend falls behind) instead of
    /// as fast as the frontend consumes them (lossless).
    #[arg(long, help_heading = "input")]
    pub realtime: bool,
    #[command(flatten)]
    pub rate: FrameRateArgs,
}

/// The frame rate of inputs that carry none.
#[derive(Args, Debug, Clone)]
pub struct FrameRateArgs {
    /// Frame rate assumed for image folders and videos without one (0.1-1000).
    #[arg(long, help_heading = "input", default_value_t = 30.0, value_parser = checks::frame_rate)]
    pub fps: f64,
}

/// The camera calibration of the input.
#[derive(Args, Debug, Clone)]
pub struct CalibrationArgs {
    /// Calibration file (egoslam, ORB-SLAM or Kalibr YAML, KITTI calib.txt, COLMAP
    /// cameras.txt: docs/config.md); default: the dataset's own, found next to the input.
    #[arg(
        id = "calibration",
        long = "calib",
        value_name = "CALIB",
        help_heading = "input"
    )]
    pub calib: Option<PathBuf>,
}

/// Where results, statistics and state go.
#[derive(Args, Debug, Clone)]
pub struct OutputArgs {
    /// Output folder (created): the results (trajectory.tum, keyframes.tum, map.ply,
    /// report.json), the services' statistics (stats/) and state (state/).
    #[arg(
        id = "dir",
        long = "out",
        value_name = "OUT",
        help_heading = "output",
        default_value = "out"
    )]
    pub out: PathBuf,
}

#[derive(Args, Debug)]
pub struct RunArgs {
    #[command(flatten)]
    pub sequence: SequenceArgs,
    #[command(flatten)]
    pub calibration: CalibrationArgs,
    #[command(flatten)]
    pub output: OutputArgs,
    /// Ground truth to evaluate against; default: found next to the input, if any.
    #[arg(long)]
    pub gt: Option<PathBuf>,
    #[command(flatten)]
    pub pipeline: PipelineArgs,
    #[command(flatten)]
    pub egress: EgressArgs,
    #[command(flatten)]
    pub map: MapArgs,
    #[command(flatten)]
    pub view: ViewArgs,
}

/// The live view and recording (docs/viewer.md).
#[derive(Args, Debug, Clone, Default)]
pub struct ViewArgs {
    /// Serve the run to Foxglove (WebSocket, `foxglove.sdk.v1`) on HOST:PORT from the start,
    /// e.g. 127.0.0.1:8765 (port 0: a free one, logged).
    #[arg(long, help_heading = "view", value_name = "HOST:PORT")]
    pub foxglove: Option<String>,
    /// Record the same channels into this MCAP file (replaced if present).
    #[arg(long, help_heading = "view", value_name = "FILE.mcap")]
    pub record: Option<PathBuf>,
}

impl ViewArgs {
    pub fn wanted(&self) -> bool {
        self.foxglove.is_some() || self.record.is_some()
    }
}

/// The saved map (docs/relocalization.md).
#[derive(Args, Debug, Clone, Default)]
pub struct MapArgs {
    /// Write the map (keyframes, poses, points, descriptors) here at the end of the run,
    /// for `egoslam localize --map`.
    #[arg(
        id = "save",
        long = "map-out",
        value_name = "MAP_OUT",
        help_heading = "map"
    )]
    pub map_out: Option<PathBuf>,
    /// Start from this saved map (`--map-out` of an earlier run) and extend it: the run's
    /// keyframes join it once they relocalize in it, from then on posed in its frame and
    /// scale; `--map-out` then writes both (docs/relocalization.md, "Extending a map").
    #[arg(
        id = "extend",
        long = "map-in",
        value_name = "FILE.egomap",
        help_heading = "map"
    )]
    pub map_in: Option<PathBuf>,
    /// Vocabulary tree file (`egoslam vocab train`); default: the one built into egoslam.
    #[arg(long)]
    pub vocabulary: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct ReplayArgs {
    #[command(flatten)]
    pub sequence: SequenceArgs,
    #[command(flatten)]
    pub service: ServiceArgs,
}

#[derive(Args, Debug, Clone)]
pub struct ServiceArgs {
    /// Bus namespace (iceoryx2 service names egoslam/<namespace>/...).
    #[arg(long, help_heading = "bus", default_value = "default")]
    pub namespace: String,
    #[command(flatten)]
    pub output: OutputArgs,
    /// Calibration YAML in egoslam format (the launcher writes DIR/camera.yaml).
    #[arg(long)]
    pub camera: Option<PathBuf>,
    #[command(flatten)]
    pub pipeline: PipelineArgs,
    #[command(flatten)]
    pub egress: EgressArgs,
    #[command(flatten)]
    pub map: MapArgs,
    /// The solver estimates these self-calibrations (focal, radial) from the stream's first
    /// frames and writes them to state/intrinsics_estimate.json; `egoslam run` asks for
    /// them on a recorded input and starts it again with the camera they correct.
    #[arg(long, hide = true, value_delimiter = ',')]
    pub estimate_intrinsics: Vec<EstimatedIntrinsic>,
    /// Keyframes wait while the frontend estimates an `auto` readout, and go out
    /// corrected (`false`: they go out uncorrected at once).
    #[arg(long, hide = true, default_value_t = true, action = clap::ArgAction::Set)]
    pub hold_for_readout: bool,
    /// The revision of a frame's first published pose (the merger's; `egoslam run` numbers
    /// a run started again above the round before).
    #[arg(long, hide = true, default_value_t = 0)]
    pub first_revision: u32,
}

/// A self-calibration the solver can make from the stream (`--estimate-intrinsics`).
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum EstimatedIntrinsic {
    Focal,
    Radial,
}

impl ServiceArgs {
    /// The frontend service's options from these flags.
    pub fn frontend_options(&self) -> egoslam_frontend_service::FrontendServiceOptions {
        egoslam_frontend_service::FrontendServiceOptions {
            namespace: self.namespace.clone(),
            out: self.output.out.clone(),
            camera: self.camera.clone(),
            tracker: self.pipeline.tracker_options(0.0),
            rolling_shutter_ms: self.pipeline.rolling_shutter_ms.given_ms(),
            readout_frames: self.pipeline.readout_frames,
            hold_for_readout: self.hold_for_readout,
            map_in: self.map.map_in.clone(),
        }
    }

    /// The solver service's options from these flags.
    pub fn solver_options(&self) -> anyhow::Result<egoslam_solver_service::SolverServiceOptions> {
        use anyhow::Context;
        let wants = |what| self.estimate_intrinsics.contains(&what);
        let estimate_intrinsics = if self.estimate_intrinsics.is_empty() {
            None
        } else {
            let path = self
                .camera
                .as_deref()
                .context("--estimate-intrinsics needs --camera")?;
            let calibration = egoslam_sources::calibration::read_calibration_file(path)?;
            let (Some(w), Some(h)) = (calibration.width, calibration.height) else {
                anyhow::bail!("{}: lacks the image size", path.display())
            };
            let (options, solver) = crate::calibration::focal::calibration_options(&self.pipeline);
            Some(
                egoslam_solver_service::intrinsics_estimation::IntrinsicsRequest {
                    camera: calibration.camera_for(w, h)?,
                    radial: wants(EstimatedIntrinsic::Radial),
                    focal: wants(EstimatedIntrinsic::Focal),
                    options,
                    solver,
                },
            )
        };
        Ok(egoslam_solver_service::SolverServiceOptions {
            estimate_intrinsics,
            namespace: self.namespace.clone(),
            out: self.output.out.clone(),
            windows: egoslam_solver::WindowOptions {
                size: usize::from(self.pipeline.window),
                overlap: self.pipeline.overlap,
                ..egoslam_solver::WindowOptions::default()
            },
            loop_closure_span: usize::from(self.pipeline.loop_closures),
        })
    }

    /// The merger service's options from these flags.
    pub fn merger_options(&self) -> egoslam_merger_service::MergerServiceOptions {
        let pipeline = &self.pipeline;
        let publishes = !self.egress.zenoh_listen.iter().any(|e| e == "none");
        egoslam_merger_service::MergerServiceOptions {
            namespace: self.namespace.clone(),
            first_revision: self.first_revision,
            out: self.output.out.clone(),
            map_in: self.map.map_in.clone(),
            map_out: self.map.map_out.clone(),
            vocabulary: self.map.vocabulary.clone(),
            egress: publishes.then(|| egoslam_egress::EgressOptions {
                device: self.egress.device.clone(),
                network: self.egress.network(),
            }),
            session: egoslam_merger::SessionOptions {
                global_ba_px: pipeline.global_ba_px,
                refine_keyframes: pipeline.refine_keyframes,
                refinement_lag: pipeline.refinement_lag,
                loop_closure: pipeline.loop_closure,
                reassociate_points: pipeline.reassociate_points,
                cull_keyframes: pipeline.cull_keyframes,
                max_map_keyframes: pipeline.max_map_keyframes,
                patch_retention_s: match pipeline.patch_retention_min {
                    m if m > 0.0 => 60.0 * m,
                    _ => f64::INFINITY,
                },
            },
            max_point_std: pipeline.max_point_std,
            map_all_points: pipeline.map_all_points,
            frame_horizon_s: match pipeline.frame_horizon_min {
                m if m > 0.0 => 60.0 * m,
                _ => f64::INFINITY,
            },
            rolling_shutter_ms: pipeline.rolling_shutter_ms.given_ms(),
        }
    }
}

impl PipelineArgs {
    /// The tracker's options from the pipeline's, with the readout given in seconds.
    pub fn tracker_options(&self, rolling_shutter_s: f64) -> TrackerOptions {
        TrackerOptions {
            target_tracks: self.tracks,
            lk_window_px: self.lk_window,
            predict_motion: self.predict_motion,
            rolling_shutter_s,
            keyframes: KeyframePolicy {
                max_frames_between: self.keyframe_every,
                max_mean_flow_px: self.keyframe_flow_px,
                ..KeyframePolicy::default()
            },
            ..TrackerOptions::default()
        }
    }
}
