//! Revolute joint: the child rotates about an axis with unit direction `d` through point `p`.
//!
//! Standardised parameters after the common block of [`super::rigid`]:
//! - `xi[5..8] = v ~ N(0, I)`, `d = v / |v|` (uniform prior over directions);
//! - `xi[8..11]`: axis point `p = com0 + axis_point_sd_m * xi[8..11]` \[m\]; besides its `N(0, I)`
//!   prior, the axis must reach the part ([`reach_prior`]).
//!
//! Joint coordinate `q` \[m\]: path length of the centre of mass, so the rotation angle is
//! `q / r` with `r = sqrt(dist(com, axis)^2 + min_radius_m^2)`. Measuring every movable joint in
//! metres of centre-of-mass path makes the smoothness prior on coordinates the same statement for
//! prismatic and revolute joints; otherwise its Occam factor (one per frame) would favour one type
//! by the ratio of the units.

use super::{c, normalize, rotation, Displacement, JointParams, ModelConfig, Real};
use nalgebra::{Matrix3, Vector3};

/// Number of standardised parameters of a revolute joint.
pub const NUM_PARAMS: usize = super::rigid::NUM_PARAMS + 6;

pub(super) fn decode<T: Real>(mut p: JointParams<T>, xi: &[T], com0: &Vector3<f64>, cfg: &ModelConfig) -> JointParams<T> {
    let d = normalize(&Vector3::new(xi[0], xi[1], xi[2]));
    let point = Vector3::new(
        c::<T>(com0.x) + xi[3] * cfg.axis_point_sd_m,
        c::<T>(com0.y) + xi[4] * cfg.axis_point_sd_m,
        c::<T>(com0.z) + xi[5] * cfg.axis_point_sd_m,
    );
    let rel = p.com - point;
    let perp = rel - d * rel.dot(&d);
    p.radius = (perp.dot(&perp) + cfg.min_radius_m * cfg.min_radius_m).sqrt();
    p.direction = d;
    p.point = point;
    p
}

pub(super) fn displacement<T: Real>(p: &JointParams<T>, q: T) -> Displacement<T> {
    let r = rotation(&p.direction, q / p.radius);
    Displacement { r, t: p.point - super::mat_vec(&r, &p.point) }
}

/// Log prior that the axis reaches the part it carries \[nats\]: 0 while the axis passes within
/// `reach + m` of the part's reference centre of mass `com0`, else `-0.5 ((dist - reach - m) / m)^2`,
/// with `dist` the axis line's distance from `com0` \[m\], `reach` the part's extent (distance from
/// `com0` to its farthest model points, [`super::likelihood::PartSeries::reach`]) and
/// `m = hinge_reach_m`. 0 when `m` is 0 (off) or the part is smaller than `2 m` (a marker patch,
/// a knob: a small model cannot bound where its hinge is).
///
/// Why: a hinge is a physical connection between the part and its parent, so its line passes
/// through or next to the part (a door's edge, a lid's back, a latch's shaft); `m` allows for a
/// strip at the hinge edge that perception does not see. The standard-normal prior on the
/// axis point alone (`axis_point_sd_m` around `com0`) lets a short, nearly straight track with a
/// small spurious turn be explained by a hinge metres away, which costs it a few tens of nats
/// while the turn it explains earns a revolute joint hundreds (issue 24: a slider whose
/// registration picked up a persistent 2.6 degree turn, called revolute about an axis 1.2 m from
/// it at P = 0.99).
pub fn reach_prior<T: Real>(p: &JointParams<T>, com0: &Vector3<f64>, reach: f64, cfg: &ModelConfig) -> T {
    let Some(bound) = reach_bound(reach, cfg) else {
        return c(0.0);
    };
    let rel = com0.map(c::<T>) - p.point;
    let along = rel.dot(&p.direction);
    let perp = rel - p.direction * along;
    let dist = (perp.dot(&perp) + c::<T>(1e-12)).sqrt();
    let excess = dist - c::<T>(bound);
    if excess.re() <= 0.0 {
        return c(0.0);
    }
    let z = excess / c::<T>(cfg.hinge_reach_m);
    -(z * z) * c::<T>(0.5)
}

