//! Part tracking by registration: each part's pose relative to its reference configuration, by
//! robust ICP of its points against a model of the part that grows as new surfaces come into view.
//!
//! Why registration and not the centroid of the visible points: a part's *visible* surface changes
//! as the object moves — a cabinet's interior appears when its door opens, a door turned away
//! shows its edge — and the centroid of what is visible drifts by tens of centimetres while the
//! part does not move at all. Registering the points against a model of the part's surface
//! measures the part's motion, not the motion of its visible patch.
//!
//! Per frame (points in the fixed frame, `x = T y` with `y` in the reference configuration):
//! 1. **Costs**: point-to-plane distances to the nearest model point plus a weaker point-to-point
//!    term (weight `point_to_point_weight`), both with a Cauchy kernel, so that newly revealed
//!    surfaces, points of a neighbouring part and label noise cost at most a bounded amount. The
//!    kernel's scale is the noise of the points, estimated from each frame's residuals (1.4826 x
//!    their median absolute point-to-plane distance, within `[point_sd_min_m, point_sd_max_m]`):
//!    a fixed scale would make millimetre motions of a precisely seen part look insignificant. Points within `boundary_m` of a point of
//!    another part (where segmentation swaps labels) count with `boundary_weight`, or
//!    `edge_weight` where they are their own part's outline (see `split_parts` in the parent module).
//! 2. **ICP**: Gauss-Newton with iteratively reweighted correspondences, the first half of the
//!    iterations matching within `match_gate_m`, the second half within `fine_gate_m`.
//! 3. **Hypotheses**: the previous pose, the reference pose, and ICP from the previous pose, from
//!    a constant-velocity prediction and from the previous pose shifted by the motion of the
//!    points' centroid. Moving away from the previous pose costs `move_penalty_nats`: a part whose
//!    points are explained as well where it was does not move — unless the applied wrench pushes
//!    it in this frame and the move takes the part at the contact point along the force: then
//!    moving costs `push_move_penalty_nats` ([`super::PushGate`]). Returning to the reference pose
//!    costs `reference_penalty_nats` (nothing by default), so that a static part whose
//!    registration slipped along a direction its surface does not constrain comes back.
//!    This stops a static part sliding along directions its visible surface does not constrain (a
//!    cabinet front is a plane; only its edges fix its position in that plane).
//! 4. **Growth**: points of the frame (away from other parts) that lie farther than one voxel from
//!    the model become candidates in a voxel grid of size `voxel_m`; a candidate seen in
//!    `confirm_frames` different frames joins the model. Transient points — label noise, a door
//!    resting in front of the cabinet for a moment — are not confirmed in other poses.
//!
//! The fit's Gauss-Newton matrix gives the pose covariance, which says which directions the
//! points constrain (a flat panel does not constrain sliding in its own plane).

use std::collections::HashMap;

use kiddo::{KdTree, SquaredEuclidean};
use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};

use super::geometry::normal_of;
use super::PerceptionConfig;

/// Neighbours used for a surface normal.
const NORMAL_NEIGHBOURS: usize = 12;
/// Largest surface variation of a neighbourhood that still counts as a plane.
const PLANAR_MAX: f64 = 0.08;

/// Skew-symmetric cross-product matrix `[v]x`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The dominant plane of `pts` (a smoothing neighbourhood, [`Smoothing`]): unit normal, a point on
/// it and the inlier distance \[m\], or None when fewer than [`SMOOTHING_MIN_NEIGHBOURS`] points
/// or not most of them lie on one plane, or the inliers are not planar (surface variation
/// [`PLANAR_MAX`] or more). The distance's floor, a tenth of a voxel, keeps an exact
/// plane (simulated, noise-free) from rejecting its own rounding.
fn robust_plane(pts: &[Vector3<f64>], voxel: f64) -> Option<(Vector3<f64>, Vector3<f64>, f64)> {
    if pts.len() < SMOOTHING_MIN_NEIGHBOURS {
        return None;
    }
    let mut inliers: Vec<Vector3<f64>> = pts.to_vec();
    let (mut n, mut c, mut tol) = (Vector3::z(), Vector3::zeros(), 0.0);
    for _ in 0..SMOOTHING_ITERATIONS {
        if inliers.len() < SMOOTHING_MIN_NEIGHBOURS || 2 * inliers.len() <= pts.len() {
            return None;
        }
        let (normal, variation) = normal_of(&inliers);
        // The registration's own test of a plane (as for a normal): a curved patch (a handle, a
        // knob) is not flattened.
        if variation >= PLANAR_MAX {
            return None;
        }
        n = normal;
        c = inliers.iter().sum::<Vector3<f64>>() / inliers.len() as f64;
        tol = (SMOOTHING_TRIM * robust_sd(pts.iter().map(|q| n.dot(&(q - c)).abs()).collect())).max(0.1 * voxel);
        inliers = pts.iter().filter(|q| n.dot(&(*q - c)).abs() <= tol).copied().collect();
    }
    (inliers.len() >= SMOOTHING_MIN_NEIGHBOURS && 2 * inliers.len() > pts.len()).then_some((n, c, tol))
}

fn voxel_key(y: &Vector3<f64>, voxel: f64) -> [i64; 3] {
    [(y.x / voxel).floor() as i64, (y.y / voxel).floor() as i64, (y.z / voxel).floor() as i64]
}

#[derive(Debug, Clone)]
struct Candidate {
    count: usize,
    mean: Vector3<f64>,
    last_frame: usize,
}

/// A part's surface model in its reference configuration (fixed frame): points, normals and a
/// k-d tree over them. A point whose neighbourhood is not planar (an edge, a corner, the inside of
/// a volumetric blob) has no normal and is matched point to point.
pub struct PartModel {
    pub points: Vec<Vector3<f64>>,
    pub normals: Vec<Option<Vector3<f64>>>,
    tree: KdTree<f64, 3>,
    occupied: std::collections::HashSet<[i64; 3]>,
    candidates: HashMap<[i64; 3], Candidate>,
    /// Model size when every normal was last recomputed.
    refreshed_at: usize,
    /// Points before this index have had their one smoothing step ([`PartModel::smooth`]).
    smoothed: usize,
    voxel: f64,
    smoothing: Smoothing,
}

