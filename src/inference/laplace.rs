//! Laplace fits of small blocks of continuous latent variables: the mode of a log density by
//! Levenberg-damped Newton steps on its gradient (dual numbers) with a finite-difference Hessian,
//! the Gaussian centred there with the inverse negative Hessian as covariance, and that Gaussian's
//! ELBO to second order (Laplace's approximation of the evidence).
//!
//! Used for the kinodynamic factors of BOM-SVI ([`super::svi`]) and for the refits of model
//! criticism ([`crate::criticism`]), where every block has at most a handful of dimensions.
//!
//! Why Newton and not Adam: damping and friction trade off along a long, narrow ridge (a push
//! moves as far with more damping and less friction), along which Adam's per-coordinate steps
//! crawl for thousands of iterations.

use nalgebra::{DMatrix, DVector};

/// A log density and its gradient.
pub type LogDensity<'a> = dyn FnMut(&[f64]) -> (f64, Vec<f64>) + 'a;

/// A coarse grid over +-2 prior sds of the first two coordinates (damping and friction), then a
/// finer one around the best; the other coordinates of `x` stay as given. Finds the basin before
/// Newton's method.
pub fn coarse_grid(post: &mut LogDensity<'_>, x: &mut [f64]) {
    let mut best = (f64::NEG_INFINITY, x[0], x[1]);
    for step in [0.75, 0.2] {
        let c = if step < 0.5 { (best.1, best.2) } else { (0.0, 0.0) };
        for a in -3..=3 {
            for m in -3..=3 {
                let (xb, xm) = (c.0 + step * a as f64, c.1 + step * m as f64);
                (x[0], x[1]) = (xb, xm);
                let l = post(x).0;
                if l > best.0 {
                    best = (l, xb, xm);
                }
            }
        }
    }
    (x[0], x[1]) = (best.1, best.2);
}

/// Symmetrised finite-difference Hessian of `post` at `x` from its gradients.
pub fn hessian(post: &mut LogDensity<'_>, x: &[f64]) -> DMatrix<f64> {
    let d = x.len();
    let mut h = DMatrix::<f64>::zeros(d, d);
    for j in 0..d {
        let e = 1e-4;
        let (mut a, mut b) = (x.to_vec(), x.to_vec());
        a[j] += e;
        b[j] -= e;
        let (ga, gb) = (post(&a).1, post(&b).1);
        for r in 0..d {
            h[(r, j)] = (ga[r] - gb[r]) / (2.0 * e);
        }
    }
    (h.clone() + h.transpose()) * 0.5
}

/// The mode of `post` from `x`: at most [`MODE_STEPS`] Levenberg-damped Newton steps (each
/// clamped to one unit per coordinate), stopping when no step improves or the gradient is below
/// 1e-3.
pub fn mode(post: &mut LogDensity<'_>, x: Vec<f64>) -> Vec<f64> {
    mode_steps(post, x, MODE_STEPS)
}

/// Newton steps of [`mode`].
pub const MODE_STEPS: usize = 12;

/// [`mode`] with at most `max_steps` Newton steps. Along the damping-friction ridge of a door
/// the damped steps stay short, and 12 of them can stop several nats below the mode.
pub fn mode_steps(post: &mut LogDensity<'_>, mut x: Vec<f64>, max_steps: usize) -> Vec<f64> {
    let dim = x.len();
    let (mut fx, mut gx) = post(&x);
    let mut lambda = 1e-3;
    for _ in 0..max_steps {
        let neg_h = -hessian(post, &x);
        let mut improved = false;
        for _ in 0..8 {
            let damped = &neg_h + DMatrix::identity(dim, dim) * (lambda * (1.0 + neg_h.trace().abs() / dim as f64));
            let Some(chol) = damped.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = chol.solve(&DVector::from_column_slice(&gx));
            let trial: Vec<f64> = x.iter().zip(step.iter()).map(|(a, s)| a + s.clamp(-1.0, 1.0)).collect();
            let (ft, gt) = post(&trial);
            if ft.is_finite() && ft > fx {
                (x, fx, gx) = (trial, ft, gt);
                lambda = (lambda * 0.3).max(1e-6);
                improved = true;
                break;
            }
            lambda *= 10.0;
        }
        if !improved || gx.iter().map(|g| g * g).sum::<f64>().sqrt() < 1e-3 {
            break;
        }
    }
    x
}

