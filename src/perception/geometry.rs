//! Geometry of point sets: robust stray-point removal, principal axes, convex-hull mass
//! properties (parry3d), surface normals and the contact areas between parts.

use nalgebra::{Isometry3, Matrix3, Point3, SymmetricEigen, Vector3};

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        return 0.0;
    }
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

/// Indices of the points that are not strays: points farther from the coordinate-wise median
/// than `max(median + 6 x 1.4826 x MAD, 4 x median, 1 mm)` of the distances are dropped (a robust
/// 6-sigma rule that still keeps the corners of a box-shaped part).
pub fn inliers(pts: &[Point3<f64>]) -> Vec<usize> {
    let mut c = [0.0; 3];
    for (k, ck) in c.iter_mut().enumerate() {
        let mut v: Vec<f64> = pts.iter().map(|p| p[k]).collect();
        *ck = median(&mut v);
    }
    let centre = Point3::new(c[0], c[1], c[2]);
    let d: Vec<f64> = pts.iter().map(|p| (p - centre).norm()).collect();
    let med = median(&mut d.clone());
    let mad = median(&mut d.iter().map(|x| (x - med).abs()).collect::<Vec<_>>());
    let cut = (med + 6.0 * 1.4826 * mad).max(4.0 * med).max(1e-3);
    (0..pts.len()).filter(|&i| d[i] <= cut).collect()
}

/// Indices of the points that are not isolated (statistical outlier removal; Rusu et al. 2008,
/// "Towards 3D point cloud based object maps for household environments", section 4): a point
/// whose mean distance to its `k` nearest neighbours exceeds the median of that mean distance
/// over all points by more than `max(3 x 1.4826 x MAD, median / 2)` is dropped. Why: a part's
/// model gathers, over a recording, a few points that segmentation gave it elsewhere (behind a
/// panel, on a neighbour's edge); the convex hull takes each of them in whole, and one such
/// cluster moves the hull's centroid — the part's centre of mass — by centimetres. Returns every
/// index when there are no more than `k` points or `k` is 0. Exact duplicates count once.
pub fn isolated_free(pts: &[Point3<f64>], k: usize) -> Vec<usize> {
    use kiddo::{KdTree, SquaredEuclidean};
    if k == 0 || pts.len() <= k + 1 {
        return (0..pts.len()).collect();
    }
    let mut tree: KdTree<f64, 3> = KdTree::new();
    let mut seen = std::collections::HashSet::new();
    for (i, p) in pts.iter().enumerate() {
        if seen.insert((p.x.to_bits(), p.y.to_bits(), p.z.to_bits())) {
            tree.add(&[p.x, p.y, p.z], i as u64);
        }
    }
    if seen.len() <= k + 1 {
        return (0..pts.len()).collect();
    }
    // Mean distance to the k nearest other points (the nearest returned is the point itself).
    let mean_d: Vec<f64> = pts
        .iter()
        .map(|p| {
            let nb = tree.nearest_n::<SquaredEuclidean>(&[p.x, p.y, p.z], k + 1);
            nb.iter().skip(1).map(|n| n.distance.sqrt()).sum::<f64>() / k as f64
        })
        .collect();
    let med = median(&mut mean_d.clone());
    let mad = median(&mut mean_d.iter().map(|x| (x - med).abs()).collect::<Vec<_>>());
    let cut = med + (3.0 * 1.4826 * mad).max(0.5 * med);
    (0..pts.len()).filter(|&i| mean_d[i] <= cut).collect()
}

/// Principal axes of a point set: mean, variances in decreasing order and the matching unit
/// axes (columns).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Principal {
    pub mean: Vector3<f64>,
    pub variances: [f64; 3],
    pub axes: Matrix3<f64>,
}

/// Principal axes of `pts` (at least one point).
pub fn principal(pts: &[Point3<f64>]) -> Principal {
    let n = pts.len().max(1) as f64;
    let mean = pts.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let cov = pts.iter().fold(Matrix3::zeros(), |a, p| {
        let r = p.coords - mean;
        a + r * r.transpose()
    }) / n;
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let variances = order.map(|i| eig.eigenvalues[i].max(0.0));
    let axes = Matrix3::from_columns(&order.map(|i| eig.eigenvectors.column(i).into_owned()));
    Principal { mean, variances, axes }
}

/// Mass properties of the convex hull of a point set, per unit mass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HullProperties {
    /// Centroid of the hull (uniform density) \[m\].
    pub centroid: Vector3<f64>,
    /// Rotational inertia about the centroid per kilogram, same axes as the points (m²).
    pub unit_inertia: Matrix3<f64>,
    /// Hull volume (m³).
    pub volume: f64,
}

