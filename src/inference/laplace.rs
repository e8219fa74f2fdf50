//! Laplace fits of small blocks of continuous latent variables: the mode of a log density by
//! Levenberg-damped Newton steps on its gradient (dual numbers) with a finite-difference Hessian,
//! the Gaussian centred there with the inverse negative Hessian as covariance, and that Gaussian's
//! ELBO to second order (Laplace's approximation of the evidence).
//!
//! Used for the kinodynamic factors of BOM-SVI ([`super::svi`]) and for the refits of model
//! criticism ([`crate::criticism`]), where every block has at most a handful of dimensions. Both
//! widen the intervals they report for misspecification, dividing the likelihood's share of the
//! precision ([`inflated`]) by the AR(1) factor of the physics' deviations within windows
//! ([`ar1_inflation`]); BOM-SVI also by the window-robust sandwich ([`cluster_inflation`]) where
//! that is larger.
//!
//! Why Newton and not Adam: damping and friction trade off along a long, narrow ridge (a push
//! moves as far with more damping and less friction), along which Adam's per-coordinate steps
//! crawl for thousands of iterations.

use nalgebra::{DMatrix, DVector};

/// A log density and its gradient.
pub type LogDensity<'a> = dyn FnMut(&[f64]) -> (f64, Vec<f64>) + 'a;

/// A log density's value alone: what a grid search needs, at a fraction of the gradient's cost
/// where the gradient comes from dual numbers.
pub type LogValue<'a> = dyn FnMut(&[f64]) -> f64 + 'a;

/// A coarse grid over +-2 prior sds of the first two coordinates (damping and friction), then a
/// finer one around the best; the other coordinates of `x` stay as given. Finds the basin before
/// Newton's method. Only the log density's `value` is needed (a [`LogValue`]: no gradient).
pub fn coarse_grid(value: &mut LogValue<'_>, x: &mut [f64]) {
    let mut best = (f64::NEG_INFINITY, x[0], x[1]);
    for step in [0.75, 0.2] {
        let c = if step < 0.5 { (best.1, best.2) } else { (0.0, 0.0) };
        for a in -3..=3 {
            for m in -3..=3 {
                let (xb, xm) = (c.0 + step * a as f64, c.1 + step * m as f64);
                (x[0], x[1]) = (xb, xm);
                let l = value(x);
                if l > best.0 {
                    best = (l, xb, xm);
                }
            }
        }
    }
    (x[0], x[1]) = (best.1, best.2);
}

