//! Process supervision: the launcher of `egoslam run`, restarts, signals, systemd
//! notifications, and what the terminal shows.

pub mod launcher;
pub mod live_view;
pub mod memory_files;
pub mod progress;
pub mod services;
pub mod stream_calibration;
pub mod supervisor;
