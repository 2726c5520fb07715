//! The one configuration file (TOML) that every egoslam process reads: `--config FILE` or
//! `EGOSLAM_CONFIG`; an example in deploy/egoslam.toml, the keys in docs/config.md (generated
//! from the same definitions). Command-line flags (and their environment variables) win over
//! the file, the file wins over built-in defaults.
//!
//! The file has no schema of its own: a key is an option's clap definition (options.rs),
//! named by its help heading and id (`[solver] window` is `--window`, heading "solver", id
//! "window"). Its value goes through the option's own value parser, so the file, the flag
//! and the environment variable are checked by the same code, and becomes the option's
//! default value before the command line is parsed, which gives the precedence above.
//! Unknown keys and bad values are refused at start with a message naming the key.

use anyhow::{bail, Context};
use std::path::{Path, PathBuf};

/// The file key of an option: `section.key` (its help heading and id); options without a
/// heading are not in the file.
pub fn file_key(arg: &clap::Arg) -> String {
    match arg.get_help_heading() {
        Some(section) => format!("{section}.{}", arg.get_id()),
        None => arg.get_id().to_string(),
    }
}

/// Every option the file can set, in every subcommand: (key, subcommand, option).
pub fn file_options(command: &clap::Command) -> Vec<(String, &clap::Command, &clap::Arg)> {
    let mut options = Vec::new();
    for sub in command.get_subcommands() {
        for arg in sub.get_arguments() {
            if arg.get_help_heading().is_some() && arg.get_long().is_some() {
                options.push((file_key(arg), sub, arg));
            }
        }
    }
    options
}

/// One key of the file with its values (several for a list).
#[derive(Debug, Clone, PartialEq)]
struct Setting {
    key: String,
    values: Vec<String>,
}

/// A read and checked configuration file.
#[derive(Debug)]
pub struct ConfigFile {
    settings: Vec<Setting>,
}

/// A scalar of the file as the text a flag would carry.
fn scalar_text(value: &toml::Value) -> Option<String> {
    match value {
        toml::Value::String(s) => Some(s.clone()),
        toml::Value::Integer(i) => Some(i.to_string()),
        toml::Value::Float(f) => Some(f.to_string()),
        toml::Value::Boolean(b) => Some(b.to_string()),
        toml::Value::Datetime(_) | toml::Value::Array(_) | toml::Value::Table(_) => None,
    }
}

/// The leaves of `table` as `section.key` (sections nest: `[zenoh.tls]`).
fn leaves(table: &toml::Table, section: &str, out: &mut Vec<(String, toml::Value)>) {
    for (name, value) in table {
        let key = if section.is_empty() {
            name.clone()
        } else {
            format!("{section}.{name}")
        };
        match value {
            toml::Value::Table(inner) => leaves(inner, &key, out),
            _ => out.push((key, value.clone())),
        }
    }
}

/// Whether `value` is one the option takes, checked by its own value parser (through a
/// command that holds only the option; clap does not expose the parser's check).
fn check_value(arg: &clap::Arg, value: &str) -> Result<(), String> {
    if !arg.get_action().takes_values() {
        // An on/off flag: the file says which.
        return value
            .parse::<bool>()
            .map(drop)
            .map_err(|_| "expected true or false".to_string());
    }
    let long = arg.get_long().unwrap_or_default();
    let alone = arg.clone().env(None::<&str>).required(false);
    clap::Command::new("egoslam")
        .no_binary_name(true)
        .arg(alone)
        .try_get_matches_from([format!("--{long}={value}")])
        .map(drop)
        .map_err(|e| {
            let message = e.to_string();
            let first = message.lines().next().unwrap_or_default();
            first.trim_start_matches("error: ").to_string()
        })
}