/// [`coarse_grid`], unless `x` as given (a converged fit's damping and friction, say) has the
/// higher log density: the grid is centred on the priors' medians and does not hold the start, so
/// alone it can move a start from a good basin to a worse one (README, issue 25, stop 118).
pub fn coarse_grid_or_start(value: &mut LogValue<'_>, x: &mut [f64]) {
    let (at_start, start) = (value(x), (x[0], x[1]));
    coarse_grid(value, x);
    if at_start >= value(x) {
        (x[0], x[1]) = start;
    }
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

// Misspecification: how much wider a Laplace fit's intervals must be where the physics' deviations
// are correlated in time or the windows disagree (`svi::laplace_kinodynamics` for the reported
// kinodynamics, `criticism::effect_inflation` for the adopted effects).

/// The covariance `cov` of standardised parameters (prior `N(0, I)`) with the likelihood part of
/// its precision divided by `c >= 1`: `((cov^-1 - I) / c + I)^-1`; `cov` itself where it is not
/// invertible.
pub fn inflated(cov: DMatrix<f64>, c: f64) -> DMatrix<f64> {
    if c <= 1.0 {
        return cov;
    }
    let d = cov.nrows();
    let eye = DMatrix::<f64>::identity(d, d);
    cov.clone()
        .try_inverse()
        .map(|p| (p - &eye) / c + &eye)
        .and_then(|p| p.try_inverse())
        .unwrap_or(cov)
}

/// Draws `draws[k]` (each a vector of standardised parameters with prior `N(0, I)`) moved so that
/// their covariance is [`inflated`]`(cov, c)`, `cov` their own: `x' = m + L' L^-1 (x - m)`, `m`
/// their mean and `L`, `L'` the Cholesky factors of the two covariances (a linear map, so the
/// moved draws' covariance is the inflated one exactly and a Gaussian stays Gaussian). The
/// draws as they are when `c <= 1`, with fewer draws than twice the dimension, or where either
/// covariance has no Cholesky factor.
///
/// Why: BOM-NUTS samples the model's posterior, whose likelihood counts correlated deviations as
/// independent frames, as SVI's Laplace fit does; its reported intervals allow for that by the
/// same factor SVI's do (`inference::nuts`'s module docs).
pub fn inflated_draws(draws: &[Vec<f64>], c: f64) -> Vec<Vec<f64>> {
    let Some(d) = draws.first().map(Vec::len) else { return Vec::new() };
    if c <= 1.0 || d == 0 || draws.len() < 2 * d || draws.iter().any(|x| x.len() != d) {
        return draws.to_vec();
    }
    let n = draws.len() as f64;
    let m = draws.iter().fold(DVector::zeros(d), |acc, x| acc + DVector::from_column_slice(x)) / n;
    let cov = draws.iter().fold(DMatrix::zeros(d, d), |acc, x| {
        let e = DVector::from_column_slice(x) - &m;
        acc + &e * e.transpose()
    }) / (n - 1.0);
    let (Some(l), Some(l2)) = (cov.clone().cholesky(), inflated(cov, c).cholesky()) else { return draws.to_vec() };
    let Some(l_inv) = l.l().try_inverse() else { return draws.to_vec() };
    let a = l2.l() * l_inv;
    draws.iter().map(|x| (&m + &a * (DVector::from_column_slice(x) - &m)).as_slice().to_vec()).collect()
}

/// The variance inflation factor that the windows' disagreement calls for: the least `c >= 1`
/// for which the reported covariance `(H / c + I)^-1` ([`inflated`]) gives damping and friction
/// (standardised coordinates 0 and 1) at least the variances of the cluster-robust sandwich
/// `P^-1 (G / (G - 1) sum_w g_w g_w^T + I) P^-1`, with `P = H + I` the negative Hessian `neg_h` of
/// the block's log posterior at the mode (`H` the physics prior's, `I` the standard-normal
/// prior's) and `g_w` the physics prior's score of each of the `G` windows that simulate the
/// joint (`scores`, from `svi::physics_prior`).
///
/// Why: where the physics misses something the bags' simulator has, the deviations are not only
/// correlated within a window (which [`ar1_inflation`] allows for) but biased the same way
/// for a whole push, and pushes at other speeds or forces pull the parameters along the
/// damping-friction ridge in different directions. Windows are independent given the parameters,
/// so the spread of their scores measures the information the data really hold (the sandwich
/// covariance of a misspecified model: Huber 1967; White 1982; with windows as clusters and the
/// small-sample factor `G / (G - 1)`, Cameron and Miller, *J. Human Resources* 50(2), 2015; for
/// the Bayesian use, Müller, *Econometrica* 81(5), 2013). Where the model holds, the sandwich
/// equals the Laplace covariance on average and `c` stays near 1. 1 with fewer than two such
/// windows or a Hessian that is not positive definite.
pub fn cluster_inflation(neg_h: &DMatrix<f64>, scores: &[Vec<f64>]) -> f64 {
    // A window that does not simulate the joint scores nothing on damping and friction.
    let used: Vec<&Vec<f64>> = scores.iter().filter(|g| g.len() >= 2 && (g[0] != 0.0 || g[1] != 0.0)).collect();
    let (g, d) = (used.len(), neg_h.nrows());
    if g < 2 || d < 2 {
        return 1.0;
    }
    let eye = DMatrix::<f64>::identity(d, d);
    let Some(p_inv) = neg_h.clone().cholesky().map(|c| c.inverse()) else { return 1.0 };
    let mut meat = eye.clone();
    for s in &used {
        let v = DVector::from_column_slice(s);
        meat += &v * v.transpose() * (g as f64 / (g as f64 - 1.0));
    }
    let sandwich = &p_inv * meat * &p_inv;
    let h = neg_h - &eye;
    let reported = |c: f64| (&h / c + &eye).cholesky().map(|l| l.inverse());
    let covers = |c: f64| reported(c).is_some_and(|v| (0..2).all(|j| v[(j, j)] >= sandwich[(j, j)]));
    if covers(1.0) {
        return 1.0;
    }
    // Bisection on log c: the reported variances grow with c (H positive semi-definite).
    let (mut lo, mut hi) = (0.0f64, MAX_INFLATION.ln());
    if !covers(MAX_INFLATION) {
        return MAX_INFLATION;
    }
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if covers(mid.exp()) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    hi.exp()
}

/// The largest variance inflation [`cluster_inflation`] reports.
pub const MAX_INFLATION: f64 = 1e4;

/// The variance of the mean of `n` AR(1) terms with lag-1 autocorrelation `rho` over that of `n`
/// independent ones, `(1 + rho) / (1 - rho) - 2 rho (1 - rho^n) / (n (1 - rho)^2)` (the
/// asymptotic `(1 + rho) / (1 - rho)` overstates it for short series: it never exceeds `n`), for
/// the pooled `rho` of several series (see [`lag1_autocorrelation`], clamped to `[0, 0.99]`) and
/// `n` their mean length; 1 when it cannot be estimated.
pub fn ar1_inflation(series: &[Vec<f64>]) -> f64 {
    ar1_factor(series, false)
}

/// [`ar1_inflation`] of the physics prior's deviation scores in several windows (`d/d q_t` of
/// each window's prior at its frames, in order), each window's first and last frame left out: the
/// first is the simulation's start, and the rest between windows also acts on the last. BOM-SVI's
/// reported kinodynamics and model criticism's effects are widened by it.
pub fn deviation_inflation(windows: &[Vec<f64>]) -> f64 {
    let interiors: Vec<Vec<f64>> = windows.iter().map(|w| w.iter().skip(1).take(w.len().saturating_sub(2)).copied().collect()).collect();
    ar1_inflation(&interiors)
}

/// [`ar1_mean_variance_factor`] at the pooled lag-1 autocorrelation of `series` and their mean
/// length `n`, the autocorrelation raised by `(1 + 3 rho) / n` first when `bias_corrected`, then
/// clamped to `[0, 0.99]`; 1 when it cannot be estimated.
pub fn ar1_factor(series: &[Vec<f64>], bias_corrected: bool) -> f64 {
    let Some(rho) = lag1_autocorrelation(series) else { return 1.0 };
    let used: Vec<usize> = series.iter().map(Vec::len).filter(|&l| l > 1).collect();
    let n = used.iter().sum::<usize>() as f64 / used.len().max(1) as f64;
    let rho = if bias_corrected { rho + (1.0 + 3.0 * rho) / n } else { rho };
    ar1_mean_variance_factor(rho.clamp(0.0, 0.99), n)
}

/// `n Var(mean of n AR(1) terms) / Var(one term)` for lag-1 autocorrelation `rho` in `[0, 1)`
/// (at least 1).
pub fn ar1_mean_variance_factor(rho: f64, n: f64) -> f64 {
    ((1.0 + rho) / (1.0 - rho) - 2.0 * rho * (1.0 - rho.powf(n)) / (n * (1.0 - rho).powi(2))).max(1.0)
}

/// Pooled lag-1 autocorrelation about zero of several series: `sum x_k x_{k+1}` over
/// `sqrt(sum x_k^2 * sum x_{k+1}^2)`, over the consecutive pairs within each series; `None` with
/// fewer than 8 pairs. (Biased low by about `(1 + 3 rho) / n` on series of length `n`.)
pub fn lag1_autocorrelation(series: &[Vec<f64>]) -> Option<f64> {
    let (mut num, mut a, mut b, mut n) = (0.0, 0.0, 0.0, 0usize);
    for x in series {
        for k in 1..x.len() {
            num += x[k - 1] * x[k];
            a += x[k - 1] * x[k - 1];
            b += x[k] * x[k];
            n += 1;
        }
    }
    (n >= 8 && a > 0.0 && b > 0.0).then(|| num / (a * b).sqrt())
}

/// The mean-field gap of a Gaussian block: `KL(q || p) = (sum_t ln L_tt - ln det L) / 2 >= 0`
/// (Hadamard's inequality) between the product of the best independent Gaussians `q` and a
/// Gaussian `p` with precision `L`. The block's ELBO under a mean-field guide falls short of its
/// Laplace evidence by this much, so adding it to a conditional ELBO puts the block on the
/// footing of a collapsed (marginalised) one — exact for a Gaussian block (Bishop, *Pattern
/// Recognition and Machine Learning*, 2006, §10.1.2; Opper and Archambeau, *Neural Computation*
/// 21(3), 2009).
///
/// `L = Lp + diag(h)`: `prior_diag[t]` is node `t`'s diagonal of the prior precision `Lp`, whose
/// off-diagonal is `-w` on each `edges` entry `(u, v, w)` (`w > 0`, `u != v`); the data's share is
/// `h_t = max(0, guide_precision[t] - prior_diag[t])`, the guide's own precision less the prior's
/// (at the mean-field optimum `1 / s_t^2 = L_tt`). Gaussian elimination, leaves first: a forest (a
/// star, a chain: what the joint-coordinate priors are) costs `O(n)` without fill; nodes on
/// cycles follow by fewest neighbours. 0 for an empty block, and where a pivot is not positive
/// (`L` not positive definite: no gap is claimed).
pub fn mean_field_gap(guide_precision: &[f64], prior_diag: &[f64], edges: &[(usize, usize, f64)]) -> f64 {
    use std::collections::{BTreeMap, BTreeSet};
    let n = guide_precision.len().min(prior_diag.len());
    let mut d: Vec<f64> = (0..n).map(|t| guide_precision[t].max(prior_diag[t])).collect();
    let sum_ln_diag: f64 = d.iter().filter(|v| **v > 0.0).map(|v| v.ln()).sum();
    // Off-diagonal entries, parallel edges merged.
    let mut merged: Vec<(usize, usize, f64)> = edges.iter().filter(|e| e.0 < n && e.1 < n && e.0 != e.1 && e.2 > 0.0).map(|&(u, v, w)| (u.min(v), u.max(v), -w)).collect();
    merged.sort_by_key(|x| (x.0, x.1));
    merged.dedup_by(|x, y| {
        let same = x.0 == y.0 && x.1 == y.1;
        if same {
            y.2 += x.2;
        }
        same
    });
    let mut adj: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    for &(u, v, l) in &merged {
        adj[u].push((v, l));
        adj[v].push((u, l));
    }
    let mut ln_det = 0.0;
    let ok = |p: f64| p > 0.0 && p.is_finite();
    // Leaves first, in O(n) without fill (all of a forest: a star, a chain).
    let mut deg: Vec<usize> = adj.iter().map(Vec::len).collect();
    let mut alive = vec![true; n];
    let mut leaves: Vec<usize> = (0..n).filter(|&t| deg[t] <= 1).collect();
    while let Some(u) = leaves.pop() {
        if !alive[u] || deg[u] > 1 {
            continue;
        }
        alive[u] = false;
        if !ok(d[u]) {
            return 0.0;
        }
        ln_det += d[u].ln();
        if let Some(&(v, l)) = adj[u].iter().find(|(v, _)| alive[*v]) {
            d[v] -= l * l / d[u];
            deg[v] -= 1;
            if deg[v] <= 1 {
                leaves.push(v);
            }
        }
    }
    // What is left lies on cycles: elimination by fewest neighbours, with fill.
    let mut rest: Vec<BTreeMap<usize, f64>> = vec![BTreeMap::new(); n];
    for &(u, v, l) in &merged {
        if alive[u] && alive[v] {
            rest[u].insert(v, l);
            rest[v].insert(u, l);
        }
    }
    let mut order: BTreeSet<(usize, usize)> = (0..n).filter(|&t| alive[t]).map(|t| (rest[t].len(), t)).collect();
    while let Some((_, u)) = order.pop_first() {
        let pivot = d[u];
        if !ok(pivot) {
            return 0.0;
        }
        ln_det += pivot.ln();
        let nb: Vec<(usize, f64)> = std::mem::take(&mut rest[u]).into_iter().collect();
        for &(v, _) in &nb {
            order.remove(&(rest[v].len(), v));
            rest[v].remove(&u);
        }
        for (a, &(v, lv)) in nb.iter().enumerate() {
            d[v] -= lv * lv / pivot;
            for &(x, lx) in &nb[a + 1..] {
                let fill = lv * lx / pivot;
                *rest[v].entry(x).or_insert(0.0) -= fill;
                *rest[x].entry(v).or_insert(0.0) -= fill;
            }
        }
        for &(v, _) in &nb {
            order.insert((rest[v].len(), v));
        }
    }
    (0.5 * (sum_ln_diag - ln_det)).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A start in a narrow, high basin off the grid (a converged fit's damping and friction) is
    /// kept; a start worse than the grid's best is moved there, as `coarse_grid` alone moves both.
    #[test]
    fn the_grid_keeps_a_start_better_than_every_grid_point() {
        // A broad basin at the priors' medians and a narrow, higher one at (1.1, -0.35), which
        // no grid point comes within 0.05 of.
        let mut post = |x: &[f64]| {
            let broad = -1.0 - 0.1 * (x[0] * x[0] + x[1] * x[1]);
            let narrow = -1e4 * ((x[0] - 1.1).powi(2) + (x[1] + 0.35).powi(2));
            broad.max(narrow)
        };
        let mut x = vec![1.1, -0.35, 0.3];
        coarse_grid(&mut post, &mut x);
        assert!(x[0].abs() < 0.5 && x[1].abs() < 0.5, "the grid alone leaves the narrow basin: {x:?}");
        let mut x = vec![1.1, -0.35, 0.3];
        coarse_grid_or_start(&mut post, &mut x);
        assert_eq!(x, vec![1.1, -0.35, 0.3]);
        let mut x = vec![1.8, 1.8, 0.3];
        coarse_grid_or_start(&mut post, &mut x);
        assert!(x[0].abs() < 0.5 && x[1].abs() < 0.5 && x[2] == 0.3, "a poor start is not moved to the grid's best: {x:?}");
    }

    /// Moved draws have the inflated covariance exactly, keep their mean, and stay put at `c = 1`.
    #[test]
    fn inflated_draws_have_the_inflated_covariance() {
        // Correlated draws on a grid (no RNG needed): x = B u, u over a 3-D grid.
        let b = DMatrix::<f64>::from_row_slice(3, 3, &[0.2, 0.0, 0.0, 0.1, 0.3, 0.0, -0.05, 0.02, 0.1]);
        let mut draws = Vec::new();
        for i in 0..7 {
            for j in 0..7 {
                for k in 0..7 {
                    let u = DVector::from_column_slice(&[i as f64 - 3.0, (j as f64 - 3.0) * 0.7, (k as f64 - 3.0) * 1.3]);
                    draws.push((DVector::from_column_slice(&[0.5, -1.0, 2.0]) + &b * u).as_slice().to_vec());
                }
            }
        }
        let moments = |d: &[Vec<f64>]| {
            let n = d.len() as f64;
            let m = d.iter().fold(DVector::zeros(3), |a, x| a + DVector::from_column_slice(x)) / n;
            let c = d.iter().fold(DMatrix::zeros(3, 3), |a, x| {
                let e = DVector::from_column_slice(x) - &m;
                a + &e * e.transpose()
            }) / (n - 1.0);
            (m, c)
        };
        let (m0, c0) = moments(&draws);
        let moved = inflated_draws(&draws, 4.0);
        let (m1, c1) = moments(&moved);
        let want = inflated(c0.clone(), 4.0);
        assert!((&m1 - &m0).norm() < 1e-12, "{m1} vs {m0}");
        assert!((&c1 - &want).norm() < 1e-12 * want.norm(), "{c1} vs {want}");
        // Wider where the likelihood dominates: every variance grows, by less than 4.
        for j in 0..3 {
            assert!(c1[(j, j)] > c0[(j, j)] && c1[(j, j)] < 4.0 * c0[(j, j)], "{j}: {} vs {}", c1[(j, j)], c0[(j, j)]);
        }
        assert_eq!(inflated_draws(&draws, 1.0), draws);
    }

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

    /// With prior precision 1 and physics precision `h`, the variance `1 / (1 + h)` becomes
    /// `1 / (1 + h / c)`: unchanged at `c = 1`, the prior's as `c` grows.
    #[test]
    fn inflation_divides_the_physics_precision() {
        let h = 99.0;
        let cov = DMatrix::from_element(1, 1, 1.0 / (1.0 + h));
        assert!((inflated(cov.clone(), 1.0)[(0, 0)] - 0.01).abs() < 1e-12);
        assert!((inflated(cov.clone(), 9.0)[(0, 0)] - 1.0 / 12.0).abs() < 1e-12);
        assert!((inflated(cov, 1e9)[(0, 0)] - 1.0).abs() < 1e-6);
    }

    /// The lag-1 autocorrelation of AR(1) series of the length of a window's deviations is
    /// recovered to its small-sample bias; the inflation factor follows it.
    #[test]
    fn ar1_inflation_recovers_the_autocorrelation() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for rho in [0.0, 0.5, 0.9] {
            let series: Vec<Vec<f64>> = (0..40)
                .map(|_| {
                    let mut x: f64 = StandardNormal.sample(&mut rng);
                    (0..50)
                        .map(|_| {
                            let e: f64 = StandardNormal.sample(&mut rng);
                            x = rho * x + (1.0 - rho * rho).sqrt() * e;
                            x
                        })
                        .collect()
                })
                .collect();
            let r = lag1_autocorrelation(&series).expect("enough pairs");
            let bias = (1.0 + 3.0 * rho) / 50.0;
            assert!((r - rho).abs() < bias + 0.03, "rho {rho}: estimated {r:.3}");
            let c = ar1_inflation(&series);
            assert!(c >= 1.0 && (rho == 0.0 || c > 0.8 * (1.0 + rho - bias) / (1.0 - rho + bias)), "rho {rho}: inflation {c:.2}");
        }
        assert_eq!(ar1_inflation(&[vec![1.0, 2.0, 3.0]]), 1.0, "too few values");
    }

    /// The window-robust inflation against its closed form: physics precision `H = 4 I` on two
    /// parameters (`neg_h = 5 I`), windows' scores `+-2` along each, so the sandwich variance is
    /// `(4/3 * 8 + 1) / 25 = 7/15` and `1 / (4 / c + 1)` reaches it at `c = 7/2`. Scores that
    /// agree with `H` call for none, and one window cannot tell.
    #[test]
    fn cluster_inflation_matches_the_sandwich() {
        let neg_h = DMatrix::<f64>::identity(2, 2) * 5.0;
        let spread = [vec![2.0, 0.0], vec![-2.0, 0.0], vec![0.0, 2.0], vec![0.0, -2.0]];
        let c = cluster_inflation(&neg_h, &spread);
        assert!((c - 3.5).abs() < 1e-6, "inflation {c}");
        // sum g g^T * 4/3 = 8/3 I < H: the windows agree better than the model expects.
        let agree = [vec![1.0, 0.0], vec![-1.0, 0.0], vec![0.0, 1.0], vec![0.0, -1.0]];
        assert_eq!(cluster_inflation(&neg_h, &agree), 1.0);
        // Windows that do not simulate the joint (no score on damping or friction) do not count.
        let neg_h3 = DMatrix::<f64>::identity(3, 3) * 5.0;
        assert_eq!(cluster_inflation(&neg_h3, &[vec![2.0, 0.0, 0.0], vec![0.0, 0.0, 1.0]]), 1.0);
    }

    /// The finite-length factor is the variance of the mean of AR(1) series (Monte Carlo), and
    /// never exceeds the series' length (a fully correlated window is one observation).
    #[test]
    fn ar1_factor_is_the_variance_of_the_mean() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for (rho, n) in [(0.5, 20usize), (0.9, 20), (0.99, 20)] {
            let reps = 20000;
            let means: Vec<f64> = (0..reps)
                .map(|_| {
                    let mut x: f64 = StandardNormal.sample(&mut rng);
                    let mut sum = x;
                    for _ in 1..n {
                        let e: f64 = StandardNormal.sample(&mut rng);
                        x = rho * x + (1.0 - rho * rho).sqrt() * e;
                        sum += x;
                    }
                    sum / n as f64
                })
                .collect();
            let mc = n as f64 * means.iter().map(|m| m * m).sum::<f64>() / reps as f64;
            let f = ar1_mean_variance_factor(rho, n as f64);
            assert!((f - mc).abs() < 0.05 * mc, "rho {rho}: formula {f:.2}, Monte Carlo {mc:.2}");
            assert!(f <= n as f64 + 1e-9);
        }
    }

    /// The gap against a dense log-determinant: a star (one window's frames tied to its first)
    /// with a chain of rest frames and a cycle (a rest frame tied to two windows), data on some
    /// frames only; none for a diagonal precision; the closed form of an unobserved star.
    #[test]
    fn mean_field_gap_matches_the_dense_determinant() {
        let n = 9;
        let edges = vec![(0, 1, 4.0), (0, 2, 4.0), (0, 3, 4.0), (3, 4, 2.0), (4, 5, 2.0), (5, 0, 1.0), (5, 6, 3.0), (6, 7, 3.0), (6, 8, 3.0)];
        let mut prior_diag = vec![0.0; n];
        prior_diag[0] += 0.5;
        for &(u, v, w) in &edges {
            prior_diag[u] += w;
            prior_diag[v] += w;
        }
        let h = [0.0, 7.0, 0.0, 1.5, 0.0, 0.0, 9.0, 0.0, 0.2];
        let guide: Vec<f64> = (0..n).map(|t| prior_diag[t] + h[t]).collect();
        let mut l = DMatrix::<f64>::from_diagonal(&DVector::from_vec(guide.clone()));
        for &(u, v, w) in &edges {
            l[(u, v)] -= w;
            l[(v, u)] -= w;
        }
        let dense = 0.5 * (guide.iter().map(|v| v.ln()).sum::<f64>() - l.clone().cholesky().expect("positive definite").l().diagonal().iter().map(|v| 2.0 * v.ln()).sum::<f64>());
        let gap = mean_field_gap(&guide, &prior_diag, &edges);
        assert!((gap - dense).abs() < 1e-10 && gap > 0.0, "gap {gap} vs dense {dense}");
        assert!(mean_field_gap(&guide, &prior_diag, &[]).abs() < 1e-12);
        // A window of `m` unobserved frames tied to its first with weight w, the first with prior
        // precision p: (1/2) ln(1 + m w / p).
        let (m, w, p) = (50usize, 1e4, 1.0);
        let star: Vec<(usize, usize, f64)> = (1..=m).map(|t| (0, t, w)).collect();
        let mut pd = vec![w; m + 1];
        pd[0] = p + m as f64 * w;
        let g = mean_field_gap(&pd, &pd, &star);
        let want = 0.5 * (1.0 + m as f64 * w / p).ln();
        assert!((g - want).abs() < 1e-8, "{g} vs {want}");
    }
}
