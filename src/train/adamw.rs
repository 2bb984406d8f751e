//! AdamW with decoupled weight decay (Loshchilov & Hutter), whose moment estimates and step
//! count are saved beside a checkpoint, so that `train --resume` continues exactly where an
//! uninterrupted run would be (candle-nn's optimiser keeps them private: a resumed run
//! restarted them, and its first steps were large, noisy updates).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{backprop::GradStore, DType, Device, Result, Tensor, Var};
use candle_nn::VarMap;

/// AdamW's constants (β₁ 0.9, β₂ 0.999, ε 1e-8, as in PyTorch and candle-nn).
const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const EPS: f64 = 1e-8;

struct Slot {
    name: String,
    var: Var,
    m: Vec<f32>,
    v: Vec<f32>,
}

/// The optimiser over every variable of a [`VarMap`].
pub struct AdamW {
    slots: Vec<Slot>,
    step: u64,
    /// The training step at which these moments started (0 unless they restarted on a
    /// resumed checkpoint that had none): with [`AdamW::steps`], which training step they
    /// belong to.
    origin: u64,
    /// Learning rate of the next step.
    pub lr: f64,
    /// Decoupled weight decay.
    pub weight_decay: f64,
}

impl AdamW {
    /// Fresh moments (zero) for every variable of `varmap`, in name order.
    pub fn new(varmap: &VarMap, lr: f64, weight_decay: f64) -> Self {
        let data = varmap
            .data()
            .lock()
            .expect("the var map lock is not poisoned");
        let mut slots: Vec<Slot> = data
            .iter()
            .map(|(name, var)| {
                let n = var.elem_count();
                Slot {
                    name: name.clone(),
                    var: var.clone(),
                    m: vec![0.0; n],
                    v: vec![0.0; n],
                }
            })
            .collect();
        slots.sort_by(|a, b| a.name.cmp(&b.name));
        Self {
            slots,
            step: 0,
            origin: 0,
            lr,
            weight_decay,
        }
    }

    /// Steps taken (what the bias correction counts).
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// Fresh moments, as [`AdamW::new`], for training that is already at step `origin`: a
    /// checkpoint resumed without optimiser state.
    pub fn starting_at(varmap: &VarMap, lr: f64, weight_decay: f64, origin: u64) -> Self {
        Self {
            origin,
            ..Self::new(varmap, lr, weight_decay)
        }
    }

    /// The training step these moments are at: [`AdamW::steps`] after the step they started
    /// at.
    pub fn training_step(&self) -> u64 {
        self.origin + self.step
    }

    /// One update from `grads`; variables without a gradient are left as they are.
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.step += 1;
        let t = self.step as i32;
        let (c1, c2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
        let decay = (1.0 - self.lr * self.weight_decay) as f32;
        let (b1, b2) = (BETA1 as f32, BETA2 as f32);
        // Bias corrections folded into the step size and ε: θ -= lr·m̂/(√v̂ + ε).
        let step = (self.lr / c1) as f32;
        let (sc2, eps) = ((1.0 / c2).sqrt() as f32, EPS as f32);
        for s in &mut self.slots {
            let Some(g) = grads.get(s.var.as_tensor()) else {
                continue;
            };
            let g: Vec<f32> = g.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
            let mut theta: Vec<f32> = s.var.as_tensor().flatten_all()?.to_vec1()?;
            for (((th, m), v), g) in theta.iter_mut().zip(&mut s.m).zip(&mut s.v).zip(&g) {
                *m = b1 * *m + (1.0 - b1) * g;
                *v = b2 * *v + (1.0 - b2) * g * g;
                *th = *th * decay - step * *m / (v.sqrt() * sc2 + eps);
            }
            s.var
                .set(&Tensor::from_vec(theta, s.var.shape(), s.var.device())?)?;
        }
        Ok(())
    }

    /// Writes the moments and step count to `path` (safetensors).
    pub fn save(&self, path: &Path) -> Result<()> {
        let dev = Device::Cpu;
        let mut map: HashMap<String, Tensor> = HashMap::new();
        for s in &self.slots {
            map.insert(
                format!("m/{}", s.name),
                Tensor::from_slice(&s.m, s.var.shape(), &dev)?,
            );
            map.insert(
                format!("v/{}", s.name),
                Tensor::from_slice(&s.v, s.var.shape(), &dev)?,
            );
        }
        map.insert("step".into(), Tensor::new(&[self.step as f64], &dev)?);
        map.insert("origin".into(), Tensor::new(&[self.origin as f64], &dev)?);
        candle_core::safetensors::save(&map, path)
    }