/// Moving-least-squares smoothing of a part model (Alexa et al. 2003, "Computing and rendering
/// point set surfaces", IEEE TVCG 9(1), the projection's first step, with a robust plane): each
/// point is projected once onto the plane of the model points within `radius_m` of it, fitted by
/// least squares on the points within `SMOOTHING_TRIM` (2.5) robust standard deviations of it
/// (iterated), and only when the point itself lies within them and the plane holds most of the
/// neighbourhood, and its inliers pass the registration's plane test (surface variation below
/// `PLANAR_MAX`, as for a normal). A point on another surface — the rim of a thin plate, the far
/// face at an edge, a corner — is an outlier of that plane and stays where it was seen, so the
/// features that fix a part's position in its own plane are kept; a curved patch smaller than the
/// radius (a handle) is not flattened.
///
/// Why: a model point is the mean of the few noisy depth samples that confirmed its voxel, so a
/// flat panel seen from afar becomes a slab as thick as the depth noise (8-14 mm rms at 1.6 m in
/// the corpus), and registration against a slab lets the panel slide and tilt within it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Smoothing {
    /// Neighbourhood radius \[m\]; 0 turns smoothing off.
    pub radius_m: f64,
}

/// Inliers of a smoothing plane lie within this many robust standard deviations (1.4826 x the
/// median absolute distance) of it.
const SMOOTHING_TRIM: f64 = 2.5;
/// Plane-fit iterations (each refits on the previous fit's inliers).
const SMOOTHING_ITERATIONS: usize = 3;
/// Fewest neighbours for a smoothing plane.
const SMOOTHING_MIN_NEIGHBOURS: usize = 8;

impl std::fmt::Debug for PartModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PartModel({} points)", self.points.len())
    }
}

impl PartModel {
    /// The diagonal of the model points' axis-aligned bounding box in the reference frame \[m\]
    /// (0 for an empty model): the part's size, by which a carrier is told from what it carries.
    pub fn extent(&self) -> f64 {
        let Some(first) = self.points.first() else { return 0.0 };
        let (lo, hi) = self.points.iter().fold((*first, *first), |(lo, hi), p| (lo.inf(p), hi.sup(p)));
        (hi - lo).norm()
    }

    /// A model from a first set of points (already free of strays, fixed frame \[m\]), one point
    /// per voxel of size `voxel` \[m\].
    pub fn new(points: &[Vector3<f64>], voxel: f64, smoothing: Smoothing) -> PartModel {
        let mut m = PartModel {
            points: Vec::new(),
            normals: Vec::new(),
            tree: KdTree::new(),
            occupied: Default::default(),
            candidates: HashMap::new(),
            refreshed_at: 0,
            smoothed: 0,
            voxel,
            smoothing,
        };
        for p in points {
            m.insert(*p);
        }
        m.refresh_normals();
        m
    }

    fn insert(&mut self, p: Vector3<f64>) -> bool {
        if !self.occupied.insert(voxel_key(&p, self.voxel)) {
            return false;
        }
        self.tree.add(&[p.x, p.y, p.z], self.points.len() as u64);
        self.points.push(p);
        self.normals.push(None);
        true
    }

    fn compute_normal(&self, i: usize) -> Option<Vector3<f64>> {
        let p = self.points[i];
        let nb: Vec<Vector3<f64>> = self
            .tree
            .nearest_n::<SquaredEuclidean>(&[p.x, p.y, p.z], NORMAL_NEIGHBOURS)
            .iter()
            .map(|n| self.points[n.item as usize])
            .collect();
        let (n, variation) = normal_of(&nb);
        (nb.len() >= 4 && variation < PLANAR_MAX).then_some(n)
    }

    /// Squared residual of `y` against model point `j`: along its normal, or the full distance
    /// where it has none.
    fn residual2(&self, j: usize, y: &Vector3<f64>) -> f64 {
        let e = y - self.points[j];
        match self.normals[j] {
            Some(n) => e.dot(&n).powi(2),
            None => e.norm_squared(),
        }
    }

    fn refresh_normals(&mut self) {
        self.smooth();
        for i in 0..self.points.len() {
            self.normals[i] = self.compute_normal(i);
        }
        self.refreshed_at = self.points.len();
    }

    /// Project the points added since the last call onto their neighbourhood's least-squares
    /// plane ([`Smoothing`]), once each: a point projected again and again would drift with its
    /// already-projected neighbours.
    fn smooth(&mut self) {
        let r = self.smoothing.radius_m;
        if r <= 0.0 {
            self.smoothed = self.points.len();
            return;
        }
        let moved: Vec<(usize, Vector3<f64>)> = (self.smoothed..self.points.len())
            .filter_map(|i| {
                let p = self.points[i];
                let nb: Vec<Vector3<f64>> =
                    self.tree.within_unsorted::<SquaredEuclidean>(&[p.x, p.y, p.z], r * r).iter().map(|n| self.points[n.item as usize]).collect();
                robust_plane(&nb, self.voxel).and_then(|(n, c, tol)| {
                    let d = n.dot(&(p - c));
                    (d.abs() <= tol).then(|| p - n * d)
                })
                .map(|q| (i, q))
            })
            .collect();
        // Moved after all are computed, so that the order of the points does not matter.
        for (i, q) in moved {
            let p = self.points[i];
            self.tree.remove(&[p.x, p.y, p.z], i as u64);
            self.tree.add(&[q.x, q.y, q.z], i as u64);
            self.points[i] = q;
        }
        self.smoothed = self.points.len();
    }

    /// Nearest model point to `y` within `gate` \[m\]: its index and squared distance.
    pub fn nearest(&self, y: &Vector3<f64>, gate: f64) -> Option<(usize, f64)> {
        if self.points.is_empty() {
            return None;
        }
        let n = self.tree.nearest_one::<SquaredEuclidean>(&[y.x, y.y, y.z]);
        (n.distance <= gate * gate).then_some((n.item as usize, n.distance))
    }

    /// Offer points of frame `frame` (reference coordinates, away from other parts) for growth;
    /// returns how many joined the model.
    pub fn grow(&mut self, ys: &[Vector3<f64>], frame: usize, confirm: usize, max_points: usize) -> usize {
        let mut added = Vec::new();
        for y in ys {
            if self.points.len() + added.len() >= max_points {
                break;
            }
            if self.nearest(y, 1.5 * self.voxel).is_some() {
                continue;
            }
            let key = voxel_key(y, self.voxel);
            if self.occupied.contains(&key) {
                continue;
            }
            let c = self.candidates.entry(key).or_insert(Candidate { count: 0, mean: *y, last_frame: usize::MAX });
            if c.last_frame == frame {
                continue;
            }
            c.count += 1;
            c.mean += (y - c.mean) / c.count as f64;
            c.last_frame = frame;
            if c.count >= confirm {
                added.push(c.mean);
                self.candidates.remove(&key);
            }
        }
        let mut n = 0;
        for p in added {
            if self.insert(p) {
                let i = self.points.len() - 1;
                self.normals[i] = self.compute_normal(i);
                n += 1;
            }
        }
        // Normals of older points were estimated from sparser neighbourhoods: refresh them all
        // once the model has grown by a quarter.
        if self.points.len() > self.refreshed_at + self.refreshed_at / 4 + 8 {
            self.refresh_normals();
        }
        n
    }
}

