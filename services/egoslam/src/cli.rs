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
    /// Configuration file (TOML, docs/config.md): one key per option, in the section its
    /// heading below names (`[solver] window = 12`); flags given on the command line win.
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

/// docs/config.md's tables of the configuration file's keys and of `egoslam run`'s options
/// are generated from the definitions above, so that they cannot drift from them: the test
/// fails while the file's tables differ, and `EGOSLAM_WRITE_DOCS=1 cargo test -p egoslam
/// options_tables` rewrites them (and still fails, so that a rewrite is always looked at
/// before it is committed).
#[cfg(test)]
mod docs_table {
    use super::Cli;
    use clap::CommandFactory;

    const RUN_OPTIONS: (&str, &str) = (
        "<!-- egoslam run options: begin (generated from services/egoslam/src/cli.rs, do not edit) -->",
        "<!-- egoslam run options: end -->",
    );
    const FILE_KEYS: (&str, &str) = (
        "<!-- egoslam config keys: begin (generated from services/egoslam/src/cli.rs, do not edit) -->",
        "<!-- egoslam config keys: end -->",
    );

    /// A help text on one line, safe in a table cell.
    fn one_line(text: Option<&clap::builder::StyledStr>) -> String {
        text.map(|h| {
            h.to_string()
                .split_whitespace()
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_default()
        .replace('|', "\\|")
    }

    /// Up to the first full stop that ends a sentence.
    fn first_sentence(text: &str) -> &str {
        match text.find(". ") {
            Some(end) => &text[..end],
            None => text.trim_end_matches('.'),
        }
    }

    /// The defaults of `arg` as the flag takes them (`off` for an on/off flag).
    fn flag_default(arg: &clap::Arg) -> String {
        let defaults: Vec<String> = arg
            .get_default_values()
            .iter()
            .map(|v| v.to_string_lossy().into_owned())
            .collect();
        if !arg.get_action().takes_values() {
            "off".to_string()
        } else if defaults.is_empty() {
            "-".to_string()
        } else {
            format!("`{}`", defaults.join(" "))
        }
    }

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
            let value = match arg.get_value_names().and_then(|v| v.first()) {
                _ if !arg.get_action().takes_values() => String::new(),
                Some(name) => format!(" {name}"),
                None => format!(" {}", arg.get_id().as_str().to_uppercase()),
            };
            let help = one_line(arg.get_long_help().or(arg.get_help()));
            let env = arg
                .get_env()
                .map(|e| format!(" (env `{}`)", e.to_string_lossy()))
                .unwrap_or_default();
            table.push_str(&format!(
                "| `--{long}{value}` | {} | {help}{env} |\n",
                flag_default(arg)
            ));
        }
        table
    }

    /// One row per key of the configuration file: the flag it stands for, its default as
    /// the file writes it, the commands that take it and the first sentence of its help.
    fn file_keys_markdown() -> String {
        let command = Cli::command();
        let options = crate::config::file_options(&command);
        let mut table =
            String::from("| key | flag | default | commands | meaning |\n|---|---|---|---|---|\n");
        let mut seen = Vec::new();
        for (key, _, arg) in &options {
            if seen.contains(key) {
                continue;
            }
            seen.push(key.clone());
            let readers: Vec<&str> = options
                .iter()
                .filter(|(k, _, _)| k == key)
                .map(|(_, sub, _)| sub.get_name())
                .collect();
            let default = match arg.get_action() {
                clap::ArgAction::SetTrue => "`false`".to_string(),
                clap::ArgAction::SetFalse => "`true`".to_string(),
                _ => flag_default(arg),
            };
            let flag = arg.get_long().unwrap_or_default();
            let inverse = if matches!(arg.get_action(), clap::ArgAction::SetFalse) {
                " (sets false)"
            } else {
                ""
            };
            table.push_str(&format!(
                "| `{key}` | `--{flag}`{inverse} | {default} | {} | {} |\n",
                readers.join(", "),
                first_sentence(&one_line(arg.get_help()))
            ));
        }
        table
    }

    #[test]
    fn options_tables() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/config.md");
        let mut doc = std::fs::read_to_string(&path).expect("docs/config.md");
        let mut stale = Vec::new();
        for ((begin, end), wanted) in [
            (FILE_KEYS, file_keys_markdown()),
            (RUN_OPTIONS, run_options_markdown()),
        ] {
            let (Some(b), Some(e)) = (doc.find(begin), doc.find(end)) else {
                panic!("docs/config.md lacks the markers {begin} ... {end}");
            };
            let wanted = format!("\n{wanted}");
            if doc[b + begin.len()..e] != wanted {
                doc = format!("{}{begin}{wanted}{}", &doc[..b], &doc[e..]);
                stale.push(begin);
            }
        }
        if stale.is_empty() {
            return;
        }
        if std::env::var_os("EGOSLAM_WRITE_DOCS").is_some() {
            std::fs::write(&path, doc).expect("writing docs/config.md");
            panic!("docs/config.md's tables rewritten: review and commit them");
        }
        panic!(
            "docs/config.md's tables are stale ({stale:?}): run \
             EGOSLAM_WRITE_DOCS=1 cargo test -p egoslam options_tables"
        );
    }
}
