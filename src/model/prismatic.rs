//! Prismatic joint: the child translates along a unit direction `d`.
//!
//! Standardised parameters after the common block of [`super::rigid`]:
//! - `xi[5..8] = v ~ N(0, I)`, `d = v / |v|`: a standard normal vector normalised is uniform on
//!   the sphere, so the prior over directions is uniform (the 6D screw of paper §3.2 with zero
//!   rotational part).
//!
//! Joint coordinate `q` \[m\]: displacement along `d`, which is the path length of the centre of mass.

use super::{normalize, Displacement, JointParams, Real};
use nalgebra::{Matrix3, Vector3};

/// Number of standardised parameters of a prismatic joint.
pub const NUM_PARAMS: usize = super::rigid::NUM_PARAMS + 3;

pub(super) fn decode<T: Real>(mut p: JointParams<T>, xi: &[T]) -> JointParams<T> {
    p.direction = normalize(&Vector3::new(xi[0], xi[1], xi[2]));
    p
}

pub(super) fn displacement<T: Real>(p: &JointParams<T>, q: T) -> Displacement<T> {
    Displacement { r: Matrix3::identity(), t: p.direction * q }
}

/// Initial standardised axis parameters and coordinates from a centre-of-mass track (fixed
/// frame): the principal direction of the positions, `|v| = 3` so that the guide's spread on `v`
/// maps to a small angle, and `q` the projections onto it.
pub fn init(track: &[Vector3<f64>], com0: &Vector3<f64>) -> ([f64; 3], Vec<f64>) {
    let d = principal_direction(track).unwrap_or(Vector3::x());
    let q = track.iter().map(|y| (y - com0).dot(&d)).collect();
    ([3.0 * d.x, 3.0 * d.y, 3.0 * d.z], q)
}

/// Direction of largest spread of a set of points, if they spread at all.
pub fn principal_direction(track: &[Vector3<f64>]) -> Option<Vector3<f64>> {
    let n = track.len() as f64;
    if track.len() < 2 {
        return None;
    }
    let mean = track.iter().sum::<Vector3<f64>>() / n;
    let cov = track.iter().map(|y| (y - mean) * (y - mean).transpose()).sum::<Matrix3<f64>>() / n;
    let e = cov.symmetric_eigen();
    let i = e.eigenvalues.imax();
    (e.eigenvalues[i] > 0.0).then(|| e.eigenvectors.column(i).into_owned())
}