/// Convex-hull mass properties (parry3d, uniform density) of points that span a volume: at least
/// 8 points and a smallest principal standard deviation of `min_thickness` \[m\]; `None` for flat or
/// tiny sets. Parry works in `f32`, so the points are expressed relative to their mean first.
pub fn hull_properties(pts: &[Point3<f64>], min_thickness: f64) -> Option<HullProperties> {
    let pr = principal(pts);
    if pts.len() < 8 || pr.variances[2].sqrt() < min_thickness {
        return None;
    }
    let local: Vec<parry3d::math::Vector> = pts
        .iter()
        .map(|p| {
            let r = p.coords - pr.mean;
            parry3d::math::Vector::new(r.x as f32, r.y as f32, r.z as f32)
        })
        .collect();
    let (verts, idx) = parry3d::transformation::try_convex_hull(&local).ok()?;
    let mp = parry3d::mass_properties::MassProperties::from_convex_polyhedron(1.0, &verts, &idx);
    let (mass, lc) = (mp.mass() as f64, mp.local_com);
    if !(mass > 0.0 && lc.x.is_finite() && lc.y.is_finite() && lc.z.is_finite()) {
        return None;
    }
    let centroid = pr.mean + Vector3::new(lc.x as f64, lc.y as f64, lc.z as f64);
    // Inertia about the centroid per unit mass (parry gives it for the density-1 hull).
    let cols = mp.reconstruct_inertia_matrix().to_cols_array();
    let unit_inertia = Matrix3::from_column_slice(&cols.map(|v| v as f64)) / mass;
    Some(HullProperties { centroid, unit_inertia, volume: mass })
}

/// Unit surface normal of a neighbourhood of points — the direction of least spread — and its
/// surface variation `l_min / (l_0 + l_1 + l_2)` (0 on a plane, 1/3 for an isotropic blob).
pub fn normal_of(pts: &[Vector3<f64>]) -> (Vector3<f64>, f64) {
    let n = pts.len().max(1) as f64;
    let mean = pts.iter().sum::<Vector3<f64>>() / n;
    let cov = pts.iter().fold(Matrix3::zeros(), |a, p| a + (p - mean) * (p - mean).transpose());
    let eig = SymmetricEigen::new(cov);
    let i = eig.eigenvalues.imin();
    let v = eig.eigenvectors.column(i).into_owned();
    let total = eig.eigenvalues.iter().map(|l| l.max(0.0)).sum::<f64>();
    let variation = if total > 0.0 { eig.eigenvalues[i].max(0.0) / total } else { 1.0 / 3.0 };
    if v.iter().all(|x| x.is_finite()) && v.norm() > 0.5 { (v.normalize(), variation) } else { (Vector3::z(), 1.0 / 3.0) }
}

/// The point-to-plane information about small rotations of the surface sampled by `pts` (m)
/// about `centre` (m): `Σ j jᵀ / N` with `j = (p - c) x n`, `n` each point's normal from its `k`
/// nearest points ([`normal_of`]), in m² (3x3, fixed frame). A rotation `w` moves a surface
/// point off its surface by `w · j`, so an axis with little information is one the surface does
/// not pin (a sphere's every axis, a disc's or flat plate's spin); unlike second moments it sees
/// that a cube's faces or a slab's edges pin theirs. Zero for fewer than `k + 1` points.
pub fn rotation_information(pts: &[Vector3<f64>], centre: &Vector3<f64>, k: usize) -> Matrix3<f64> {
    use kiddo::{KdTree, SquaredEuclidean};
    if pts.len() < k + 1 {
        return Matrix3::zeros();
    }
    let mut tree: KdTree<f64, 3> = KdTree::new();
    for (i, p) in pts.iter().enumerate() {
        tree.add(&[p.x, p.y, p.z], i as u64);
    }
    let mut a = Matrix3::zeros();
    for p in pts {
        let nb: Vec<Vector3<f64>> = tree.nearest_n::<SquaredEuclidean>(&[p.x, p.y, p.z], k).iter().map(|n| pts[n.item as usize]).collect();
        let (n, _) = normal_of(&nb);
        let j = (p - centre).cross(&n);
        a += j * j.transpose();
    }
    a / pts.len() as f64
}

