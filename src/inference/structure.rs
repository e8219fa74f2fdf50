//! The initial structure of BOM-SVI: which part hangs from which, and by which joint type, before
//! the variational fit refines it.
//!
//! Following Sturm, Stachniss & Burgard (JAIR 2011, "A probabilistic framework for learning
//! kinematic models of articulated objects", §4), every part's motion is fitted *relative to every
//! candidate parent* — the fixed frame or another part, whose motion is then removed — with each
//! joint type, scored by the model's own likelihood at the fit less a BIC penalty
//! `0.5 ln(n) (#parameters + #coordinates)` (or, [`CoordinatePenalty::PerFrame`],
//! `0.5 ln(n) #parameters + sum_t 0.5 ln(n_t)`, `n_t` a coordinate's own frame's observations),
//! and the tree is the maximum spanning arborescence (Chu-Liu/Edmonds) of the best scores plus
//! the contact prior's log weights. A candidate parent's motion is its best fit relative to the
//! fixed frame, not its raw registration: two parts that move together (a microwave standing on
//! a slider) then score alike whichever carries the other, instead of the noisier one always
//! being the child, and the contact prior decides.
//!
//! Why: the guide's continuous parameters describe a joint *relative to its parent*. Fitted under
//! a wrong parent — a latch under the fixed frame while it rides on a door — they follow the
//! parent's motion, and the tree's natural-gradient updates, which score each parent with the
//! current fits, then keep the wrong parent (a local optimum of the mean-field ELBO). Starting
//! from the structure that explains each part's relative motion best avoids that.

use crate::model::likelihood::Evidence;
use crate::model::tree::{descendants, max_arborescence};
use crate::model::{decode, displacement, Displacement, JointType, ModelConfig};

use super::guide::init_block;
use crate::model::density::block_pass;

/// The initial structure.
#[derive(Debug, Clone)]
pub struct InitialStructure {
    /// Parent node of each part (0 = fixed frame, `k + 1` = part `k`).
    pub parent: Vec<usize>,
    /// Score of part `i` under node `j` (its best joint type's), `-inf` for itself.
    pub parent_score: Vec<Vec<f64>>,
    /// Score of each joint type of each part under its parent.
    pub type_score: Vec<[f64; 3]>,
    /// Score of each joint type of part `i` under node `j` (`-inf` for itself), `n` rows of
    /// `n + 1`.
    pub type_score_by_parent: Vec<Vec<[f64; 3]>>,
    /// The contact prior's log weights the tree was chosen with (`n` rows of `n + 1`).
    pub log_w: Vec<Vec<f64>>,
    /// Whether node `j` (`n + 1` nodes) is taken as static: the fixed frame, and every part that
    /// does not clearly move (see `moves`). A part scores the same under any static node.
    pub static_node: Vec<bool>,
}

impl InitialStructure {
    /// The tree's score: its parts' best scores under their parents plus the contact prior's log
    /// weights (`-inf` for a part's impossible attachment).
    pub fn tree_score(&self) -> f64 {
        (0..self.parent.len()).map(|i| self.parent_score[i][self.parent[i]] + self.log_w[i][self.parent[i]]).sum()
    }

    /// The best-scoring joint type of each part under its parent (a [`JointType::index`]).
    pub fn best_types(&self) -> Vec<usize> {
        self.type_score.iter().map(|s| (0..3).max_by(|&a, &b| s[a].total_cmp(&s[b])).unwrap_or(0)).collect()
    }

