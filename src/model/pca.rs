//! PCA of future trajectories (in each agent's own frame): the space the diffusion model works
//! in. Fitted on training futures and stored with the checkpoint.

use nalgebra::{DMatrix, DVector, SymmetricEigen};
use serde::{Deserialize, Serialize};

/// A fitted PCA basis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pca {
    /// Mean of the training vectors.
    pub mean: Vec<f64>,
    /// Components, row-major `k × dim`, orthonormal, by decreasing variance.
    pub components: Vec<f64>,
    /// Variance along each component.
    pub variances: Vec<f64>,
    /// Dimension of the vectors.
    pub dim: usize,
}

/// Why a basis cannot be fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PcaError {
    /// Fewer samples than components.
    #[error("PCA needs at least {needed} samples, got {got}")]
    TooFewSamples {
        /// Needed.
        needed: usize,
        /// Given.
        got: usize,
    },
    /// Vectors of different lengths, or non-finite values.
    #[error("sample {index}: {message}")]
    BadSample {
        /// Which sample.
        index: usize,
        /// What is wrong.
        message: String,
    },
}

impl Pca {
    /// Fits `k` components to `samples` (all of one length).
    pub fn fit(samples: &[Vec<f64>], k: usize) -> Result<Self, PcaError> {
        if samples.len() < k.max(2) {
            return Err(PcaError::TooFewSamples {
                needed: k.max(2),
                got: samples.len(),
            });
        }
        let dim = samples[0].len();
        for (index, s) in samples.iter().enumerate() {
            if s.len() != dim {
                return Err(PcaError::BadSample {
                    index,
                    message: format!("length {} (expected {dim})", s.len()),
                });
            }
            if s.iter().any(|v| !v.is_finite()) {
                return Err(PcaError::BadSample {
                    index,
                    message: "non-finite value".into(),
                });
            }
        }
        let n = samples.len() as f64;
        let mut mean = vec![0.0; dim];
        for s in samples {
            for (m, v) in mean.iter_mut().zip(s) {
                *m += v / n;
            }
        }
        let mut cov = DMatrix::<f64>::zeros(dim, dim);
        for s in samples {
            let d = DVector::from_iterator(dim, s.iter().zip(&mean).map(|(v, m)| v - m));
            cov.ger(1.0 / (n - 1.0), &d, &d, 1.0);
        }
        let eig = SymmetricEigen::new(cov);
        let mut order: Vec<usize> = (0..dim).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
        let k = k.min(dim);
        let mut components = Vec::with_capacity(k * dim);
        let mut variances = Vec::with_capacity(k);
        for &i in order.iter().take(k) {
            components.extend(eig.eigenvectors.column(i).iter());
            variances.push(eig.eigenvalues[i].max(0.0));
        }
        Ok(Self {
            mean,
            components,
            variances,
            dim,
        })
    }

    /// Number of components.
    pub fn k(&self) -> usize {
        self.variances.len()
    }

    /// Coefficients of `v`.
    pub fn encode(&self, v: &[f64]) -> Vec<f64> {
        (0..self.k())
            .map(|i| {
                let c = &self.components[i * self.dim..(i + 1) * self.dim];
                c.iter()
                    .zip(v)
                    .zip(&self.mean)
                    .map(|((c, x), m)| c * (x - m))
                    .sum()
            })
            .collect()
    }

    /// Coefficients of `v` where only the `(x, y, heading)` triples with `seen[j]` are known:
    /// the most probable coefficients under the basis' own variances (a Gaussian prior per
    /// component) given those triples, observed with noise of standard deviation `noise`.
    /// With every triple seen and small noise this is [`Pca::encode`]; with none it is the
    /// mean (all zeros), and in between the unseen steps follow what the seen ones imply.
    pub fn encode_seen(&self, v: &[f64], seen: &[bool], noise: f64) -> Vec<f64> {
        let k = self.k();
        let mut a = DMatrix::<f64>::zeros(k, k);
        let mut b = DVector::<f64>::zeros(k);
        let rows: Vec<usize> = seen
            .iter()
            .enumerate()
            .filter(|(_, s)| **s)
            .flat_map(|(j, _)| 3 * j..3 * j + 3)
            .filter(|&r| r < self.dim)
            .collect();
        let comp = |i: usize, r: usize| self.components[i * self.dim + r];
        for i in 0..k {
            for j in i..k {
                let s: f64 = rows.iter().map(|&r| comp(i, r) * comp(j, r)).sum();
                a[(i, j)] = s;
                a[(j, i)] = s;
            }
            b[i] = rows
                .iter()
                .map(|&r| comp(i, r) * (v[r] - self.mean[r]))
                .sum();
            a[(i, i)] += noise * noise / self.variances[i].max(1e-12);
        }
        match a.cholesky() {
            Some(ch) => ch.solve(&b).iter().copied().collect(),
            None => vec![0.0; k],
        }
    }

