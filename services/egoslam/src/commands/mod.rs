//! The commands a user runs besides `run`: benchmarks, rendering, evaluation, export,
//! relocalization and vocabulary training.

pub mod bench;
pub mod endurance_bench;
pub mod eval;
pub mod eval_plots;
pub mod export;
pub mod latency_bench;
pub mod relocalization;
pub mod synth;
