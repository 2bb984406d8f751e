//! Guards against gradients that candle drops without a word (fused kernels applied without a
//! backward pass: `LayerNorm` once, the attention softmax after it). Two checks that any such
//! op fails: every parameter of a model that has taken a training step receives a non-zero
//! gradient, and the denoiser's gradient w.r.t. its input, which guidance through the denoiser
//! uses, equals central finite differences in f64.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};

use crate::io::{load_scene, LoadOptions};
use crate::model::{Denoiser, Pca, Scores};
use crate::scene::Scene;
use crate::train::dataset::residual_futures;
use crate::train::rng::Rng;
use crate::train::trainer::{loss, tiny_config};
use crate::train::{build, train, windows, Batch, Goals, Normaliser, TrainConfig, Window};

fn scenes() -> Vec<Scene> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
    ["highway.yaml", "highway_cut_in.yaml", "highway_crash.yaml"]
        .iter()
        .map(|f| load_scene(&dir.join(f), 0, &LoadOptions::default()).unwrap())
        .collect()
}

/// A batch of the tiny configuration's windows, with a normaliser fitted on them.
fn batch(cfg: &TrainConfig, norm: Option<&Normaliser>) -> (Batch, Normaliser) {
    let w: Vec<Window> = scenes()
        .iter()
        .flat_map(|s| windows(s, &cfg.window))
        .collect();
    let norm = norm.cloned().unwrap_or_else(|| {
        let futures = residual_futures(&w, &cfg.window);
        Normaliser::new(Pca::fit(&futures, cfg.model.k).unwrap(), cfg.edm.sigma_data)
    });
    // Windows from different scenes, one rotated, so that every lane connectivity kind and
    // several agent counts occur.
    let picked: Vec<Window> = (0..cfg.batch)
        .map(|i| w[(i * 7) % w.len()].rotated(0.3 * i as f64))
        .collect();
    let refs: Vec<&Window> = picked.iter().collect();
    (
        build(
            &refs,
            &cfg.window,
            &norm,
            Goals::Drawn { keep: 0.5, seed: 5 },
            &Device::Cpu,
        )
        .unwrap(),
        norm,
    )
}

/// The tiny configuration, with the lanes' nearest points among the agent-lane pair features.
fn with_nearest_lane_pose(mut cfg: TrainConfig) -> TrainConfig {
    cfg.window.nearest_lane_pose = true;
    cfg.model.agent_lane_features = cfg.window.agent_lane_features();
    cfg
}

/// The tiny configuration, with agents' end points as inputs.
fn with_goals(mut cfg: TrainConfig) -> TrainConfig {
    cfg.window.goals = true;
    cfg.model.goals = true;
    cfg
}

/// The tiny configuration, measuring each agent's noisy future against the lanes at three
/// times.
fn with_route(mut cfg: TrainConfig) -> TrainConfig {
    cfg.window.route_times = 3;
    cfg.model.route_times = 3;
    cfg
}

/// The tiny configuration, with futures told against lane routes and the route as an input.
fn with_route_frame(mut cfg: TrainConfig) -> TrainConfig {
    cfg.window.route_frame = true;
    cfg.model.route_frame = true;
    cfg
}

#[test]
fn every_parameter_receives_a_gradient_after_a_training_step() {
    for cfg in [
        tiny_config(1, 3, 1),
        with_nearest_lane_pose(tiny_config(1, 3, 1)),
        with_route(tiny_config(1, 3, 1)),
        with_goals(tiny_config(1, 3, 1)),
        with_route_frame(tiny_config(1, 3, 1)),
        TrainConfig {
            across_weight: 4.0,
            ..tiny_config(1, 3, 1)
        },
    ] {
        every_parameter_receives_a_gradient(cfg);
    }
}