/// Contact areas \[m²\] between the parts' surfaces (model points moved by their poses) at the first grid
/// frame in which both parts of a pair are seen: the number of model points of one part within
/// `range` of the other's, times the surface each point stands for (`voxel²`), averaged over both
/// directions. `poses[i][t]`: part `i`'s pose at frame `t` (None: not seen); `models[i]`: its
/// model points in its reference configuration. Returns the symmetric `n x n` matrix, 0 on the
/// diagonal and for pairs never seen together.
pub fn contact_areas(poses: &[&[Option<Isometry3<f64>>]], models: &[&[Vector3<f64>]], range: f64, voxel: f64) -> Vec<Vec<f64>> {
    use kiddo::{KdTree, SquaredEuclidean};
    let n = poses.len();
    let tree_of = |pose: &Isometry3<f64>, pts: &[Vector3<f64>]| {
        let mut tree: KdTree<f64, 3> = KdTree::new();
        let mut seen = std::collections::HashSet::new();
        for (j, p) in pts.iter().enumerate() {
            let x = pose * nalgebra::Point3::from(*p);
            if seen.insert((x.x.to_bits(), x.y.to_bits(), x.z.to_bits())) {
                tree.add(&[x.x, x.y, x.z], j as u64);
            }
        }
        tree
    };
    let near = |tree: &KdTree<f64, 3>, pose: &Isometry3<f64>, pts: &[Vector3<f64>]| {
        pts.iter()
            .filter(|p| {
                let x = pose * nalgebra::Point3::from(**p);
                tree.nearest_one::<SquaredEuclidean>(&[x.x, x.y, x.z]).distance <= range * range
            })
            .count()
    };
    let mut a = vec![vec![0.0; n]; n];
    for i in 0..n {
        for k in i + 1..n {
            let both = (0..poses[i].len()).find_map(|t| Some((poses[i][t]?, poses[k][t]?)));
            let area = match both {
                Some((pi, pk)) if !models[i].is_empty() && !models[k].is_empty() => {
                    let (ti, tk) = (tree_of(&pi, models[i]), tree_of(&pk, models[k]));
                    0.5 * (near(&tk, &pi, models[i]) + near(&ti, &pk, models[k])) as f64 * voxel * voxel
                }
                _ => 0.0,
            };
            a[i][k] = area;
            a[k][i] = area;
        }
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn hull_of_a_box_ignores_density_and_gives_its_inertia() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        // A 0.4 x 0.2 x 0.1 box centred at (1, 2, 3), sampled much more densely on one half,
        // plus a stray point that the inlier rule drops.
        let mut pts: Vec<Point3<f64>> = (0..3000)
            .map(|i| {
                let x = if i % 4 == 0 { rng.random_range(-0.2..0.2) } else { rng.random_range(0.0..0.2) };
                Point3::new(1.0 + x, 2.0 + rng.random_range(-0.1..0.1), 3.0 + rng.random_range(-0.05..0.05))
            })
            .collect();
        pts.push(Point3::new(5.0, 5.0, 5.0));
        let keep = inliers(&pts);
        assert_eq!(keep.len(), pts.len() - 1);
        let kept: Vec<Point3<f64>> = keep.iter().map(|&i| pts[i]).collect();
        let h = hull_properties(&kept, 0.005).expect("a box spans a volume");
        assert!((h.centroid - Vector3::new(1.0, 2.0, 3.0)).norm() < 0.01, "{}", h.centroid);
        assert!((h.volume - 0.4 * 0.2 * 0.1).abs() < 0.001, "{}", h.volume);
        // Box inertia per kg about x: (b^2 + c^2) / 12.
        let ixx = (0.2f64.powi(2) + 0.1f64.powi(2)) / 12.0;
        assert!((h.unit_inertia[(0, 0)] - ixx).abs() < 0.1 * ixx, "{}", h.unit_inertia);
        // A flat patch spans no volume.
        let flat: Vec<Point3<f64>> = (0..25).map(|i| Point3::new(0.01 * (i % 5) as f64, 0.01 * (i / 5) as f64, 0.5)).collect();
        assert!(hull_properties(&flat, 0.005).is_none());
        let (n, variation) = normal_of(&flat.iter().map(|p| p.coords).collect::<Vec<_>>());
        assert!(n.z.abs() > 0.999 && variation < 1e-9, "{n} {variation}");
    }

    #[test]
    fn isolated_points_leave_the_hull_and_its_centroid() {
        // A panel's model: a 0.4 x 0.6 m face and its back 16 mm behind, on an 8 mm grid (the
        // model voxel), plus 20 points segmentation gave the panel 25-35 cm behind it, scattered as
        // they are on real models (stop 42: effects-corpus obj015's door).
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut pts: Vec<Point3<f64>> = Vec::new();
        for i in 0..50 {
            for j in 0..75 {
                pts.push(Point3::new(0.008 * i as f64, 0.008 * j as f64, 0.0));
                pts.push(Point3::new(0.008 * i as f64, 0.008 * j as f64, -0.016));
            }
        }
        let n_panel = pts.len();
        for _ in 0..20 {
            pts.push(Point3::new(rng.random_range(0.0..0.4), rng.random_range(0.0..0.6), -rng.random_range(0.25..0.35)));
        }
        let all = hull_properties(&pts, 0.005).expect("volume");
        let keep = isolated_free(&pts, 8);
        // Every stray goes, and (nearly) every panel point stays: the rule looks at a point's
        // mean distance to its neighbours, which a grid's edges raise only a little.
        assert!(keep.iter().all(|&i| i < n_panel), "a stray was kept");
        assert!(keep.len() >= n_panel * 99 / 100, "{} of {n_panel}", keep.len());
        let kept: Vec<Point3<f64>> = keep.iter().map(|&i| pts[i]).collect();
        let clean = hull_properties(&kept, 0.005).expect("volume");
        let truth = Vector3::new(0.196, 0.296, -0.008);
        assert!((clean.centroid - truth).norm() < 0.01, "{}", clean.centroid);
        assert!((all.centroid - truth).norm() > 0.1, "the strays' hull should be off: {}", all.centroid);
        // Off, or too few points to judge: every index.
        assert_eq!(isolated_free(&pts, 0).len(), pts.len());
        assert_eq!(isolated_free(&pts[..5], 8).len(), 5);
    }
}
