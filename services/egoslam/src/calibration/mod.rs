//! The calibration estimates `egoslam run` makes from the video before streaming: focal
//! length, radial distortion and the rolling-shutter readout.

pub mod focal;
pub mod readout;
pub mod self_calibration;
pub mod settings;