/// Model points remembered per frame point by [`Correspondences`].
const CACHED_NEIGHBOURS: usize = 4;

/// The nearest model points of one frame's points, remembered across the many registrations of
/// that frame against one model (every ICP iteration of every hypothesis, their costs, the noise
/// scale): the k-d tree search is most of perception's time, and ICP iterations and nearby
/// hypotheses move the points by less than the spacing of the model's points.
///
/// Exact, by the triangle inequality: a frame point searched at `y0` remembers its
/// `CACHED_NEIGHBOURS` nearest model points, the farthest of them at distance `dk`. At `y`, a
/// distance `δ = |y - y0|` away, every other model point is at least `dk - δ` from `y`, so the
/// nearest of the remembered points is the nearest of all while it lies within `dk - δ`; the tree
/// is searched again only when it does not. The borrow of the model keeps it from growing while
/// the answers are in use.
pub struct Correspondences<'m> {
    model: &'m PartModel,
    /// Per frame point: where it was searched, and the remembered model points with their
    /// distances from there (ascending) \[m\].
    cache: Vec<Option<Remembered>>,
    /// Tree searches made and answers reused (diagnostics).
    pub searched: usize,
    pub reused: usize,
}

#[derive(Debug, Clone)]
struct Remembered {
    at: Vector3<f64>,
    len: usize,
    items: [u32; CACHED_NEIGHBOURS],
    distances: [f64; CACHED_NEIGHBOURS],
}

impl Remembered {
    /// The nearest model point to `y` if the remembered points prove it (see [`Correspondences`]).
    fn nearest(&self, y: &Vector3<f64>, points: &[Vector3<f64>]) -> Option<(usize, f64)> {
        let moved = (y - self.at).norm();
        // Every model point but the first remembered was at least `distances[1]` away: the first
        // is still the nearest if it is within `distances[1] - moved` (the common case, one distance).
        let j0 = self.items[0] as usize;
        let d0 = (y - points[j0]).norm_squared();
        let second = if self.len > 1 { self.distances[1] } else { f64::INFINITY };
        let reach = second - moved;
        if reach > 0.0 && d0 <= reach * reach {
            return Some((j0, d0));
        }
        // Else the nearest remembered point, if within `dk - moved` (any other point is farther).
        let last = if self.len < CACHED_NEIGHBOURS { f64::INFINITY } else { self.distances[self.len - 1] };
        let reach = last - moved;
        let (j, d2) = (0..self.len)
            .map(|k| (self.items[k] as usize, (y - points[self.items[k] as usize]).norm_squared()))
            .min_by(|a, b| a.1.total_cmp(&b.1))?;
        (reach > 0.0 && d2 <= reach * reach).then_some((j, d2))
    }
}

impl<'m> Correspondences<'m> {
    /// Correspondences of a frame of `n` points against `model`.
    pub fn new(model: &'m PartModel, n: usize) -> Self {
        Correspondences { model, cache: vec![None; n], searched: 0, reused: 0 }
    }

    /// Nearest model point to frame point `i`, now at `y` (reference configuration), within
    /// `gate` \[m\]: its index and squared distance; the same answer as [`PartModel::nearest`].
    pub fn nearest(&mut self, i: usize, y: &Vector3<f64>, gate: f64) -> Option<(usize, f64)> {
        let points = &self.model.points;
        let found = match self.cache[i].as_ref().and_then(|r| r.nearest(y, points)) {
            Some(found) => {
                self.reused += 1;
                found
            }
            None => {
                self.searched += 1;
                let nn = self.model.tree.nearest_n::<SquaredEuclidean>(&[y.x, y.y, y.z], CACHED_NEIGHBOURS);
                let mut r = Remembered { at: *y, len: nn.len(), items: [0; CACHED_NEIGHBOURS], distances: [0.0; CACHED_NEIGHBOURS] };
                for (k, m) in nn.iter().enumerate() {
                    r.items[k] = m.item as u32;
                    r.distances[k] = m.distance.sqrt();
                }
                let first = nn.first()?;
                self.cache[i] = Some(r);
                (first.item as usize, (y - points[first.item as usize]).norm_squared())
            }
        };
        (found.1 <= gate * gate).then_some(found)
    }
}

/// Scales of the Cauchy kernels \[m\].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scales {
    pub plane: f64,
    pub point: f64,
}

impl Scales {
    fn new(plane: f64, cfg: &PerceptionConfig) -> Scales {
        let plane = plane.clamp(cfg.point_sd_min_m, cfg.point_sd_max_m);
        Scales { plane, point: (cfg.point_to_point_ratio * plane).max(cfg.voxel_m) }
    }
}

/// The points of one part in one frame with their weights.
pub struct FramePoints<'a> {
    /// Points \[m\], fixed frame.
    pub points: &'a [Vector3<f64>],
    /// Weight of each point (1; near another part `boundary_weight`, or `edge_weight` on the
    /// part's own outline).
    pub weights: &'a [f64],
    /// The robot's hand on the part in this frame, if it pushes it and the option is on
    /// ([`super::PerceptionConfig::hand_sd_m`]).
    pub hand: Option<Hand>,
}

/// The hand as an observation of the material point it touches: `point` is the contact point
/// \[m\] (fixed frame, from the robot's `/tf`), `touch` the material point it touched when the
/// push began \[m\] (reference configuration), `sd` the scale of their distance \[m\]. It enters
/// the registration cost as one more point-to-point match, `0.5 |T⁻¹ point - touch|² / sd²`:
/// Gaussian, not Cauchy like the points' matches, because the robot's kinematics place the hand
/// to millimetres and the push keeps it on the part, while a Cauchy term of one match is
/// outweighed by a hundred points whose cost is flat along the directions the part's visible
/// surface leaves loose, the very directions it is there for (`obj045`'s hatch lagged the hand
/// by 29 mm with a Cauchy term, by 15 mm with this one).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hand {
    pub point: Vector3<f64>,
    pub touch: Vector3<f64>,
    pub sd: f64,
}

impl Hand {
    /// The hand in the reference configuration, `T⁻¹ point`, and its residual `T⁻¹ point -
    /// touch`, given `inv = T⁻¹`.
    fn residual(&self, inv: &Isometry3<f64>) -> (Vector3<f64>, Vector3<f64>) {
        let y = (inv * nalgebra::Point3::from(self.point)).coords;
        (y, y - self.touch)
    }
}

