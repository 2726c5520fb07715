//! The one configuration file (TOML) that every egoslam process reads: `--config FILE` or
//! `EGOSLAM_CONFIG`; schema and defaults in docs/config.md, an example in
//! deploy/egoslam.toml. Command-line flags (and their environment variables) win over the
//! file, the file wins over built-in defaults. Unknown keys and bad values are rejected at
//! start with a message naming the key.

use crate::cli::Command;
use crate::options::{EgressArgs, PipelineArgs};
use anyhow::{bail, Context};
use clap::parser::ValueSource;
use clap::ArgMatches;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// `[input]`: the sequence or camera.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputSection {
    pub path: Option<PathBuf>,
    pub calibration: Option<PathBuf>,
    pub fps: Option<f64>,
    pub realtime: Option<bool>,
}

/// `[output]`: results, checkpoint and journal folder.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputSection {
    pub dir: Option<PathBuf>,
}

/// `[map]`: saved maps (docs/relocalization.md).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapSection {
    /// A saved map the run extends (`--map-in`).
    pub extend: Option<PathBuf>,
    /// Where the map is saved at the end of the stream (`--map-out`).
    pub save: Option<PathBuf>,
}

/// `[view]`: the live view and recording of `egoslam run` (docs/viewer.md).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewSection {
    pub foxglove: Option<String>,
    pub record: Option<PathBuf>,
}

/// `[frontend]`: tracking and the paper's keyframe rule.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrontendSection {
    pub keyframe_every: Option<u32>,
    pub keyframe_flow_px: Option<f64>,
    pub tracks: Option<usize>,
    pub lk_window: Option<i32>,
    pub predict_motion: Option<bool>,
    pub rolling_shutter_ms: Option<crate::calibration::settings::Readout>,
    pub readout_frames: Option<u32>,
    pub calibrate_focal: Option<bool>,
    pub calibrate_radial: Option<crate::calibration::settings::RadialSetting>,
}

/// `[solver]`: temporal windows and the view graph.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SolverSection {
    pub window: Option<u16>,
    pub overlap: Option<usize>,
    pub loop_closures: Option<u16>,
}

/// `[merger]`: background refinement.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MergerSection {
    pub global_ba_px: Option<f64>,
    pub refine_keyframes: Option<usize>,
    pub refinement_lag: Option<u32>,
    pub loop_closure: Option<bool>,
    pub cull_keyframes: Option<bool>,
    pub max_map_keyframes: Option<usize>,
    pub max_point_std: Option<f64>,
    pub map_all_points: Option<bool>,
    pub patch_retention_min: Option<f64>,
}

/// `[zenoh]`: where results are published.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSection {
    pub device: Option<String>,
    pub listen: Option<Vec<String>>,
    pub connect: Option<Vec<String>>,
    pub remote_read_only: Option<bool>,
    #[serde(default)]
    pub tls: ZenohTlsSection,
}

/// `[zenoh.tls]`: certificates for tls/ endpoints (docs/egress.md).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohTlsSection {
    pub root_ca: Option<PathBuf>,
    pub certificate: Option<PathBuf>,
    pub private_key: Option<PathBuf>,
    pub mutual: Option<bool>,
    pub allowed_common_names: Option<Vec<String>>,
}

/// `[bus]`: iceoryx2 service names.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusSection {
    pub namespace: Option<String>,
}

/// The whole file; every section and key is optional.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub input: InputSection,
    #[serde(default)]
    pub output: OutputSection,
    #[serde(default)]
    pub frontend: FrontendSection,
    #[serde(default)]
    pub solver: SolverSection,
    #[serde(default)]
    pub merger: MergerSection,
    #[serde(default)]
    pub zenoh: ZenohSection,
    #[serde(default)]
    pub bus: BusSection,
    #[serde(default)]
    pub view: ViewSection,
    #[serde(default)]
    pub map: MapSection,
}

impl Config {
    /// Reads and validates a file.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the config file {}", path.display()))?;
        let config: Config =
            toml::from_str(&text).with_context(|| format!("config file {}", path.display()))?;
        config
            .validate()
            .with_context(|| format!("config file {}", path.display()))?;
        Ok(config)
    }

    /// What only the file can get wrong; value ranges are checked once, on the merged
    /// options (option_checks.rs), whatever their source.
    fn validate(&self) -> anyhow::Result<()> {
        for e in self
            .zenoh
            .listen
            .iter()
            .chain(&self.zenoh.connect)
            .flatten()
        {
            if e != "none" && !e.contains('/') {
                bail!("zenoh endpoint {e:?}: expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447");
            }
        }
        Ok(())
    }
}