    /// Restores what [`AdamW::save`] wrote; every variable must be there with its shape.
    pub fn load(&mut self, path: &Path) -> Result<()> {
        let map = candle_core::safetensors::load(path, &Device::Cpu)?;
        let get = |key: &str, shape: &candle_core::Shape| -> Result<Vec<f32>> {
            let t = map
                .get(key)
                .ok_or_else(|| candle_core::Error::Msg(format!("no tensor {key}")))?;
            if t.shape() != shape {
                candle_core::bail!("{key} has shape {:?}, the model {:?}", t.shape(), shape);
            }
            let v: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
            if v.iter().any(|x| !x.is_finite()) {
                candle_core::bail!("{key} holds non-finite values");
            }
            // Second moments are running means of squares: a negative one (a damaged or
            // hand-edited file) made its weights NaN at the first update, and training wrote
            // them into the checkpoint with exit 0.
            if key.starts_with("v/") {
                if let Some(x) = v.iter().find(|x| **x < 0.0) {
                    candle_core::bail!(
                        "{key} holds {x}: second moments are means of squares, never negative"
                    );
                }
            }
            Ok(v)
        };
        // Moments of variables this model does not have: the state of another model (or a
        // model of other sizes), which loading by name alone accepted without a word.
        let known = |k: &str| {
            k == "step"
                || k == "origin"
                || self.slots.iter().any(|s| {
                    k.strip_prefix("m/")
                        .or_else(|| k.strip_prefix("v/"))
                        .is_some_and(|n| n == s.name)
                })
        };
        let mut extra: Vec<&String> = map.keys().filter(|k| !known(k)).collect();
        if !extra.is_empty() {
            extra.sort();
            candle_core::bail!(
                "holds {} tensors the model has no variable for ({}): the optimiser state of \
                 another model",
                extra.len(),
                crate::io::name::first_few(&extra, 3)
            );
        }
        let mut restored = Vec::with_capacity(self.slots.len());
        for s in &self.slots {
            let shape = s.var.shape();
            restored.push((
                get(&format!("m/{}", s.name), shape)?,
                get(&format!("v/{}", s.name), shape)?,
            ));
        }
        let count = |key: &str| -> Result<u64> {
            let v = map
                .get(key)
                .ok_or_else(|| candle_core::Error::Msg(format!("no tensor {key}")))?
                .to_dtype(DType::F64)?
                .flatten_all()?
                .to_vec1::<f64>()?;
            match v.as_slice() {
                [s] if s.is_finite() && *s >= 0.0 && s.fract() == 0.0 && *s < 1e15 => Ok(*s as u64),
                _ => candle_core::bail!("{key} is not one non-negative integer"),
            }
        };
        let step = count("step")?;
        // Files written before moments could restart mid-run have no origin: they started at 0.
        let origin = if map.contains_key("origin") {
            count("origin")?
        } else {
            0
        };
        for (s, (m, v)) in self.slots.iter_mut().zip(restored) {
            s.m = m;
            s.v = v;
        }
        self.step = step;
        self.origin = origin;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::{Init, VarBuilder};

    /// The error loading a one-variable optimiser's saved state gives once `edit` has changed
    /// the file (the unchanged file loads).
    fn load_error_after(edit: impl FnOnce(&mut HashMap<String, Tensor>, &Device)) -> String {
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        vb.get_with_hints((3, 2), "w", Init::Const(0.5)).unwrap();
        let mut opt = AdamW::new(&vm, 0.01, 0.1);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("optimizer.safetensors");
        opt.save(&path).unwrap();
        opt.load(&path).unwrap();
        let mut map = candle_core::safetensors::load(&path, &dev).unwrap();
        edit(&mut map, &dev);
        candle_core::safetensors::save(&map, &path).unwrap();
        opt.load(&path).unwrap_err().to_string()
    }

    #[test]
    fn negative_second_moments_are_refused_on_load() {
        let e = load_error_after(|map, dev| {
            map.insert(
                "v/w".into(),
                Tensor::new(&[[0f32, -1.0], [0.0, 0.0], [0.0, 0.0]], dev).unwrap(),
            );
        });
        assert!(e.contains("v/w holds -1: second moments"), "{e}");
    }

    #[test]
    fn moments_of_variables_the_model_lacks_are_refused_on_load() {
        let e = load_error_after(|map, dev| {
            map.insert("m/other.weight".into(), Tensor::new(&[1f32], dev).unwrap());
        });
        assert!(
            e.contains("holds 1 tensors the model has no variable for (m/other.weight)"),
            "{e}"
        );
    }

    /// Matches candle-nn's AdamW (the optimiser the earlier checkpoints were trained with) on
    /// a quadratic, step by step.
    #[test]
    fn updates_match_candle_nn_adamw() {
        use candle_nn::Optimizer;
        let dev = Device::Cpu;
        let make = || {
            let vm = VarMap::new();
            let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
            vb.get_with_hints((3, 2), "w", Init::Const(0.5)).unwrap();
            vm
        };
        let (a, b) = (make(), make());
        let mut ours = AdamW::new(&a, 0.01, 0.1);
        let mut theirs = candle_nn::AdamW::new(
            b.all_vars(),
            candle_nn::ParamsAdamW {
                lr: 0.01,
                weight_decay: 0.1,
                ..Default::default()
            },
        )
        .unwrap();
        let target = Tensor::new(&[[1f32, -2.0], [3.0, 0.0], [-1.0, 0.5]], &dev).unwrap();
        for _ in 0..20 {
            for (vm, ours_turn) in [(&a, true), (&b, false)] {
                let w = vm.all_vars().remove(0);
                let loss = (w.as_tensor() - &target)
                    .unwrap()
                    .sqr()
                    .unwrap()
                    .sum_all()
                    .unwrap();
                let g = loss.backward().unwrap();
                if ours_turn {
                    ours.step(&g).unwrap();
                } else {
                    theirs.step(&g).unwrap();
                }
            }
        }
        let (wa, wb) = (a.all_vars().remove(0), b.all_vars().remove(0));
        let diff = (wa.as_tensor() - wb.as_tensor())
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(diff < 1e-5, "{diff}");
    }
}
