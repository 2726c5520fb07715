//! The one validation of option values, whatever their source (flag, environment variable or
//! configuration file): run on the merged options, before any work, so that a value out of
//! range is refused with the option named and exit code 2, never passed on to OpenCV (which
//! aborts on an LK window of 2) or to an allocation (which aborts on 10^9 tracks).

use crate::cli::Command;
use crate::options::PipelineArgs;

/// An option value outside its range.
#[derive(Debug, thiserror::Error)]
#[error("--{flag} = {value} (config {key}): {problem}")]
pub struct InvalidOption {
    /// The command-line flag, without the dashes.
    pub flag: &'static str,
    /// The configuration file's key.
    pub key: &'static str,
    pub value: String,
    pub problem: String,
}

fn invalid(
    flag: &'static str,
    key: &'static str,
    value: impl ToString,
    problem: String,
) -> InvalidOption {
    InvalidOption {
        flag,
        key,
        value: value.to_string(),
        problem,
    }
}

/// `value` within `[min, max]` (NaN never is).
fn within<T: PartialOrd + std::fmt::Display + Copy>(
    flag: &'static str,
    key: &'static str,
    value: T,
    min: T,
    max: T,
) -> Result<(), InvalidOption> {
    if value >= min && value <= max {
        Ok(())
    } else {
        Err(invalid(
            flag,
            key,
            value,
            format!("must be between {min} and {max}"),
        ))
    }
}

/// Positive, `inf` allowed (it disables what the threshold starts), NaN not.
fn positive(
    flag: &'static str,
    key: &'static str,
    value: f64,
    inf_means: &str,
) -> Result<(), InvalidOption> {
    if value > 0.0 {
        Ok(())
    } else {
        Err(invalid(
            flag,
            key,
            value,
            format!("must be positive (inf {inf_means})"),
        ))
    }
}

impl PipelineArgs {
    /// Checks every value's range.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        within(
            "keyframe-every",
            "frontend.keyframe_every",
            self.keyframe_every,
            1,
            1000,
        )?;
        within(
            "keyframe-flow-px",
            "frontend.keyframe_flow_px",
            self.keyframe_flow_px,
            0.1,
            1000.0,
        )?;
        within("tracks", "frontend.tracks", self.tracks, 50, 20_000)?;
        within("lk-window", "frontend.lk_window", self.lk_window, 3, 51)?;
        if self.lk_window % 2 == 0 {
            return Err(invalid(
                "lk-window",
                "frontend.lk_window",
                self.lk_window,
                "must be odd".into(),
            ));
        }
        within(
            "readout-frames",
            "frontend.readout_frames",
            self.readout_frames,
            23,
            10_000,
        )?;
        within("window", "solver.window", self.window, 10, 30)?;
        within(
            "loop-closures",
            "solver.loop_closures",
            self.loop_closures,
            1,
            29,
        )?;
        within(
            "overlap",
            "solver.overlap",
            self.overlap,
            3,
            usize::from(self.window) - 1,
        )?;
        positive(
            "global-ba-px",
            "merger.global_ba_px",
            self.global_ba_px,
            "disables it",
        )?;
        positive(
            "max-point-std",
            "merger.max_point_std",
            self.max_point_std,
            "publishes every point",
        )?;
        within(
            "refinement-lag",
            "merger.refinement_lag",
            self.refinement_lag,
            0,
            1000,
        )?;
        Ok(())
    }
}

fn frame_rate(fps: f64) -> Result<(), InvalidOption> {
    within("fps", "input.fps", fps, 0.1, 1000.0)
}

/// Checks the options of `command` (after the configuration file was applied).
pub fn validate(command: &Command) -> Result<(), InvalidOption> {
    match command {
        Command::Run(a) => {
            frame_rate(a.fps)?;
            a.pipeline.validate()
        }
        Command::Replay(a) => {
            frame_rate(a.fps)?;
            a.service.pipeline.validate()
        }
        Command::CalibrateReadout(a) => {
            frame_rate(a.fps)?;
            a.pipeline.validate()
        }
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

    fn checked(args: &[&str]) -> Result<(), InvalidOption> {
        let argv = ["egoslam", "run"].iter().chain(args);
        let matches = crate::cli::Cli::command()
            .try_get_matches_from(argv)
            .expect("parses");
        let cli = crate::cli::Cli::from_arg_matches(&matches).expect("cli");
        validate(&cli.command)
    }

    #[test]
    fn the_defaults_are_valid() {
        checked(&[]).expect("defaults");
    }

    #[test]
    fn values_out_of_range_name_the_flag_and_the_key() {
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
            (&["--overlap", "20"], "--overlap"),
        ] {
            let e = checked(args).expect_err(flag);
            assert!(e.to_string().starts_with(flag), "{args:?}: {e}");
        }
        checked(&["--global-ba-px", "inf", "--max-point-std", "inf"]).expect("inf allowed");
    }

    #[test]
    fn values_from_the_configuration_file_are_checked_the_same_way() {
        let c: crate::config::Config =
            toml::from_str("[frontend]\ntracks = 1000000000\n").expect("toml");
        let matches = crate::cli::Cli::command()
            .try_get_matches_from(["egoslam", "run"])
            .expect("parses");
        let mut cli = crate::cli::Cli::from_arg_matches(&matches).expect("cli");
        let (_, sub) = matches.subcommand().expect("subcommand");
        crate::config::apply(&c, sub, &mut cli.command);
        let e = validate(&cli.command).expect_err("range");
        assert!(e.to_string().contains("frontend.tracks"), "{e}");
    }
}