/// The distance from `com0` within which [`reach_prior`] costs nothing, `reach + hinge_reach_m`
/// \[m\]; `None` where the prior does not apply (switched off, or a part smaller than twice the
/// margin).
fn reach_bound(reach: f64, cfg: &ModelConfig) -> Option<f64> {
    let m = cfg.hinge_reach_m;
    (m > 0.0 && reach >= 2.0 * m).then_some(reach + m)
}

/// The coordinate \[m of path\] of a revolute joint that best explains part of an observed
/// rotation `o` (fixed frame, since the reference configuration), with its variance \[m²\]:
/// the joint angle `theta = q / radius` at which the predicted rotation `pre.r * R(d, theta)`
/// (`pre`: the parent's displacement at this frame) comes closest to `o.r` in the rotation
/// likelihood's metric ([`super::likelihood::log_likelihood_rotation`]: per observable axis `u`,
/// variance `var_u + rot_noise^2`), by Gauss-Newton steps from `q0`. `None` for a joint that is
/// not revolute or a rotation that says nothing about the angle (no observable axis along the
/// joint's axis in the fixed frame).
///
/// Why: a revolute part's rotation measures its angle directly, while its centre of mass measures
/// it only through the radius (a door's centre is 0.2-0.3 m from its hinge, a lid's or a latch's
/// less); the kinematic likelihood (eq. 2) uses both, and the observed coordinates of the collapsed
/// kinodynamic fit ([`crate::inference::svi`]) and of model criticism take this in place of the
/// centre's where the part's shape shows the turn ([`super::observed_coordinate`]).
pub fn rotation_coordinate(p: &JointParams<f64>, pre: &Displacement<f64>, o: &super::likelihood::RotationObs, q0: f64) -> Option<(f64, f64)> {
    if p.joint != super::JointType::Revolute || !(p.radius > 0.0) {
        return None;
    }
    let axis = pre.r * p.direction;
    let s2 = p.rot_noise * p.rot_noise;
    let info: f64 = o.axes.iter().map(|(u, v)| axis.dot(u).powi(2) / (v + s2)).sum();
    // Less than the information of one axis at 1 rad of sd: the rotation does not see the angle.
    if !(info > 1.0) {
        return None;
    }
    let mut theta = q0 / p.radius;
    for _ in 0..3 {
        // The error as in the likelihood; to first order it turns by `axis` per radian of `theta`.
        let w = o.error(&(pre.r * rotation(&p.direction, theta)));
        let g: f64 = o.axes.iter().map(|(u, v)| axis.dot(u) * w.dot(u) / (v + s2)).sum();
        theta -= g / info;
    }
    theta.is_finite().then(|| (theta * p.radius, p.radius * p.radius / info))
}

/// How far from `com0` an initial axis point may be \[m\]: 3 prior sd, and no farther than the
/// part's `reach` plus `hinge_reach_m` where [`reach_prior`] applies (a start outside it would
/// spend the fit's first steps walking the axis in).
pub fn init_max_offset(reach: f64, cfg: &ModelConfig) -> f64 {
    let prior = 3.0 * cfg.axis_point_sd_m;
    reach_bound(reach, cfg).map_or(prior, |b| prior.min(b))
}

