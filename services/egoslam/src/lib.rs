//! `egoslam`: the launcher and, as subcommands, the services it starts.
//!
//! One multi-call binary keeps deployment simple (one file on the wearable box, one build)
//! while every service still runs as its own process, linked to the others by iceoryx2.
//! The services also build as lean binaries of their own (`egoslam-frontend`,
//! `egoslam-solver`, `egoslam-merger`, src/bin/): the multi-call binary links OpenCV's
//! video and image decoding, which load ~250 shared libraries at every start (0.15 s of
//! CPU each time, against 0.003 s for the ~28 a service needs, and ~15 MiB of relocated
//! data per process), and `egoslam run` starts its services again after a fault.

mod calibration;
pub mod cli;
mod commands;
mod config;
#[cfg(test)]
mod fuzz_tests;
mod option_checks;
mod options;
mod replay;
mod supervision;

use clap::{CommandFactory, FromArgMatches};
use std::ffi::OsString;

/// What a command line runs once parsed: every command ([`run_command`]), or one service
/// (the lean service binaries, [`run_frontend`] and its siblings).
pub type Dispatch = fn(cli::Cli) -> anyhow::Result<()>;

/// The program: parses `argv` (with the configuration file), sets up logging and runs
/// `dispatch` on the parsed command line.
pub fn main_with(argv: Vec<OsString>, dispatch: Dispatch) -> std::process::ExitCode {
    main_of(cli::Cli::command(), argv, dispatch)
}

/// The program of a lean service binary (`egoslam-SERVICE`): `egoslam SERVICE`'s command
/// line ([`service_argv`]), whose usage names the binary alone.
pub fn main_service(service: &str, dispatch: Dispatch) -> std::process::ExitCode {
    let binary = egoslam_runtime::process_role::lean_binary_name(service);
    let command = cli::Cli::command()
        .mut_subcommand(service, |c| c.override_usage(format!("{binary} [OPTIONS]")));
    main_of(command, service_argv(service), dispatch)
}

fn main_of(
    command: clap::Command,
    argv: Vec<OsString>,
    dispatch: Dispatch,
) -> std::process::ExitCode {
    // Egocentric video shows the wearer's life: everything egoslam writes (results, state,
    // logs, saved maps) is for its owner only (files 0600, folders 0700).
    // SAFETY: umask(2) only sets the process's file mode mask.
    unsafe { libc::umask(0o077) };
    let matches = match config::parse_command_line(command, argv) {
        Ok(m) => m,
        Err(e) => {
            eprintln!("error: {e:#}");
            return std::process::ExitCode::from(2);
        }
    };
    let cli = match cli::Cli::from_arg_matches(&matches) {
        Ok(c) => c,
        Err(e) => e.exit(),
    };
    init_tracing(cli.verbose);
    // Usage errors exit with 2, as clap's own do.
    if let Err(e) = option_checks::validate(&cli.command) {
        eprintln!("error: {e}");
        return std::process::ExitCode::from(2);
    }
    let result = dispatch(cli);
    egoslam_runtime::systemd::notify("STOPPING=1");
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => match e.downcast_ref::<supervision::launcher::Interrupted>() {
            Some(stop) => {
                eprintln!("{stop}");
                std::process::ExitCode::from(u8::try_from(128 + stop.signal).unwrap_or(1))
            }
            None if e.downcast_ref::<egoslam_bus::StoppedBySignal>().is_some() => {
                // A service stopped as services are (systemd, the launcher): not an error
                // to print, but still not a finished stream (the exit status says so).
                tracing::info!("{e:#}");
                std::process::ExitCode::FAILURE
            }
            None => {
                eprintln!("error: {e:#}");
                std::process::ExitCode::FAILURE
            }
        },
    }
}

/// Libraries' lines an operator has no use for: zenoh's and foxglove's sessions and clients
/// coming and going, and zenoh's warning that gossip is off (egoslam turns it off: peers
/// connect explicitly).
pub const QUIET_TARGETS: &str = "zenoh=warn,foxglove=warn,zenoh::net::routing::hat::peer=error";

fn init_tracing(verbose: u8) {
    let default = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    // zenoh's and foxglove's own INFO lines (sessions and clients coming and going) are
    // noise to an operator.
    let filter = tracing_subscriber::EnvFilter::try_from_env("EGOSLAM_LOG").unwrap_or_else(|_| {
        tracing_subscriber::EnvFilter::new(format!("{default},{QUIET_TARGETS}"))
    });
    // EGOSLAM_LOG_FORMAT=json: one JSON object per line, for journald (the systemd units).
    // Colour only on a terminal: a log file or a pipe gets plain lines.
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(|| supervision::progress::LogWriter)
        .with_ansi(colour)
        .with_target(false);
    if std::env::var("EGOSLAM_LOG_FORMAT").is_ok_and(|f| f == "json") {
        builder.json().with_current_span(true).init();
    } else {
        builder.init();
    }
}

/// Every command of the `egoslam` binary.
pub fn run_command(cli: cli::Cli) -> anyhow::Result<()> {
    match cli.command {
        cli::Command::Run(args) => supervision::launcher::run(args),
        cli::Command::Eval(args) => egoslam_evaluation::run(args),
        cli::Command::Export(args) => commands::export::run(args),
        cli::Command::View(args) => supervision::live_view::view(args),
        cli::Command::Synth(args) => commands::synth::run(args),
        cli::Command::CalibrateReadout(args) => calibration::readout::calibrate(args),
        cli::Command::Bench(args) => egoslam_bench::run(args, cli.config.as_deref()),
        cli::Command::Localize(args) => commands::relocalization::localize(args),
        cli::Command::Vocab(cli::VocabCommand::Train(args)) => {
            commands::relocalization::vocab_train(args)
        }
        cli::Command::Replay(args) => replay::run(args),
        cli::Command::Frontend(_) => run_frontend(cli),
        cli::Command::Solver(_) => run_solver(cli),
        cli::Command::Merger(_) => run_merger(cli),
    }
}

/// The frontend service alone (the `egoslam-frontend` binary).
pub fn run_frontend(cli: cli::Cli) -> anyhow::Result<()> {
    match cli.command {
        cli::Command::Frontend(args) => egoslam_frontend_service::run(args.frontend_options()),
        _ => anyhow::bail!("not a frontend command line"),
    }
}

/// The solver service alone (the `egoslam-solver` binary).
pub fn run_solver(cli: cli::Cli) -> anyhow::Result<()> {
    match cli.command {
        cli::Command::Solver(args) => args.solver_options().and_then(egoslam_solver_service::run),
        _ => anyhow::bail!("not a solver command line"),
    }
}

/// The merger service alone (the `egoslam-merger` binary).
pub fn run_merger(cli: cli::Cli) -> anyhow::Result<()> {
    match cli.command {
        cli::Command::Merger(args) => egoslam_merger_service::run(args.merger_options()),
        _ => anyhow::bail!("not a merger command line"),
    }
}

/// This process's arguments as those of `egoslam SERVICE ...`: what a lean service binary
/// (`egoslam-SERVICE ...`) parses, so that it takes every flag and configuration key the
/// multi-call binary's subcommand does.
fn service_argv(service: &str) -> Vec<OsString> {
    let mut args = std::env::args_os();
    let mut argv: Vec<OsString> = args.next().into_iter().collect();
    let rest: Vec<OsString> = args.collect();
    // The version is the program's, asked of it before any subcommand.
    if !matches!(rest.as_slice(), [flag] if flag == "--version" || flag == "-V") {
        argv.push(service.into());
    }
    argv.extend(rest);
    argv
}