    /// The flatter runner-up: [`Self::parent`] with one part that hangs from a moving part hung
    /// from its best static node instead (the fixed frame or a part that does not move: a part
    /// scores the same under any of them), every other part's parent kept; the best-scoring such
    /// tree over the parts (a second-best arborescence restricted to one changed edge, cf.
    /// Camerini, Fratta & Maffioli 1980, "The k best spanning arborescences of a network"), with
    /// its parts' type scores under their parents. `None` where there is no such tree (no part
    /// hangs from a moving one, or no other attachment is possible).
    ///
    /// Why: kinematics alone cannot tell some trees apart. A door hinged on the same line as the
    /// door above it, or a drawer sliding parallel to its neighbour, explains its motion equally
    /// well on the cabinet or on the other part (its coordinate then cancels the other's motion),
    /// and tracking noise picks one; only the physics — the pushed part would drag the other
    /// through its joint's damping — tells them apart, and the scores here leave it out. Fitting
    /// the flatter tree too lets the ELBO, physics included, choose (corpus validation object 70:
    /// the upper door hung from the lower one at P = 1.00, ELBO 2344.9; from the cabinet, ELBO
    /// 2566.8; tune object 57: a drawer hung from the drawer beside it). Only towards a static
    /// node: the other way round — a slider on the cabinet re-hung from the flap that rides on it,
    /// which carries it instead — the two trees differ only in which of two parts that moved
    /// together carries the other, which neither the scores nor the physics can tell (tune
    /// object 96, episodes: the ELBO preferred the wrong carrier by 23 nats); the contact prior
    /// decides that ([`initial_structure`]).
    pub fn runner_up(&self) -> Option<InitialStructure> {
        let n = self.parent.len();
        let edge = |i: usize, j: usize| self.parent_score[i][j] + self.log_w[i][j];
        let total = self.tree_score();
        let mut best: Option<(f64, Vec<usize>)> = None;
        for i in (0..n).filter(|&i| !self.static_node[self.parent[i]]) {
            // Not under one of its own descendants (a static part may hang from a moving one).
            let below = descendants(&self.parent, i);
            for j in (0..=n).filter(|&j| self.static_node[j] && j != i + 1 && (j == 0 || !below.contains(&(j - 1)))) {
                let t = total - edge(i, self.parent[i]) + edge(i, j);
                if t.is_finite() && best.as_ref().is_none_or(|(b, _)| t > *b) {
                    let mut p = self.parent.clone();
                    p[i] = j;
                    best = Some((t, p));
                }
            }
        }
        best.map(|(_, parent)| InitialStructure {
            type_score: (0..n).map(|i| self.type_score_by_parent[i][parent[i]]).collect(),
            parent,
            parent_score: self.parent_score.clone(),
            type_score_by_parent: self.type_score_by_parent.clone(),
            log_w: self.log_w.clone(),
            static_node: self.static_node.clone(),
        })
    }
}

/// The observed displacement of node `j` at every grid frame (identity for the fixed frame; held
/// over frames in which the part is not seen).
pub fn observed_displacements(ev: &Evidence, j: usize) -> Vec<Displacement<f64>> {
    if j == 0 {
        return vec![Displacement::identity(); ev.len()];
    }
    let mut last = Displacement::identity();
    ev.parts[j - 1]
        .disp
        .iter()
        .map(|d| {
            if let Some(iso) = d {
                last = Displacement { r: iso.rotation.to_rotation_matrix().into_inner(), t: iso.translation.vector };
            }
            last
        })
        .collect()
}

/// The displacement of part `j` at every grid frame under its best-scoring joint type relative to
/// the fixed frame (its registration, smoothed by the joint's one degree of freedom).
fn fitted_displacements(ev: &Evidence, j: usize, model: &ModelConfig, penalty: CoordinatePenalty) -> Vec<Displacement<f64>> {
    let world = vec![Displacement::identity(); ev.len()];
    let scores = JointType::ALL.map(|k| score(ev, j, k, &world, model, penalty));
    let best = JointType::ALL
        .into_iter()
        .zip(scores)
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .map_or(JointType::Rigid, |(k, _)| k);
    let (xi, q) = init_block(ev, j, best, &world, model);
    let p = decode::<f64>(best, &xi, &ev.parts[j].com0, model);
    q.iter().map(|&qt| displacement(&p, qt)).collect()
}

/// How the initial structure charges a movable joint's per-frame coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CoordinatePenalty {
    /// BIC's `0.5 ln n` per coordinate, `n` all the part's observations: a strong preference for
    /// fewer moving joints (a flap riding on a slider scores rigid on it, not prismatic on the
    /// fixed frame).
    Bic,
    /// `0.5 ln n_t` per coordinate, `n_t` its own frame's observations: a joint that moved in one
    /// window of several is not outweighed by the frames in which it rested.
    PerFrame,
}

