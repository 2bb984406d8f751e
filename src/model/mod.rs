//! The diffusion model's pieces. So far: the PCA space of future trajectories.

pub mod pca;

pub use pca::{Pca, PcaError};