#[test]
fn the_across_path_error_is_weighed_apart_and_linearly() {
    let cfg = tiny_config(1, 3, 1);
    let t = train(&scenes(), cfg.clone(), None, None, |_, _, _| ()).unwrap();
    let (b, _) = batch(&cfg, Some(&t.meta.normaliser));
    // Normals: unit, across the recorded heading, where a target's future step is observed;
    // zero elsewhere.
    let normals: Vec<f32> = b.normals.flatten_all().unwrap().to_vec1().unwrap();
    let seen: Vec<f32> = b.seen.flatten_all().unwrap().to_vec1().unwrap();
    let mut unit = 0;
    for (nv, sv) in normals.chunks(3).zip(seen.chunks(3)) {
        let len = (nv[0] * nv[0] + nv[1] * nv[1]).sqrt();
        assert_eq!(nv[2], 0.0);
        if sv[0] == 1.0 {
            assert!((len - 1.0).abs() < 1e-5, "{nv:?}");
            unit += 1;
        } else {
            assert_eq!(len, 0.0, "{nv:?}");
        }
    }
    assert!(unit > 0);
    let dims = b.target.dims3().unwrap();
    let mut rng = Rng::new(3);
    let noise: Vec<f32> = (0..dims.0 * dims.1 * dims.2)
        .map(|_| rng.normal() as f32)
        .collect();
    let noise = Tensor::from_vec(noise, dims, &Device::Cpu).unwrap();
    let sigma = [0.5, 2.0, 5.0, 20.0];
    let at = |w: f64| {
        loss(&t.model, &cfg.edm, &b, &sigma[..cfg.batch], &noise, w)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap() as f64
    };
    let (plain, two, five) = (at(1.0), at(2.0), at(5.0));
    // The across part is counted once in the plain error and w - 1 times more.
    let across = two - plain;
    assert!(across > 0.0 && across < plain, "{plain} {two}");
    assert!(
        ((five - plain) - 4.0 * across).abs() < 1e-3 * five,
        "{plain} {two} {five}"
    );
}

fn every_parameter_receives_a_gradient(cfg: TrainConfig) {
    // One step first: the output layer starts at zero, which blocks every gradient upstream
    // of it at step 0.
    let t = train(&scenes(), cfg.clone(), None, None, |_, _, _| ()).unwrap();
    let (b, _) = batch(&cfg, Some(&t.meta.normaliser));
    let dims = b.target.dims3().unwrap();
    let mut rng = Rng::new(11);
    let noise: Vec<f32> = (0..dims.0 * dims.1 * dims.2)
        .map(|_| rng.normal() as f32)
        .collect();
    let noise = Tensor::from_vec(noise, dims, &Device::Cpu).unwrap();
    let sigma = [0.05, 0.5, 2.0, 20.0];
    let l = loss(&t.model, &cfg.edm, &b, &sigma[..cfg.batch], &noise, 1.0).unwrap();
    let grads = l.backward().unwrap();
    let data = t.varmap.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut missing = Vec::new();
    for name in names {
        let norm = grads.get(data[name].as_tensor()).map(|g| {
            g.sqr()
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap()
        });
        match norm {
            Some(n) if n > 0.0 && n.is_finite() => {}
            Some(n) => missing.push(format!("{name} (|g|² = {n})")),
            None => missing.push(format!("{name} (no gradient at all)")),
        }
    }
    assert!(
        missing.is_empty(),
        "parameters that receive no gradient: {}",
        missing.join(", ")
    );
}

/// A small f64 denoiser with every weight and bias random (non-zero), so that every path
/// carries gradient.
fn f64_model(cfg: &TrainConfig) -> Denoiser {
    let vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F64, &Device::Cpu);
    let model = Denoiser::new(cfg.model, cfg.edm, vb).unwrap();
    let data = vm.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut rng = Rng::new(5);
    for name in names {
        let var: &Var = &data[name];
        let dims = var.dims().to_vec();
        let n: usize = dims.iter().product();
        let scale = if dims.len() == 1 {
            0.2
        } else {
            1.0 / (dims[dims.len() - 1] as f64).sqrt()
        };
        let gain = if name.contains(".ln") && name.ends_with("weight") {
            1.0
        } else {
            0.0
        };
        let v: Vec<f64> = (0..n).map(|_| gain + scale * rng.normal()).collect();
        var.set(&Tensor::from_vec(v, dims.as_slice(), &Device::Cpu).unwrap())
            .unwrap();
    }
    model
}

#[test]
fn the_input_gradient_matches_central_finite_differences_in_f64() {
    // Both forms of the scores: checkpoints of either kind guide samples.
    for scores in [Scores::Normalised, Scores::Raw] {
        let mut cfg = tiny_config(1, 3, 1);
        cfg.model.scores = scores;
        input_gradient_matches_finite_differences(&cfg);
    }
    input_gradient_matches_finite_differences(&with_nearest_lane_pose(tiny_config(1, 3, 1)));
    // The route features' choice of nearest lane point is piecewise constant in the input;
    // between switches their gradient is the decoded pose's.
    input_gradient_matches_finite_differences(&with_route(tiny_config(1, 3, 1)));
    input_gradient_matches_finite_differences(&with_route_frame(tiny_config(1, 3, 1)));
}

