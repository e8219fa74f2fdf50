//! Perception stage: segmented clouds (fixed frame) to per-part centres of mass and orientations,
//! each with an uncertainty.
//!
//! Per frame and part:
//! 1. **Stray points** are removed: points farther from the coordinate-wise median than
//!    `max(median + 6 x 1.4826 x MAD, 4 x median)` of the distances are dropped (a robust
//!    6-sigma rule that still keeps the corners of a box-shaped part).
//! 2. **Centre of mass**: where the inliers span a volume (at least 8 points and the smallest
//!    principal standard deviation above `min_thickness_m`), the centroid of their convex hull
//!    computed with parry3d's mass properties (uniform density). **Fallback** for flat or tiny
//!    clouds (a door front seen face-on, a small patch): the mean of the inliers, which for a
//!    planar patch is its area centroid up to sampling density.
//! 3. **Uncertainty**: the isotropic standard error `sqrt(mean principal variance / n) + floor`,
//!    where the floor (`com_sd_floor_m`) stands for the systematic error of partial views.
//! 4. **Orientation** from the principal axes of the inliers, where the cloud supports it: the
//!    three principal variances must differ pairwise by at least `orientation_min_ratio`, else the
//!    frame is undefined (a square patch, a sphere) and no orientation is reported. The signs of
//!    the first two axes agree with the previous frame of the same part (continuity), or, with no
//!    history, point to the side of larger third moment; the third axis completes a right-handed
//!    frame. The reported spread is the first-order angle error of an eigenvector,
//!    `atan(sqrt(l_small * l_big / (n (l_big - l_small)^2)))` for the closest pair of variances.
//! 5. **Surface normal**: where the cloud is flat (second principal variance at least
//!    `orientation_min_ratio` x the third) its axis of least spread, kept sign-continuous per part;
//!    this is the part of the orientation that a flat front (door, drawer) supports even when its
//!    in-plane axes are ambiguous. Spread as above plus `normal_sd_floor_rad`.

use std::collections::BTreeMap;

use nalgebra::{Matrix3, Point3, Rotation3, SymmetricEigen, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::input::CloudFrame;

/// Perception settings (`perception` section of the config).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct PerceptionConfig {
    /// Minimum smallest principal standard deviation for the convex-hull centroid \[m\].
    pub min_thickness_m: f64,
    /// Systematic floor added to the standard error of a centre of mass \[m\].
    pub com_sd_floor_m: f64,
    /// Minimum ratio between principal variances for an orientation (or a surface normal) to be
    /// reported.
    pub orientation_min_ratio: f64,
    /// Floor added to the standard deviation of a surface normal \[rad\].
    pub normal_sd_floor_rad: f64,
    /// Fewer points than this and the part is treated as not seen in that frame.
    pub min_points: usize,
}

impl Default for PerceptionConfig {
    fn default() -> Self {
        PerceptionConfig { min_thickness_m: 0.005, com_sd_floor_m: 0.001, orientation_min_ratio: 1.3, normal_sd_floor_rad: 0.02, min_points: 3 }
    }
}

/// One part seen in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PartObservation {
    /// Header stamp \[s\].
    pub stamp: f64,
    /// Estimated centre of mass \[m\], fixed frame.
    pub com: Point3<f64>,
    /// Isotropic standard deviation of `com` \[m\].
    pub com_sd: f64,
    /// Orientation of the principal axes in the fixed frame, when the cloud supports it.
    pub orientation: Option<UnitQuaternion<f64>>,
    /// Standard deviation of the orientation \[rad\] (NaN when `orientation` is None).
    pub orientation_sd: f64,
    /// Unit surface normal (axis of least spread) where the cloud is flat enough to define it
    /// (second principal variance > `orientation_min_ratio` x the third), sign continuous in time.
    pub normal: Option<Vector3<f64>>,
    /// Standard deviation of `normal` \[rad\] (NaN when None).
    pub normal_sd: f64,
    /// Inlier points used.
    pub points: usize,
    /// Stray points removed.
    pub outliers: usize,
}

/// Per-part observation tracks, by label, in time order.
pub type PartTracks = BTreeMap<u32, Vec<PartObservation>>;

/// Stateful perception: keeps the previous orientation of each part for sign continuity.
#[derive(Debug, Default)]
pub struct Perception {
    pub config: PerceptionConfig,
    last_axes: BTreeMap<u32, Matrix3<f64>>,
    last_normal: BTreeMap<u32, Vector3<f64>>,
}

