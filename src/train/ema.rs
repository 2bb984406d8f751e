//! An exponential moving average of the weights, the weights a checkpoint samples with (as in
//! Karras et al.'s EDM). With batches of 8 windows each step's weights carry that step's noise,
//! and a denoiser's errors show as motion: cars that stand in the log creep and jitter. The
//! average over the last few hundred steps keeps what every batch agrees on.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Result, Tensor};
use candle_nn::VarMap;

/// The averaged weights and how many updates they have had.
pub struct Ema {
    weights: HashMap<String, Tensor>,
    /// Steps after which an old step's weight in the average has halved.
    pub half_life: f64,
    /// Updates so far (the warm-up of [`Ema::decay`] counts them).
    pub updates: u64,
}

impl Ema {
    /// An average that starts at `varmap`'s current weights (copied, not shared: the optimiser
    /// writes the variables in place).
    pub fn new(varmap: &VarMap, half_life: f64) -> Result<Self> {
        Ok(Self {
            weights: copies(varmap)?,
            half_life,
            updates: 0,
        })
    }

    /// An average continued from `weights` after `updates` updates.
    pub fn from_weights(weights: HashMap<String, Tensor>, half_life: f64, updates: u64) -> Self {
        Self {
            weights,
            half_life,
            updates,
        }
    }

    /// The share the average keeps at the next update: `0.5^(1/half_life)`, but no more than
    /// `(1 + n) / (10 + n)` after `n` updates, so that an average started from a fresh or
    /// resumed network follows the first steps instead of holding on to where it started.
    pub fn decay(&self) -> f64 {
        let beta = 0.5f64.powf(1.0 / self.half_life.max(1e-9));
        let n = self.updates as f64;
        beta.min((1.0 + n) / (10.0 + n))
    }

    /// Moves the average towards `varmap`'s weights by one step.
    pub fn update(&mut self, varmap: &VarMap) -> Result<()> {
        let beta = self.decay();
        let data = varmap
            .data()
            .lock()
            .expect("the var map lock is not poisoned");
        for (name, var) in data.iter() {
            let now = var.as_tensor().detach();
            // Detached: an average that recorded its op would hold the one before it, and so
            // every average since the start (a cities run reached 24 GB in 3,750 steps).
            let avg = match self.weights.get(name) {
                Some(a) => (a.affine(beta, 0.0)? + now.affine(1.0 - beta, 0.0)?)?,
                None => now.copy()?,
            }
            .detach();
            self.weights.insert(name.clone(), avg);
        }
        self.updates += 1;
        Ok(())
    }

    /// The averaged weights by name.
    pub fn weights(&self) -> &HashMap<String, Tensor> {
        &self.weights
    }

    /// Writes the averaged weights to `path` (safetensors, the names of the network's
    /// variables: a file any checkpoint reader loads as the model's weights).
    pub fn save(&self, path: &Path) -> Result<()> {
        candle_core::safetensors::save(&self.weights, path)
    }
}

/// Every weight of `varmap`, copied.
pub fn copies(varmap: &VarMap) -> Result<HashMap<String, Tensor>> {
    let data = varmap
        .data()
        .lock()
        .expect("the var map lock is not poisoned");
    data.iter()
        .map(|(k, v)| {
            // A copy of a variable records the copy: detached, it holds no graph.
            let t = v.as_tensor().to_dtype(DType::F32)?.copy()?.detach();
            Ok((k.clone(), t))
        })
        .collect()
}

/// The weights of a safetensors file as tensors on the CPU.
pub fn read(path: &Path) -> Result<HashMap<String, Tensor>> {
    candle_core::safetensors::load(path, &Device::Cpu)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::Init;

    fn one_weight(v: f32) -> VarMap {
        let vm = VarMap::new();
        vm.get((2,), "w", Init::Const(v as f64), DType::F32, &Device::Cpu)
            .unwrap();
        vm
    }

    fn set(vm: &VarMap, v: f32) {
        let data = vm.data().lock().unwrap();
        data["w"]
            .set(&Tensor::new(&[v, 2.0 * v], &Device::Cpu).unwrap())
            .unwrap();
    }

    fn avg(e: &Ema) -> Vec<f32> {
        e.weights()["w"].to_vec1().unwrap()
    }

    #[test]
    fn the_average_follows_the_recursion_with_its_warm_up() {
        let vm = one_weight(0.0);
        let mut e = Ema::new(&vm, 2.0).unwrap();
        // Warm-up first: 1/10, 2/11, 3/12, ..., then 0.5^(1/2) = 0.7071 from the 22nd update,
        // once it is the smaller.
        let mut want = 0.0f64;
        let values: Vec<f32> = (1..=30).map(|i| (i * i) as f32 / 10.0).collect();
        for (i, v) in values.iter().enumerate() {
            let n = i as f64;
            let beta = 0.5f64.sqrt().min((1.0 + n) / (10.0 + n));
            assert!((e.decay() - beta).abs() < 1e-12, "update {i}");
            set(&vm, *v);
            e.update(&vm).unwrap();
            want = beta * want + (1.0 - beta) * *v as f64;
            let got = avg(&e);
            assert!(
                (got[0] as f64 - want).abs() < 1e-4,
                "update {i}: {got:?} vs {want}"
            );
            assert!((got[1] as f64 - 2.0 * want).abs() < 2e-4);
        }
        assert_eq!(e.updates, 30);
        assert!((e.decay() - 0.5f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn the_average_holds_no_graph_of_the_averages_before_it() {
        let vm = one_weight(0.0);
        let mut e = Ema::new(&vm, 5.0).unwrap();
        assert!(!e.weights()["w"].track_op());
        for v in 0..3 {
            set(&vm, v as f32);
            e.update(&vm).unwrap();
            assert!(!e.weights()["w"].track_op(), "update {v}");
        }
        assert!(!copies(&vm).unwrap()["w"].track_op());
    }

    #[test]
    fn the_average_is_a_copy_the_optimiser_does_not_write() {
        let vm = one_weight(1.0);
        let e = Ema::new(&vm, 100.0).unwrap();
        set(&vm, 5.0);
        assert_eq!(avg(&e), vec![1.0, 1.0]);
    }

    #[test]
    fn saved_weights_read_back_under_the_variable_names() {
        let vm = one_weight(0.0);
        let mut e = Ema::new(&vm, 3.0).unwrap();
        set(&vm, 4.0);
        e.update(&vm).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("w.safetensors");
        e.save(&p).unwrap();
        let back = read(&p).unwrap();
        assert_eq!(back["w"].to_vec1::<f32>().unwrap(), avg(&e));
        // A fresh var map loads the file as its weights.
        let vm2 = one_weight(0.0);
        let mut vm2 = vm2;
        vm2.load(&p).unwrap();
        assert_eq!(
            copies(&vm2).unwrap()["w"].to_vec1::<f32>().unwrap(),
            avg(&e)
        );
    }
}