/// A Gaussian guide `N(mean, L L^T)` fitted by Laplace's method.
#[derive(Debug, Clone)]
pub struct LaplaceFit {
    pub mean: Vec<f64>,
    /// Lower Cholesky factor of the covariance.
    pub chol: DMatrix<f64>,
    /// Log density at the mode.
    pub log_density: f64,
}

impl LaplaceFit {
    /// Laplace's method from `x0`: the mode, and the inverse negative Hessian there (where that is
    /// not positive definite, its diagonal, floored so that every sd is at most 1).
    pub fn fit(post: &mut LogDensity<'_>, x0: Vec<f64>) -> LaplaceFit {
        let mean = mode(post, x0);
        let d = mean.len();
        let neg_h = -hessian(post, &mean);
        let chol = neg_h
            .clone()
            .cholesky()
            .and_then(|c| c.inverse().cholesky())
            .map(|c| c.l())
            .unwrap_or_else(|| DMatrix::from_diagonal(&DVector::from_iterator(d, (0..d).map(|j| 1.0 / neg_h[(j, j)].max(1.0).sqrt()))));
        let log_density = post(&mean).0;
        LaplaceFit { mean, chol, log_density }
    }

    /// The ELBO of this guide, `E_q[log p(x, data)] + H[q]` \[nats\], with `E_q[log p]` to
    /// second order about the mode: `log p(m) + (d/2) log(2 pi) + log det L` — Laplace's
    /// approximation of the log evidence (MacKay, *Information Theory, Inference, and Learning
    /// Algorithms*, 2003, §27; Bishop, *PRML*, 2006, eq. 4.135). Deterministic, so that models
    /// compared on the same data are compared without Monte Carlo noise; exact for a Gaussian
    /// posterior.
    pub fn elbo(&self) -> f64 {
        let d = self.mean.len();
        let log_det: f64 = (0..d).map(|j| self.chol[(j, j)].abs().max(1e-300).ln()).sum();
        self.log_density + 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln() + log_det
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a Gaussian log density, Laplace's method is exact and its ELBO is the log evidence.
    #[test]
    fn laplace_is_exact_on_a_gaussian() {
        // log p(x) = log Z - 0.5 (x - m)^T A (x - m) - 0.5 d log(2 pi) + 0.5 log det A.
        let a = DMatrix::<f64>::from_row_slice(2, 2, &[4.0, 1.0, 1.0, 2.0]);
        let m = [0.3, -0.7];
        let log_z = 1.7;
        let log_det_a: f64 = a.determinant().ln();
        let mut post = |x: &[f64]| {
            let d = DVector::from_column_slice(&[x[0] - m[0], x[1] - m[1]]);
            let ad = &a * &d;
            let l = log_z - 0.5 * d.dot(&ad) - (2.0 * std::f64::consts::PI).ln() + 0.5 * log_det_a;
            (l, vec![-ad[0], -ad[1]])
        };
        let fit = LaplaceFit::fit(&mut post, vec![2.0, 2.0]);
        assert!((fit.mean[0] - m[0]).abs() < 1e-3 && (fit.mean[1] - m[1]).abs() < 1e-3, "{:?}", fit.mean);
        let cov = &fit.chol * fit.chol.transpose();
        let want = a.clone().try_inverse().unwrap();
        assert!((cov - want).norm() < 1e-6);
        let elbo = fit.elbo();
        assert!((elbo - log_z).abs() < 1e-6, "ELBO {elbo} vs log evidence {log_z}");
    }
}
