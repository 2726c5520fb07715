//! The commands a user runs besides `run`: rendering, evaluation, export, relocalization and
//! vocabulary training (`egoslam bench` is services/bench).

pub mod eval;
pub mod eval_plots;
pub mod export;
pub mod relocalization;
pub mod synth;
