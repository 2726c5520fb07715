//! Command-line interface: the commands and their flags (the option groups are options.rs);
//! docs/config.md's table of `egoslam run` options is generated from it (the `docs_table`
//! test below).

use crate::options::{ReplayArgs, RunArgs, ServiceArgs};
use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "egoslam",
    version,
    about = "Monocular SLAM for egocentric video: temporal windows solved as global SfM"
)]
pub struct Cli {
    /// More logging (-v debug, -vv trace); EGOSLAM_LOG overrides (tracing filter syntax).
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    /// Configuration file (TOML, docs/config.md); flags given on the command line win.
    #[arg(long, global = true, env = "EGOSLAM_CONFIG")]
    pub config: Option<PathBuf>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run the whole pipeline on a sequence (default: the embedded TUM clip) and write results.
    Run(RunArgs),
    /// ATE RMSE of a TUM trajectory against ground truth (TUM, KITTI or EuRoC layout).
    Eval(egoslam_evaluation::EvalArgs),
    /// Follow a running egoslam (a deployed merger) in Foxglove and/or record it into MCAP
    /// (docs/viewer.md).
    View(crate::supervision::live_view::ViewCommandArgs),
    /// Write a finished run's map for COLMAP or nerfstudio (docs/export.md).
    Export(crate::commands::export::ExportArgs),
    /// Run the benchmark suite (real and rendered sequences) and write the table.
    Bench(egoslam_bench::BenchArgs),
    /// Render a synthetic egocentric sequence with ground truth (TUM layout).
    Synth(crate::commands::synth::SynthArgs),
    /// Estimate a camera's rolling-shutter readout from a recording (for
    /// `--rolling-shutter-ms` / `frontend.rolling_shutter_ms` when it is used live).
    CalibrateReadout(crate::calibration::readout::CalibrateReadoutArgs),
    /// Localize every frame of a sequence in a saved map (`run --map-out`).
    Localize(crate::commands::relocalization::LocalizeArgs),
    /// Vocabulary tree for relocalization.
    #[command(subcommand)]
    Vocab(VocabCommand),
    /// Service: publish a sequence's frames on the bus.
    Replay(ReplayArgs),
    /// Service: track frames, publish keyframes.
    Frontend(ServiceArgs),
    /// Service: solve windows of keyframes.
    Solver(ServiceArgs),
    /// Service: merge windows into one map, write the outputs.
    Merger(ServiceArgs),
}

#[derive(Subcommand, Debug)]
pub enum VocabCommand {
    /// Train a vocabulary tree on the ORB descriptors of images.
    Train(crate::commands::relocalization::VocabTrainArgs),
}

/// docs/config.md's table of `egoslam run`'s options is generated from the definitions
/// above, so that it cannot drift from them: the test fails while the file's table differs,
/// and `EGOSLAM_WRITE_DOCS=1 cargo test -p egoslam run_options_table` rewrites it (and
/// still fails, so that a rewrite is always looked at before it is committed).
#[cfg(test)]
mod docs_table {
    use super::Cli;
    use clap::CommandFactory;

    const BEGIN: &str = "<!-- egoslam run options: begin (generated from services/egoslam/src/cli.rs, do not edit) -->";
    const END: &str = "<!-- egoslam run options: end -->";

    /// One row per option of `egoslam run`: flag and value name, default, help text (and
    /// its environment variable).
    fn run_options_markdown() -> String {
        let command = Cli::command();
        let run = command.find_subcommand("run").expect("the run subcommand");
        let mut table = String::from("| option | default | meaning |\n|---|---|---|\n");
        for arg in run.get_arguments().filter(|a| !a.is_hide_set()) {
            let Some(long) = arg.get_long() else { continue };
            if long == "help" || long == "version" {
                continue;
            }
            let takes_value = arg.get_action().takes_values();
            let value = match arg.get_value_names().and_then(|v| v.first()) {
                _ if !takes_value => String::new(),
                Some(name) => format!(" {name}"),
                None => format!(" {}", arg.get_id().as_str().to_uppercase()),
            };
            let defaults: Vec<String> = arg
                .get_default_values()
                .iter()
                .map(|v| v.to_string_lossy().into_owned())
                .collect();
            let default = if !takes_value {
                "off".to_string()
            } else if defaults.is_empty() {
                "-".to_string()
            } else {
                format!("`{}`", defaults.join(" "))
            };
            let help = arg
                .get_long_help()
                .or(arg.get_help())
                .map(|h| {
                    h.to_string()
                        .split_whitespace()
                        .collect::<Vec<_>>()
                        .join(" ")
                })
                .unwrap_or_default()
                .replace('|', "\\|");
            let env = arg
                .get_env()
                .map(|e| format!(" (env `{}`)", e.to_string_lossy()))
                .unwrap_or_default();
            table.push_str(&format!(
                "| `--{long}{value}` | {default} | {help}{env} |\n"
            ));
        }
        table
    }

    #[test]
    fn run_options_table() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/config.md");
        let doc = std::fs::read_to_string(&path).expect("docs/config.md");
        let (Some(begin), Some(end)) = (doc.find(BEGIN), doc.find(END)) else {
            panic!("docs/config.md lacks the markers {BEGIN} ... {END}");
        };
        let current = &doc[begin + BEGIN.len()..end];
        let wanted = format!("\n{}", run_options_markdown());
        if current == wanted {
            return;
        }
        if std::env::var_os("EGOSLAM_WRITE_DOCS").is_some() {
            let rewritten = format!("{}{BEGIN}{wanted}{}", &doc[..begin], &doc[end..]);
            std::fs::write(&path, rewritten).expect("writing docs/config.md");
            panic!("docs/config.md's options table rewritten: review and commit it");
        }
        panic!(
            "docs/config.md's options table is stale: run \
             EGOSLAM_WRITE_DOCS=1 cargo test -p egoslam run_options_table"
        );
    }
}