/// Score of part `i` with joint type `joint` relative to the motion `pre` of a parent.
fn score(ev: &Evidence, i: usize, joint: JointType, pre: &[Displacement<f64>], model: &ModelConfig, penalty: CoordinatePenalty) -> f64 {
    let (xi, q) = init_block(ev, i, joint, pre, model);
    let ll = block_pass(ev, i, joint, &xi, &q, pre, &[], model).0;
    let part = &ev.parts[i];
    // Observations in frame t: a position (3) and the rotation axes seen.
    let frame_obs = |t: usize| part.obs[t].map_or(0, |_| 3) + part.rot[t].as_ref().map_or(0, |r| r.axes.len());
    let n_obs: usize = (0..ev.len()).map(frame_obs).sum();
    let seen = part.obs.iter().filter(|o| o.is_some()).count();
    match penalty {
        CoordinatePenalty::Bic => {
            let k = joint.num_params() + if joint.movable() { seen.saturating_sub(1) } else { 0 };
            ll - 0.5 * (n_obs.max(2) as f64).ln() * k as f64
        }
        CoordinatePenalty::PerFrame => {
            let coordinates: f64 = if joint.movable() {
                (0..ev.len())
                    .filter(|&t| part.obs[t].is_some())
                    .skip(1)
                    .map(|t| 0.5 * (frame_obs(t) as f64).ln())
                    .sum()
            } else {
                0.0
            };
            ll - 0.5 * (n_obs.max(2) as f64).ln() * joint.num_params() as f64 - coordinates
        }
    }
}

/// Whether part `j` clearly moves: in some window, its median displacement from the reference
/// exceeds 1 cm at its centre of mass or 3 degrees (a median, because a static part's registration
/// slips now and then). A part that does not is taken as static when other parts are fitted
/// relative to it: a static part's registration jitters by millimetres, and subtracting that
/// jitter from a child's motion would only add noise to it.
///
/// Per window, not over the whole recording: a drawer pushed in one window of four, and left
/// where the push took it, showed a median shift of 8.6 mm over the recording (corpus object 57 of
/// the tune split); taken as static, the contact prior then hung the cabinet from it, and the
/// drawer came out rigid with P = 1.00 (its prismatic joint would have moved the cabinet).
fn moves(ev: &Evidence, j: usize) -> bool {
    let part = &ev.parts[j];
    let median = |v: &mut Vec<f64>| {
        v.sort_by(|a, b| a.total_cmp(b));
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    };
    let (mut shift, mut turn) = (Vec::new(), Vec::new());
    let (mut best_shift, mut best_turn) = (0.0f64, 0.0f64);
    for t in 0..ev.len() {
        if ev.window_start[t] && !shift.is_empty() {
            best_shift = best_shift.max(median(&mut shift));
            best_turn = best_turn.max(median(&mut turn));
            shift.clear();
            turn.clear();
        }
        if let Some(d) = &part.disp[t] {
            shift.push((d * nalgebra::Point3::from(part.com0) - nalgebra::Point3::from(part.com0)).norm());
            turn.push(d.rotation.angle());
        }
    }
    if !shift.is_empty() {
        best_shift = best_shift.max(median(&mut shift));
        best_turn = best_turn.max(median(&mut turn));
    }
    tracing::debug!("part {} moves: largest window median shift {best_shift:.4} m, turn {:.2} deg", part.label, best_turn.to_degrees());
    best_shift > 0.01 || best_turn > 3f64.to_radians()
}