/// Initial standardised axis parameters and path-length coordinates from a centre-of-mass track
/// (fixed frame): the plane of the track by principal components, the circle in it by the
/// algebraic (Kåsa) least-squares fit, clamped to [`init_max_offset`] from `com0` when the track
/// is nearly straight (`reach`: the part's extent, [`reach_prior`]).
pub fn init(track: &[Vector3<f64>], com0: &Vector3<f64>, reach: f64, cfg: &ModelConfig) -> ([f64; 6], Vec<f64>) {
    let n = track.len().max(1) as f64;
    let mean = track.iter().sum::<Vector3<f64>>() / n;
    let cov = track.iter().map(|y| (y - mean) * (y - mean).transpose()).sum::<Matrix3<f64>>() / n;
    let e = cov.symmetric_eigen();
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| e.eigenvalues[b].total_cmp(&e.eigenvalues[a]));
    let (u, w, normal) = (
        e.eigenvectors.column(idx[0]).into_owned(),
        e.eigenvectors.column(idx[1]).into_owned(),
        e.eigenvectors.column(idx[2]).into_owned(),
    );
    // Kåsa fit: x^2 + y^2 = a x + b y + c in plane coordinates.
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    for y in track {
        let r = y - mean;
        let (px, py) = (r.dot(&u), r.dot(&w));
        let row = Vector3::new(px, py, 1.0);
        ata += row * row.transpose();
        atb += row * (px * px + py * py);
    }
    let max_off = init_max_offset(reach, cfg);
    let centre = match ata.try_inverse() {
        Some(inv) => {
            let s = inv * atb;
            mean + u * (s.x / 2.0) + w * (s.y / 2.0)
        }
        None => mean + w * max_off,
    };
    let mut off = centre - com0;
    if !off.iter().all(|x| x.is_finite()) {
        off = w * max_off;
    }
    if off.norm() > max_off {
        off *= max_off / off.norm();
    }
    let point = com0 + off;
    let d = normal;
    let rel = com0 - point;
    let perp = rel - d * rel.dot(&d);
    let radius = (perp.norm_squared() + cfg.min_radius_m * cfg.min_radius_m).sqrt();
    // Unwrapped angle of each sample around the axis, converted to path length.
    let e1 = if perp.norm() > 1e-9 { perp / perp.norm() } else { u };
    let e2 = d.cross(&e1);
    let mut q = Vec::with_capacity(track.len());
    let mut prev = 0.0f64;
    for y in track {
        let r = y - point;
        let mut a = r.dot(&e2).atan2(r.dot(&e1));
        while a - prev > std::f64::consts::PI {
            a -= 2.0 * std::f64::consts::PI;
        }
        while a - prev < -std::f64::consts::PI {
            a += 2.0 * std::f64::consts::PI;
        }
        prev = a;
        q.push(a * radius);
    }
    let s = cfg.axis_point_sd_m;
    ([3.0 * d.x, 3.0 * d.y, 3.0 * d.z, off.x / s, off.y / s, off.z / s], q)
}

