//! EDM (Karras et al. 2022) preconditioning, loss weighting, training noise levels and the
//! sampling schedule.

/// EDM hyper-parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Edm {
    /// Standard deviation of the (normalised) data.
    pub sigma_data: f64,
    /// Smallest noise level of the schedule.
    pub sigma_min: f64,
    /// Largest noise level of the schedule.
    pub sigma_max: f64,
    /// Schedule curvature.
    pub rho: f64,
    /// Mean of ln σ during training.
    pub p_mean: f64,
    /// Standard deviation of ln σ during training.
    pub p_std: f64,
}

/// The highest noise level, as a fraction of σ_data, that the sampler's last Heun step may
/// start from ([`Edm::min_steps`]).
pub const MAX_LAST_LEVEL: f64 = 0.08;

impl Default for Edm {
    fn default() -> Self {
        Self {
            sigma_data: 0.5,
            sigma_min: 0.002,
            sigma_max: 80.0,
            rho: 7.0,
            p_mean: -1.2,
            p_std: 1.2,
        }
    }
}

impl Edm {
    /// `(c_skip, c_out, c_in, c_noise)` at noise level σ.
    pub fn precondition(&self, sigma: f64) -> (f64, f64, f64, f64) {
        let sd2 = self.sigma_data * self.sigma_data;
        let s2 = sigma * sigma;
        (
            sd2 / (s2 + sd2),
            sigma * self.sigma_data / (s2 + sd2).sqrt(),
            1.0 / (s2 + sd2).sqrt(),
            sigma.ln() / 4.0,
        )
    }

    /// Loss weight λ(σ) = (σ² + σ_d²) / (σ σ_d)², which makes the effective target unit-variance.
    pub fn loss_weight(&self, sigma: f64) -> f64 {
        (sigma * sigma + self.sigma_data * self.sigma_data) / (sigma * self.sigma_data).powi(2)
    }

    /// The training noise level for a standard normal draw `z`: exp(P_mean + P_std · z).
    pub fn train_sigma(&self, z: f64) -> f64 {
        (self.p_mean + self.p_std * z).exp()
    }

    /// The fewest sampling steps that leave no noise in the samples. The last Heun step of
    /// [`Edm::schedule`] goes from its second-smallest level σ_a down to σ_min; when σ_a is
    /// far above σ_min, the Euler prediction it starts from is off the data by about σ_a, the
    /// denoiser at σ_min cannot correct that, and the trapezoid keeps about σ_a / 2 of
    /// arbitrary error in the output (the last step, to 0, only removes noise of σ_min). So
    /// σ_a must be small beside the data's spread: at most [`MAX_LAST_LEVEL`]·σ_data (or
    /// twice σ_min, where a schedule's σ_min is already near that). With the default
    /// schedule σ_a is 0.47 at 4 steps, 0.085 at 6, 0.052 at 7 and 0.035 at 8, so this is 8;
    /// on the shipped checkpoint (USA_US101-3_3_T-1, 4 samples, `eval --task conditional`)
    /// every vehicle moved implausibly at 4 steps (median speed 42 m/s; 3.7 km/s at 2), 44 %
    /// at 6, 15 % at 7, 2 % at 8 and none at 12 or 32, where ADE settled.
    pub fn min_steps(&self) -> usize {
        let bound = (MAX_LAST_LEVEL * self.sigma_data).max(2.0 * self.sigma_min);
        // A schedule no step count meets (non-finite levels) is left to the sampler's own
        // checks rather than refused here.
        (2..=1000)
            .find(|&n| self.schedule(n)[n - 2] <= bound)
            .unwrap_or(2)
    }

    /// The `n` decreasing sampling noise levels followed by 0.
    pub fn schedule(&self, n: usize) -> Vec<f64> {
        let (a, b) = (
            self.sigma_max.powf(1.0 / self.rho),
            self.sigma_min.powf(1.0 / self.rho),
        );
        let mut s: Vec<f64> = (0..n)
            .map(|i| (a + i as f64 / (n.max(2) - 1) as f64 * (b - a)).powf(self.rho))
            .collect();
        s.push(0.0);
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn preconditioning_limits() {
        let e = Edm::default();
        let (skip, out, cin, _) = e.precondition(1e-4);
        assert!((skip - 1.0).abs() < 1e-6 && out < 1e-3 && (cin - 2.0).abs() < 1e-3);
        let (skip, out, _, _) = e.precondition(80.0);
        assert!(skip < 1e-4 && (out - 0.5).abs() < 1e-3);
        let s = e.schedule(32);
        assert_eq!(s.len(), 33);
        assert!((s[0] - 80.0).abs() < 1e-9 && (s[31] - 0.002).abs() < 1e-12 && s[32] == 0.0);
        assert!(s.windows(2).all(|w| w[0] > w[1]));
    }

    #[test]
    fn fewer_steps_than_the_schedule_denoises_with_are_known() {
        // 7 steps start the last Heun step at σ = 0.052, 8 at 0.035 (σ_data 0.5).
        assert_eq!(Edm::default().min_steps(), 8);
        // A schedule whose σ_min is itself near the bound.
        let coarse = Edm {
            sigma_min: 0.1,
            ..Edm::default()
        };
        assert!(coarse.schedule(coarse.min_steps())[coarse.min_steps() - 2] <= 0.2);
        let broken = Edm {
            rho: f64::NAN,
            ..Edm::default()
        };
        assert_eq!(broken.min_steps(), 2);
    }
}