/// Whether `id` was given explicitly (flag or environment variable).
fn explicit(m: &ArgMatches, id: &str) -> bool {
    matches!(
        m.value_source(id),
        Some(ValueSource::CommandLine | ValueSource::EnvVariable)
    )
}

/// Sets `target` from the file unless the command line set it.
fn fill<T: Clone>(m: &ArgMatches, id: &str, target: &mut T, value: &Option<T>) {
    if let (Some(v), false) = (value, explicit(m, id)) {
        *target = v.clone();
    }
}

/// Sets an optional `target` from the file unless the command line set it.
fn fill_optional<T: Clone>(m: &ArgMatches, id: &str, target: &mut Option<T>, value: &Option<T>) {
    if value.is_some() && !explicit(m, id) {
        target.clone_from(value);
    }
}

fn fill_pipeline(c: &Config, m: &ArgMatches, p: &mut PipelineArgs) {
    fill(
        m,
        "keyframe_every",
        &mut p.keyframe_every,
        &c.frontend.keyframe_every,
    );
    fill(
        m,
        "keyframe_flow_px",
        &mut p.keyframe_flow_px,
        &c.frontend.keyframe_flow_px,
    );
    fill(m, "tracks", &mut p.tracks, &c.frontend.tracks);
    fill(m, "lk_window", &mut p.lk_window, &c.frontend.lk_window);
    fill(
        m,
        "predict_motion",
        &mut p.predict_motion,
        &c.frontend.predict_motion,
    );
    fill(
        m,
        "rolling_shutter_ms",
        &mut p.rolling_shutter_ms,
        &c.frontend.rolling_shutter_ms,
    );
    fill(
        m,
        "readout_frames",
        &mut p.readout_frames,
        &c.frontend.readout_frames,
    );
    fill(
        m,
        "calibrate_focal",
        &mut p.calibrate_focal,
        &c.frontend.calibrate_focal,
    );
    fill(
        m,
        "calibrate_radial",
        &mut p.calibrate_radial,
        &c.frontend.calibrate_radial,
    );
    fill(m, "window", &mut p.window, &c.solver.window);
    fill(m, "overlap", &mut p.overlap, &c.solver.overlap);
    fill(
        m,
        "loop_closures",
        &mut p.loop_closures,
        &c.solver.loop_closures,
    );
    fill(
        m,
        "global_ba_px",
        &mut p.global_ba_px,
        &c.merger.global_ba_px,
    );
    fill(
        m,
        "max_point_std",
        &mut p.max_point_std,
        &c.merger.max_point_std,
    );
    fill(
        m,
        "map_all_points",
        &mut p.map_all_points,
        &c.merger.map_all_points,
    );
    fill(
        m,
        "refine_keyframes",
        &mut p.refine_keyframes,
        &c.merger.refine_keyframes,
    );
    fill(
        m,
        "refinement_lag",
        &mut p.refinement_lag,
        &c.merger.refinement_lag,
    );
    fill(
        m,
        "loop_closure",
        &mut p.loop_closure,
        &c.merger.loop_closure,
    );
    fill(
        m,
        "cull_keyframes",
        &mut p.cull_keyframes,
        &c.merger.cull_keyframes,
    );
    fill(
        m,
        "max_map_keyframes",
        &mut p.max_map_keyframes,
        &c.merger.max_map_keyframes,
    );
    fill(
        m,
        "patch_retention_min",
        &mut p.patch_retention_min,
        &c.merger.patch_retention_min,
    );
}