/// Initial standardised axis parameters and path-length coordinates from observed rotations
/// `rots[k]` (since the reference frame, fixed frame) at positions `track[k]` of the centre of
/// mass: the axis direction is the mean rotation axis of the frames turned by more than 2 degrees,
/// the axis point the least-squares solution of `(I - R_k) p = y_k - R_k com0` (its component along
/// the axis taken from `com0`), the coordinates the signed angles times the radius. `None` when no
/// frame turned that much.
pub fn init_from_rotations(track: &[Vector3<f64>], rots: &[Matrix3<f64>], com0: &Vector3<f64>, reach: f64, cfg: &ModelConfig) -> Option<([f64; 6], Vec<f64>)> {
    let vee = |r: &Matrix3<f64>| Vector3::new(r[(2, 1)] - r[(1, 2)], r[(0, 2)] - r[(2, 0)], r[(1, 0)] - r[(0, 1)]) * 0.5;
    let angle_axis = |r: &Matrix3<f64>| {
        let w = vee(r);
        let angle = w.norm().atan2((r.trace() - 1.0) / 2.0);
        (angle, if w.norm() > 1e-12 { w / w.norm() } else { Vector3::z() })
    };
    let turned: Vec<(f64, Vector3<f64>)> = rots.iter().map(angle_axis).filter(|(a, _)| *a > 2f64.to_radians()).collect();
    let (_, big) = turned.iter().cloned().max_by(|a, b| a.0.total_cmp(&b.0))?;
    let d = turned.iter().fold(Vector3::zeros(), |acc, (a, ax)| acc + ax * (a * ax.dot(&big).signum()));
    let d = d.try_normalize(1e-12)?;
    // (I - R) p = y - R com0 for every turned frame, plus a weak pull of p towards com0 along d.
    let (mut ata, mut atb) = (d * d.transpose() * 1e-6, Vector3::zeros());
    for (y, r) in track.iter().zip(rots) {
        let a = Matrix3::identity() - r;
        let b = y - r * com0;
        ata += a.transpose() * a;
        atb += a.transpose() * b;
    }
    atb += d * d.dot(com0) * 1e-6;
    let p = ata.try_inverse()? * atb;
    let max_off = init_max_offset(reach, cfg);
    let mut off = p - com0;
    if !off.iter().all(|x| x.is_finite()) {
        return None;
    }
    if off.norm() > max_off {
        off *= max_off / off.norm();
    }
    let rel = -off;
    let perp = rel - d * rel.dot(&d);
    let radius = (perp.norm_squared() + cfg.min_radius_m * cfg.min_radius_m).sqrt();
    let q = rots.iter().map(|r| vee(r).dot(&d).atan2((r.trace() - 1.0) / 2.0 - 0.0) * radius).collect();
    let s = cfg.axis_point_sd_m;
    Some(([3.0 * d.x, 3.0 * d.y, 3.0 * d.z, off.x / s, off.y / s, off.z / s], q))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_axis_must_reach_its_part() {
        let cfg = ModelConfig::default();
        let com0 = Vector3::new(0.3, 0.0, 0.5);
        // Standardised parameters of a vertical axis through (x, 0, 0).
        let xi_at = |x: f64| [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, (x - com0.x) / cfg.axis_point_sd_m, 0.0, -com0.z / cfg.axis_point_sd_m];
        let prior = |xi: &[f64], reach: f64| reach_prior(&super::super::decode(super::super::JointType::Revolute, xi, &com0, &cfg), &com0, reach, &cfg);
        // A door 0.6 m wide hinged at its edge: within its extent, no cost.
        assert_eq!(prior(&xi_at(0.0), 0.35), 0.0);
        // The same part about an axis 1.2 m from its centre: 0.8 m beyond reach + margin.
        let far = prior(&xi_at(-0.9), 0.35);
        assert!((far + 0.5 * (0.8f64 / cfg.hinge_reach_m).powi(2)).abs() < 1e-6, "{far}");
        // A part smaller than twice the margin (a marker patch) and the prior switched off.
        assert_eq!(prior(&xi_at(-0.9), 0.05), 0.0);
        let off = ModelConfig { hinge_reach_m: 0.0, ..cfg.clone() };
        assert_eq!(reach_prior(&super::super::decode(super::super::JointType::Revolute, &xi_at(-0.9), &com0, &off), &com0, 0.35, &off), 0.0);
        // Its gradient from dual numbers against central differences, off the axis's symmetry.
        type D = num_dual::DualSVec64<11>;
        let mut xi = xi_at(-0.9);
        xi[5] = 0.4;
        xi[9] = 0.7;
        let xd: Vec<D> = xi.iter().enumerate().map(|(j, &x)| D::from_re(x).derivative(j)).collect();
        let g = reach_prior(&super::super::decode(super::super::JointType::Revolute, &xd, &com0, &cfg), &com0, 0.35, &cfg);
        let eps = g.eps.0.expect("a gradient");
        for j in 0..xi.len() {
            let h = 1e-6;
            let (mut a, mut b) = (xi, xi);
            a[j] += h;
            b[j] -= h;
            let fd = (prior(&a, 0.35) - prior(&b, 0.35)) / (2.0 * h);
            assert!((eps[j] - fd).abs() < 1e-4 * (1.0 + fd.abs()), "d/dxi[{j}]: dual {} fd {fd}", eps[j]);
        }
    }

    /// The coordinate read from a rotation recovers the joint's angle under a turned parent,
    /// ignores a turn about another axis, weighs the observable axes by their variances, and
    /// says nothing where no observable axis sees the joint's.
    #[test]
    fn a_rotation_measures_the_revolute_coordinate() {
        use super::super::likelihood::RotationObs;
        use super::super::JointType;
        let cfg = ModelConfig::default();
        let com0 = Vector3::new(0.3, 0.1, 0.5);
        // A hinge tilted from the vertical, 0.25 m from the centre of mass.
        let xi = [0.0, 0.0, 0.0, 0.0, 0.0, 0.2, -0.1, 3.0, -0.25 / cfg.axis_point_sd_m, 0.0, 0.0];
        let p = super::super::decode::<f64>(JointType::Revolute, &xi, &com0, &cfg);
        let pre = Displacement { r: rotation(&Vector3::new(1.0, 0.0, 0.0), 0.3), t: Vector3::new(0.0, 0.02, 0.0) };
        let q = 0.4 * p.radius;
        let axis = pre.r * p.direction;
        // Observed: the joint's rotation, then 0.05 rad about a direction off the joint's axis.
        let off = axis.cross(&Vector3::new(0.0, 1.0, 0.0)).normalize();
        let r_obs = rotation(&off, 0.05) * pre.r * rotation(&p.direction, 0.4);
        let axes: Vec<(Vector3<f64>, f64)> = [Vector3::x(), Vector3::y(), Vector3::z()].into_iter().zip([1e-4, 4e-4, 2.5e-5]).collect();
        // Without the off-axis turn the angle comes back exactly.
        let exact = RotationObs { r: pre.r * rotation(&p.direction, 0.4), axes: axes.clone() };
        let (qr, _) = rotation_coordinate(&p, &pre, &exact, 0.0).expect("the rotation sees the hinge");
        assert!((qr - q).abs() < 1e-9, "q {qr} against {q}");
        // With it, the coordinate minimises the likelihood's quadratic form (its derivative is 0).
        let o = RotationObs { r: r_obs, axes: axes.clone() };
        let (qr, var) = rotation_coordinate(&p, &pre, &o, 0.0).expect("the rotation sees the hinge");
        assert!((qr - q).abs() < 0.02 * p.radius, "q {qr} against {q}");
        let s2 = p.rot_noise * p.rot_noise;
        let form = |q: f64| {
            let w = o.error(&(pre.r * rotation(&p.direction, q / p.radius)));
            axes.iter().map(|(u, v)| w.dot(u).powi(2) / (v + s2)).sum::<f64>()
        };
        let h = 1e-6;
        let slope = (form(qr + h) - form(qr - h)) / (2.0 * h);
        assert!(slope.abs() < 1e-3 * (form(qr + 0.01) - form(qr)).abs() / 0.01, "slope {slope}");
        let info: f64 = axes.iter().map(|(u, v)| axis.dot(u).powi(2) / (v + s2)).sum();
        assert!((var - p.radius * p.radius / info).abs() < 1e-12 * var.max(1.0));
        // Only an axis perpendicular to the joint's observable: nothing about the angle.
        let o = RotationObs { r: r_obs, axes: vec![(off, 1e-4)] };
        assert!(rotation_coordinate(&p, &pre, &o, 0.0).is_none());
        // A prismatic joint's rotation does not move with its coordinate.
        let pp = super::super::decode::<f64>(JointType::Prismatic, &xi[..JointType::Prismatic.num_params()], &com0, &cfg);
        assert!(rotation_coordinate(&pp, &pre, &RotationObs { r: r_obs, axes }, 0.0).is_none());
    }

    #[test]
    fn quarter_turn_moves_com_along_the_circle() {
        let cfg = ModelConfig::default();
        let com0 = Vector3::new(1.0, 0.0, 0.0);
        // Axis z through the origin: p = com0 + axis_point_sd_m * xi.
        let xi = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, -1.0 / cfg.axis_point_sd_m, 0.0, 0.0];
        let p = super::super::decode(super::super::JointType::Revolute, &xi, &com0, &cfg);
        let quarter = std::f64::consts::FRAC_PI_2 * p.radius;
        let x = super::super::displacement(&p, quarter).apply(&p.com);
        assert!((x - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-3, "{x}");
        // A 0.5 m arc: the fitted centre is the origin, the coordinate the path length.
        let com0 = Vector3::new(0.5, 0.0, 0.0);
        let track: Vec<Vector3<f64>> = (0..20).map(|i| { let a = 0.05 * i as f64; Vector3::new(0.5 * a.cos(), 0.5 * a.sin(), 0.0) }).collect();
        let (axis, q) = init(&track, &com0, 0.0, &cfg);
        assert!((axis[3] * cfg.axis_point_sd_m + 0.5).abs() < 1e-6, "{axis:?}");
        assert!((q[19].abs() - 0.475).abs() < 2e-3, "{}", q[19]);
        // The same arc with its rotations observed.
        let rots: Vec<Matrix3<f64>> = (0..20).map(|i| super::super::rotation(&Vector3::z(), 0.05 * i as f64)).collect();
        let (axis, q) = init_from_rotations(&track, &rots, &com0, 0.0, &cfg).expect("it turns");
        assert!((axis[2] - 3.0).abs() < 1e-9 && (axis[3] * cfg.axis_point_sd_m + 0.5).abs() < 1e-6, "{axis:?}");
        let radius = (0.25f64 + cfg.min_radius_m.powi(2)).sqrt();
        assert!((q[19] - 0.95 * radius).abs() < 1e-9, "{}", q[19]);
    }
}