/// Robust registration cost of `frame` under `pose` (reference -> fixed frame) and the fraction
/// of points matched within the fine gate.
pub fn cost(nn: &mut Correspondences<'_>, frame: &FramePoints<'_>, pose: &Isometry3<f64>, sc: Scales, cfg: &PerceptionConfig) -> (f64, f64) {
    let model = nn.model;
    let inv = pose.inverse();
    let (spl, spp, wpp, gate) = (sc.plane, sc.point, cfg.point_to_point_weight, cfg.fine_gate_m);
    let far = (1.0 + (gate / spl).powi(2)).ln() + wpp * (1.0 + (gate / spp).powi(2)).ln();
    let (mut c, mut matched) = (0.0, 0usize);
    for (i, (x, w)) in frame.points.iter().zip(frame.weights).enumerate() {
        let y = inv * nalgebra::Point3::from(*x);
        let term = match nn.nearest(i, &y.coords, gate) {
            Some((j, d2)) => {
                matched += 1;
                (1.0 + model.residual2(j, &y.coords) / (spl * spl)).ln() + wpp * (1.0 + d2 / (spp * spp)).ln()
            }
            None => far,
        };
        c += 0.5 * w * term;
    }
    if let Some(h) = &frame.hand {
        c += 0.5 * h.residual(&inv).1.norm_squared() / (h.sd * h.sd);
    }
    (c, matched as f64 / frame.points.len().max(1) as f64)
}

/// Gauss-Newton ICP from `start`. Returns the registered pose and the Gauss-Newton matrix of the
/// last iteration (information about the increment `(w, u)`, `y -> y + w x y + u`, in the
/// reference configuration), or `None` when too few points match.
pub fn icp(
    nn: &mut Correspondences<'_>,
    frame: &FramePoints<'_>,
    start: &Isometry3<f64>,
    sc: Scales,
    cfg: &PerceptionConfig,
) -> Option<(Isometry3<f64>, Matrix6<f64>)> {
    let model = nn.model;
    let (inv_spl2, inv_spp2, wpp) = ((sc.plane * sc.plane).recip(), (sc.point * sc.point).recip(), cfg.point_to_point_weight);
    let mut pose = *start;
    let mut last = None;
    let iters = cfg.icp_iterations.max(1);
    for it in 0..iters {
        let gate = if it < iters / 2 { cfg.match_gate_m } else { cfg.fine_gate_m };
        let inv = pose.inverse();
        // As a matrix: this transforms every point of every iteration.
        let (rot, shift) = (inv.rotation.to_rotation_matrix().into_inner(), inv.translation.vector);
        let (mut sums, mut matched) = (NormalEquations::default(), 0usize);
        for (i, (x, w)) in frame.points.iter().zip(frame.weights).enumerate() {
            let y = rot * x + shift;
            let Some((j, d2)) = nn.nearest(i, &y, gate) else { continue };
            matched += 1;
            let r = y - model.points[j];
            // The weaker point-to-point term (edges fix a plane's position within it).
            let mut wp = w * wpp / (1.0 + d2 * inv_spp2) * inv_spp2;
            match model.normals[j] {
                // Point to plane: d(n . (y' - m))/d(w, u) = [y x n, n].
                Some(n) => {
                    let e = r.dot(&n);
                    let wc = w / (1.0 + e * e * inv_spl2) * inv_spl2;
                    let yn = y.cross(&n);
                    sums.add_plane(&[yn.x, yn.y, yn.z, n.x, n.y, n.z], e, wc);
                }
                // No plane here: the full distance at the plane's scale.
                None => wp += w / (1.0 + d2 * inv_spl2) * inv_spl2,
            }
            sums.add_point(&y, &r, wp);
        }
        if matched < cfg.min_points.max(6) {
            return None;
        }
        if let Some(h) = &frame.hand {
            // The hand's match: a Gaussian point-to-point term at its own scale (see `Hand`).
            let (y, r) = h.residual(&inv);
            sums.add_point(&y, &r, 1.0 / (h.sd * h.sd));
        }
        let (a, b) = sums.solve_form();
        let damped = a + Matrix6::identity() * (1e-4 * a.trace() / 6.0 + 1e-12);
        let dx = -(damped.cholesky()?.solve(&b));
        let delta = Isometry3::from_parts(
            Translation3::new(dx[3], dx[4], dx[5]),
            UnitQuaternion::from_scaled_axis(Vector3::new(dx[0], dx[1], dx[2])),
        );
        pose *= delta.inverse();
        last = Some(a);
        if dx.norm() < 1e-8 {
            break;
        }
    }
    last.map(|a| (pose, a))
}

/// The Gauss-Newton normal equations `A dx = -b` of one ICP iteration, accumulated as sums
/// (this runs for every point of every iteration, so only what differs per point is summed).
///
/// Point to plane, per match: `A += w jᵀj`, `b += w e j` with `j = [y x n, n]` (upper triangle
/// only: `A` is symmetric). Point to point: with `J = d(y + w x y + u)/d(w, u) = [-[y]x, I]`,
/// `JᵀJ = [[|y|²I - yyᵀ, [y]x], [-[y]x, I]]` and `Jᵀr = [y x r, r]`, so the sums of `wp`,
/// `wp y`, `wp yyᵀ`, `wp r` and `wp y x r` give its part of `A` and `b` in closed form.
#[derive(Debug, Default)]
struct NormalEquations {
    /// Point to plane: `Σ w jᵀj` (upper triangle, row by row) and `Σ w e j`.
    plane: [f64; 21],
    plane_b: [f64; 6],
    /// Point to point: `Σ wp`, `Σ wp y`, `Σ wp yyᵀ` (xx, xy, xz, yy, yz, zz), `Σ wp r`, `Σ wp y x r`.
    w: f64,
    wy: Vector3<f64>,
    wyy: [f64; 6],
    wr: Vector3<f64>,
    wyr: Vector3<f64>,
}

impl NormalEquations {
    /// One point-to-plane match: Jacobian row `j`, residual `e` \[m\], weight `w` \[1/m²\].
    fn add_plane(&mut self, j: &[f64; 6], e: f64, w: f64) {
        let mut k = 0;
        for r in 0..6 {
            let wr = w * j[r];
            for c in r..6 {
                self.plane[k] += wr * j[c];
                k += 1;
            }
            self.plane_b[r] += wr * e;
        }
    }

    /// One point-to-point match of `y` (reference configuration) with residual `r` \[m\] and
    /// weight `wp` \[1/m²\].
    fn add_point(&mut self, y: &Vector3<f64>, r: &Vector3<f64>, wp: f64) {
        let wy = wp * y;
        self.w += wp;
        self.wy += wy;
        self.wyy[0] += wy.x * y.x;
        self.wyy[1] += wy.x * y.y;
        self.wyy[2] += wy.x * y.z;
        self.wyy[3] += wy.y * y.y;
        self.wyy[4] += wy.y * y.z;
        self.wyy[5] += wy.z * y.z;
        self.wr += wp * r;
        self.wyr += wy.cross(r);
    }

