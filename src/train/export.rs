//! The training windows as the network's input tensors on disk, for training the same network
//! with another framework on an accelerator (`benches/torch/train.py`): drivescript cuts and
//! encodes the windows, so the two trainers learn from the same numbers, and the other
//! trainer's weights load here as a checkpoint.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};

use super::batch::{build, Goals};
use super::dataset::Window;
use super::rng::Rng;
use super::store::WindowSource;
use super::trainer::{loss, CheckpointMeta, TrainError, Trained};

/// Windows in the loss check (`check.safetensors`).
pub const CHECK_WINDOWS: usize = 8;

/// What [`export`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Exported {
    /// Training windows.
    pub train: usize,
    /// Validation windows.
    pub val: usize,
    /// Files of windows (`train-NNNNN.safetensors`, `val-NNNNN.safetensors`).
    pub shards: usize,
}

/// Writes every window of `source` into `dir` (which must be absent or empty) with the
/// encoding, sizes and normaliser of `from`:
///
/// - `train-NNNNN.safetensors`, `val-NNNNN.safetensors`: up to `per_shard` windows each, the
///   tensors of [`build`] (the context's fields by name, `agent_route` where the checkpoint
///   tells futures against routes, `target`, `loss_mask`, `seen`) with
///   lanes padded to the window's `max_lanes`, so that every file has the same shapes;
/// - `basis.safetensors`: the loss basis (`basis`);
/// - `check.safetensors`: noise levels `sigma`, noise `noise` and the loss `loss` that `from`'s
///   network gives the first [`CHECK_WINDOWS`] training windows: another implementation that
///   reproduces this loss computes what drivescript's trainer computes;
/// - `config.json`: `from`'s metadata with this corpus' scenes and agent types, the start of
///   the checkpoint the other trainer writes.
///
/// `progress(done, total)` is called after each file of windows.
pub fn export(
    source: &dyn WindowSource,
    from: &Trained,
    dir: &Path,
    per_shard: usize,
    mut progress: impl FnMut(usize, usize),
) -> Result<Exported, TrainError> {
    let io = |path: &Path, e: String| TrainError::Io {
        path: path.display().to_string(),
        message: e,
    };
    if per_shard == 0 {
        return Err(TrainError::Config(
            "windows per file must be at least 1".into(),
        ));
    }
    // The port trains the plain error: an export of a run that weighs the across part apart
    // would train another loss than the run's without a word.
    if from.meta.config.across_weight != 1.0 {
        return Err(TrainError::Config(format!(
            "the checkpoint weighs the error across the path {} times (across_weight), which \
             the PyTorch port (benches/torch) does not: it has nothing to export to",
            crate::geom::num(from.meta.config.across_weight)
        )));
    }
    if from.meta.config.window.goals {
        return Err(TrainError::Config(
            "the checkpoint reads agents' end points (window.goals), which the PyTorch port \
             (benches/torch) does not: it has nothing to export to"
                .into(),
        ));
    }
    if from.meta.config.window.route_times > 0 {
        return Err(TrainError::Config(format!(
            "{}: it has nothing to export to",
            crate::model::route::NOT_PORTED
        )));
    }
    if source.train_len() < CHECK_WINDOWS {
        return Err(TrainError::Data(format!(
            "{} training windows: the export's loss check needs at least {CHECK_WINDOWS}",
            source.train_len()
        )));
    }
    match std::fs::read_dir(dir) {
        Ok(mut entries) => {
            if entries.next().is_some() {
                return Err(io(
                    dir,
                    "is not empty: export into a new or empty directory (nothing in it is \
                     replaced)"
                        .into(),
                ));
            }
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            std::fs::create_dir_all(dir).map_err(|e| io(dir, e.to_string()))?;
        }
        Err(e) => return Err(io(dir, e.to_string())),
    }
    let dev = Device::Cpu;
    let meta = &from.meta;
    let mut window = meta.config.window;
    window.pad_lanes = true;
    let norm = &meta.normaliser;
    let save = |name: &str, tensors: HashMap<String, Tensor>| -> Result<(), TrainError> {
        let path = dir.join(name);
        crate::io::write_atomic_from(&path, |p| candle_core::safetensors::save(&tensors, p))
            .map_err(|e| io(&path, e.to_string()))
    };
    let tensors = |ws: &[Window]| -> Result<HashMap<String, Tensor>, TrainError> {
        let refs: Vec<&Window> = ws.iter().collect();
        let b = build(&refs, &window, norm, Goals::Hidden, &dev)?;
        let c = b.ctx;
        let route = c.agent_route.map(|r| ("agent_route".to_string(), r));
        Ok(HashMap::from_iter(route.into_iter().chain([
            ("lane_points".to_string(), c.lane_points),
            ("lane_mask".to_string(), c.lane_mask),
            ("lane_rel".to_string(), c.lane_rel),
            ("lane_conn".to_string(), c.lane_conn),
            ("agent_hist".to_string(), c.agent_hist),
            ("agent_mask".to_string(), c.agent_mask),
            ("agent_lane_rel".to_string(), c.agent_lane_rel),
            ("agent_rel".to_string(), c.agent_rel),
            ("agent_attr".to_string(), c.agent_attr),
            ("target".to_string(), b.target),
            ("loss_mask".to_string(), b.loss_mask),
            ("seen".to_string(), b.seen),
        ])))
    };
    let (nt, nv) = (source.train_len(), source.val_len());
    let files = nt.div_ceil(per_shard) + nv.div_ceil(per_shard);
    let mut written = 0;
    for (kind, len) in [("train", nt), ("val", nv)] {
        for (s, start) in (0..len).step_by(per_shard).enumerate() {
            let ws: Vec<Window> = (start..(start + per_shard).min(len))
                .map(|i| match kind {
                    "train" => source.train_window(i),
                    _ => source.val_window(i),
                })
                .collect::<Result<_, _>>()?;
            save(&format!("{kind}-{s:05}.safetensors"), tensors(&ws)?)?;
            written += 1;
            progress(written, files);
        }
    }
    let first: Vec<Window> = (0..CHECK_WINDOWS)
        .map(|i| source.train_window(i))
        .collect::<Result<_, _>>()?;
    let refs: Vec<&Window> = first.iter().collect();
    let b = build(&refs, &window, norm, Goals::Hidden, &dev)?;
    let edm = &meta.config.edm;
    let mut rng = Rng::new(meta.config.seed ^ 0xE8907);
    let sigma: Vec<f64> = (0..CHECK_WINDOWS)
        .map(|_| edm.train_sigma(rng.normal()))
        .collect();
    let (_, n, k) = b.target.dims3()?;
    let noise: Vec<f32> = (0..CHECK_WINDOWS * n * k)
        .map(|_| rng.normal() as f32)
        .collect();
    let noise = Tensor::from_vec(noise, (CHECK_WINDOWS, n, k), &dev)?;
    let l = loss(&from.model, edm, &b, &sigma, &noise, 1.0)?;
    let sigma = Tensor::from_vec(sigma, CHECK_WINDOWS, &dev)?;
    save(
        "check.safetensors",
        HashMap::from([
            ("sigma".to_string(), sigma),
            ("noise".to_string(), noise),
            ("loss".to_string(), l),
        ]),
    )?;
    save(
        "basis.safetensors",
        HashMap::from([("basis".to_string(), b.basis)]),
    )?;
    let meta = CheckpointMeta {
        train_scenes: source.train_scenes(),
        val_scenes: source.val_scenes(),
        types: source.type_counts(),
        ..meta.clone()
    };
    let json = serde_json::to_string_pretty(&meta).expect("metadata serialises");
    let path = dir.join("config.json");
    crate::io::write_atomic(&path, json.as_bytes()).map_err(|e| io(&path, e.to_string()))?;
    Ok(Exported {
        train: nt,
        val: nv,
        shards: written,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};
    use crate::model::Context;
    use crate::scene::Scene;
    use crate::train::store::SceneWindows;
    use crate::train::trainer::{tiny_config, train};

    fn trained_and_source() -> (Trained, SceneWindows) {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
        let scenes: Vec<Scene> = ["highway.yaml", "highway_cut_in.yaml", "highway_left.yaml"]
            .iter()
            .map(|f| load_scene(&dir.join(f), 0, &LoadOptions::default()).unwrap())
            .collect();
        let cfg = tiny_config(2, 1, 1);
        let source = SceneWindows::new(&scenes, &cfg.window, cfg.val_fold);
        let t = train(&scenes, cfg, None, None, |_, _, _| {}).unwrap();
        (t, source)
    }

    fn temp(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("ds-export-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn the_exported_tensors_give_the_loss_the_trainer_computes() {
        let (trained, source) = trained_and_source();
        assert!(
            source.train_len() >= 2 * CHECK_WINDOWS,
            "{}",
            source.train_len()
        );
        let dir = temp("loss");
        let mut calls = Vec::new();
        let e = export(&source, &trained, &dir, 5, |a, b| calls.push((a, b))).unwrap();
        assert_eq!(e.train, source.train_len());
        assert_eq!(e.val, source.val_len());
        assert_eq!(e.shards, e.train.div_ceil(5) + e.val.div_ceil(5));
        assert_eq!(calls.last(), Some(&(e.shards, e.shards)));
        let read =
            |name: &str| candle_core::safetensors::load(dir.join(name), &Device::Cpu).unwrap();
        // The check's windows span the first two files: joined back, they must be what the
        // trainer's loss saw.
        let (a, b) = (
            read("train-00000.safetensors"),
            read("train-00001.safetensors"),
        );
        let cat = |name: &str| {
            Tensor::cat(&[&a[name], &b[name]], 0)
                .unwrap()
                .narrow(0, 0, CHECK_WINDOWS)
                .unwrap()
        };
        let ctx = Context {
            lane_points: cat("lane_points"),
            lane_mask: cat("lane_mask"),
            lane_rel: cat("lane_rel"),
            lane_conn: cat("lane_conn"),
            agent_hist: cat("agent_hist"),
            agent_mask: cat("agent_mask"),
            agent_lane_rel: cat("agent_lane_rel"),
            agent_rel: cat("agent_rel"),
            agent_attr: cat("agent_attr"),
            route: None,
            agent_goal: None,
            agent_route: None,
        };
        let batch = crate::train::Batch {
            ctx,
            target: cat("target"),
            loss_mask: cat("loss_mask"),
            seen: cat("seen"),
            normals: cat("seen").zeros_like().unwrap(),
            basis: read("basis.safetensors")["basis"].clone(),
        };
        let check = read("check.safetensors");
        let sigma: Vec<f64> = check["sigma"].to_vec1().unwrap();
        let l = loss(
            &trained.model,
            &trained.meta.config.edm,
            &batch,
            &sigma,
            &check["noise"],
            1.0,
        )
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
        let want = check["loss"].to_scalar::<f32>().unwrap();
        assert!(want.is_finite() && want > 0.0, "{want}");
        assert!((l - want).abs() <= 1e-5 * want, "{l} vs {want}");
        // Every file has the padded shapes.
        let lanes = trained.meta.config.window.max_lanes;
        assert_eq!(a["lane_rel"].dims()[1..], [lanes, lanes, 4]);
        let meta: CheckpointMeta =
            serde_json::from_slice(&std::fs::read(dir.join("config.json")).unwrap()).unwrap();
        assert_eq!(meta.train_scenes, source.train_scenes());
        // JSON keeps 17 significant digits: the basis comes back to rounding.
        assert_eq!(meta.normaliser.pca.k(), trained.meta.normaliser.pca.k());
        assert_eq!(meta.config.model.d, trained.meta.config.model.d);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_directory_that_holds_anything_is_refused_and_left_as_it_was() {
        let (trained, source) = trained_and_source();
        let dir = temp("full");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("mine.txt"), "keep").unwrap();
        let e = export(&source, &trained, &dir, 4, |_, _| {})
            .err()
            .expect("refused");
        assert!(e.to_string().contains("is not empty"), "{e}");
        assert_eq!(
            std::fs::read_to_string(dir.join("mine.txt")).unwrap(),
            "keep"
        );
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
