//! The commands a user runs besides `run`: rendering, export, relocalization and vocabulary
//! training (`egoslam bench` is services/bench, `egoslam eval` services/evaluation).

pub mod export;
pub mod relocalization;
pub mod synth;