    /// `(A, b)` with `A` (6x6, symmetric) about the increment `(w, u)`.
    fn solve_form(&self) -> (Matrix6<f64>, Vector6<f64>) {
        let mut a = Matrix6::zeros();
        let mut k = 0;
        for r in 0..6 {
            for c in r..6 {
                a[(r, c)] = self.plane[k];
                a[(c, r)] = self.plane[k];
                k += 1;
            }
        }
        let s = &self.wyy;
        let yy = Matrix3::new(s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5]);
        let rot = Matrix3::identity() * yy.trace() - yy;
        let cross = skew(&self.wy);
        for r in 0..3 {
            for c in 0..3 {
                a[(r, c)] += rot[(r, c)];
                a[(r, c + 3)] += cross[(r, c)];
                a[(r + 3, c)] -= cross[(r, c)];
            }
            a[(r + 3, r + 3)] += self.w;
        }
        let mut b = Vector6::from_column_slice(&self.plane_b);
        for r in 0..3 {
            b[r] += self.wyr[r];
            b[r + 3] += self.wr[r];
        }
        (a, b)
    }
}

/// Robust noise scale of a fit: 1.4826 x the median absolute point-to-plane distance of the points
/// matched within the fine gate.
fn residual_scale(nn: &mut Correspondences<'_>, frame: &FramePoints<'_>, pose: &Isometry3<f64>, cfg: &PerceptionConfig) -> Option<f64> {
    let model = nn.model;
    let inv = pose.inverse();
    let r: Vec<f64> = frame
        .points
        .iter()
        .enumerate()
        .filter_map(|(i, x)| {
            let y = (inv * nalgebra::Point3::from(*x)).coords;
            // Per axis: a distance without a plane spreads over three directions.
            nn.nearest(i, &y, cfg.fine_gate_m).map(|(j, _)| {
                let r2 = model.residual2(j, &y);
                if model.normals[j].is_some() { r2.sqrt() } else { (r2 / 3.0).sqrt() }
            })
        })
        .collect();
    if r.len() < cfg.min_points.max(6) {
        return None;
    }
    Some(robust_sd(r))
}

/// Robust standard deviation of absolute residuals `r` (not empty): 1.4826 x their (upper)
/// median, the normal distribution's sd from its median absolute deviation.
fn robust_sd(mut r: Vec<f64>) -> f64 {
    r.sort_by(f64::total_cmp);
    1.4826 * r[r.len() / 2]
}

/// The result of registering one frame.
#[derive(Debug, Clone)]
pub struct Registered {
    pub pose: Isometry3<f64>,
    /// Gauss-Newton information about `(w, u)` at `pose` (see [`icp`]).
    pub information: Matrix6<f64>,
    /// Fraction of points matched within the fine gate.
    pub matched: f64,
    /// The hand's match in this registration, if one was used ([`Hand`]).
    pub hand: Option<Hand>,
}

/// Tracks one part: its model and its pose over time.
#[derive(Debug)]
pub struct Tracker {
    pub model: PartModel,
    pub pose: Isometry3<f64>,
    previous: Isometry3<f64>,
    frames: usize,
    scales: Scales,
    /// Centroid of the previous frame's points \[m\].
    centroid: Option<Vector3<f64>>,
    /// The material point the hand touched when the current push began \[m\] (reference
    /// configuration; [`PerceptionConfig::hand_sd_m`]); `None` between pushes.
    pub touch: Option<Vector3<f64>>,
}

impl Tracker {
    /// Start tracking from the part's first points (fixed frame): the reference configuration
    /// is the part's pose at this frame.
    pub fn new(points: &[Vector3<f64>], cfg: &PerceptionConfig) -> Tracker {
        Tracker {
            model: PartModel::new(points, cfg.voxel_m, Smoothing { radius_m: cfg.smoothing_radius_m }),
            pose: Isometry3::identity(),
            previous: Isometry3::identity(),
            frames: 1,
            scales: Scales::new(cfg.point_sd_max_m, cfg),
            centroid: Some(points.iter().sum::<Vector3<f64>>() / points.len().max(1) as f64),
            touch: None,
        }
    }

