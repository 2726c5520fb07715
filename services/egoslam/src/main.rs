//! The `egoslam` multi-call binary: every command and every service (library: lib.rs).

fn main() -> std::process::ExitCode {
    egoslam::main_with(std::env::args_os().collect(), egoslam::run_command)
}
