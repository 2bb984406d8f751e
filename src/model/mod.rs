//! The diffusion model (candle): the PCA space of future trajectories, MiniPointNet and agent
//! encoders, relative attention, the denoiser and EDM preconditioning. One concept per file.

pub mod attention;
pub mod denoiser;
pub mod edm;
pub mod encoder;
pub mod error;
#[cfg(test)]
mod gradients;
pub mod ops;
pub mod pca;
pub mod route;

pub use attention::Scores;
pub use denoiser::{
    Context, Denoiser, DenoiserConfig, SceneEncoding, GOAL_FEATURES, ROUTE_FEATURES,
};
pub use edm::Edm;
pub use pca::{Pca, PcaError};