impl ConfigFile {
    /// Reads `path` and checks every key and value against `command`'s options.
    pub fn load(path: &Path, command: &clap::Command) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the config file {}", path.display()))?;
        Self::parse(&text, command).with_context(|| format!("config file {}", path.display()))
    }

    fn parse(text: &str, command: &clap::Command) -> anyhow::Result<Self> {
        let table: toml::Table = toml::from_str(text)?;
        let mut found = Vec::new();
        leaves(&table, "", &mut found);
        let options = file_options(command);
        let mut settings = Vec::new();
        for (key, value) in found {
            let Some((_, _, arg)) = options.iter().find(|(k, _, _)| *k == key) else {
                let section = key.rsplit_once('.').map_or("", |(s, _)| s);
                let mut known: Vec<&str> = options
                    .iter()
                    .filter_map(|(k, _, _)| k.strip_prefix(section)?.strip_prefix('.'))
                    .filter(|k| !k.contains('.'))
                    .collect();
                known.sort_unstable();
                known.dedup();
                if known.is_empty() {
                    bail!("unknown key {key}: no section [{section}]");
                }
                bail!("unknown key {key}; [{section}] has {}", known.join(", "));
            };
            let list = matches!(arg.get_action(), clap::ArgAction::Append);
            let values = match (&value, list) {
                (toml::Value::Array(items), true) => items.iter().map(scalar_text).collect(),
                (toml::Value::Array(_), false) => None,
                (v, _) => scalar_text(v).map(|t| vec![t]),
            };
            let Some(values) = values else {
                let expected = if list {
                    "a list of values"
                } else {
                    "one value"
                };
                bail!("{key} = {value}: expected {expected}");
            };
            for v in &values {
                check_value(arg, v).map_err(|e| anyhow::anyhow!("{key} = {v}: {e}"))?;
            }
            settings.push(Setting { key, values });
        }
        Ok(Self { settings })
    }

    /// `command` with the file's values as the defaults of the options they set, in every
    /// subcommand that has them.
    pub fn apply(&self, mut command: clap::Command) -> clap::Command {
        let targets: Vec<(String, String, &Setting)> = file_options(&command)
            .into_iter()
            .filter_map(|(key, sub, arg)| {
                let setting = self.settings.iter().find(|s| s.key == key)?;
                Some((
                    sub.get_name().to_string(),
                    arg.get_id().to_string(),
                    setting,
                ))
            })
            .collect();
        for (sub, id, setting) in targets {
            command = command.mut_subcommand(sub, |s| {
                s.mut_arg(id, |a| a.default_values(setting.values.clone()))
            });
        }
        command
    }
}

