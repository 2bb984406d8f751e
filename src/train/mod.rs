//! Training data for the diffusion model: windows cut from scenes.

pub mod dataset;

pub use dataset::{windows, Window, WindowConfig};