    /// The vector with coefficients `c`.
    pub fn decode(&self, c: &[f64]) -> Vec<f64> {
        let mut v = self.mean.clone();
        for (i, ci) in c.iter().enumerate() {
            for (x, comp) in v
                .iter_mut()
                .zip(&self.components[i * self.dim..(i + 1) * self.dim])
            {
                *x += ci * comp;
            }
        }
        v
    }

    /// Root-mean-square position error (metres) of encoding then decoding `samples`, whose
    /// entries are `(x, y, heading)` triples; headings are left out of the error.
    pub fn position_rmse(&self, samples: &[Vec<f64>]) -> f64 {
        let mut sum = 0.0;
        let mut n = 0usize;
        for s in samples {
            let r = self.decode(&self.encode(s));
            for (a, b) in s.chunks(3).zip(r.chunks(3)) {
                sum += (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
                n += 1;
            }
        }
        (sum / n.max(1) as f64).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Straight lines at different speeds and lateral drifts: rank 2 plus the mean.
    fn lines() -> Vec<Vec<f64>> {
        (0..50)
            .map(|i| {
                let (v, drift) = (5.0 + i as f64 * 0.3, (i % 7) as f64 * 0.1 - 0.3);
                (1..=10)
                    .flat_map(|t| [v * t as f64 * 0.1, drift * t as f64 * 0.1, 0.0])
                    .collect()
            })
            .collect()
    }

    #[test]
    fn recovers_a_low_rank_family_exactly() {
        let samples = lines();
        let p = Pca::fit(&samples, 2).unwrap();
        assert_eq!((p.k(), p.dim), (2, 30));
        assert!(p.position_rmse(&samples) < 1e-9);
        let one = Pca::fit(&samples, 1).unwrap();
        assert!(
            one.position_rmse(&samples) > 1e-3,
            "one component cannot hold both"
        );
        assert!(p.variances[0] >= p.variances[1]);
    }

    #[test]
    fn a_future_seen_in_part_is_completed_from_what_is_seen() {
        let samples = lines();
        let p = Pca::fit(&samples, 2).unwrap();
        let s = &samples[17];
        let all = vec![true; 10];
        let full = p.encode(s);
        let seen_all = p.encode_seen(s, &all, 1e-6);
        for (a, b) in full.iter().zip(&seen_all) {
            assert!((a - b).abs() < 1e-6, "{a} {b}");
        }
        // The first four steps alone pin a straight line: the last six follow.
        let first: Vec<bool> = (0..10).map(|t| t < 4).collect();
        let back = p.decode(&p.encode_seen(s, &first, 1e-6));
        for (a, b) in back.iter().zip(s) {
            assert!((a - b).abs() < 1e-4, "{a} {b}");
        }
        // Nothing seen: the mean.
        let none = p.encode_seen(s, &[false; 10], 0.05);
        assert!(none.iter().all(|c| c.abs() < 1e-12), "{none:?}");
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(matches!(
            Pca::fit(&[vec![1.0]], 2),
            Err(PcaError::TooFewSamples { .. })
        ));
        let e = Pca::fit(&[vec![1.0, 2.0], vec![1.0], vec![0.0, 0.0]], 1).unwrap_err();
        assert_eq!(
            e,
            PcaError::BadSample {
                index: 1,
                message: "length 1 (expected 2)".into()
            }
        );
    }
}
