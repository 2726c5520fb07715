//! The frontend service alone: `egoslam frontend` without the code (and the shared libraries: video
//! decoding, image codecs) the other commands need, so that it starts in a fraction of the
//! time. `egoslam run` starts it when it lies next to `egoslam` (supervision/supervisor.rs).

fn main() -> std::process::ExitCode {
    egoslam::main_service("frontend", egoslam::run_frontend)
}
