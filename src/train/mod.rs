//! Training the diffusion model: windows cut from scenes, their tensors, and the EDM training
//! loop with checkpoints.

pub mod adamw;
pub mod batch;
pub mod dataset;
pub mod rng;
pub mod store;
pub mod trainer;

pub use batch::{build, Batch, Normaliser};
pub use dataset::{window_among, window_at, windows, Window, WindowConfig};
pub use store::{Corpus, Holdout, SceneWindows, SplitBy, WindowSource, WindowStore};
pub use trainer::{
    is_validation, learning_rate, load, save, train, train_from, val_fold, CheckpointMeta,
    TrainConfig, TrainError, Trained, OPTIMIZER_FILE, VAL_FOLDS,
};
