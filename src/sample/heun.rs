//! EDM's Heun integrator over the noise schedule, and the polish: descent on the guidance
//! cost from the sampled coefficients.

use candle_core::Tensor;

use super::config::SampleError;

/// Largest step of [`polish`], in normalised coefficient units (σ_data is 0.5 of them: a
/// step moves an agent's most-pulled coefficient by at most 2 data deviations).
const POLISH_MAX_STEP: f32 = 1.0;

/// Descends the guidance cost from the sampled coefficients `x` (`samples` equal blocks of
/// agents' coefficients, `variances.len()` each) for at most `iterations` steps. Each agent's
/// gradient is weighted by its components' standard deviations in the data (relative to the
/// largest), scaled down until its largest entry is at most 1, and taken times its sample's
/// step size; a step is kept only where it lowers its sample's cost, and the step size grows
/// by half after a kept step and halves after a refused one. `eval` gives, for trial
/// coefficients, the coefficients as decoded (copies made consistent), every sample's cost and
/// the gradient.
///
/// Why: the fading schedule leaves the last denoising steps to the model, which pulls a rare
/// manoeuvre (a stop in flowing traffic, the last metre into the victim's lane) back towards
/// the common motion it was trained on. Descent on the same cost, realism included, finishes
/// what guidance planned within the kinematic bounds. Weighted by the data's deviations it
/// moves along the shapes the data takes (slowing, drifting across) before the rare,
/// high-frequency ones: unweighted, a speed cost is steepest along wiggles, and the descent
/// crawls (a held-out stop from 14 m/s still rolled at 6.6 m/s after 1,000 steps). Over the
/// 17 stops of the fold-0 windows: weighted by the variances, 5 and 9 pass after 100 and 300
/// steps; by the deviations, 8 and 16.
pub(super) fn polish(
    x: &mut [f32],
    samples: usize,
    variances: &[f64],
    iterations: usize,
    mut eval: impl FnMut(&[f32]) -> Result<(Vec<f32>, Vec<f64>, Vec<f32>), SampleError>,
) -> Result<(), SampleError> {
    let per = x.len() / samples;
    let k = variances.len();
    let top = variances.iter().fold(0f64, |m, &v| m.max(v));
    // A basis with no variance anywhere (a degenerate checkpoint) gets equal weights.
    let prior: Vec<f32> = variances
        .iter()
        .map(|&v| {
            if top > 0.0 {
                (v / top).sqrt() as f32
            } else {
                1.0
            }
        })
        .collect();
    let (c, mut cost, mut g) = eval(x)?;
    x.copy_from_slice(&c);
    let mut step = vec![0.1f32; samples];
    let mut trial = x.to_vec();
    for _ in 0..iterations {
        trial.copy_from_slice(x);
        let mut moving = false;
        for s in 0..samples {
            if step[s] < 1e-4 {
                continue;
            }
            let r = s * per..(s + 1) * per;
            for (t, gs) in trial[r.clone()].chunks_mut(k).zip(g[r].chunks(k)) {
                // Per agent, as Clamp::Agent: a car far over realism's bounds, with a steep
                // gradient, does not freeze the one the script asks to move.
                let m = gs
                    .iter()
                    .zip(&prior)
                    .fold(1f32, |m, (v, w)| m.max((v * w).abs()));
                for ((t, gv), w) in t.iter_mut().zip(gs).zip(&prior) {
                    moving |= *gv != 0.0;
                    *t -= step[s] * gv * w / m;
                }
            }
        }
        if !moving {
            break;
        }
        let (c, tc, tg) = eval(&trial)?;
        for s in 0..samples {
            let r = s * per..(s + 1) * per;
            if tc[s] < cost[s] {
                x[r.clone()].copy_from_slice(&c[r.clone()]);
                g[r.clone()].copy_from_slice(&tg[r]);
                cost[s] = tc[s];
                step[s] = (step[s] * 1.5).min(POLISH_MAX_STEP);
            } else {
                step[s] *= 0.5;
            }
        }
    }
    Ok(())
}

/// EDM's Heun integrator from `x0` over `sigmas` (ending at 0), with `denoised(x, σ, step)`
/// the (guided) denoiser.
pub(super) fn heun(
    x0: Tensor,
    sigmas: &[f64],
    mut denoised: impl FnMut(&Tensor, f64, usize) -> Result<Tensor, SampleError>,
) -> Result<Tensor, SampleError> {
    let mut x = x0;
    for i in 0..sigmas.len() - 1 {
        let (s0, s1) = (sigmas[i], sigmas[i + 1]);
        let d0 = denoised(&x, s0, i)?;
        let slope = ((&x - &d0)? / s0)?;
        let mut next = (&x + (&slope * (s1 - s0))?)?;
        if s1 > 0.0 {
            let d1 = denoised(&next, s1, i)?;
            let slope1 = ((&next - &d1)? / s1)?;
            next = (&x + ((slope + slope1)? * (0.5 * (s1 - s0)))?)?;
        }
        x = next;
    }
    Ok(x)
}