/// The command line parsed with the configuration file (`--config` or `EGOSLAM_CONFIG`)
/// applied; a usage error or help exits as clap does, a bad file is an error.
pub fn parse_command_line(
    command: clap::Command,
    argv: Vec<std::ffi::OsString>,
) -> anyhow::Result<clap::ArgMatches> {
    let first = command.clone().get_matches_from(argv.iter());
    let Some(path) = first.get_one::<PathBuf>("config") else {
        return Ok(first);
    };
    let file = ConfigFile::load(path, &command)?;
    Ok(file.apply(command).get_matches_from(argv))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::{Cli, Command};
    use clap::{CommandFactory, FromArgMatches};

    fn parse(text: &str) -> anyhow::Result<ConfigFile> {
        ConfigFile::parse(text, &Cli::command())
    }

    /// `argv` parsed with the file `text` applied.
    fn command_with(text: &str, argv: &[&str]) -> Command {
        let file = parse(text).expect("valid");
        let matches = file
            .apply(Cli::command())
            .try_get_matches_from(argv)
            .expect("args");
        Cli::from_arg_matches(&matches).expect("cli").command
    }

    #[test]
    fn the_shipped_example_is_valid_and_sets_every_key() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/egoslam.toml");
        let file = ConfigFile::load(&path, &Cli::command()).expect("deploy/egoslam.toml");
        let window = file.settings.iter().find(|s| s.key == "solver.window");
        assert_eq!(window.map(|s| s.values.clone()), Some(vec!["20".into()]));
        let listen = file.settings.iter().find(|s| s.key == "zenoh.listen");
        assert_eq!(
            listen.map(|s| s.values.clone()),
            Some(vec!["tcp/127.0.0.1:7447".into()])
        );
        // Every key is there, set or commented out, in its section.
        let text = std::fs::read_to_string(&path).expect("deploy/egoslam.toml");
        let command = Cli::command();
        for (key, _, _) in file_options(&command) {
            let (section, name) = key.rsplit_once('.').expect("a section");
            let body = text
                .split(&format!("[{section}]\n"))
                .nth(1)
                .and_then(|rest| rest.split("\n[").next())
                .unwrap_or_else(|| panic!("deploy/egoslam.toml has no [{section}]"));
            let listed = body.lines().any(|line| {
                let line = line.trim_start_matches('#').trim_start();
                line.starts_with(&format!("{name} ="))
            });
            assert!(listed, "deploy/egoslam.toml does not list {key}");
        }
    }

    #[test]
    fn a_key_taken_by_several_commands_is_one_definition() {
        let command = Cli::command();
        let options = file_options(&command);
        let text = |arg: &clap::Arg| {
            let help = arg.get_help().map(|h| h.to_string());
            let defaults: Vec<_> = arg.get_default_values().to_vec();
            (help, defaults, arg.get_long().map(str::to_string))
        };
        for (key, sub, arg) in &options {
            let (_, first_sub, first) = options
                .iter()
                .find(|(k, _, _)| k == key)
                .expect("the key itself");
            assert_eq!(
                text(arg),
                text(first),
                "{key} differs between {} and {}",
                first_sub.get_name(),
                sub.get_name()
            );
        }
    }

    #[test]
    fn unknown_keys_and_bad_values_name_the_key() {
        for (text, named) in [
            ("[solver]\nwindw = 20\n", "windw"),
            ("[sovler]\nwindow = 20\n", "sovler"),
            ("[solver]\nwindow = \"twenty\"\n", "solver.window"),
            ("[solver]\nwindow = 40\n", "solver.window = 40"),
            ("[frontend]\ntracks = 1000000000\n", "frontend.tracks"),
            ("[frontend]\nlk_window = 10\n", "frontend.lk_window"),
            (
                "[frontend]\nrolling_shutter_ms = 500\n",
                "rolling_shutter_ms",
            ),
            ("[frontend]\ncalibrate_radial = 3\n", "calibrate_radial"),
            ("[zenoh]\nlisten = [\"127.0.0.1:7447\"]\n", "127.0.0.1:7447"),
            ("[zenoh]\ndevice = [\"a\", \"b\"]\n", "zenoh.device"),
            ("[zenoh.tls]\nmutal = true\n", "mutal"),
            ("[map]\nextends = \"x\"\n", "extends"),
        ] {
            let e = parse(text).expect_err(text);
            assert!(format!("{e:#}").contains(named), "{text}: {e:#}");
        }
        let e = parse("[solver]\nwindw = 20\n").expect_err("unknown");
        assert!(
            format!("{e:#}").contains("loop_closures"),
            "lists the keys: {e:#}"
        );
        for text in [
            "[merger]\nglobal_ba_px = inf\n",
            "[frontend]\nrolling_shutter_ms = 20\ncalibrate_radial = true\n",
            "[frontend]\nrolling_shutter_ms = \"auto\"\ncalibrate_radial = \"auto\"\n",
        ] {
            parse(text).expect(text);
        }
    }

    #[test]
    fn flags_win_over_the_file_and_the_file_over_defaults() {
        let text = "[solver]\nwindow = 12\noverlap = 4\n[zenoh]\ndevice = \"glasses\"\n";
        let Command::Solver(a) = command_with(text, &["egoslam", "solver", "--overlap", "6"])
        else {
            panic!("solver")
        };
        assert_eq!(a.pipeline.window, 12, "from the file");
        assert_eq!(a.pipeline.overlap, 6, "the flag wins");
        assert_eq!(a.egress.device, "glasses");
        assert_eq!(a.pipeline.tracks, 1000, "built-in default");
    }

    #[test]
    fn the_input_output_and_map_sections_reach_their_commands() {
        let text = "[input]\npath = \"/dev/video0\"\nfps = 15\nrealtime = true\n\
                    calibration = \"/etc/egoslam/camera.yaml\"\n[output]\ndir = \"/var/lib/egoslam\"\n\
                    [map]\nextend = \"/var/lib/egoslam/home.egomap\"\nsave = \"today.egomap\"\n\
                    [bus]\nnamespace = \"glasses\"\n";
        let Command::Run(run) = command_with(text, &["egoslam", "run"]) else {
            panic!("run")
        };
        assert_eq!(run.sequence.input, Some(PathBuf::from("/dev/video0")));
        assert_eq!(
            run.calibration.calib,
            Some(PathBuf::from("/etc/egoslam/camera.yaml"))
        );
        assert_eq!((run.sequence.rate.fps, run.sequence.realtime), (15.0, true));
        assert_eq!(run.output.out, PathBuf::from("/var/lib/egoslam"));
        let Command::Replay(replay) = command_with(text, &["egoslam", "replay"]) else {
            panic!("replay")
        };
        assert_eq!(replay.service.namespace, "glasses");
        for service in ["frontend", "merger"] {
            let (Command::Frontend(a) | Command::Merger(a)) =
                command_with(text, &["egoslam", service])
            else {
                panic!("{service}")
            };
            let home = PathBuf::from("/var/lib/egoslam/home.egomap");
            assert_eq!(a.map.map_in, Some(home), "{service}");
            assert_eq!(a.map.map_out, Some(PathBuf::from("today.egomap")));
        }
    }

    #[test]
    fn the_tls_section_reaches_the_network_options() {
        let text = "[zenoh]\nlisten = [\"tls/0.0.0.0:7447\"]\nremote_read_only = true\n\
             [zenoh.tls]\nroot_ca = \"/etc/egoslam/ca.pem\"\n\
             certificate = \"/etc/egoslam/box.pem\"\nprivate_key = \"/etc/egoslam/box.key\"\n\
             mutual = true\nallowed_common_names = [\"viewer\"]\n";
        let Command::Merger(a) = command_with(text, &["egoslam", "merger"]) else {
            panic!("merger")
        };
        let network = a.egress.network();
        assert_eq!(network.listen, vec!["tls/0.0.0.0:7447".to_string()]);
        assert!(network.remote_read_only);
        let tls = network.tls.expect("tls");
        assert_eq!(tls.certificate, Some(PathBuf::from("/etc/egoslam/box.pem")));
        assert!(tls.mutual);
        assert_eq!(tls.allowed_common_names, vec!["viewer".to_string()]);
        let writable = "[zenoh]\nremote_read_only = false\n";
        let Command::Merger(a) = command_with(writable, &["egoslam", "merger"]) else {
            panic!("merger")
        };
        assert!(!a.egress.network().remote_read_only);
        let Command::Merger(a) = command_with("", &["egoslam", "merger"]) else {
            panic!("merger")
        };
        assert!(a.egress.network().remote_read_only, "read-only by default");
    }
}