    /// Register a frame, choose among the hypotheses (a moved pose costs `move_penalty`
    /// under `push`, the push acting on the part if any), grow the model. `starts` are further
    /// poses (reference -> fixed frame) beside the tracker's own: the part moved with a larger
    /// one ([`super::PerceptionConfig::carrier_starts`]), each a hypothesis at no move penalty
    /// and an ICP start. `None` when no hypothesis matches enough points (the pose is then kept).
    ///
    /// With [`PerceptionConfig::hand_sd_m`] above 0, a push's first registered frame anchors the
    /// material point at the contact (`touch`), and in each later frame of the push the hand is
    /// one more match of the cost ([`Hand`]) and the pose that carries that point to the hand is
    /// one more ICP start: the hand moves with what it pushes, also along directions the part's
    /// visible surface leaves loose (a hatch sliding in its door's plane). The hand is built here
    /// from `push` and the touch, so `frame.hand` is not read (callers pass `None`); the hand used
    /// is returned in [`Registered::hand`] for [`Tracker::refine`], which does read it.
    pub fn update(&mut self, frame: &FramePoints<'_>, push: Option<&super::Push>, starts: &[Isometry3<f64>], cfg: &PerceptionConfig) -> Option<Registered> {
        let frame_index = self.frames;
        self.frames += 1;
        if push.is_none() || cfg.hand_sd_m <= 0.0 {
            self.touch = None;
        }
        let hand = match (push, self.touch) {
            (Some(p), Some(touch)) if p.point.coords.iter().all(|v| v.is_finite()) => Some(Hand { point: p.point.coords, touch, sd: cfg.hand_sd_m }),
            _ => None,
        };
        let with_hand = FramePoints { points: frame.points, weights: frame.weights, hand };
        let frame = &with_hand;
        // Constant-velocity prediction: the last motion applied once more; and the previous pose
        // shifted by the motion of the points' centroid (biased by changes of the visible surface,
        // but immune to the local minima of a regular structure).
        let predicted = self.pose * (self.previous.inverse() * self.pose);
        let mut hyps: Vec<(Isometry3<f64>, f64)> = vec![(self.pose, 0.0), (Isometry3::identity(), cfg.reference_penalty_nats)];
        let centroid = frame.points.iter().sum::<Vector3<f64>>() / frame.points.len().max(1) as f64;
        let last = self.centroid.unwrap_or(centroid);
        let shifted = Translation3::from(centroid - last) * self.pose;
        // A further start as it is: the part rigid on its carrier, which, like staying where it
        // was, is no motion of its own and pays no move penalty.
        hyps.extend(starts.iter().map(|s| (*s, 0.0)));
        // Each further start also an ICP start, and shifted so that the last frame's centroid,
        // carried along with it, lands on this frame's (a hatch that slid in its door while out
        // of view).
        let last_ref = self.pose.inverse() * nalgebra::Point3::from(last);
        let mut starts: Vec<Isometry3<f64>> =
            starts.iter().flat_map(|s| [*s, Translation3::from(centroid - (s * last_ref).coords) * s]).collect();
        // The previous pose shifted so that the touched point lands on the hand.
        if let Some(h) = &hand {
            starts.push(Translation3::from(h.point - (self.pose * nalgebra::Point3::from(h.touch)).coords) * self.pose);
        }
        self.centroid = Some(centroid);
        let mut info = None;
        let mut nn = Correspondences::new(&self.model, frame.points.len());
        for start in [self.pose, predicted, shifted].iter().chain(&starts) {
            if let Some((p, a)) = icp(&mut nn, frame, start, self.scales, cfg) {
                if info.is_none() {
                    // The noise of this frame's points, from the residuals of the first fit.
                    if let Some(s) = residual_scale(&mut nn, frame, &p, cfg) {
                        self.scales = Scales::new(s, cfg);
                    }
                }
                hyps.push((p, self.move_penalty(&p, push, cfg)));
                info.get_or_insert(a);
            }
        }
        let mut best: Option<(f64, f64, Isometry3<f64>)> = None;
        for (p, penalty) in hyps {
            let (c, matched) = cost(&mut nn, frame, &p, self.scales, cfg);
            if best.as_ref().is_none_or(|b| c + penalty < b.0) {
                best = Some((c + penalty, matched, p));
            }
        }
        let (_, matched, pose) = best?;
        if matched * (frame.points.len() as f64) < cfg.min_points.max(6) as f64 {
            return None;
        }
        self.previous = self.pose;
        self.pose = pose;
        if let (Some(p), None, true) = (push, self.touch, cfg.hand_sd_m > 0.0) {
            let x = (pose.inverse() * p.point).coords;
            self.touch = x.iter().all(|v| v.is_finite()).then_some(x);
        }
        // The information at the chosen pose (one Gauss-Newton pass from it, no step kept).
        let information = icp_information(&mut nn, frame, &pose, self.scales, cfg).or(info).unwrap_or_else(Matrix6::zeros);
        let inv = pose.inverse();
        let grow: Vec<Vector3<f64>> = frame
            .points
            .iter()
            .zip(frame.weights)
            .filter(|(_, w)| **w >= 1.0)
            .map(|(x, _)| (inv * nalgebra::Point3::from(*x)).coords)
            .collect();
        // While a part rests in its reference pose at the start of its track, its points need no
        // confirmation: they are registered exactly, and densify the first frame's sparse model.
        let confirm = if frame_index < cfg.initial_frames && pose == Isometry3::identity() { 1 } else { cfg.confirm_frames };
        self.model.grow(&grow, frame_index, confirm, cfg.max_model_points);
        Some(Registered { pose, information, matched, hand })
    }
}

impl Tracker {
    /// What moving from the current pose to `moved` costs \[nats\]: `move_penalty_nats`, or
    /// `push_move_penalty_nats` when a push acts on the part and the move takes the part's point
    /// at the contact along the force (positive work, as a pushed passive part moves; a
    /// registration that slips across the push or turns about the hand does not).
    fn move_penalty(&self, moved: &Isometry3<f64>, push: Option<&super::Push>, cfg: &PerceptionConfig) -> f64 {
        let Some(push) = push else { return cfg.move_penalty_nats };
        // The material point at the contact now, and where the previous pose had it.
        let before = self.pose * (moved.inverse() * push.point);
        if push.force.dot(&(push.point - before)) > 0.0 {
            cfg.push_move_penalty_nats.min(cfg.move_penalty_nats)
        } else {
            cfg.move_penalty_nats
        }
    }

    /// Register a frame again against the model as it is now, starting from `pose` (its first
    /// registration, against the model of that time): the pose moves only if that explains the
    /// points better by more than `refine_penalty_nats`. Returns the pose and its information.
    pub fn refine(&self, frame: &FramePoints<'_>, pose: &Isometry3<f64>, cfg: &PerceptionConfig) -> Option<Registered> {
        let mut nn = Correspondences::new(&self.model, frame.points.len());
        let scales = residual_scale(&mut nn, frame, pose, cfg).map(|s| Scales::new(s, cfg)).unwrap_or(self.scales);
        let fine = PerceptionConfig { match_gate_m: cfg.fine_gate_m, ..cfg.clone() };
        let (c0, m0) = cost(&mut nn, frame, pose, scales, cfg);
        let mut best = (c0, m0, *pose);
        if let Some((p, _)) = icp(&mut nn, frame, pose, scales, &fine) {
            let (c, m) = cost(&mut nn, frame, &p, scales, cfg);
            if c + cfg.refine_penalty_nats < best.0 {
                best = (c, m, p);
            }
        }
        let information = icp_information(&mut nn, frame, &best.2, scales, cfg)?;
        Some(Registered { pose: best.2, information, matched: best.1, hand: frame.hand })
    }
}