impl Perception {
    pub fn new(config: PerceptionConfig) -> Self {
        Perception { config, last_axes: BTreeMap::new(), last_normal: BTreeMap::new() }
    }

    /// Observe every part of one cloud; parts with fewer than `min_points` points are skipped.
    pub fn observe(&mut self, cloud: &CloudFrame) -> Vec<(u32, PartObservation)> {
        let mut by_label: BTreeMap<u32, Vec<Point3<f64>>> = BTreeMap::new();
        for (p, l) in cloud.points.iter().zip(&cloud.labels) {
            by_label.entry(*l).or_default().push(*p);
        }
        let mut out = Vec::new();
        for (label, pts) in by_label {
            if pts.len() < self.config.min_points {
                continue;
            }
            let prev = self.last_axes.get(&label).copied();
            let (mut obs, axes) = estimate(&pts, cloud.stamp, &self.config, prev);
            if let Some(a) = axes {
                self.last_axes.insert(label, a);
            }
            if let Some(n) = obs.normal.as_mut() {
                if let Some(prev) = self.last_normal.get(&label) {
                    if n.dot(prev) < 0.0 {
                        *n = -*n;
                    }
                }
                self.last_normal.insert(label, *n);
            }
            out.push((label, obs));
        }
        out
    }

    /// Observe a whole recording.
    pub fn observe_all(&mut self, clouds: &[CloudFrame]) -> PartTracks {
        let mut tracks = PartTracks::new();
        for c in clouds {
            for (label, obs) in self.observe(c) {
                tracks.entry(label).or_default().push(obs);
            }
        }
        tracks
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

/// First-order angular sd \[rad\] of the eigenvector of variance `small` against the one of
/// variance `big` (`big > small`), from `n` points: `atan(sqrt(small * big / (n * (big - small)^2)))`.
fn eigenvector_sd(small: f64, big: f64, n: usize) -> f64 {
    (small * big / (n as f64 * (big - small).powi(2)).max(1e-300)).sqrt().atan()
}

/// Estimate the centre of mass, its uncertainty and the orientation of one part's points.
/// Returns the observation and the principal axes (columns) when an orientation was found.
pub fn estimate(
    pts: &[Point3<f64>],
    stamp: f64,
    cfg: &PerceptionConfig,
    prev_axes: Option<Matrix3<f64>>,
) -> (PartObservation, Option<Matrix3<f64>>) {
    // 1. Robust centre and stray-point rejection.
    let mut c = [0.0; 3];
    for (k, ck) in c.iter_mut().enumerate() {
        let mut v: Vec<f64> = pts.iter().map(|p| p[k]).collect();
        *ck = median(&mut v);
    }
    let centre = Point3::new(c[0], c[1], c[2]);
    let mut d: Vec<f64> = pts.iter().map(|p| (p - centre).norm()).collect();
    let med = median(&mut d.clone());
    let mad = median(&mut d.iter().map(|x| (x - med).abs()).collect::<Vec<_>>());
    let cut = (med + 6.0 * 1.4826 * mad).max(4.0 * med).max(1e-3);
    d = pts.iter().map(|p| (p - centre).norm()).collect();
    let inliers: Vec<Point3<f64>> = pts.iter().zip(&d).filter(|(_, &di)| di <= cut).map(|(p, _)| *p).collect();
    let n = inliers.len().max(1);

    // 2. Principal axes of the inliers.
    let mean = inliers.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n as f64;
    let mut cov = Matrix3::zeros();
    for p in &inliers {
        let r = p.coords - mean;
        cov += r * r.transpose();
    }
    cov /= n as f64;
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let lam: Vec<f64> = order.iter().map(|&i| eig.eigenvalues[i].max(0.0)).collect();

    // 3. Centre of mass: convex hull centroid where the points span a volume, else the mean.
    let mut com = Point3::from(mean);
    if inliers.len() >= 8 && lam[2].sqrt() >= cfg.min_thickness_m {
        // parry works in f32: express the points relative to their mean to keep precision.
        let local: Vec<parry3d::math::Vector> = inliers
            .iter()
            .map(|p| {
                let r = p.coords - mean;
                parry3d::math::Vector::new(r.x as f32, r.y as f32, r.z as f32)
            })
            .collect();
        if let Ok((verts, idx)) = parry3d::transformation::try_convex_hull(&local) {
            let mp = parry3d::mass_properties::MassProperties::from_convex_polyhedron(1.0, &verts, &idx);
            let lc = mp.local_com;
            if mp.mass() > 0.0 && lc.x.is_finite() && lc.y.is_finite() && lc.z.is_finite() {
                com = Point3::from(mean + Vector3::new(lc.x as f64, lc.y as f64, lc.z as f64));
            }
        }
    }
    let se = (lam.iter().sum::<f64>() / 3.0 / n as f64).sqrt();
    let com_sd = se + cfg.com_sd_floor_m;

    // 4. Orientation where the principal variances are distinct.
    let r = cfg.orientation_min_ratio;
    let distinct = lam[2] > 0.0 && lam[0] > r * lam[1] && lam[1] > r * lam[2];
    let (orientation, orientation_sd, axes) = if distinct {
        let mut a = Matrix3::from_columns(&[
            eig.eigenvectors.column(order[0]).into_owned(),
            eig.eigenvectors.column(order[1]).into_owned(),
            eig.eigenvectors.column(order[2]).into_owned(),
        ]);
        for k in 0..2 {
            let flip = match prev_axes {
                Some(p) => a.column(k).dot(&p.column(k)) < 0.0,
                // No history: make the axis point to the side with the larger third moment.
                None => inliers.iter().map(|p| (p.coords - mean).dot(&a.column(k)).powi(3)).sum::<f64>() < 0.0,
            };
            if flip {
                let col = -a.column(k);
                a.set_column(k, &col);
            }
        }
        let z = a.column(0).cross(&a.column(1));
        a.set_column(2, &z);
        let sd = eigenvector_sd(lam[1], lam[0], n).max(eigenvector_sd(lam[2], lam[1], n));
        let rot = Rotation3::from_matrix_unchecked(a);
        (Some(UnitQuaternion::from_rotation_matrix(&rot)), sd, Some(a))
    } else {
        (None, f64::NAN, None)
    };
    // Surface normal of a flat cloud; with no history its largest component is made positive.
    let (normal, normal_sd) = if lam[1] > r * lam[2] {
        let mut nrm = eig.eigenvectors.column(order[2]).into_owned();
        if nrm[nrm.iamax()] < 0.0 {
            nrm = -nrm;
        }
        let sd = eigenvector_sd(lam[2], lam[1], n) + cfg.normal_sd_floor_rad;
        (Some(nrm), sd)
    } else {
        (None, f64::NAN)
    };
    let obs = PartObservation {
        stamp,
        normal,
        normal_sd,
        com,
        com_sd,
        orientation,
        orientation_sd,
        points: inliers.len(),
        outliers: pts.len() - inliers.len(),
    };
    (obs, axes)
}

/// The part whose points lie nearest to `point` (contract: the pushed part is the one nearest the
/// contact point), with that distance \[m\].
pub fn nearest_part(cloud: &CloudFrame, point: &Point3<f64>) -> Option<(u32, f64)> {
    cloud
        .points
        .iter()
        .zip(&cloud.labels)
        .map(|(p, l)| (*l, (p - point).norm()))
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn hull_centroid_of_a_box_ignores_strays_and_density() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        // A 0.4 x 0.2 x 0.1 box centred at (1, 2, 3), sampled much more densely on one half.
        let mut pts: Vec<Point3<f64>> = (0..3000)
            .map(|i| {
                let x = if i % 4 == 0 { rng.random_range(-0.2..0.2) } else { rng.random_range(0.0..0.2) };
                Point3::new(1.0 + x, 2.0 + rng.random_range(-0.1..0.1), 3.0 + rng.random_range(-0.05..0.05))
            })
            .collect();
        pts.push(Point3::new(5.0, 5.0, 5.0));
        let (o, _) = estimate(&pts, 0.0, &PerceptionConfig::default(), None);
        assert_eq!(o.outliers, 1);
        assert!((o.com - Point3::new(1.0, 2.0, 3.0)).norm() < 0.01, "{}", o.com);
        assert!(o.com_sd > 0.0 && o.com_sd < 0.01);
        let q = o.orientation.expect("a box has distinct principal axes");
        let x = q * Vector3::x();
        assert!(x.x.abs() > 0.99, "{x}");
    }

    #[test]
    fn flat_square_patch_falls_back_to_mean_without_orientation() {
        let pts: Vec<Point3<f64>> =
            (0..25).map(|i| Point3::new(0.01 * (i % 5) as f64, 0.01 * (i / 5) as f64, 0.5)).collect();
        let (o, axes) = estimate(&pts, 0.0, &PerceptionConfig::default(), None);
        assert!((o.com - Point3::new(0.02, 0.02, 0.5)).norm() < 1e-9);
        assert!(o.orientation.is_none() && axes.is_none());
    }
}