fn fill_egress(c: &Config, m: &ArgMatches, e: &mut EgressArgs) {
    fill(m, "device", &mut e.device, &c.zenoh.device);
    fill(m, "zenoh_listen", &mut e.zenoh_listen, &c.zenoh.listen);
    fill(m, "zenoh_connect", &mut e.zenoh_connect, &c.zenoh.connect);
    let tls = &c.zenoh.tls;
    fill_optional(
        m,
        "zenoh_tls_root_ca",
        &mut e.zenoh_tls_root_ca,
        &tls.root_ca,
    );
    fill_optional(
        m,
        "zenoh_tls_certificate",
        &mut e.zenoh_tls_certificate,
        &tls.certificate,
    );
    fill_optional(
        m,
        "zenoh_tls_private_key",
        &mut e.zenoh_tls_private_key,
        &tls.private_key,
    );
    fill(m, "zenoh_tls_mutual", &mut e.zenoh_tls_mutual, &tls.mutual);
    fill(
        m,
        "zenoh_allow_common_name",
        &mut e.zenoh_allow_common_name,
        &tls.allowed_common_names,
    );
    let writable = c.zenoh.remote_read_only.map(|read_only| !read_only);
    fill(
        m,
        "zenoh_remote_writable",
        &mut e.zenoh_remote_writable,
        &writable,
    );
}

fn fill_map(c: &Config, m: &ArgMatches, a: &mut crate::options::MapArgs) {
    fill_optional(m, "map_in", &mut a.map_in, &c.map.extend);
    fill_optional(m, "map_out", &mut a.map_out, &c.map.save);
}