/// The Gauss-Newton matrix of the registration cost at `pose` (fine gate).
fn icp_information(nn: &mut Correspondences<'_>, frame: &FramePoints<'_>, pose: &Isometry3<f64>, sc: Scales, cfg: &PerceptionConfig) -> Option<Matrix6<f64>> {
    let one = PerceptionConfig { icp_iterations: 1, match_gate_m: cfg.fine_gate_m, ..cfg.clone() };
    icp(nn, frame, pose, sc, &one).map(|(_, a)| a)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn normal_equations_sum_jt_j() {
        // Against the explicit Jacobians: point to plane `[y x n, n]`, point to point `[-[y]x, I]`.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let (mut sums, mut a, mut b) = (NormalEquations::default(), Matrix6::zeros(), Vector6::zeros());
        for _ in 0..5 {
            let y = Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let r = Vector3::from_fn(|_, _| rng.random_range(-0.05..0.05));
            let n = Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
            let (wc, wp) = (rng.random_range(0.1..3.0), rng.random_range(0.1..3.0));
            let yn = y.cross(&n);
            let jr = Vector6::new(yn.x, yn.y, yn.z, n.x, n.y, n.z);
            sums.add_plane(&[yn.x, yn.y, yn.z, n.x, n.y, n.z], r.dot(&n), wc);
            a += jr * jr.transpose() * wc;
            b += jr * r.dot(&n) * wc;
            let mut jp = nalgebra::Matrix3x6::<f64>::zeros();
            jp.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-skew(&y)));
            jp.fixed_view_mut::<3, 3>(0, 3).copy_from(&Matrix3::identity());
            sums.add_point(&y, &r, wp);
            a += jp.transpose() * jp * wp;
            b += jp.transpose() * r * wp;
        }
        let (sa, sb) = sums.solve_form();
        assert!((sa - a).norm() < 1e-12 * a.norm(), "{sa} vs {a}");
        assert!((sb - b).norm() < 1e-12 * b.norm(), "{sb} vs {b}");
    }

    #[test]
    fn remembered_correspondences_are_the_nearest_model_points() {
        // Queries drift as ICP iterations move them: every answer equals a fresh k-d tree search,
        // on a model smaller than the remembered neighbourhood too, and the tree is searched far
        // less often than asked.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for n_model in [3, 400] {
            let size = Vector3::new(0.4, 0.25, 0.1);
            let model = PartModel::new(&box_surface(&mut rng, n_model, size), 0.008, Smoothing { radius_m: 0.0 });
            let frame = box_surface(&mut rng, 200, size);
            let mut nn = Correspondences::new(&model, frame.len());
            let mut asked = 0;
            for step in 0..30 {
                let drift = Vector3::new(0.002, -0.001, 0.0005) * step as f64;
                for (i, x) in frame.iter().enumerate() {
                    let y = x + drift + Vector3::from_fn(|_, _| rng.random_range(-0.0005..0.0005));
                    let gate = if step % 2 == 0 { 0.1 } else { 0.02 };
                    let got = nn.nearest(i, &y, gate);
                    let want = model.nearest(&y, gate);
                    asked += 1;
                    match (got, want) {
                        (Some((j, d)), Some((k, e))) => assert!(j == k || (d - e).abs() < 1e-15, "point {i}: {j} at {d} vs {k} at {e}"),
                        (a, b) => assert_eq!(a.is_some(), b.is_some(), "point {i} at step {step}: {a:?} vs {b:?}"),
                    }
                }
            }
            assert_eq!(nn.searched + nn.reused, asked);
            if n_model > 3 {
                assert!(nn.searched * 3 < asked, "searched {} of {asked}", nn.searched);
            }
        }
    }

    /// Points on the surface of a box: a sparse random sample per frame.
    fn box_surface(rng: &mut impl Rng, n: usize, size: Vector3<f64>) -> Vec<Vector3<f64>> {
        (0..n)
            .map(|_| {
                let mut p = Vector3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
                let k = rng.random_range(0..3);
                p[k] = if rng.random_bool(0.5) { 0.5 } else { -0.5 };
                p.component_mul(&size)
            })
            .collect()
    }

    /// `n` points of a `size` box centred at `centre`, moved by `pose`, with Gaussian noise of
    /// sd `sd` \[m\] on every coordinate.
    fn noisy_box(rng: &mut rand_chacha::ChaCha8Rng, n: usize, size: Vector3<f64>, centre: Vector3<f64>, sd: f64, pose: &Isometry3<f64>) -> Vec<Vector3<f64>> {
        let noise = rand_distr::Normal::new(0.0, sd).unwrap();
        box_surface(rng, n, size).iter().map(|p| (pose * nalgebra::Point3::from(p + centre)).coords + Vector3::from_fn(|_, _| rng.sample(noise))).collect()
    }

    #[test]
    fn tracks_a_sparse_noisy_box_through_a_turn() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let cfg = PerceptionConfig::default();
        let size = Vector3::new(0.4, 0.25, 0.1);
        let centre = Vector3::new(0.3, 0.2, 0.9);
        let sample = |rng: &mut rand_chacha::ChaCha8Rng, pose: &Isometry3<f64>| noisy_box(rng, 150, size, centre, 0.003, pose);
        let first = sample(&mut rng, &Isometry3::identity());
        let mut tr = Tracker::new(&first, &cfg);
        let hinge = Vector3::new(0.1, 0.2, 0.9);
        let mut worst: f64 = 0.0;
        for k in 1..60 {
            // Still for 10 frames, then turning about a vertical hinge at 2 degrees a frame.
            let angle = (k as f64 - 10.0).max(0.0) * 2f64.to_radians();
            let rot = UnitQuaternion::from_scaled_axis(Vector3::z() * angle);
            let truth = Isometry3::from_parts(Translation3::from(hinge - rot * hinge), rot);
            let pts = sample(&mut rng, &truth);
            let w = vec![1.0; pts.len()];
            let reg = tr.update(&FramePoints { points: &pts, weights: &w, hand: None }, None, &[], &cfg).expect("registers");
            let err = (reg.pose * nalgebra::Point3::from(centre) - truth * nalgebra::Point3::from(centre)).norm();
            worst = worst.max(err);
            if k < 10 {
                assert!(err < 0.005, "a still part stays where it is: {err} m at frame {k}");
            }
        }
        assert!(worst < 0.01, "centre error {worst} m");
        assert!(tr.model.points.len() > 150, "the model grew: {}", tr.model.points.len());
    }

    /// A sparsely seen box (80 points, 5 mm noise) pushed slowly along x (0.5 mm a frame): with
    /// the push prior (`push_move_penalty_nats` below `move_penalty_nats`) and the force along
    /// the motion the track follows; without a push, or with a force across the motion (the
    /// motion's steps do no work), each frame's small gain stays under the full penalty and the
    /// track moves in late steps (the mean lag over the push is compared).
    #[test]
    fn a_slow_push_is_followed_with_the_push_prior_only_along_the_force() {
        let size = Vector3::new(0.4, 0.25, 0.1);
        let centre = Vector3::new(0.3, 0.2, 0.9);
        let run = |push_along: Option<Vector3<f64>>, push_move_penalty_nats: f64| -> f64 {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
            let cfg = PerceptionConfig { push_move_penalty_nats, hand_sd_m: 0.0, ..PerceptionConfig::default() };
            let sample = |rng: &mut rand_chacha::ChaCha8Rng, pose: &Isometry3<f64>| noisy_box(rng, 80, size, centre, 0.005, pose);
            let first = sample(&mut rng, &Isometry3::identity());
            let mut tr = Tracker::new(&first, &cfg);
            let mut lag = 0.0;
            for k in 1..=60 {
                let truth = Isometry3::translation(0.0005 * k as f64, 0.0, 0.0);
                let pts = sample(&mut rng, &truth);
                let w = vec![1.0; pts.len()];
                // The hand on the box's -x face, pushing with 5 N.
                let contact = truth * nalgebra::Point3::from(centre - Vector3::new(size.x / 2.0, 0.0, 0.0));
                let push = push_along.map(|d| super::super::Push { point: contact, force: d * 5.0 });
                let reg = tr.update(&FramePoints { points: &pts, weights: &w, hand: None }, push.as_ref(), &[], &cfg).expect("registers");
                lag += (truth * nalgebra::Point3::from(centre) - reg.pose * nalgebra::Point3::from(centre)).x / 60.0;
            }
            lag
        };
        let off = run(None, 2.0);
        let along = run(Some(Vector3::x()), 2.0);
        let across = run(Some(Vector3::y()), 2.0);
        let default = run(Some(Vector3::x()), PerceptionConfig::default().push_move_penalty_nats);
        assert!(along < 0.5 * off, "pushed along the motion: {along} m behind on average, without a push {off} m");
        // Across the motion only moves with some slip along the force pass the work test, and none
        // of the motion's own steps needs it to: no help in following the motion.
        assert!(across > 2.0 * along, "a force across the motion: {across} m behind, along it {along} m");
        assert_eq!(default, off, "the default is off");
    }

    /// A thin panel seen face-on (points on its front face only, 3 mm noise) slides 3 mm a
    /// frame in its own plane while the hand pushes its edge: the face leaves that direction
    /// loose (only the sparse outline fixes it), so the track lags; with the hand as a match of
    /// the registration (`hand_sd_m`) it follows (the lag at the last frame is compared). The
    /// hand's first pushed frame anchors the touched point.
    #[test]
    fn the_hand_keeps_a_loosely_seen_pushed_panel_on_track() {
        let run = |hand_sd_m: f64| -> (f64, Option<Vector3<f64>>) {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
            let noise = rand_distr::Normal::new(0.0, 0.003).unwrap();
            let cfg = PerceptionConfig { hand_sd_m, ..PerceptionConfig::default() };
            let face = |rng: &mut rand_chacha::ChaCha8Rng, x0: f64| -> Vec<Vector3<f64>> {
                (0..60)
                    .map(|_| Vector3::new(x0 + rng.random_range(-0.1..0.1), rng.random_range(-0.06..0.06), 0.9) + Vector3::from_fn(|_, _| rng.sample(noise)))
                    .collect()
            };
            let first = face(&mut rng, 0.0);
            let mut tr = Tracker::new(&first, &cfg);
            let mut lag = 0.0f64;
            for k in 1..=30 {
                let x0 = 0.003 * k as f64;
                let pts = face(&mut rng, x0);
                let w = vec![1.0; pts.len()];
                let push = super::super::Push { point: nalgebra::Point3::new(x0 - 0.1, 0.0, 0.9), force: Vector3::x() * 4.0 };
                let reg = tr.update(&FramePoints { points: &pts, weights: &w, hand: None }, Some(&push), &[], &cfg).expect("registers");
                lag = x0 - reg.pose.translation.vector.x;
            }
            (lag, tr.touch)
        };
        let (off, no_touch) = run(0.0);
        let (on, touch) = run(0.005);
        assert!(no_touch.is_none(), "off: no touched point is kept");
        let touch = touch.expect("the push's first frame anchors the touched point");
        assert!((touch - Vector3::new(-0.1, 0.0, 0.9)).norm() < 0.025, "the touched point is the panel's pushed edge: {touch:?}");
        assert!(off > 0.02, "without the hand the track lags: {off} m");
        assert!(on < 0.3 * off && on < 0.02, "with the hand {on} m behind, without {off} m");
    }

    /// Smoothing thins a noisy plate to its plane and leaves what is not that plane alone: a lip
    /// standing on the plate's edge (which fixes the plate's position in its own plane) and a
    /// handle (a cylinder narrower than the smoothing radius).
    #[test]
    fn smoothing_thins_a_noisy_plate_and_keeps_its_lip_and_handle() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let noise = rand_distr::Normal::new(0.0, 0.004).unwrap();
        let mut pts = Vec::new();
        for _ in 0..6000 {
            // Plate z = 0, 0.4 x 0.3 m; lip x = 0.2, 4 cm high; handle: radius 1.5 cm about the
            // line (y = 0, z = 0.1), x in [-0.1, 0.1].
            let (x, y) = (rng.random_range(-0.2..0.2), rng.random_range(-0.15..0.15));
            let z = rng.sample(noise);
            pts.push(Vector3::new(x, y, z));
        }
        for _ in 0..1500 {
            pts.push(Vector3::new(0.2 + 0.001 * rng.sample(noise), rng.random_range(-0.15..0.15), rng.random_range(0.0..0.04)));
            let a: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            pts.push(Vector3::new(rng.random_range(-0.1..0.1), 0.015 * a.cos(), 0.1 + 0.015 * a.sin()));
        }
        let off = |m: &PartModel| {
            let plate: Vec<f64> = m.points.iter().filter(|p| p.x.abs() < 0.15 && p.z.abs() < 0.03).map(|p| p.z * p.z).collect();
            (plate.iter().sum::<f64>() / plate.len() as f64).sqrt()
        };
        let lip = |m: &PartModel| m.points.iter().filter(|p| p.x > 0.19 && p.z > 0.025).count();
        let handle = |m: &PartModel| {
            let r: Vec<f64> = m.points.iter().filter(|p| p.z > 0.07).map(|p| ((p.y.powi(2) + (p.z - 0.1).powi(2)).sqrt() - 0.015).powi(2)).collect();
            (r.iter().sum::<f64>() / r.len() as f64).sqrt()
        };
        let raw = PartModel::new(&pts, 0.008, Smoothing { radius_m: 0.0 });
        let smooth = PartModel::new(&pts, 0.008, Smoothing { radius_m: 0.032 });
        assert_eq!(raw.points.len(), smooth.points.len());
        assert!(off(&smooth) < 0.5 * off(&raw), "plate off its plane: {:.4} m smoothed, {:.4} m raw", off(&smooth), off(&raw));
        assert!(lip(&raw) > 20 && lip(&smooth) >= lip(&raw) * 9 / 10, "lip points above 2.5 cm: {} smoothed, {} raw", lip(&smooth), lip(&raw));
        assert!(handle(&smooth) < 0.002, "handle off its cylinder: {:.4} m (raw {:.4} m)", handle(&smooth), handle(&raw));
        // Smoothing is done once per point: a second refresh moves nothing.
        let mut again = PartModel::new(&pts, 0.008, Smoothing { radius_m: 0.032 });
        let before = again.points.clone();
        again.refresh_normals();
        assert_eq!(before, again.points);
    }
}
