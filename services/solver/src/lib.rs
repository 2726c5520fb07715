//! The window solver (paper, sections 3-4). Keyframes are grouped into overlapping temporal
//! windows ([`windowing`]); each window is solved as a global SfM problem: relative poses on
//! a view graph with local loop closures ([`view_graph`]), robust rotation averaging
//! ([`rotation_averaging`]), translation averaging with camera-to-point constraints
//! ([`translation_averaging`]), triangulation ([`triangulation`]) and bundle adjustment
//! ([`bundle_adjustment`]). One estimator per module, each with an options struct.

pub mod bundle_adjustment;
pub mod detached_keyframes;
pub mod essential_decomposition;
pub mod essential_ransac;
pub mod essential_refinement;
pub mod five_point;
pub mod focal_calibration;
mod huber;
mod normal_equations;
mod refinement_collapse;
pub mod relative_pose;
pub mod retriangulation;
pub mod rotation_averaging;
pub mod schur;
pub mod sparse_schur;
pub mod translation_averaging;
pub mod triangulation;
pub mod unobserved_keyframes;
pub mod view_graph;
pub mod window_solver;
pub mod windowing;

#[cfg(test)]
mod test_support;

pub use windowing::{WindowBuilder, WindowOptions};