fn input_gradient_matches_finite_differences(cfg: &TrainConfig) {
    let model = f64_model(cfg);
    let (b, _) = batch(cfg, None);
    let ctx = b.ctx.to_dtype(DType::F64).unwrap();
    let map = model.encode_scene(&ctx).unwrap();
    let dims = b.target.dims3().unwrap();
    let n = dims.0 * dims.1 * dims.2;
    let mut rng = Rng::new(9);
    let x0: Vec<f64> = (0..n).map(|_| rng.normal()).collect();
    let g: Vec<f64> = (0..n).map(|_| rng.normal()).collect();
    let gt = Tensor::from_vec(g.clone(), dims, &Device::Cpu).unwrap();
    for sigma in [0.5, 3.0] {
        let sig = vec![sigma; dims.0];
        // L(x) = Σ D(x)·g: its gradient is Jᵀg, exactly what guidance pulls back.
        let value = |x: &[f64]| -> f64 {
            let x = Tensor::from_vec(x.to_vec(), dims, &Device::Cpu).unwrap();
            let d = model.denoise(&ctx, &map, &x, &sig).unwrap();
            (d * &gt).unwrap().sum_all().unwrap().to_scalar().unwrap()
        };
        let xv = Var::from_vec(x0.clone(), dims, &Device::Cpu).unwrap();
        let d = model.denoise(&ctx, &map, xv.as_tensor(), &sig).unwrap();
        let grads = (d * &gt).unwrap().sum_all().unwrap().backward().unwrap();
        let analytic: Vec<f64> = grads
            .get(xv.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let scale = analytic.iter().fold(0f64, |m, v| m.max(v.abs()));
        let h = 1e-5;
        let mut worst = (0.0, 0);
        for i in 0..n {
            let (mut p, mut m) = (x0.clone(), x0.clone());
            p[i] += h;
            m[i] -= h;
            let fd = (value(&p) - value(&m)) / (2.0 * h);
            let err = (fd - analytic[i]).abs();
            if err > worst.0 {
                worst = (err, i);
            }
        }
        assert!(
            worst.0 <= 1e-6 * scale.max(1.0),
            "{:?}, σ = {sigma}: input {} has analytic gradient {} but finite differences disagree by {} (largest gradient {scale})",
            cfg.model.scores,
            worst.1,
            analytic[worst.1],
            worst.0
        );
    }
}

#[test]
fn the_frozen_model_gives_the_same_input_gradient_and_tracks_no_weight() {
    let cfg = tiny_config(3, 4, 3);
    let t = train(&scenes(), cfg.clone(), None, None, |_, _, _| ()).unwrap();
    let weights = t.detached_weights();
    let frozen = Denoiser::new(
        cfg.model,
        cfg.edm,
        VarBuilder::from_tensors(weights.clone(), DType::F32, &Device::Cpu),
    )
    .unwrap();
    let (b, _) = batch(&cfg, Some(&t.meta.normaliser));
    let dims = b.target.dims3().unwrap();
    let mut rng = Rng::new(2);
    let x: Vec<f32> = (0..dims.0 * dims.1 * dims.2)
        .map(|_| rng.normal() as f32)
        .collect();
    let sig = vec![0.7; dims.0];
    let mut got: HashMap<&str, Vec<f32>> = HashMap::new();
    for (name, model) in [("trained", &t.model), ("frozen", &frozen)] {
        let map = model.encode_scene(&b.ctx).unwrap();
        let xv = Var::from_vec(x.clone(), dims, &Device::Cpu).unwrap();
        let d = model.denoise(&b.ctx, &map, xv.as_tensor(), &sig).unwrap();
        let out = d.sum_all().unwrap();
        // What the backward pass walks through: every tracked node between the output and
        // the leaves.
        let walked: std::collections::HashSet<_> =
            out.sorted_nodes().iter().map(|t| t.id()).collect();
        if name == "frozen" {
            assert!(
                map.tensors().iter().all(|t| !walked.contains(&t.id())),
                "the frozen model's backward walks through the scene encoding"
            );
            for (k, w) in &weights {
                assert!(
                    !walked.contains(&w.id()),
                    "the frozen model's backward walks through weight {k}"
                );
            }
        } else {
            // The same check on the trainable model finds both: it can fail.
            assert!(map.tensors().iter().all(|t| walked.contains(&t.id())));
            let data = t.varmap.data().lock().unwrap();
            assert!(data.values().all(|v| walked.contains(&v.as_tensor().id())));
        }
        let grads = out.backward().unwrap();
        got.insert(
            name,
            grads
                .get(xv.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap(),
        );
    }
    assert_eq!(got["trained"], got["frozen"]);
}
