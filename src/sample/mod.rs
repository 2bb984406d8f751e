//! Sampling from the diffusion model, guided by cost scripts.

pub mod guided;

pub use guided::{prepare, sample, Guidance, Sample, SampleConfig, SampleError, Task};
