//! The calibration settings and estimates of `egoslam run`: the rolling-shutter readout
//! (`egoslam calibrate-readout`), and the focal and radial corrections the services
//! estimate from the stream (supervision/stream_calibration.rs).

pub mod focal;
pub mod readout;
pub mod settings;
