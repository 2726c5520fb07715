//! The ranges of option values. Each is the value parser of its flag (options.rs), so a
//! flag, its environment variable and its configuration-file key (config.rs) are checked
//! by the same code, before any work: a value out of range is refused with the option named
//! and exit code 2, never passed on to OpenCV (which aborts on an LK window of 2) or to an
//! allocation (which aborts on 10^9 tracks). What spans two options is checked once they
//! are merged ([`validate`]).

use crate::cli::Command;
use crate::options::PipelineArgs;

/// A number in `[min, max]` (NaN never is).
fn number_within(text: &str, min: f64, max: f64) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if (min..=max).contains(&v) => Ok(v),
        Ok(v) => Err(format!("{v} is not between {min} and {max}")),
        Err(e) => Err(format!("{text:?}: {e}")),
    }
}

/// `--keyframe-flow-px`: 0.1-1000 pixels.
pub fn flow_px(text: &str) -> Result<f64, String> {
    number_within(text, 0.1, 1000.0)
}

/// `--fps`: 0.1-1000 frames per second.
pub fn frame_rate(text: &str) -> Result<f64, String> {
    number_within(text, 0.1, 1000.0)
}

/// `--lk-window`: odd, 3-51 pixels.
pub fn lk_window(text: &str) -> Result<i32, String> {
    match text.trim().parse::<i32>() {
        Ok(v) if !(3..=51).contains(&v) => Err(format!("{v} is not between 3 and 51")),
        Ok(v) if v % 2 == 0 => Err(format!("{v} is not odd")),
        Ok(v) => Ok(v),
        Err(e) => Err(format!("{text:?}: {e}")),
    }
}

/// A positive threshold; `inf` (allowed) disables what it starts, NaN is refused.
pub fn positive_or_inf(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v > 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not positive (inf: never)")),
        Err(e) => Err(format!("{text:?}: {e}")),
    }
}

/// A retention in minutes: finite and not negative.
pub fn non_negative_minutes(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(m) if m.is_finite() && m >= 0.0 => Ok(m),
        _ => Err(format!("{text:?}: minutes, a number >= 0 (0: no limit)")),
    }
}

/// A zenoh endpoint, `PROTOCOL/ADDRESS`, or `none`.
pub fn zenoh_endpoint(text: &str) -> Result<String, String> {
    if text == "none" || text.contains('/') {
        Ok(text.to_string())
    } else {
        Err(format!(
            "{text:?}: expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447"
        ))
    }
}

/// Options that are valid alone but not together.
#[derive(Debug, thiserror::Error)]
#[error("--{flag} = {value} (config {key}): {problem}")]
pub struct InvalidOption {
    /// The command-line flag, without the dashes.
    pub flag: String,
    /// The configuration file's key.
    pub key: String,
    pub value: String,
    pub problem: String,
}

impl InvalidOption {
    /// The option whose clap id is `id`, named as a flag and as a file key.
    fn of(id: &str, value: impl ToString, problem: String) -> Self {
        let command = <crate::cli::Cli as clap::CommandFactory>::command();
        let run = command.find_subcommand("run");
        let arg = run.and_then(|r| r.get_arguments().find(|a| a.get_id() == id));
        Self {
            flag: arg.and_then(|a| a.get_long()).unwrap_or(id).to_string(),
            key: arg.map_or_else(|| id.to_string(), crate::config::file_key),
            value: value.to_string(),
            problem,
        }
    }
}

impl PipelineArgs {
    /// What spans two options: the windows' overlap must leave each window new keyframes.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        if self.overlap >= usize::from(self.window) {
            return Err(InvalidOption::of(
                "overlap",
                self.overlap,
                format!("must be below the window ({})", self.window),
            ));
        }
        Ok(())
    }
}

/// Checks the options of `command` (after the configuration file was applied).
pub fn validate(command: &Command) -> Result<(), InvalidOption> {
    match command {
        Command::Run(a) => a.pipeline.validate(),
        Command::Replay(a) => a.service.pipeline.validate(),
        Command::CalibrateReadout(a) => a.pipeline.validate(),
        Command::Frontend(a) | Command::Solver(a) | Command::Merger(a) => a.pipeline.validate(),
        Command::Eval(_)
        | Command::Export(_)
        | Command::View(_)
        | Command::Synth(_)
        | Command::Bench(_)
        | Command::Localize(_)
        | Command::Vocab(_) => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{CommandFactory, FromArgMatches};

    fn checked(args: &[&str]) -> Result<(), String> {
        let argv = ["egoslam", "run"].iter().chain(args);
        let matches = crate::cli::Cli::command()
            .try_get_matches_from(argv)
            .map_err(|e| e.to_string())?;
        let cli = crate::cli::Cli::from_arg_matches(&matches).map_err(|e| e.to_string())?;
        validate(&cli.command).map_err(|e| e.to_string())
    }

    #[test]
    fn the_defaults_are_valid() {
        checked(&[]).expect("defaults");
    }

    #[test]
    fn values_out_of_range_name_the_flag() {
        for (args, flag) in [
            (&["--tracks", "1000000000"][..], "--tracks"),
            (&["--lk-window", "2"], "--lk-window"),
            (&["--lk-window", "10"], "--lk-window"),
            (&["--keyframe-every", "0"], "--keyframe-every"),
            (&["--keyframe-flow-px", "NaN"], "--keyframe-flow-px"),
            (&["--global-ba-px", "0"], "--global-ba-px"),
            (&["--global-ba-px", "NaN"], "--global-ba-px"),
            (&["--max-point-std=-1"], "--max-point-std"),
            (&["--fps", "0"], "--fps"),
            (&["--zenoh-listen", "127.0.0.1:7447"], "--zenoh-listen"),
        ] {
            let e = checked(args).expect_err(flag);
            assert!(e.contains(flag), "{args:?}: {e}");
        }
        checked(&["--global-ba-px", "inf", "--max-point-std", "inf"]).expect("inf allowed");
    }

    #[test]
    fn an_overlap_as_large_as_the_window_names_the_flag_and_the_key() {
        let e = checked(&["--window", "12", "--overlap", "12"]).expect_err("overlap");
        assert!(
            e.starts_with("--overlap = 12 (config solver.overlap)"),
            "{e}"
        );
        checked(&["--window", "12", "--overlap", "11"]).expect("below the window");
    }
}