/// The initial structure of the parts of `ev`, with the contact prior's log weights `log_w`
/// (`n` rows of `n + 1`), its coordinates charged by `penalty`.
pub fn initial_structure(ev: &Evidence, model: &ModelConfig, log_w: &[Vec<f64>], penalty: CoordinatePenalty) -> InitialStructure {
    let n = ev.parts.len();
    let world = vec![Displacement::identity(); ev.len()];
    let static_node: Vec<bool> = (0..=n).map(|j| j == 0 || !moves(ev, j - 1)).collect();
    let pres: Vec<Vec<Displacement<f64>>> =
        (0..=n).map(|j| if static_node[j] { world.clone() } else { fitted_displacements(ev, j - 1, model, penalty) }).collect();
    let mut parent_score = vec![vec![f64::NEG_INFINITY; n + 1]; n];
    let mut all_types = vec![vec![[f64::NEG_INFINITY; 3]; n + 1]; n];
    for i in 0..n {
        for j in (0..=n).filter(|&j| j != i + 1) {
            let s = JointType::ALL.map(|k| score(ev, i, k, &pres[j], model, penalty));
            all_types[i][j] = s;
            parent_score[i][j] = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        }
    }
    // Two parts that move rigidly together are one body to the kinematics: which of them carries
    // the other is not observable, so both attachments get the same score (the mean), and so do
    // both ways of hanging the pair from a third node (the mean per joint type: in the model the
    // pair's joint is fitted to both parts' observations, whichever carries the other, while these
    // scores fit it to one part's alone, which would hand the pair to the better-tracked part —
    // a microwave standing on a slider then carried the slider). The contact prior decides.
    let rigid = JointType::Rigid.index();
    for i in 0..n {
        for k in i + 1..n {
            let (a, b) = (&all_types[i][k + 1], &all_types[k][i + 1]);
            let best = |s: &[f64; 3]| s[rigid] >= s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            if best(a) && best(b) {
                let m = 0.5 * (a[rigid] + b[rigid]);
                parent_score[i][k + 1] = m;
                parent_score[k][i + 1] = m;
                for p in (0..=n).filter(|&p| p != i + 1 && p != k + 1) {
                    let s: [f64; 3] = std::array::from_fn(|t| 0.5 * (all_types[i][p][t] + all_types[k][p][t]));
                    let best = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                    all_types[i][p] = s;
                    all_types[k][p] = s;
                    parent_score[i][p] = best;
                    parent_score[k][p] = best;
                }
            }
        }
    }
    for i in 0..n {
        tracing::debug!("initial structure: part {} type scores by parent {:.1?}", ev.parts[i].label, all_types[i]);
    }
    let weights: Vec<Vec<f64>> = (0..n).map(|i| (0..=n).map(|j| parent_score[i][j] + log_w[i][j]).collect()).collect();
    let parent = max_arborescence(&weights);
    let type_score = (0..n).map(|i| all_types[i][parent[i]]).collect();
    InitialStructure { parent, parent_score, type_score, type_score_by_parent: all_types, log_w: log_w.to_vec(), static_node }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::likelihood::{PartSeries, PositionObs};
    use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// Two parts that slide together along x, `sd` of perception noise on each: a carrier that
    /// touches the fixed frame, tracked badly (5 mm), and a load on it that does not, tracked
    /// well (1 mm). The start tree hangs the carrier from the fixed frame, as the contact prior
    /// says, instead of handing the pair to the better-tracked load.
    #[test]
    fn parts_moving_together_follow_the_contact_prior() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let k = 30;
        let times: Vec<f64> = (0..k).map(|t| t as f64 * 0.1).collect();
        let part = |label: u32, com0: Vector3<f64>, sd: f64, rng: &mut rand_chacha::ChaCha8Rng| {
            let noise = Normal::new(0.0, sd).unwrap();
            let mut obs = Vec::new();
            let mut disp = Vec::new();
            for t in 0..k {
                let shift = Vector3::new(0.01 * t as f64, 0.0, 0.0);
                let e = Vector3::new(noise.sample(rng), noise.sample(rng), noise.sample(rng));
                obs.push(Some(PositionObs { y: com0 + shift + e, basis: Matrix3::identity(), var: Vector3::repeat(sd * sd) }));
                disp.push(Some(Isometry3::from_parts(Translation3::from(shift + e), UnitQuaternion::identity())));
            }
            PartSeries { label, com0, obs, rot: vec![None; k], disp, contact: vec![], radius: 0.1, reach: 0.0, unit_inertia: Matrix3::identity() * 0.01, volume: 0.001, weight_offset: Vector3::zeros() }
        };
        let carrier = part(1, Vector3::new(0.0, 0.0, 0.5), 0.005, &mut rng);
        let load = part(2, Vector3::new(0.0, 0.0, 0.8), 0.001, &mut rng);
        let ev = Evidence {
            times,
            window_start: (0..k).map(|t| t == 0).collect(),
            parts: vec![carrier, load],
            contact: vec![vec![0.0, 0.01], vec![0.01, 0.0]],
            windows: vec![],
            effects: vec![Default::default(); 2],
        };
        let model = ModelConfig::default();
        // Rows: part; columns: fixed frame, carrier, load. The load never touches the fixed frame.
        let log_w = vec![vec![0.0, f64::NEG_INFINITY, 0.0], vec![-20.0, 0.0, f64::NEG_INFINITY]];
        let s = initial_structure(&ev, &model, &log_w, CoordinatePenalty::Bic);
        assert_eq!(s.parent, vec![0, 1], "scores {:?}", s.parent_score);
        let best = |t: &[f64; 3]| (0..3).max_by(|&a, &b| t[a].total_cmp(&t[b])).unwrap();
        assert_eq!(best(&s.type_score[0]), JointType::Prismatic.index());
        assert_eq!(best(&s.type_score[1]), JointType::Rigid.index());
        // The pair scores alike whichever part carries the other.
        assert!((s.parent_score[0][0] - s.parent_score[1][0]).abs() < 1e-9);
        assert!((s.parent_score[0][2] - s.parent_score[1][1]).abs() < 1e-9);
    }

    /// The runner-up of a cabinet (static, part 1) with two coaxial doors (parts 2 and 3, both
    /// moving) whose scores hang door 3 from door 2 by a hair: the runner-up hangs it from the
    /// cabinet; a tree with no part on a moving one has none.
    #[test]
    fn runner_up_hangs_a_part_from_a_static_node() {
        let ninf = f64::NEG_INFINITY;
        // Rows: parts 1..3; columns: fixed frame, parts 1..3.
        let parent_score = vec![
            vec![500.0, ninf, 100.0, 90.0],
            vec![300.0, 300.0, ninf, 290.0],
            vec![700.0, 700.0, 710.0, ninf],
        ];
        let log_w = vec![vec![0.0, ninf, -1.0, -1.0], vec![-1.0, 0.0, ninf, -1.0], vec![-1.0, 0.0, -1.0, ninf]];
        let weights: Vec<Vec<f64>> = (0..3).map(|i| (0..4).map(|j| parent_score[i][j] + log_w[i][j]).collect()).collect();
        let parent = max_arborescence(&weights);
        assert_eq!(parent, vec![0, 1, 2]);
        let s = InitialStructure {
            parent,
            parent_score: parent_score.clone(),
            type_score: vec![[0.0; 3]; 3],
            type_score_by_parent: (0..3).map(|i| (0..4).map(|j| [parent_score[i][j], ninf, ninf]).collect()).collect(),
            log_w,
            static_node: vec![true, true, false, false],
        };
        let r = s.runner_up().expect("a runner-up");
        // Door 3 on the cabinet (tree score 1500; on the fixed frame 1499), the rest kept (door 2
        // on door 3, 1489, is not a flatter tree).
        assert_eq!(r.parent, vec![0, 1, 1]);
        assert_eq!(r.type_score[2][0], 700.0);
        assert!(InitialStructure { parent: r.parent.clone(), ..s.clone() }.runner_up().is_none());
        // A single part has no runner-up.
        let one = InitialStructure {
            parent: vec![0],
            parent_score: vec![vec![1.0, ninf]],
            type_score: vec![[1.0, ninf, ninf]],
            type_score_by_parent: vec![vec![[1.0, ninf, ninf], [ninf; 3]]],
            log_w: vec![vec![0.0, ninf]],
            static_node: vec![true, false],
        };
        assert!(one.runner_up().is_none());
    }
}
