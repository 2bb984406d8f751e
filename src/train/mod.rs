//! Training the diffusion model: windows cut from scenes, their tensors, and the EDM training
//! loop with checkpoints.

pub mod adamw;
pub mod batch;
pub mod dataset;
pub mod ema;
pub mod export;
pub mod rng;
pub mod store;
pub mod trainer;

pub use batch::{build, Batch, ComponentScale, Goals, Normaliser};
pub use dataset::{window_among, window_at, windows, RouteHint, Window, WindowConfig};
pub use ema::Ema;
pub use export::{export, Exported};
pub use store::{
    check_cache_beside_checkpoint, check_cache_dir, check_export_dir, check_out_dir,
    check_replaces_checkpoint, Corpus, Holdout, SceneWindows, SplitBy, WindowSource, WindowStore,
};
pub use trainer::{
    is_validation, learning_rate, load, load_for_training, save, train, train_from, val_fold,
    CheckpointMeta, CheckpointOrigin, TrainConfig, TrainError, Trained, ONLINE_FILE,
    OPTIMIZER_FILE, VAL_FOLDS,
};