/// Applies the file to the parsed command (`m`: the subcommand's matches).
pub fn apply(c: &Config, m: &ArgMatches, command: &mut Command) {
    match command {
        Command::Run(a) => {
            fill_optional(m, "input", &mut a.input, &c.input.path);
            fill_optional(m, "calib", &mut a.calib, &c.input.calibration);
            fill(m, "out", &mut a.out, &c.output.dir);
            fill(m, "fps", &mut a.fps, &c.input.fps);
            fill(m, "realtime", &mut a.realtime, &c.input.realtime);
            fill_optional(m, "foxglove", &mut a.view.foxglove, &c.view.foxglove);
            fill_optional(m, "record", &mut a.view.record, &c.view.record);
            fill_pipeline(c, m, &mut a.pipeline);
            fill_egress(c, m, &mut a.egress);
            fill_map(c, m, &mut a.map);
        }
        Command::Replay(a) => {
            fill_optional(m, "input", &mut a.input, &c.input.path);
            fill(m, "fps", &mut a.fps, &c.input.fps);
            fill(m, "realtime", &mut a.realtime, &c.input.realtime);
            fill(m, "namespace", &mut a.service.namespace, &c.bus.namespace);
            fill(m, "out", &mut a.service.out, &c.output.dir);
            fill_pipeline(c, m, &mut a.service.pipeline);
            fill_egress(c, m, &mut a.service.egress);
        }
        Command::CalibrateReadout(a) => {
            fill(m, "fps", &mut a.fps, &c.input.fps);
            fill_optional(m, "calib", &mut a.calib, &c.input.calibration);
            fill_pipeline(c, m, &mut a.pipeline);
        }
        Command::Frontend(a) | Command::Solver(a) | Command::Merger(a) => {
            fill(m, "namespace", &mut a.namespace, &c.bus.namespace);
            fill(m, "out", &mut a.out, &c.output.dir);
            fill_pipeline(c, m, &mut a.pipeline);
            fill_egress(c, m, &mut a.egress);
            fill_map(c, m, &mut a.map);
        }
        Command::Eval(_)
        | Command::Export(_)
        | Command::View(_)
        | Command::Synth(_)
        | Command::Bench(_)
        | Command::Localize(_)
        | Command::Vocab(_) => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> anyhow::Result<Config> {
        let c: Config = toml::from_str(text)?;
        c.validate()?;
        Ok(c)
    }

    #[test]
    fn the_shipped_example_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/egoslam.toml");
        let c = Config::load(&path).expect("deploy/egoslam.toml");
        assert_eq!(c.solver.window, Some(20));
        assert_eq!(c.zenoh.listen, Some(vec!["tcp/127.0.0.1:7447".to_string()]));
    }

    #[test]
    fn unknown_keys_and_bad_values_name_the_key() {
        let e = parse("[solver]\nwindw = 20\n").expect_err("unknown key");
        assert!(format!("{e:#}").contains("windw"), "{e:#}");
        let e = parse("[sovler]\nwindow = 20\n").expect_err("unknown section");
        assert!(format!("{e:#}").contains("sovler"), "{e:#}");
        let e = parse("[solver]\nwindow = \"twenty\"\n").expect_err("type");
        assert!(format!("{e:#}").contains("window"), "{e:#}");
        let e = parse("[zenoh]\nlisten = [\"127.0.0.1:7447\"]\n").expect_err("endpoint");
        assert!(format!("{e:#}").contains("127.0.0.1:7447"), "{e:#}");
        assert!(parse("[merger]\nglobal_ba_px = inf\n").is_ok());
    }

    #[test]
    fn flags_win_over_the_file_and_the_file_over_defaults() {
        use clap::{CommandFactory, FromArgMatches};
        let c = parse("[solver]\nwindow = 12\noverlap = 4\n[zenoh]\ndevice = \"glasses\"\n")
            .expect("valid");
        let matches = crate::cli::Cli::command()
            .try_get_matches_from(["egoslam", "solver", "--overlap", "6"])
            .expect("args");
        let mut cli = crate::cli::Cli::from_arg_matches(&matches).expect("cli");
        let (_, sub) = matches.subcommand().expect("subcommand");
        apply(&c, sub, &mut cli.command);
        let Command::Solver(a) = cli.command else {
            panic!("solver")
        };
        assert_eq!(a.pipeline.window, 12, "from the file");
        assert_eq!(a.pipeline.overlap, 6, "the flag wins");
        assert_eq!(a.egress.device, "glasses");
        assert_eq!(a.pipeline.tracks, 1000, "built-in default");
    }

    #[test]
    fn the_map_section_reaches_frontend_and_merger() {
        use clap::{CommandFactory, FromArgMatches};
        let c =
            parse("[map]\nextend = \"/var/lib/egoslam/home.egomap\"\nsave = \"today.egomap\"\n")
                .expect("valid");
        for service in ["frontend", "merger"] {
            let matches = crate::cli::Cli::command()
                .try_get_matches_from(["egoslam", service])
                .expect("args");
            let mut cli = crate::cli::Cli::from_arg_matches(&matches).expect("cli");
            let (_, sub) = matches.subcommand().expect("subcommand");
            apply(&c, sub, &mut cli.command);
            let (Command::Frontend(a) | Command::Merger(a)) = cli.command else {
                panic!("{service}")
            };
            let home = PathBuf::from("/var/lib/egoslam/home.egomap");
            assert_eq!(a.map.map_in, Some(home), "{service}");
            assert_eq!(a.map.map_out, Some(PathBuf::from("today.egomap")));
        }
        let e = parse("[map]\nextends = \"x\"\n").expect_err("unknown key");
        assert!(format!("{e:#}").contains("extends"), "{e:#}");
    }

    #[test]
    fn the_tls_section_reaches_the_network_options() {
        use clap::{CommandFactory, FromArgMatches};
        let c = parse(
            "[zenoh]\nlisten = [\"tls/0.0.0.0:7447\"]\nremote_read_only = true\n\
             [zenoh.tls]\nroot_ca = \"/etc/egoslam/ca.pem\"\n\
             certificate = \"/etc/egoslam/box.pem\"\nprivate_key = \"/etc/egoslam/box.key\"\n\
             mutual = true\nallowed_common_names = [\"viewer\"]\n",
        )
        .expect("valid");
        let matches = crate::cli::Cli::command()
            .try_get_matches_from(["egoslam", "merger"])
            .expect("args");
        let mut cli = crate::cli::Cli::from_arg_matches(&matches).expect("cli");
        let (_, sub) = matches.subcommand().expect("subcommand");
        apply(&c, sub, &mut cli.command);
        let Command::Merger(a) = cli.command else {
            panic!("merger")
        };
        let network = a.egress.network();
        assert_eq!(network.listen, vec!["tls/0.0.0.0:7447".to_string()]);
        assert!(network.remote_read_only);
        let tls = network.tls.expect("tls");
        assert_eq!(tls.certificate, Some(PathBuf::from("/etc/egoslam/box.pem")));
        assert!(tls.mutual);
        assert_eq!(tls.allowed_common_names, vec!["viewer".to_string()]);
        let e = parse("[zenoh.tls]\nmutal = true\n").expect_err("unknown key");
        assert!(format!("{e:#}").contains("mutal"), "{e:#}");
    }
}
