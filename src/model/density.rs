//! The model as one log density (issue 26): for a fixed *structure* — the tree and every part's
//! joint type, with the declared and adopted effects of the evidence — the unnormalised log
//! posterior of all continuous latents and its gradient, the interface that inference
//! algorithms consume (as `CpuLogpFunc` in nuts-rs, or a Pyro model's `log_density`).
//!
//! The terms are the paper's generative model (§3.2-3.4):
//! - the likelihood of every observed part pose (eq. 2, Student-t positions and rotations,
//!   [`crate::model::likelihood`]) through the chain of screw displacements of the tree
//!   ([`block_pass`], the part's subtree moving with it);
//! - `N(0, I)` priors on every standardised parameter: kinematic ([`crate::model::decode`]:
//!   reference centre of mass, noise levels, screw axis — whose direction vector keeps the uniform
//!   direction of `N(0, I)` with its length held near 1, [`direction_length_prior`]), kinodynamic
//!   ([`crate::model::dynamics::decode`]: damping, friction, mass, deviation, effects) and, in
//!   kinematic mode, the coordinates' velocity scale;
//! - the prior of the joint coordinates: kinematic mode, the random walk of
//!   [`crate::model::likelihood::coordinate_prior`]; dynamic mode, window starts
//!   ([`crate::model::likelihood::window_start_prior`]: reset or anywhere), the physics prior of
//!   each window made robust to windows it cannot explain, and the rests between and after
//!   windows ([`physics_prior`]).
//!
//! The latents are unconstrained already: the priors are defined on the standardised
//! parameters (decoding to physical units is part of the model, not a change of variables), and
//! coordinates are metres of path, so no Jacobian enters. [`Density::log_density`] is exact; its
//! gradient is exact for the likelihood and the coordinate priors (dual numbers through the model
//! code) and for each part's own physics prior — its kinodynamics, coordinates and own kinematic
//! parameters (axis, centre of mass) seeded in the same dual numbers, one simulation a window
//! ([`physics_prior_kinematic`]). What one part's parameters do to another part's physics (a
//! parent's axis moving a child's joint, a child's mass and centre of mass loading its parent)
//! is taken by forward differences of that part's value ([`cross_physics_differences`]), and so
//! is what another part's *coordinate* at a window's first frame does to a nested joint's
//! physics in that window ([`coordinate_cross_differences`]; left out until stop 115). A
//! gradient that is not exactly the density's keeps Hamiltonian Monte Carlo exact (leapfrog
//! steps stay volume-preserving and reversible, and acceptance uses the exact density), but it
//! costs more than step size: a wrong force's energy error grows with the trajectory's length,
//! not with the step, so the step size adaptation shrinks the step until the depth limit caps
//! the trajectory (`slide_microwave` at step size 1e-3-1e-4 before stop 115).
//! SVI's conditional ELBOs are expectations of the same terms under its guide
//! ([`crate::inference::svi`]).

use std::cell::RefCell;
use std::collections::VecDeque;

use nalgebra::{Matrix3, Vector3};
use num_dual::DualSVec64;

use crate::model::dynamics::{self, JointInWindow, SubtreeBody};
use crate::model::effects::EffectSet;
use crate::model::likelihood::{coordinate_prior, log_likelihood_contact, log_likelihood_position, log_likelihood_rotation, window_start_prior, Evidence, WindowEvidence};
use crate::model::{decode, displacement, mat_mul, tree, Displacement, JointParams, JointType, ModelConfig};


/// One part's values: decoded kinematic parameters, joint coordinates on the evidence grid
/// \[m of path; zeros for a rigid joint\], and standardised kinodynamic parameters (dynamic mode,
/// movable joints).
#[derive(Debug, Clone, Copy)]
pub struct PartValue<'a> {
    pub params: &'a JointParams<f64>,
    pub q: &'a [f64],
    pub kd: Option<&'a [f64]>,
}

/// Transform of every part at every grid frame for a tree (`parent[i]`: 0 the fixed frame,
/// `j + 1` part `j`) and per-part values.
pub fn part_transforms(parent: &[usize], values: &[PartValue<'_>], frames: usize) -> Vec<Vec<Displacement<f64>>> {
    tree::part_transforms(parent, frames, |i, t| displacement(values[i].params, values[i].q[t]))
}

/// The inverse rigid displacement.
pub fn inverse(d: &Displacement<f64>) -> Displacement<f64> {
    let rt = d.r.transpose();
    Displacement { r: rt, t: -(rt * d.t) }
}

/// The descendants of part `i` under `parent`, each relative to part `i`'s frame at every grid
/// frame (for [`block_pass`]); `transforms` from [`part_transforms`], `positions[m][t]` the centre
/// of mass of part `m` at frame `t` (fixed frame).
pub fn subtree_members(
    ev: &Evidence,
    parent: &[usize],
    i: usize,
    transforms: &[Vec<Displacement<f64>>],
    positions: &[Vec<Vector3<f64>>],
    values: &[PartValue<'_>],
) -> Vec<Member> {
    let frames = transforms.first().map_or(0, Vec::len);
    let inv: Vec<Displacement<f64>> = (0..frames).map(|t| inverse(&transforms[i][t])).collect();
    tree::descendants(parent, i)
        .into_iter()
        .map(|m| Member {
            m,
            z: (0..frames).map(|t| inv[t].apply(&positions[m][t])).collect(),
            r: (0..frames).map(|t| inv[t].r * transforms[m][t].r).collect(),
            contact: (0..frames).map(|t| ev.parts[m].contact_at(t).map(|c| inv[t].apply(&transforms[m][t].apply(&c.x)))).collect(),
            sigma: values[m].params.noise,
            rot_sigma: values[m].params.rot_noise,
        })
        .collect()
}

/// A descendant of the part being differentiated, expressed relative to that part's frame.
pub struct Member {
    /// Part index.
    pub m: usize,
    /// Centre of mass per frame relative to the part's displacement (f64).
    pub z: Vec<Vector3<f64>>,
    /// Rotation per frame relative to the part's displacement.
    pub r: Vec<Matrix3<f64>>,
    /// Per frame, the member's contact material point ([`crate::model::likelihood::ContactObs`])
    /// relative to the part's displacement, where the contact observes it.
    pub contact: Vec<Option<Vector3<f64>>>,
    /// Position and rotation noise of the member's likelihood (its own sampled values).
    pub sigma: f64,
    pub rot_sigma: f64,
}

/// Log-likelihood of a part's subtree with part `i` under joint type `joint` and its gradient with
/// respect to that block's standardised parameters and coordinates, from dual numbers.
///
/// `pre[t]` is the parent's displacement at frame `t`; `subtree` the descendants relative to
/// part `i`'s frame. Rotations, where observable, add their likelihood; a revolute joint adds
/// the prior that its axis reaches the part ([`crate::model::revolute::reach_prior`]).
#[allow(clippy::too_many_arguments)]
pub fn block_pass(
    ev: &Evidence,
    i: usize,
    joint: JointType,
    xi: &[f64],
    q: &[f64],
    pre: &[Displacement<f64>],
    subtree: &[Member],
    cfg: &ModelConfig,
) -> (f64, Vec<f64>, Vec<f64>) {
    // Dual numbers as wide as the joint's parameters plus its coordinate (a prismatic joint's 9,
    // a rigid one's 6: the widest, a revolute joint's 12, cost twice as much per operation).
    match joint {
        JointType::Rigid => block_pass_n::<{ crate::model::rigid::NUM_PARAMS + 1 }>(ev, i, joint, xi, q, pre, subtree, cfg),
        JointType::Prismatic => block_pass_n::<{ crate::model::prismatic::NUM_PARAMS + 1 }>(ev, i, joint, xi, q, pre, subtree, cfg),
        JointType::Revolute => block_pass_n::<{ crate::model::revolute::NUM_PARAMS + 1 }>(ev, i, joint, xi, q, pre, subtree, cfg),
    }
}

/// [`block_pass`] with `N` dual directions: the joint's parameters, then its coordinate (`N - 1`).
#[allow(clippy::too_many_arguments)]
fn block_pass_n<const N: usize>(
    ev: &Evidence,
    i: usize,
    joint: JointType,
    xi: &[f64],
    q: &[f64],
    pre: &[Displacement<f64>],
    subtree: &[Member],
    cfg: &ModelConfig,
) -> (f64, Vec<f64>, Vec<f64>) {
    type D<const N: usize> = DualSVec64<N>;
    let q_slot = N - 1;
    let np = joint.num_params();
    debug_assert_eq!(np + 1, N);
    let xid: Vec<D<N>> = xi.iter().enumerate().map(|(j, &x)| D::<N>::from_re(x).derivative(j)).collect();
    let p = decode(joint, &xid, &ev.parts[i].com0, cfg);
    let (mut l, mut gx, mut gq) = (0.0, vec![0.0; np], vec![0.0; ev.len()]);
    for t in 0..ev.len() {
        let own_obs = &ev.parts[i].obs[t];
        let own_contact = ev.parts[i].contact_at(t);
        let any_sub = subtree.iter().any(|mb| ev.parts[mb.m].obs[t].is_some() || mb.contact[t].is_some());
        if own_obs.is_none() && own_contact.is_none() && !any_sub {
            continue;
        }
        let qt = if joint.movable() { D::<N>::from_re(q[t]).derivative(q_slot) } else { D::<N>::from_re(q[t]) };
        let s = pre[t].compose_lifted(&displacement(&p, qt));
        let mut ll = D::<N>::from_re(0.0);
        if let Some(o) = own_obs {
            ll += log_likelihood_position(o, &s.apply(&p.com), p.noise, cfg.student_nu);
        }
        if let Some(o) = &ev.parts[i].rot[t] {
            ll += log_likelihood_rotation(o, &s.r, p.rot_noise, cfg.student_nu);
        }
        if let Some(cobs) = own_contact {
            ll += log_likelihood_contact(cobs, &s.apply_const(&cobs.x), cfg.student_nu);
        }
        for mb in subtree {
            if let (Some(z), Some(cobs)) = (&mb.contact[t], ev.parts[mb.m].contact_at(t)) {
                ll += log_likelihood_contact(cobs, &s.apply_const(z), cfg.student_nu);
            }
            if let Some(o) = &ev.parts[mb.m].obs[t] {
                ll += log_likelihood_position(o, &s.apply_const(&mb.z[t]), D::<N>::from(mb.sigma), cfg.student_nu);
            }
            if let Some(o) = &ev.parts[mb.m].rot[t] {
                ll += log_likelihood_rotation(o, &mat_mul(&s.r, &mb.r[t]), D::<N>::from(mb.rot_sigma), cfg.student_nu);
            }
        }
        l += ll.re;
        if let Some(e) = ll.eps.0 {
            for j in 0..np {
                gx[j] += e[j];
            }
            gq[t] = e[q_slot];
        }
    }
    if joint == JointType::Revolute {
        // The axis must reach the part it carries (a prior on the axis, counted here with the
        // kinematic parameters' other non-analytic terms).
        let lp = crate::model::revolute::reach_prior(&p, &ev.parts[i].com0, ev.parts[i].reach, cfg);
        l += lp.re;
        if let Some(e) = lp.eps.0 {
            for j in 0..np {
                gx[j] += e[j];
            }
        }
    }
    (l, gx, gq)
}

/// The physics prior of part `i` (value `s`) over all windows (dynamic mode) and its gradients:
/// `(log prior, d/d xi_kd, d/d q_t per grid frame)`. `robust`: each window's physics prior made
/// robust to windows it cannot explain ([`dynamics::robust_window_prior`]) — in the ELBO's
/// iterations, which decide the tree and the joint types; the Laplace fits of the kinodynamic
/// factors (the guide's and the reported ones) use the plain physics prior, so that a window the
/// physics misses widens their intervals (the window-robust inflation) instead of dropping out of
/// them. With `scores`, also each window's share of
/// `d/d xi_kd` (one entry per window, the rest term before a window counted in it; zero on damping
/// and friction where the window does not simulate the joint).
#[allow(clippy::too_many_arguments)]
pub fn physics_prior(
    ev: &Evidence,
    i: usize,
    s: &PartValue<'_>,
    observed: Option<&dynamics::Observed>,
    pre: &[Displacement<f64>],
    desc: &[usize],
    chosen: &[PartValue<'_>],
    transforms: &[Vec<Displacement<f64>>],
    model: &ModelConfig,
    robust: bool,
    scores: Option<&mut Vec<Vec<f64>>>,
) -> (f64, Vec<f64>, Vec<f64>) {
    let (l, gx, gq, _) = physics_prior_collapsed(ev, i, s, observed, pre, desc, chosen, transforms, model, robust, scores, None);
    (l, gx, gq)
}

/// [`physics_prior`] and, fourth, its value with the coordinates of the grid frames flagged in
/// `skip` integrated out (one flag per grid frame; `None`: none): a flagged rest frame's term
/// drops, a flagged window frame after the first is integrated out of the window's prior
/// ([`dynamics::robust_window_prior_collapsed`]), and a window whose frames are all flagged drops
/// with the rest term that ties its first frame to the previous window. Exact where the flags
/// mark leaves of the prior's graph, peeled from the ends (the caller's duty: a window's last
/// frame only with the rest frames after it and the next window's first where that continues
/// it; a first frame only with its whole window).
/// The gradients are those of the full prior. See [`crate::inference::svi`] for the use: the
/// joint-type comparison on frames in which nothing observes the joint.
#[allow(clippy::too_many_arguments)]
pub fn physics_prior_collapsed(
    ev: &Evidence,
    i: usize,
    s: &PartValue<'_>,
    observed: Option<&dynamics::Observed>,
    pre: &[Displacement<f64>],
    desc: &[usize],
    chosen: &[PartValue<'_>],
    transforms: &[Vec<Displacement<f64>>],
    model: &ModelConfig,
    robust: bool,
    scores: Option<&mut Vec<Vec<f64>>>,
    skip: Option<&[bool]>,
) -> (f64, Vec<f64>, Vec<f64>, f64) {
    physics_prior_terms(ev, i, s, observed, pre, desc, chosen, transforms, model, robust, scores, skip, Terms::Kinodynamic)
}

/// The value of [`physics_prior`] alone (`physics_prior(..).0`, without observed coordinates),
/// its windows simulated in `f64` instead of dual numbers: the finite differences of
/// [`Density::log_density`] need only values, and the dual numbers cost several times as much.
#[allow(clippy::too_many_arguments)]
pub fn physics_prior_value(
    ev: &Evidence,
    i: usize,
    s: &PartValue<'_>,
    pre: &[Displacement<f64>],
    desc: &[usize],
    chosen: &[PartValue<'_>],
    transforms: &[Vec<Displacement<f64>>],
    model: &ModelConfig,
    robust: bool,
) -> f64 {
    physics_prior_terms(ev, i, s, None, pre, desc, chosen, transforms, model, robust, None, None, Terms::Value).0
}

/// [`physics_prior`] (robust windows, no observed coordinates) with, after the kinodynamic
/// gradient, the gradient with respect to part `i`'s own standardised kinematic parameters `xk`
/// at the positions [`kinematic_dims`] lists — from the same dual numbers as the kinodynamic one,
/// one simulation a window (the axis and centre of mass enter the physics through the
/// generalised inertia, the projected push, the radius and gravity's lever); with `replay`, the
/// windows' `Psi` taken from it rather than simulated ([`NonCentred`]).
#[allow(clippy::too_many_arguments)]
pub(crate) fn physics_prior_kinematic(
    ev: &Evidence,
    i: usize,
    s: &PartValue<'_>,
    xk: &[f64],
    pre: &[Displacement<f64>],
    desc: &[usize],
    chosen: &[PartValue<'_>],
    transforms: &[Vec<Displacement<f64>>],
    model: &ModelConfig,
    replay: Option<&Replay>,
) -> (f64, Vec<f64>, Vec<f64>) {
    let (l, gx, gq, _) = physics_prior_terms(ev, i, s, None, pre, desc, chosen, transforms, model, true, None, None, Terms::Kinematic(xk, replay));
    (l, gx, gq)
}

/// The standardised kinematic parameters (positions in a joint's block) that a joint's own
/// physics depends on: a revolute joint's centre of mass (its radius and lever), direction and
/// point; a prismatic joint's direction only (its generalised inertia is the carried mass, its
/// push the force along the axis, wherever the bodies are).
pub fn kinematic_dims(joint: JointType) -> &'static [usize] {
    match joint {
        JointType::Revolute => &[0, 1, 2, 5, 6, 7, 8, 9, 10],
        JointType::Prismatic => &[5, 6, 7],
        JointType::Rigid => &[],
    }
}

/// Part of [`NonCentred`]'s map handed to the density: each window's `Psi` at its frames, with
/// its derivatives, in window order; the physics prior takes them in place of simulating again.
pub(crate) type Replay = RefCell<VecDeque<FramePsi>>;

/// `Psi` of one joint in one window at the window's frames (`psi[0]` the window's first
/// coordinate), as the physics prior's dual simulation gives it: the value and its derivatives
/// over the dual directions of [`window_prior_kinematic`] — the kinodynamic parameters
/// (`0..nk`), the window's first coordinate (`nk`) and the joint's own [`kinematic_dims`]
/// (after it). Kept by [`NonCentred`], which needs `Psi` before the density can be evaluated
/// (its map) and the same derivatives after (its chain rule): one dual simulation a window serves both.
#[derive(Debug, Clone)]
pub(crate) struct FramePsi {
    /// Dual directions a frame (the `N` of the dual numbers it came from).
    n: usize,
    /// `Psi_k` \[m of path\].
    re: Vec<f64>,
    /// The derivative of `Psi_k` along dual direction `j` at `eps[k * n + j]`.
    eps: Vec<f64>,
}

impl FramePsi {
    fn from_dual<const N: usize>(psi: &[DualSVec64<N>]) -> Self {
        let mut eps = Vec::with_capacity(psi.len() * N);
        for p in psi {
            eps.extend(p.eps.unwrap_generic(nalgebra::Const::<N>, nalgebra::U1).iter());
        }
        FramePsi { n: N, re: psi.iter().map(|p| p.re).collect(), eps }
    }

    /// The dual numbers again, `None` when they had another width.
    fn to_dual<const N: usize>(&self) -> Option<Vec<DualSVec64<N>>> {
        (self.n == N).then(|| {
            self.re
                .iter()
                .zip(self.eps.chunks_exact(N))
                .map(|(&re, e)| DualSVec64::<N>::new(re, num_dual::Derivative::some(nalgebra::SVector::<f64, N>::from_column_slice(e))))
                .collect()
        })
    }

    /// The derivative of `Psi_k` along dual direction `j`.
    fn d(&self, k: usize, j: usize) -> f64 {
        self.eps[k * self.n + j]
    }
}

/// What [`physics_prior_terms`] differentiates.
#[derive(Clone, Copy)]
enum Terms<'a> {
    /// The value alone (windows simulated in `f64`).
    Value,
    /// The kinodynamic parameters and the coordinates.
    Kinodynamic,
    /// Those and the part's own kinematic parameters (its standardised block, given); with a
    /// replay, each window's `Psi` is taken from it (in window order) instead of simulated again
    /// ([`NonCentred`], which simulated it for its map).
    Kinematic(&'a [f64], Option<&'a Replay>),
}

/// [`physics_prior_collapsed`], differentiated as `terms` says: with [`Terms::Value`] the window
/// gradients are left out of the returned ones (which then hold the rest terms' only); with
/// [`Terms::Kinematic`] the second vector continues with the [`kinematic_dims`] gradient.
#[allow(clippy::too_many_arguments)]
fn physics_prior_terms(
    ev: &Evidence,
    i: usize,
    s: &PartValue<'_>,
    observed: Option<&dynamics::Observed>,
    pre: &[Displacement<f64>],
    desc: &[usize],
    chosen: &[PartValue<'_>],
    transforms: &[Vec<Displacement<f64>>],
    model: &ModelConfig,
    robust: bool,
    mut scores: Option<&mut Vec<Vec<f64>>>,
    skip: Option<&[bool]>,
    terms: Terms<'_>,
) -> (f64, Vec<f64>, Vec<f64>, f64) {
    let Some(xi) = s.kd else { return (0.0, vec![], vec![], 0.0) };
    let dyncfg = &model.dynamics;
    let n_kin = if let Terms::Kinematic(..) = terms { kinematic_dims(s.params.joint).len() } else { 0 };
    let (mut l, mut gx, mut gq) = (0.0, vec![0.0; xi.len() + n_kin], vec![0.0; ev.len()]);
    // The share of `l` that the frames flagged in `skip` carry.
    let mut skipped = 0.0;
    let flagged = |t: usize| skip.is_some_and(|f| f.get(t).copied().unwrap_or(false));
    if let Some(sc) = scores.as_deref_mut() {
        sc.clear();
    }
    // The deviation scale, also that of a joint at rest between windows and at rest frames.
    let rest_sd = dynamics::decode::<f64>(s.params.joint, xi, &ev.effects[i], dyncfg).deviation;
    for (w, win) in ev.windows.iter().enumerate() {
        let gx_before = scores.is_some().then(|| gx.clone());
        // Between windows no force acts: the joint rests where the last window left it, up to
        // the same deviation scale — while the object is watched (not across separate episodes).
        if w > 0 && win.continues {
            let (a, b) = (ev.windows[w - 1].frames[ev.windows[w - 1].frames.len() - 1], win.frames[0]);
            let r = rest_term(s.q, a, b, rest_sd, dyncfg, &mut gq, &mut gx[3]);
            l += r;
            if flagged(b) {
                skipped += r;
            }
        }
        // Before the window the joint rests where the physics window starts it (rest frames before).
        for &b in &win.rest_before {
            let r = rest_term(s.q, win.frames[0], b, rest_sd, dyncfg, &mut gq, &mut gx[3]);
            l += r;
            if flagged(b) {
                skipped += r;
            }
        }
        // After the window the joint rests where the physics window left it (rest frames).
        if let Some(&a) = win.frames.last() {
            for &b in &win.rest {
                let r = rest_term(s.q, a, b, rest_sd, dyncfg, &mut gq, &mut gx[3]);
                l += r;
                if flagged(b) {
                    skipped += r;
                }
            }
        }
        let wj = window_joint(ev, i, s, win, pre, desc, chosen, transforms, model);
        let jw = wj.view(ev.effects[i]);
        let (lw, gxw, gqw, lw_kept) = match terms {
            Terms::Value => {
                let l = window_value(&jw, win, s.q, observed, xi, model, robust);
                (l, vec![], vec![], l)
            }
            Terms::Kinodynamic if robust => {
                let (l, gx, gq, _, kept) = dynamics::robust_window_prior_collapsed(&jw, win, s.q, observed, xi, dyncfg, model.velocity_sd_mps, skip);
                (l, gx, gq, kept)
            }
            Terms::Kinodynamic => dynamics::window_prior_split(&jw, win, s.q, observed, xi, dyncfg, skip),
            Terms::Kinematic(xk, replay) => {
                let physics = window_prior_kinematic(ev, i, s, xk, win, pre, desc, chosen, transforms, model, &jw, observed, skip, replay);
                if robust {
                    let (l, gx, gq, _, kept) = dynamics::robust_mix(win, s.q, observed, dyncfg, model.velocity_sd_mps, skip, physics);
                    (l, gx, gq, kept)
                } else {
                    physics
                }
            }
        };
        l += lw;
        skipped += lw - lw_kept;
        for (a, b) in gx.iter_mut().zip(&gxw) {
            *a += b;
        }
        for (&t, g) in win.frames.iter().zip(&gqw) {
            gq[t] += g;
        }
        if let (Some(sc), Some(before)) = (scores.as_deref_mut(), &gx_before) {
            sc.push(gx.iter().zip(before).map(|(a, b)| a - b).collect());
        }
    }
    (l, gx, gq, l - skipped)
}

/// The physics prior of part `i` in window `win` ([`dynamics::window_prior_split`]) with dual
/// numbers seeded on the kinodynamic parameters, the window's first coordinate and the part's
/// own kinematic parameters at [`kinematic_dims`] (standardised block `xk`): the geometry of
/// [`window_joint`] rebuilt in dual numbers from `xk` — the axis moved by the parent's
/// displacement at the window's first frame, the part and its locked subtree carried by the
/// joint's own displacement there. Returns `(value, gradient over kinodynamics then kinematic
/// dims, gradient per window frame, value over the frames not flagged in skip)`.
#[allow(clippy::too_many_arguments)]
fn window_prior_kinematic(
    ev: &Evidence,
    i: usize,
    s: &PartValue<'_>,
    xk: &[f64],
    win: &WindowEvidence,
    pre: &[Displacement<f64>],
    desc: &[usize],
    chosen: &[PartValue<'_>],
    transforms: &[Vec<Displacement<f64>>],
    model: &ModelConfig,
    jw: &dynamics::JointInWindow<'_>,
    observed: Option<&dynamics::Observed>,
    skip: Option<&[bool]>,
    replay: Option<&Replay>,
) -> (f64, Vec<f64>, Vec<f64>, f64) {
    let args = (ev, i, s, xk, win, pre, desc, chosen, transforms, model, jw, observed, skip, replay);
    match dual_width(s) {
        8 => window_prior_kinematic_n::<8>(args),
        14 => window_prior_kinematic_n::<14>(args),
        _ => window_prior_kinematic_n::<21>(args),
    }
}

/// The width `N` of [`window_prior_kinematic`]'s dual numbers for part value `s`: its
/// kinodynamic parameters, the window's first coordinate and its [`kinematic_dims`], rounded up
/// to 8, 14 or 21.
fn dual_width(s: &PartValue<'_>) -> usize {
    match s.kd.map_or(0, |x| x.len()) + 1 + kinematic_dims(s.params.joint).len() {
        0..=8 => 8,
        9..=14 => 14,
        15..=21 => 21,
        n => panic!("{n} dual directions: at most 21 (10 kinodynamic, 1 coordinate, 9 kinematic)"),
    }
}

/// `Psi` of part `i` in window `win` at the window's frames, simulated in the dual numbers of
/// [`window_prior_kinematic`] (its arguments, as a tuple; observations, skips and replay unused;
/// [`NonCentred`]'s map).
fn window_psi_kinematic(args: KinematicArgs<'_, '_>) -> FramePsi {
    fn psi<const N: usize>(args: KinematicArgs<'_, '_>) -> FramePsi {
        let (ev, i, s, _, _, _, _, _, _, model, ..) = args;
        let xd = kinodynamic_duals::<N>(s);
        let kp = dynamics::decode(s.params.joint, &xd, &ev.effects[i], &model.dynamics);
        FramePsi::from_dual(&simulate_kinematic_n::<N>(args, &kp))
    }
    match dual_width(args.2) {
        8 => psi::<8>(args),
        14 => psi::<14>(args),
        _ => psi::<21>(args),
    }
}

type KinematicArgs<'a, 'b> = (
    &'a Evidence,
    usize,
    &'a PartValue<'b>,
    &'a [f64],
    &'a WindowEvidence,
    &'a [Displacement<f64>],
    &'a [usize],
    &'a [PartValue<'b>],
    &'a [Vec<Displacement<f64>>],
    &'a ModelConfig,
    &'a dynamics::JointInWindow<'a>,
    Option<&'a dynamics::Observed>,
    Option<&'a [bool]>,
    Option<&'a Replay>,
);

/// A movable part's kinodynamic parameters as dual numbers, seeded on directions `0..nk`.
fn kinodynamic_duals<const N: usize>(s: &PartValue<'_>) -> Vec<DualSVec64<N>> {
    let xi = s.kd.expect("a movable joint's kinodynamics");
    xi.iter().enumerate().map(|(j, &x)| DualSVec64::<N>::from_re(x).derivative(j)).collect()
}

fn window_prior_kinematic_n<const N: usize>(args: KinematicArgs<'_, '_>) -> (f64, Vec<f64>, Vec<f64>, f64) {
    let (ev, i, s, _, win, _, _, _, _, model, _, observed, skip, replay) = args;
    let (nk, n_kin) = (s.kd.map_or(0, |x| x.len()), kinematic_dims(s.params.joint).len());
    // The window's first coordinate's direction follows the kinodynamic ones.
    let q0_slot = nk;
    let xd = kinodynamic_duals::<N>(s);
    let kp = dynamics::decode(s.params.joint, &xd, &ev.effects[i], &model.dynamics);
    // A replay of another width or length (a bug) is not used: the window is simulated instead.
    let replayed = replay.and_then(|r| r.borrow_mut().pop_front()).and_then(|f| f.to_dual::<N>()).filter(|p| p.len() == win.frames.len());
    let psi = replayed.unwrap_or_else(|| simulate_kinematic_n::<N>(args, &kp));
    let (ll, mut gq, skipped) = dynamics::window_terms_at(&psi, win, s.q, observed, &kp, &model.dynamics, skip);
    let eps = ll.eps.unwrap_generic(nalgebra::Const::<N>, nalgebra::U1);
    let mut gx: Vec<f64> = (0..nk).map(|j| eps[j]).collect();
    gx.extend((0..n_kin).map(|k| eps[nk + 1 + k]));
    gq[0] += eps[q0_slot];
    (ll.re, gx, gq, ll.re - skipped)
}

/// The simulation of [`window_prior_kinematic_n`] at decoded kinodynamics `kp`: `Psi` at the
/// window's frames, dual numbers seeded on the kinodynamics (`kp`'s), the window's first
/// coordinate and the part's own kinematic parameters.
fn simulate_kinematic_n<const N: usize>(args: KinematicArgs<'_, '_>, kp: &dynamics::KinoParams<DualSVec64<N>>) -> Vec<DualSVec64<N>> {
    type Dn<const N: usize> = DualSVec64<N>;
    let (ev, i, s, xk, win, pre, desc, chosen, transforms, model, jw, ..) = args;
    let dims = kinematic_dims(s.params.joint);
    let nk = s.kd.map_or(0, |x| x.len());
    let q0_slot = nk;
    let f0 = win.frames[0];
    let q0 = Dn::<N>::from_re(s.q[f0]).derivative(q0_slot);
    let mut xkd: Vec<Dn<N>> = xk.iter().map(|&x| Dn::<N>::from_re(x)).collect();
    for (k, &j) in dims.iter().enumerate() {
        xkd[j] = xkd[j].derivative(nk + 1 + k);
    }
    let p = decode(s.params.joint, &xkd, &ev.parts[i].com0, model);
    // The joint's own displacement at the window's start, through `q0` too: gravity's moment is
    // taken at the centre of mass there and turned from `q0` on (`gravity_at`), so both carry
    // `q0`'s derivative, which cancels as it must (with the centre of mass held at its value the
    // gradient in a window's first coordinate was off by a percent under gravity).
    let own = pre[f0].compose_lifted(&displacement(&p, q0));
    let rot = |r: &Matrix3<f64>, v: &Vector3<Dn<N>>| Vector3::from_fn(|a, _| v[0] * r[(a, 0)] + v[1] * r[(a, 1)] + v[2] * r[(a, 2)]);
    let carried = |u: &Matrix3<f64>| mat_mul(&mat_mul(&own.r, u), &own.r.transpose());
    // The subtree relative to the part at the window's start, then carried by `own`.
    let to_part = inverse(&transforms[i][f0]);
    let subtree = desc
        .iter()
        .zip(&jw.subtree)
        .map(|(&m, body)| {
            let rel = to_part.compose(&transforms[m][f0]);
            let u = rel.r * ev.parts[m].unit_inertia * rel.r.transpose();
            let weight = own.apply_const(&rel.apply(&(chosen[m].params.com + ev.parts[m].weight_offset)));
            (Dn::<N>::from(body.mass), own.apply_const(&rel.apply(&chosen[m].params.com)), carried(&u), weight)
        })
        .collect();
    let geom = dynamics::WindowGeometry {
        direction: rot(&pre[f0].r, &p.direction),
        point: rot(&pre[f0].r, &p.point) + pre[f0].t.map(Dn::<N>::from),
        radius: p.radius,
        com: own.apply(&p.com),
        unit_inertia: carried(&ev.parts[i].unit_inertia),
        subtree,
        weight_com: own.apply(&(p.com + ev.parts[i].weight_offset.map(Dn::<N>::from))),
    };
    let traj = dynamics::simulate_joint_in(jw, &geom, win, q0, Dn::<N>::from(0.0), kp, &model.dynamics);
    (0..win.frames.len()).map(|k| dynamics::psi_at(traj.as_ref(), win, k, q0)).collect()
}

/// Part `i`'s joint in one window as the physics sees it (fixed frame, at the window's start
/// frame `f0`): its geometry moved by the parent's displacement `pre[f0]`, the child's centre of
/// mass and inertia, and the locked subtree `desc` (masses from `chosen`'s kinodynamics, the
/// prior median where a descendant has none), with `transforms` from [`part_transforms`].
#[allow(clippy::too_many_arguments)]
pub fn window_joint(
    ev: &Evidence,
    i: usize,
    s: &PartValue<'_>,
    win: &WindowEvidence,
    pre: &[Displacement<f64>],
    desc: &[usize],
    chosen: &[PartValue<'_>],
    transforms: &[Vec<Displacement<f64>>],
    model: &ModelConfig,
) -> WindowJoint {
    let dyncfg = &model.dynamics;
    let f0 = win.frames[0];
    let own = pre[f0].compose(&displacement(s.params, s.q[f0]));
    let mut joint = *s.params;
    joint.direction = pre[f0].r * s.params.direction;
    joint.point = pre[f0].apply(&s.params.point);
    let rotate = |d: &Displacement<f64>, u: &Matrix3<f64>| d.r * u * d.r.transpose();
    let subtree: Vec<SubtreeBody> = desc
        .iter()
        .map(|&m| SubtreeBody {
            mass: chosen[m]
                .kd
                .map(|x| dynamics::decode::<f64>(chosen[m].params.joint, x, &ev.effects[m], dyncfg).mass)
                .unwrap_or(dyncfg.mass_median_kg),
            com: transforms[m][f0].apply(&chosen[m].params.com),
            unit_inertia: rotate(&transforms[m][f0], &ev.parts[m].unit_inertia),
            weight_com: transforms[m][f0].apply(&(chosen[m].params.com + ev.parts[m].weight_offset)),
        })
        .collect();
    WindowJoint {
        com: own.apply(&s.params.com),
        weight_com: own.apply(&(s.params.com + ev.parts[i].weight_offset)),
        unit_inertia: rotate(&own, &ev.parts[i].unit_inertia),
        joint,
        subtree,
        pushed: win.pushed.is_some_and(|p| p == i || desc.contains(&p)),
    }
}

/// What [`window_joint`] returns: the owned parts of a [`JointInWindow`].
#[derive(Debug, Clone)]
pub struct WindowJoint {
    pub joint: JointParams<f64>,
    pub com: Vector3<f64>,
    /// Where the child's weight acts ([`JointInWindow::weight_com`]).
    pub weight_com: Vector3<f64>,
    pub unit_inertia: Matrix3<f64>,
    pub subtree: Vec<SubtreeBody>,
    pub pushed: bool,
}

impl WindowJoint {
    /// The physics' view, with the joint's `effects`.
    pub fn view(&self, effects: EffectSet) -> JointInWindow<'_> {
        JointInWindow { joint: &self.joint, com: self.com, unit_inertia: self.unit_inertia, weight_com: self.weight_com, subtree: self.subtree.clone(), pushed: self.pushed, effects }
    }
}

/// `log t_nu(q_b; q_a, sd)`, a joint resting at `q_a` while no force acts (between windows, and
/// at rest frames): Student-t with `cfg.rest_nu` degrees of freedom
/// ([`dynamics::DynamicsConfig::rest_nu`]), Gaussian when it is 0 (the default). Its gradients
/// are added to `gq` (coordinates) and `g_dev` (the deviation's standardised parameter, whose
/// log-normal has log-sd `cfg.deviation_log_sd`).
///
/// Why Student-t is offered: a joint that the model says rests may still move — a door falling
/// shut under a gravity or spring that the base model lacks, in the rest frames after its push.
/// As a Gaussian such a frame costs `d^2 / 2 sd^2` without bound, and the frames that do rest
/// pull the deviation scale down (`-log sd` each): with `perception.hull_outlier_neighbours: 8`
/// a door's revolute fit paid 10^6 nats for a 9 mm move at a 10 um scale and was called
/// prismatic (effects corpus, `tune` `obj015`, config seed 0; README "Generalization", stop 86).
fn rest_term(q: &[f64], a: usize, b: usize, sd: f64, cfg: &dynamics::DynamicsConfig, gq: &mut [f64], g_dev: &mut f64) -> f64 {
    let (nu, deviation_log_sd) = (cfg.rest_nu, cfg.deviation_log_sd);
    let d = q[b] - q[a];
    if !(nu.is_finite() && nu > 0.0) {
        // The Gaussian as before `rest_nu`, term for term, so that the default's fits stay
        // identical to the last bit (`log_student`'s Gaussian rounds differently).
        gq[b] -= d / (sd * sd);
        gq[a] += d / (sd * sd);
        *g_dev += (d * d / (sd * sd) - 1.0) * deviation_log_sd;
        return -(d * d) / (2.0 * sd * sd) - (sd * (2.0 * std::f64::consts::PI).sqrt()).ln();
    }
    let var = sd * sd;
    let score = dynamics::student_score(d, var, nu);
    gq[b] += score;
    gq[a] -= score;
    // d/d log(sd) = -1 - d * score.
    *g_dev += (-1.0 - d * score) * deviation_log_sd;
    super::likelihood::log_student(d * d / var, sd.ln(), 1, nu)
}

/// The discrete latents a [`Density`] conditions on: the tree (`parent[i]`: 0 the fixed frame,
/// `j + 1` part `j`, evidence order) and each part's joint type.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Structure {
    pub parent: Vec<usize>,
    pub types: Vec<JointType>,
}

impl Structure {
    /// The structure (a tree) with every part that hangs from a *static* part — one joined to
    /// the fixed frame by rigid joints only — hung from the fixed frame instead. Structures with the same
    /// static-collapsed form have the same [`Density`], term by term: a rigid joint's
    /// displacement is the identity, so a static part's transform is the fixed frame's at every
    /// frame; a static part has no kinodynamics, so it loads nothing and carries no physics; the
    /// likelihood counted once per subtree of the fixed frame is the same sum of the parts'
    /// likelihoods; and no other term reads a part's parent (a revolute joint's reach prior
    /// reads its own part only). A cabinet body that does not move and a drawer in it give two
    /// such structures (the drawer on the body, or on the fixed frame), between which the SVI
    /// posterior splits by its tree prior and its guides.
    pub fn static_collapsed(&self) -> Structure {
        // A node is static when it is the fixed frame, or a rigid part with only rigid ancestors.
        let rigid = |k: usize| self.types[k] == JointType::Rigid;
        let is_static = |node: usize| node == 0 || (rigid(node - 1) && tree::ancestors(&self.parent, node - 1).into_iter().all(rigid));
        let parent = self.parent.iter().map(|&p| if is_static(p) { 0 } else { p }).collect();
        Structure { parent, types: self.types.clone() }
    }
}

/// Where one part's latents live in the flat vector of a [`Density`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartSlots {
    pub joint: JointType,
    /// Standardised kinematic parameters: offset and count ([`JointType::num_params`]).
    pub xi: usize,
    pub np: usize,
    /// Joint coordinates, one per grid frame \[m of path\] (movable joints).
    pub q: Option<usize>,
    /// Standardised velocity scale of the coordinates' random walk (kinematic mode, movable).
    pub vel: Option<usize>,
    /// Standardised kinodynamic parameters: offset and count (dynamic mode, movable).
    pub kd: Option<(usize, usize)>,
}

/// The unnormalised log posterior of the continuous latents of the evidence `ev` under one
/// [`Structure`] (module docs). Errors: none; a non-finite value (a simulation that blew up) is
/// returned as is for the caller to reject.
pub struct Density<'a> {
    ev: &'a Evidence,
    model: &'a ModelConfig,
    structure: Structure,
    slots: Vec<PartSlots>,
    dim: usize,
}

/// Offset of a movable joint's direction vector `v` in its standardised parameters (after the
/// common block of [`crate::model::rigid`]; [`crate::model::prismatic`], [`crate::model::revolute`]).
const DIRECTION: usize = crate::model::rigid::NUM_PARAMS;

/// Log-sd of the length of a movable joint's direction vector in [`Density`] (its median is 1).
const DIRECTION_LENGTH_LOG_SD: f64 = 0.25;

/// The prior of a joint's direction vector `v` in [`Density`], and its gradient: `v / |v|`
/// uniform on the sphere, as under the model's `N(0, I)` (any density of `v` that depends on
/// `|v|` alone gives that), with `log |v| ~ N(0, 0.25^2)`, i.e.
/// `log p(v) = -(log |v|)^2 / (2 * 0.25^2) - 3 log |v|` up to a constant (the length's density
/// over the sphere's area `4 pi |v|^2`).
///
/// Why: only the direction enters the model, so the length of `v` is a nuisance that any prior
/// leaves every other posterior unchanged with, and `N(0, I)` lets it come near 0, where a step
/// of `v` turns the direction by `|step| / |v|`: a funnel. On the real track `dishwasher_002`
/// one of NUTS's four chains wandered there (`|v|` 0.16 against about 1.6 in the other draws)
/// and made 86 of the run's 111 divergent draws. A length held near 1 keeps the direction's
/// curvature in `v` near 1 (the "donut" prior for unit vectors; Stan's reference manual,
/// "Unit vector"). The value 0.25 is not fitted to anything: `|v| < 0.37` is 4 sd away. SVI's
/// guide keeps `N(0, I)`: the posterior of `v / |v|` is the same.
pub fn direction_length_prior(v: [f64; 3]) -> (f64, [f64; 3]) {
    let r2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    // Zero or NaN: no direction.
    if r2.is_nan() || r2 <= 0.0 {
        return (f64::NEG_INFINITY, [0.0; 3]);
    }
    let lr = 0.5 * r2.ln();
    let s2 = DIRECTION_LENGTH_LOG_SD * DIRECTION_LENGTH_LOG_SD;
    let l = -lr * lr / (2.0 * s2) - 3.0 * lr;
    let dl_dlr = -lr / s2 - 3.0;
    (l, v.map(|vk| dl_dlr * vk / r2))
}

/// Step of the forward differences of the physics prior (standardised units).
const FD_STEP: f64 = 1e-6;

impl<'a> Density<'a> {
    /// The density for `structure` (one entry per part of `ev`). Dynamic mode when `ev` has
    /// windows.
    pub fn new(ev: &'a Evidence, model: &'a ModelConfig, structure: Structure) -> Density<'a> {
        let frames = ev.len();
        let dynamic = !ev.windows.is_empty();
        let mut off = 0;
        let mut take = |n: usize| {
            let o = off;
            off += n;
            o
        };
        let slots = structure
            .types
            .iter()
            .enumerate()
            .map(|(i, &joint)| {
                let np = joint.num_params();
                let xi = take(np);
                let q = joint.movable().then(|| take(frames));
                let vel = (joint.movable() && !dynamic).then(|| take(1));
                let kd = (joint.movable() && dynamic).then(|| {
                    let d = dynamics::num_params(&ev.effects[i]);
                    (take(d), d)
                });
                PartSlots { joint, xi, np, q, vel, kd }
            })
            .collect();
        Density { ev, model, structure, slots, dim: off }
    }

    /// Number of continuous latents.
    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn structure(&self) -> &Structure {
        &self.structure
    }

    /// Where each part's latents are in the flat vector (evidence order).
    pub fn slots(&self) -> &[PartSlots] {
        &self.slots
    }

    pub fn evidence(&self) -> &Evidence {
        self.ev
    }

    /// Decoded kinematic parameters of part `i` at `x`.
    pub fn params(&self, x: &[f64], i: usize) -> JointParams<f64> {
        let s = &self.slots[i];
        decode(s.joint, &x[s.xi..s.xi + s.np], &self.ev.parts[i].com0, self.model)
    }

    /// `log p(x, evidence | structure)` up to a constant, and its gradient (`grad`, length
    /// [`Self::dim`], overwritten).
    pub fn log_density(&self, x: &[f64], grad: &mut [f64]) -> f64 {
        self.log_density_with(x, grad, None)
    }

    /// [`Self::log_density`], taking each movable part's window trajectories `Psi` from
    /// `replays[i]` (in window order) where given instead of simulating them (dynamic mode;
    /// [`NonCentred`], whose map has simulated them at the same windows' first coordinates).
    fn log_density_with(&self, x: &[f64], grad: &mut [f64], replays: Option<&[Replay]>) -> f64 {
        grad.iter_mut().for_each(|g| *g = 0.0);
        let (ev, model) = (self.ev, self.model);
        let (n, frames) = (ev.parts.len(), ev.len());
        let parent = &self.structure.parent;
        let params: Vec<JointParams<f64>> = (0..n).map(|i| self.params(x, i)).collect();
        let zeros = vec![0.0; frames];
        let values = self.part_values(x, &params, &zeros);
        let transforms = part_transforms(parent, &values, frames);
        let positions: Vec<Vec<Vector3<f64>>> = (0..n).map(|m| (0..frames).map(|t| transforms[m][t].apply(&params[m].com)).collect()).collect();
        let mut lp = 0.0;
        for i in 0..n {
            let s = self.slots[i];
            // N(0, I) on the standardised parameters, but for a movable joint's direction vector
            // `v` (its direction is `v / |v|`), whose length gets a log-normal instead
            // ([`direction_length_prior`]).
            for j in s.xi..s.xi + s.np {
                if s.joint.movable() && (s.xi + DIRECTION..s.xi + DIRECTION + 3).contains(&j) {
                    continue;
                }
                lp -= 0.5 * x[j] * x[j];
                grad[j] -= x[j];
            }
            if s.joint.movable() {
                let o = s.xi + DIRECTION;
                let (l, g) = direction_length_prior([x[o], x[o + 1], x[o + 2]]);
                lp += l;
                for k in 0..3 {
                    grad[o + k] += g[k];
                }
            }
            // The likelihood of the part's subtree: its gradient with respect to this part's
            // parameters is exact (the descendants move with it); the value is counted once, at
            // the children of the fixed frame. A revolute joint's reach prior is in its own
            // block's value and gradient only, so a nested one adds its value here (without it
            // the gradient was not the value's: HMC's energy error grew with the prior and the
            // step size fell towards zero on a lid hinged on a drawer).
            let pre = pre_transforms(parent, i, &transforms, frames);
            let members = subtree_members(self.ev, parent, i, &transforms, &positions, &values);
            let (l, gx, gq) = block_pass(ev, i, s.joint, &x[s.xi..s.xi + s.np], values[i].q, &pre, &members, model);
            if parent[i] == 0 {
                lp += l;
            } else if s.joint == JointType::Revolute {
                lp += crate::model::revolute::reach_prior(&params[i], &ev.parts[i].com0, ev.parts[i].reach, model);
            }
            for (j, g) in gx.iter().enumerate() {
                grad[s.xi + j] += g;
            }
            if let Some(o) = s.q {
                for t in 0..frames {
                    grad[o + t] += gq[t];
                }
            }
            if let (Some(o), Some(v)) = (s.q, s.vel) {
                let q = &x[o..o + frames];
                let (l, gm, _, gv, _) = coordinate_prior(ev, q, &zeros, x[v], 0.0, model);
                lp += l - 0.5 * x[v] * x[v];
                grad[v] += gv - x[v];
                for t in 0..frames {
                    grad[o + t] += gm[t];
                }
            }
            if let (Some(o), Some((k, d))) = (s.q, s.kd) {
                for j in k..k + d {
                    lp -= 0.5 * x[j] * x[j];
                    grad[j] -= x[j];
                }
                for f in window_starts(ev) {
                    let (l, dm, _) = window_start_prior(x[o + f], 0.0, model);
                    lp += l;
                    grad[o + f] += dm;
                }
            }
        }
        if !ev.windows.is_empty() {
            let (l, g) = self.physics(x, &values, &transforms, replays);
            lp += l;
            for (a, b) in grad.iter_mut().zip(&g) {
                *a += b;
            }
        }
        lp
    }

    /// The physics prior of all movable parts at `values` and its gradient with respect to `x`:
    /// each part's own kinodynamics, coordinates and kinematic parameters from the physics code's
    /// dual numbers ([`physics_prior_kinematic`]); what one part's parameters do to another
    /// part's physics (a parent's axis moving its child's, a child's mass and centre of mass
    /// loading its parent's) by forward differences of the other part's value
    /// ([`cross_physics_differences`]).
    fn physics(&self, x: &[f64], values: &[PartValue<'_>], transforms: &[Vec<Displacement<f64>>], replays: Option<&[Replay]>) -> (f64, Vec<f64>) {
        let n = values.len();
        let frames = self.ev.len();
        let parent = &self.structure.parent;
        let mut grad = vec![0.0; self.dim];
        let per_part: Vec<f64> = (0..n)
            .map(|i| {
                let s = self.slots[i];
                let xk = &x[s.xi..s.xi + s.np];
                let (l, gx, gq) = self.part_physics_kinematic(i, xk, values, transforms, replays.map(|r| &r[i]));
                if let (Some((k, nk)), Some(o)) = (s.kd, s.q) {
                    for (j, g) in gx.iter().take(nk).enumerate() {
                        grad[k + j] += g;
                    }
                    for (&j, g) in kinematic_dims(s.joint).iter().zip(&gx[nk..]) {
                        grad[s.xi + j] += g;
                    }
                    for t in 0..frames {
                        grad[o + t] += gq[t];
                    }
                }
                l
            })
            .collect();
        let total: f64 = per_part.iter().sum();
        if !total.is_finite() {
            return (total, grad);
        }
        let differences = cross_physics_differences(parent, &self.slots);
        // The differences' base values, from the same `f64` path as the perturbed ones.
        let mut base: Vec<Option<f64>> = vec![None; n];
        let mut xp = x.to_vec();
        for (j, idx, parts) in differences {
            let s = self.slots[j];
            xp[idx] = x[idx] + FD_STEP;
            let params: Vec<JointParams<f64>> = (0..n).map(|m| if m == j { self.params(&xp, m) } else { *values[m].params }).collect();
            let pv: Vec<PartValue<'_>> = (0..n)
                .map(|m| {
                    let mut v = values[m];
                    v.params = &params[m];
                    if m == j {
                        v.kd = s.kd.map(|(k, d)| &xp[k..k + d]);
                    }
                    v
                })
                .collect();
            let tr = part_transforms(parent, &pv, frames);
            let mut d = 0.0;
            for &i in &parts {
                let b = *base[i].get_or_insert_with(|| self.part_physics_value(i, values, transforms));
                d += self.part_physics_value(i, &pv, &tr) - b;
            }
            grad[idx] += d / FD_STEP;
            xp[idx] = x[idx];
        }
        // Another part's coordinate at a window's first frame: that window's term only. Each
        // (part, window) base value once, however many coordinates move it.
        let mut window_base: Vec<Vec<Option<f64>>> = vec![vec![None; self.ev.windows.len()]; n];
        for (j, idx, w, parts) in coordinate_cross_differences(self.ev, parent, &self.slots) {
            xp[idx] = x[idx] + FD_STEP;
            let pv: Vec<PartValue<'_>> = (0..n)
                .map(|m| {
                    let mut v = values[m];
                    if m == j {
                        v.q = self.slots[m].q.map_or(v.q, |o| &xp[o..o + frames]);
                    }
                    v
                })
                .collect();
            let tr = part_transforms(parent, &pv, frames);
            let mut d = 0.0;
            for &i in &parts {
                let b = *window_base[i][w].get_or_insert_with(|| self.part_window_value(i, w, values, transforms));
                d += self.part_window_value(i, w, &pv, &tr) - b;
            }
            grad[idx] += d / FD_STEP;
            xp[idx] = x[idx];
        }
        (total, grad)
    }

    /// [`physics_prior_kinematic`] of part `i` (own standardised kinematic block `xk`), or zeros
    /// when rigid.
    fn part_physics_kinematic(
        &self,
        i: usize,
        xk: &[f64],
        values: &[PartValue<'_>],
        transforms: &[Vec<Displacement<f64>>],
        replay: Option<&Replay>,
    ) -> (f64, Vec<f64>, Vec<f64>) {
        if values[i].kd.is_none() {
            return (0.0, vec![], vec![]);
        }
        let parent = &self.structure.parent;
        let pre = pre_transforms(parent, i, transforms, self.ev.len());
        let desc = tree::descendants(parent, i);
        physics_prior_kinematic(self.ev, i, &values[i], xk, &pre, &desc, values, transforms, self.model, replay)
    }

    /// Every part's [`PartValue`] at the coordinates `x`: `params[i]` is [`Self::params`]`(x, i)`
    /// and `zeros` one 0 per grid frame (the coordinates of a part without any).
    fn part_values<'v>(&self, x: &'v [f64], params: &'v [JointParams<f64>], zeros: &'v [f64]) -> Vec<PartValue<'v>> {
        let frames = self.ev.len();
        self.slots
            .iter()
            .zip(params)
            .map(|(s, p)| PartValue { params: p, q: s.q.map_or(zeros, |o| &x[o..o + frames]), kd: s.kd.map(|(o, d)| &x[o..o + d]) })
            .collect()
    }

    /// Part `i`'s physics prior value \[nats\] at the coordinates `x`, in `f64` as the density's
    /// forward differences take it (robust windows; 0 for a part without kinodynamics).
    pub fn physics_value(&self, x: &[f64], i: usize) -> f64 {
        let params: Vec<JointParams<f64>> = (0..self.slots.len()).map(|m| self.params(x, m)).collect();
        let zeros = vec![0.0; self.ev.len()];
        let values = self.part_values(x, &params, &zeros);
        let transforms = part_transforms(&self.structure.parent, &values, self.ev.len());
        self.part_physics_value(i, &values, &transforms)
    }

    /// `part_physics(..).0`, simulated in `f64` ([`physics_prior_value`]).
    fn part_physics_value(&self, i: usize, values: &[PartValue<'_>], transforms: &[Vec<Displacement<f64>>]) -> f64 {
        if values[i].kd.is_none() {
            return 0.0;
        }
        let parent = &self.structure.parent;
        let pre = pre_transforms(parent, i, transforms, self.ev.len());
        let desc = tree::descendants(parent, i);
        physics_prior_value(self.ev, i, &values[i], &pre, &desc, values, transforms, self.model, true)
    }

    /// Window `w`'s term of [`Self::part_physics_value`] (what [`coordinate_cross_differences`]
    /// perturbs; 0 for a part without kinodynamics).
    fn part_window_value(&self, i: usize, w: usize, values: &[PartValue<'_>], transforms: &[Vec<Displacement<f64>>]) -> f64 {
        let Some(xi) = values[i].kd else { return 0.0 };
        let parent = &self.structure.parent;
        let pre = pre_transforms(parent, i, transforms, self.ev.len());
        let desc = tree::descendants(parent, i);
        let win = &self.ev.windows[w];
        let wj = window_joint(self.ev, i, &values[i], win, &pre, &desc, values, transforms, self.model);
        window_value(&wj.view(self.ev.effects[i]), win, values[i].q, None, xi, self.model, true)
    }
}

/// The kinematic parameters of a part that the physics sees (its forward differences): all but
/// the position and rotation noise levels (`xi[3]`, `xi[4]` of every joint type,
/// [`crate::model::rigid`]), which enter only the likelihood.
fn physics_dims(s: &PartSlots) -> Vec<usize> {
    (s.xi..s.xi + s.np).filter(|&k| k != s.xi + 3 && k != s.xi + 4).collect()
}

/// The forward differences of [`Density::log_density`]'s physics: what a part `j`'s parameters
/// do to *other* parts' physics (a part's own is exact, [`physics_prior_kinematic`]), as
/// `(j, idx, parts)`, each perturbed latent `idx` with the movable parts whose physics it enters:
/// - `j`'s kinematic parameters ([`physics_dims`]): a revolute ancestor's (the centre of mass and
///   the inertia of `j` ride in its subtree at their places; a prismatic joint's inertia is the
///   mass it carries, wherever it is); when `j` is movable, a descendant's that is revolute (its
///   axis moves with `j`) or prismatic under a revolute `j` (its direction turns with `j`) —
///   except a prismatic `j`'s centre of mass, which does not enter its displacement;
/// - `j`'s mass: every movable ancestor's.
pub fn cross_physics_differences(parent: &[usize], slots: &[PartSlots]) -> Vec<(usize, usize, Vec<usize>)> {
    let movable = |i: usize| slots[i].kd.is_some();
    let mut out = Vec::new();
    for (j, s) in slots.iter().enumerate() {
        let desc = tree::descendants(parent, j);
        let ancestors: Vec<usize> = (0..slots.len()).filter(|&i| movable(i) && tree::descendants(parent, i).contains(&j)).collect();
        let revolute_ancestors: Vec<usize> = ancestors.iter().copied().filter(|&i| slots[i].joint == JointType::Revolute).collect();
        let mut kinematic = revolute_ancestors.clone();
        if s.joint.movable() {
            kinematic.extend(desc.iter().copied().filter(|&i| {
                movable(i) && (slots[i].joint == JointType::Revolute || (slots[i].joint == JointType::Prismatic && s.joint == JointType::Revolute))
            }));
        }
        for idx in physics_dims(s) {
            // A prismatic joint's displacement is `d q` whatever its centre of mass
            // ([`crate::model::prismatic`]), so the centre of mass (`xi[0..3]`) moves no
            // descendant: only a revolute ancestor's inertia sees it. Its differences for the
            // descendants would be exactly 0 (a third of the work on a nested chain such as
            // `slide_microwave`'s door on its slider).
            let parts = if s.joint == JointType::Prismatic && idx < s.xi + 3 { &revolute_ancestors } else { &kinematic };
            if !parts.is_empty() {
                out.push((j, idx, parts.clone()));
            }
        }
        if let (Some((k, _)), false) = (s.kd, ancestors.is_empty()) {
            // The mass (the third kinodynamic parameter, [`dynamics::decode`]).
            out.push((j, k + 2, ancestors));
        }
    }
    out
}

/// The forward differences of the physics through another part's *coordinates*, as `(j, idx, w,
/// parts)`: part `j`'s coordinate at window `w`'s first grid frame (`idx` into the latents) and
/// the movable parts whose window-`w` physics it enters. [`window_joint`] places a part's joint
/// and its locked subtree at the window's first frame: its axis by the parent's displacement
/// there, so every movable ancestor's coordinate at that frame moves it (a door on a slider: the
/// measured push's lever about the hinge), and its subtree's centres of mass and inertias by
/// their displacements there, so a revolute part's physics also sees the coordinates of the
/// movable parts below it (a prismatic part's sees only their masses, [`dynamics::decode`]).
/// Only window `w`'s term of a part's physics depends on that coordinate. Until stop 115 these
/// were left out of the gradient (`slide_microwave`: the slider's coordinate at a door window's
/// first frame had gradient 1.08e4 against central differences' 5.99e3 nats/m), and HMC's energy
/// error, which a wrong force does not shrink with the step, drove the step size to 1e-3-1e-4 with
/// every draw at the depth limit.
pub fn coordinate_cross_differences(ev: &Evidence, parent: &[usize], slots: &[PartSlots]) -> Vec<(usize, usize, usize, Vec<usize>)> {
    let movable = |i: usize| slots[i].kd.is_some();
    let mut out = Vec::new();
    for (j, s) in slots.iter().enumerate() {
        let Some(o) = s.q.filter(|_| movable(j)) else { continue };
        let parts: Vec<usize> = (0..slots.len())
            .filter(|&i| i != j && movable(i))
            .filter(|&i| tree::descendants(parent, j).contains(&i) || (slots[i].joint == JointType::Revolute && tree::descendants(parent, i).contains(&j)))
            .collect();
        if parts.is_empty() {
            continue;
        }
        for (w, win) in ev.windows.iter().enumerate() {
            out.push((j, o + win.frames[0], w, parts.clone()));
        }
    }
    out
}

/// One window's physics prior value for [`physics_prior_terms`]' values and
/// [`Density::part_window_value`]: window-robust ([`dynamics::robust_window_prior_value`]) or plain.
fn window_value(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], observed: Option<&dynamics::Observed>, xi: &[f64], model: &ModelConfig, robust: bool) -> f64 {
    if robust {
        dynamics::robust_window_prior_value(jw, win, q, observed, xi, &model.dynamics, model.velocity_sd_mps)
    } else {
        dynamics::window_prior_value(jw, win, q, observed, xi, &model.dynamics)
    }
}

/// The displacement of part `i`'s parent at every grid frame (identity under the fixed frame).
pub fn pre_transforms(parent: &[usize], i: usize, transforms: &[Vec<Displacement<f64>>], frames: usize) -> Vec<Displacement<f64>> {
    if parent[i] == 0 {
        vec![Displacement::identity(); frames]
    } else {
        transforms[parent[i] - 1].clone()
    }
}

/// The grid frames whose coordinate has the window-start prior in dynamic mode: the first, and
/// the first of every window that does not continue the previous one (later ones follow by
/// continuity, the rest by the physics prior).
pub fn window_starts(ev: &Evidence) -> Vec<usize> {
    let mut out = vec![0];
    for w in ev.windows.iter().filter(|w| !w.continues) {
        if !out.contains(&w.frames[0]) {
            out.push(w.frames[0]);
        }
    }
    out
}

/// Non-centred coordinates of dynamic mode: the same density as [`Density`] in coordinates `y`
/// where every movable part's coordinate at a window frame after the window's first is
/// `q_t = Psi_t + sigma_d u_t`, `Psi` the simulated trajectory of that window
/// ([`dynamics::window_psi`]) and `sigma_d` the part's deviation scale; the sampler moves
/// `u_t` in place of `q_t`, and at a rest frame `b` tied to the window's first or last frame `a`,
/// `q_b = q_a + sigma_d u_b` (since stop 111; [`NonCentred::partial`]). All other latents are
/// unchanged, among them every window's first coordinate, from which `Psi` starts.
///
/// Why: in centred coordinates the coordinates are tied to the simulation as tightly as the
/// deviation scale (on the drawer bag its posterior is 0.3 mm, the observation noise's size), so
/// a step in damping or friction that moves `Psi` must move every coordinate of the window with
/// it — a narrow ridge through hundreds of dimensions — and a smaller `sigma_d` narrows all of
/// them at once (Neal's funnel). With `u_t`, moving the kinodynamics moves the coordinates, and
/// the prior of `u_t` is the deviation's standardised Student-t whatever `sigma_d` is. This is the
/// non-centred parameterisation of hierarchical models (Papaspiliopoulos, Roberts & Sköld,
/// *Statistical Science* 22(1), 2007; Betancourt & Girolami 2015).
///
/// The map `y -> x` is triangular with `sigma_d` on the diagonal of each `u_t` and 1 elsewhere,
/// so `log p_y(y) = log p(x(y)) + n log sigma_d` (`n` non-centred coordinates of the part;
/// partially non-centred, [`NonCentred::partial`], `sigma_d^(1 - lambda_t)` on the diagonal).
/// Gradient: the chain rule through `Psi` with the derivatives of the physics prior's own dual
/// simulation (a part's kinodynamics, `q_{w,0}` and its own kinematic parameters,
/// [`kinematic_dims`]) and forward differences for what another part's parameters do to it
/// (`cross_physics_differences`). One dual simulation a window: the map runs it at `y` for `Psi`
/// and hands it to the density, whose physics prior would otherwise run it again at `x` — the
/// same trajectories, since they start from the windows' first coordinates, which `x` and `y`
/// share (until stop 108 the map simulated in `f64` and the density again in dual numbers: a
/// gradient cost 1.2-1.5 times the centred one's on the shipped 2-part bags).
pub struct NonCentred<'a> {
    density: Density<'a>,
    /// Per part: `(window, frame index in the window, grid frame, lambda)` of each (partially)
    /// non-centred coordinate; `lambda` in `[0, 1)` is its centring ([`NonCentred::partial`]).
    frames: Vec<Vec<(usize, usize, usize, f64)>>,
    /// Per part: `(anchor grid frame a, rest grid frame b, lambda)` of each (partially)
    /// non-centred rest coordinate, `q_b = q_a + sigma_d^(1 - lambda) (y_b - lambda q_a)`
    /// ([`NonCentred::partial`]).
    rests: Vec<Vec<(usize, usize, f64)>>,
}

/// A window coordinate `q_t = Psi_t + sigma_d^(1 - lambda) (y_t - lambda Psi_t)` from the
/// sampler's `y_t` ([`NonCentred::partial`]; `lambda = 0` is the non-centred `Psi_t + sigma_d u_t`).
fn model_coordinate(psi: f64, dev: f64, lambda: f64, y: f64) -> f64 {
    psi + dev.powf(1.0 - lambda) * (y - lambda * psi)
}

/// The inverse of [`model_coordinate`]: the sampler's `y_t` of a model coordinate `q_t`.
fn sampler_coordinate(psi: f64, dev: f64, lambda: f64, q: f64) -> f64 {
    lambda * psi + (q - psi) / dev.powf(1.0 - lambda)
}

/// A part's simulated trajectories per window and its deviation scale at some coordinates.
struct Simulated {
    trajectories: Trajectories,
    deviation: f64,
}

/// `Psi` per window, at the window's frames.
enum Trajectories {
    /// With their derivatives (the map and the density).
    Dual(Vec<FramePsi>),
    /// Values alone (forward differences).
    Value(Vec<Vec<f64>>),
}

impl Simulated {
    /// `Psi` of window `w` at its frame `k`.
    fn psi(&self, w: usize, k: usize) -> f64 {
        match &self.trajectories {
            Trajectories::Dual(d) => d[w].re[k],
            Trajectories::Value(v) => v[w][k],
        }
    }

    /// The windows' dual simulations (none when simulated in `f64`).
    fn duals(&self) -> &[FramePsi] {
        match &self.trajectories {
            Trajectories::Dual(d) => d,
            Trajectories::Value(_) => &[],
        }
    }
}

impl<'a> NonCentred<'a> {
    /// Non-centred coordinates for `density` when `enabled` (else, and in kinematic mode, the
    /// identity: `y = x`). A grid frame is non-centred for one window at most, and never when it
    /// starts a window.
    pub fn new(density: Density<'a>, enabled: bool) -> Self {
        Self::partial(density, |_, _| (!enabled).then_some(1.0))
    }

    /// Partially non-centred coordinates (Papaspiliopoulos, Roberts & Sköld 2007, §3;
    /// Gorinova, Moore & Hoffman, *Automatic reparameterisation of probabilistic programs*, ICML
    /// 2020, eq. 3): the sampler moves `y_t = lambda Psi_t + (q_t - Psi_t) / sigma_d^(1 - lambda)`,
    /// so `q_t = Psi_t + sigma_d^(1 - lambda) (y_t - lambda Psi_t)`. `lambda = 1` is the centred
    /// coordinate, `0` the non-centred `u_t`. `centring(part, grid frame)` gives `lambda` (clamped
    /// to `[0, 1]`; `None` is 0). For a Gaussian coordinate whose observations have variance
    /// `tau^2`, the posterior is uncorrelated with `sigma_d` at `lambda = sigma_d^2 / (sigma_d^2 +
    /// tau^2)`, which is `1 - s^2 / sigma_d^2` with `s` the coordinate's conditional posterior sd —
    /// what a mean-field guide fits (`inference::nuts` takes it from SVI's).
    ///
    /// The rest frames of the physics prior (after a window, tied to its last coordinate; before
    /// it, to its first: [`WindowEvidence::rest`], [`WindowEvidence::rest_before`]) are
    /// non-centred the same way about their anchor `q_a` in place of `Psi_t`:
    /// `q_b = q_a + sigma_d^(1 - lambda) (y_b - lambda q_a)`. Why: their rest term ties `q_b` to
    /// `q_a` by the deviation scale, the same funnel as a window's coordinates; left centred, it
    /// was what bounded the deviation scale's mixing (`microwave`, stop 111: the deviation's bulk
    /// ESS the least of all, 0.05-0.07 per draw). A frame that starts or lies in a window, and a
    /// rest frame already taken, keeps its own coordinate (the map must stay triangular).
    pub fn partial(density: Density<'a>, centring: impl Fn(usize, usize) -> Option<f64>) -> Self {
        let ev = density.evidence();
        let starts: Vec<usize> = ev.windows.iter().map(|w| w.frames[0]).collect();
        let in_windows: Vec<usize> = ev.windows.iter().flat_map(|w| w.frames.iter().copied()).collect();
        let lambda_at = |i: usize, t: usize| {
            let lambda = centring(i, t).unwrap_or(0.0);
            if lambda.is_finite() { lambda.clamp(0.0, 1.0) } else { 0.0 }
        };
        let mut frames = Vec::with_capacity(density.slots().len());
        let mut rests = Vec::with_capacity(density.slots().len());
        for (i, s) in density.slots().iter().enumerate() {
            let mut out: Vec<(usize, usize, usize, f64)> = Vec::new();
            let mut rest: Vec<(usize, usize, f64)> = Vec::new();
            if s.kd.is_some() && s.q.is_some() {
                for (w, win) in ev.windows.iter().enumerate() {
                    for (k, &t) in win.frames.iter().enumerate().skip(1) {
                        let lambda = lambda_at(i, t);
                        // A fully centred coordinate is the model's own: left out of the map.
                        if lambda < 1.0 && !starts.contains(&t) && !out.iter().any(|&(_, _, u, _)| u == t) {
                            out.push((w, k, t, lambda));
                        }
                    }
                }
                for win in &ev.windows {
                    let (first, last) = (win.frames[0], win.frames[win.frames.len() - 1]);
                    let pairs = win.rest_before.iter().map(|&b| (first, b)).chain(win.rest.iter().map(|&b| (last, b)));
                    for (a, b) in pairs {
                        let lambda = lambda_at(i, b);
                        if lambda < 1.0 && a != b && !in_windows.contains(&b) && !rest.iter().any(|&(_, u, _)| u == b) {
                            rest.push((a, b, lambda));
                        }
                    }
                }
            }
            frames.push(out);
            rests.push(rest);
        }
        NonCentred { density, frames, rests }
    }

    /// How many of the (partially) non-centred coordinates, window and rest frames, have a
    /// centring `lambda` below 0.5, and how many there are (for the sampler's debug line).
    pub fn centring_summary(&self) -> (usize, usize) {
        let all = self.frames.iter().flatten().map(|f| f.3).chain(self.rests.iter().flatten().map(|r| r.2));
        (all.clone().filter(|&l| l < 0.5).count(), all.count())
    }

    /// Every (partially) non-centred coordinate, window and rest frames: `(part, index into the
    /// coordinates, lambda)`.
    pub fn mapped(&self) -> Vec<(usize, usize, f64)> {
        let slots = &self.density.slots;
        let mut out = Vec::new();
        for (i, s) in slots.iter().enumerate() {
            let Some(o) = s.q else { continue };
            out.extend(self.frames[i].iter().map(|&(_, _, t, lambda)| (i, o + t, lambda)));
            out.extend(self.rests[i].iter().map(|&(_, b, lambda)| (i, o + b, lambda)));
        }
        out
    }

    /// Whether part `i` has (partially) non-centred coordinates.
    fn has_map(&self, i: usize) -> bool {
        !self.frames[i].is_empty() || !self.rests[i].is_empty()
    }

    pub fn density(&self) -> &Density<'a> {
        &self.density
    }

    /// Whether any coordinate is non-centred.
    fn any(&self) -> bool {
        (0..self.frames.len()).any(|i| self.has_map(i))
    }

    /// `Psi` of `parts` at `y` (non-centred entries are read as coordinates; only the windows'
    /// first frames, which are centred, enter the simulation), in the physics prior's dual numbers
    /// when `dual` ([`window_psi_kinematic`]: the density takes these, so it need not simulate
    /// again), else in `f64` ([`dynamics::window_psi`], for forward differences) — of window
    /// `only` alone where given (the others' trajectories then empty).
    fn simulate(&self, y: &[f64], params: &[JointParams<f64>], parts: &[usize], dual: bool, only: Option<usize>) -> Vec<Option<Simulated>> {
        let d = &self.density;
        let (ev, model) = (d.ev, d.model);
        let frames = ev.len();
        let n = ev.parts.len();
        let zeros = vec![0.0; frames];
        let values = d.part_values(y, params, &zeros);
        let parent = &d.structure.parent;
        let transforms = part_transforms(parent, &values, frames);
        (0..n)
            .map(|i| {
                if !parts.contains(&i) || !self.has_map(i) {
                    return None;
                }
                let xi = values[i].kd?;
                let pre = pre_transforms(parent, i, &transforms, frames);
                let desc = tree::descendants(parent, i);
                let s = &d.slots[i];
                let xk = &y[s.xi..s.xi + s.np];
                let joints: Vec<WindowJoint> = ev.windows.iter().map(|win| window_joint(ev, i, &values[i], win, &pre, &desc, &values, &transforms, model)).collect();
                let windows = ev.windows.iter().zip(&joints);
                let trajectories = if dual {
                    Trajectories::Dual(windows.map(|(win, wj)| window_psi_kinematic((ev, i, &values[i], xk, win, &pre, &desc, &values, &transforms, model, &wj.view(ev.effects[i]), None, None, None))).collect())
                } else {
                    Trajectories::Value(
                        windows
                            .enumerate()
                            .map(|(w, (win, wj))| if only.is_none_or(|o| o == w) { dynamics::window_psi(&wj.view(ev.effects[i]), win, values[i].q[win.frames[0]], xi, &model.dynamics) } else { Vec::new() })
                            .collect(),
                    )
                };
                let deviation = dynamics::decode::<f64>(s.joint, xi, &ev.effects[i], &model.dynamics).deviation;
                Some(Simulated { trajectories, deviation })
            })
            .collect()
    }

    fn all_params(&self, y: &[f64]) -> Vec<JointParams<f64>> {
        (0..self.density.ev.parts.len()).map(|i| self.density.params(y, i)).collect()
    }

    /// Model coordinates `x` (as [`Density::log_density`] takes them) of non-centred `y`.
    pub fn to_model(&self, y: &[f64]) -> Vec<f64> {
        if !self.any() {
            return y.to_vec();
        }
        let all: Vec<usize> = (0..self.frames.len()).collect();
        let sim = self.simulate(y, &self.all_params(y), &all, true, None);
        let mut x = self.apply(y, &sim, model_coordinate);
        self.rests_to_model(y, &sim, &mut x);
        x
    }

    /// Non-centred coordinates of model coordinates `x`.
    pub fn from_model(&self, x: &[f64]) -> Vec<f64> {
        if !self.any() {
            return x.to_vec();
        }
        let all: Vec<usize> = (0..self.frames.len()).collect();
        let sim = self.simulate(x, &self.all_params(x), &all, true, None);
        let mut y = self.apply(x, &sim, sampler_coordinate);
        for (i, s) in sim.iter().enumerate() {
            let (Some(s), Some(o)) = (s, self.density.slots[i].q) else { continue };
            for &(a, b, lambda) in &self.rests[i] {
                y[o + b] = sampler_coordinate(x[o + a], s.deviation, lambda, x[o + b]);
            }
        }
        y
    }

    /// The rest coordinates of `x` (window coordinates already mapped) from `y`: `q_b = q_a +
    /// sigma_d^(1 - lambda) (y_b - lambda q_a)`, the anchor `q_a` in model coordinates.
    fn rests_to_model(&self, y: &[f64], sim: &[Option<Simulated>], x: &mut [f64]) {
        for (i, s) in sim.iter().enumerate() {
            let (Some(s), Some(o)) = (s, self.density.slots[i].q) else { continue };
            for &(a, b, lambda) in &self.rests[i] {
                x[o + b] = model_coordinate(x[o + a], s.deviation, lambda, y[o + b]);
            }
        }
    }

    /// `v` with every (partially) non-centred coordinate replaced by `f(Psi_t, sigma_d, lambda, v_t)`.
    fn apply(&self, v: &[f64], sim: &[Option<Simulated>], f: impl Fn(f64, f64, f64, f64) -> f64) -> Vec<f64> {
        let mut out = v.to_vec();
        for (i, s) in sim.iter().enumerate() {
            let (Some(s), Some(o)) = (s, self.density.slots[i].q) else { continue };
            for &(w, k, t, lambda) in &self.frames[i] {
                out[o + t] = f(s.psi(w, k), s.deviation, lambda, v[o + t]);
            }
        }
        out
    }

    /// `log p_y(y)` up to the constant of [`Density::log_density`], and its gradient (`grad`,
    /// overwritten).
    pub fn log_density(&self, y: &[f64], grad: &mut [f64]) -> f64 {
        let d = &self.density;
        if !self.any() {
            return d.log_density(y, grad);
        }
        let n = self.frames.len();
        let all: Vec<usize> = (0..n).collect();
        let params = self.all_params(y);
        let sim = self.simulate(y, &params, &all, true, None);
        let mut x = self.apply(y, &sim, model_coordinate);
        self.rests_to_model(y, &sim, &mut x);
        let mut g = vec![0.0; d.dim];
        // The density's physics prior takes the map's simulation (the same trajectories: they
        // start from the windows' first coordinates, which `x` and `y` share) instead of running
        // it again.
        let replays: Vec<Replay> = sim.iter().map(|s| RefCell::new(s.as_ref().map_or_else(VecDeque::new, |s| s.duals().iter().cloned().collect()))).collect();
        let mut lp = d.log_density_with(&x, &mut g, Some(&replays));
        grad.copy_from_slice(&g);
        if !lp.is_finite() {
            return lp;
        }
        if replays.iter().any(|r| !r.borrow().is_empty()) {
            // The physics prior takes every window of a part with non-centred frames; anything
            // else is a bug, reported as a non-finite density, not a wrong value.
            return f64::NAN;
        }
        let log_sd = d.model.dynamics.deviation_log_sd;
        for (i, s) in sim.iter().enumerate() {
            let (Some(s), Some(o), Some((k, nk))) = (s, d.slots[i].q, d.slots[i].kd) else { continue };
            let (xi, dims) = (d.slots[i].xi, kinematic_dims(d.slots[i].joint));
            // q_t = Psi_t + a (y_t - lambda Psi_t), a = sigma_d^(1 - lambda): dq/dy = a,
            // dq/dPsi = 1 - lambda a, dq/d xi_d = (1 - lambda) log_sd a (y_t - lambda Psi_t).
            let mut jacobian = 0.0;
            // Rest frames first: their anchor's model gradient gains `dq_b/dq_a = 1 - lambda a`,
            // which the anchor's own map (a window frame) or `grad` (a centred anchor) carries on.
            for &(a_t, b, lambda) in &self.rests[i] {
                let (gb, qa) = (g[o + b], x[o + a_t]);
                let a = s.deviation.powf(1.0 - lambda);
                let ga = gb * (1.0 - lambda * a);
                g[o + a_t] += ga;
                grad[o + a_t] += ga;
                grad[o + b] = gb * a;
                grad[k + 3] += gb * (y[o + b] - lambda * qa) * (1.0 - lambda) * log_sd * a;
                jacobian += 1.0 - lambda;
            }
            for &(w, kk, t, lambda) in &self.frames[i] {
                let (gt, u) = (g[o + t], y[o + t]);
                // Directions of `tr`: kinodynamics, then the window's first coordinate, then `dims`.
                let tr = &s.duals()[w];
                let a = s.deviation.powf(1.0 - lambda);
                let gp = gt * (1.0 - lambda * a);
                grad[o + t] = gt * a;
                for j in 0..nk {
                    grad[k + j] += gp * tr.d(kk, j);
                }
                for (m, &j) in dims.iter().enumerate() {
                    grad[xi + j] += gp * tr.d(kk, nk + 1 + m);
                }
                grad[k + 3] += gt * (u - lambda * s.psi(w, kk)) * (1.0 - lambda) * log_sd * a;
                grad[o + d.ev.windows[w].frames[0]] += gp * tr.d(kk, nk);
                jacobian += 1.0 - lambda;
            }
            // The Jacobian's log determinant, sum of (1 - lambda) log sigma_d.
            lp += jacobian * s.deviation.ln();
            grad[k + 3] += jacobian * log_sd;
        }
        // Psi through another part's parameters (a parent's axis, a descendant's mass and centre
        // of mass): forward differences, simulated in `f64` ([`cross_physics_differences`]).
        let parent = &d.structure.parent;
        let with_frames: Vec<usize> = (0..n).filter(|&i| !self.frames[i].is_empty()).collect();
        let cross: Vec<(usize, usize, Vec<usize>)> = cross_physics_differences(parent, &d.slots)
            .into_iter()
            .filter_map(|(j, idx, parts)| {
                let parts: Vec<usize> = parts.into_iter().filter(|i| with_frames.contains(i)).collect();
                (!parts.is_empty()).then_some((j, idx, parts))
            })
            .collect();
        let coordinates: Vec<(usize, usize, Vec<usize>)> = coordinate_cross_differences(d.ev, parent, &d.slots)
            .into_iter()
            .filter_map(|(_, idx, w, parts)| {
                let parts: Vec<usize> = parts.into_iter().filter(|i| with_frames.contains(i)).collect();
                (!parts.is_empty()).then_some((idx, w, parts))
            })
            .collect();
        if cross.is_empty() && coordinates.is_empty() {
            return lp;
        }
        // The differences' base, from the same `f64` path as the perturbed ones, once for both.
        let base = self.simulate(y, &params, &with_frames, false, None);
        let mut yp = y.to_vec();
        // Another part's coordinate at a window's first frame moves that window's `Psi`
        // ([`coordinate_cross_differences`]; the coordinate is the model's there: a window's first
        // frame is never mapped).
        for (idx, w, parts) in coordinates {
            yp[idx] = y[idx] + FD_STEP;
            let moved = self.simulate(&yp, &params, &parts, false, Some(w));
            let mut acc = 0.0;
            for &i in &parts {
                let (Some(a), Some(b), Some(o)) = (&base[i], &moved[i], d.slots[i].q) else { continue };
                for &(_, kk, t, lambda) in self.frames[i].iter().filter(|f| f.0 == w) {
                    let c = 1.0 - lambda * a.deviation.powf(1.0 - lambda);
                    acc += g[o + t] * c * (b.psi(w, kk) - a.psi(w, kk));
                }
            }
            grad[idx] += acc / FD_STEP;
            yp[idx] = y[idx];
        }
        for (j, idx, parts) in cross {
            yp[idx] = y[idx] + FD_STEP;
            let mut pp = params.clone();
            pp[j] = d.params(&yp, j);
            let moved = self.simulate(&yp, &pp, &parts, false, None);
            let mut acc = 0.0;
            for &i in &parts {
                let (Some(a), Some(b), Some(o)) = (&base[i], &moved[i], d.slots[i].q) else { continue };
                for &(w, kk, t, lambda) in &self.frames[i] {
                    let c = 1.0 - lambda * a.deviation.powf(1.0 - lambda);
                    acc += g[o + t] * c * (b.psi(w, kk) - a.psi(w, kk));
                }
            }
            grad[idx] += acc / FD_STEP;
            yp[idx] = y[idx];
        }
        lp
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With `rest_nu`, a rest frame is Student-t like every other deviation of the physics: a door
    /// that the model says rests but that falls 9 mm (an effect the base model lacks) costs a few
    /// tens of nats at a collapsed 10 um deviation scale, where the Gaussian (`rest_nu` 0, the
    /// default) costs ~4e5; a still joint is still the more probable.
    #[test]
    fn a_joint_moving_where_it_should_rest_costs_logarithmically() {
        let sd = 1e-5;
        let mut scratch = (vec![0.0; 2], 0.0);
        let mut value = |d: f64, nu: f64| {
            let cfg = dynamics::DynamicsConfig { rest_nu: nu, ..Default::default() };
            rest_term(&[0.0, d], 0, 1, sd, &cfg, &mut scratch.0, &mut scratch.1)
        };
        let (moved, still) = (value(0.009, 4.0), value(0.0, 4.0));
        assert!(moved > -50.0, "Student-t: {moved:.1} nats for 9 mm");
        assert!(still > moved, "a still joint is more probable: {still:.1} vs {moved:.1}");
        let gaussian = value(0.009, 0.0);
        assert!(gaussian < -1e5, "the Gaussian's cost, for contrast: {gaussian:.1}");
    }

    /// Static parts are the fixed frame and rigid chains to it: what hangs from them hangs from the
    /// fixed frame; what hangs from a movable part, or from a rigid part on one, stays.
    #[test]
    fn parts_on_static_parts_hang_from_the_fixed_frame() {
        use JointType::{Prismatic, Revolute, Rigid};
        // 1 body rigid on the frame, 2 shelf rigid on the body, 3 drawer on the shelf, 4 lid on
        // the drawer, 5 handle rigid on the drawer, 6 knob rigid on the handle.
        let s = Structure { parent: vec![0, 1, 2, 3, 3, 5], types: vec![Rigid, Rigid, Prismatic, Revolute, Rigid, Rigid] };
        let c = s.static_collapsed();
        assert_eq!(c.parent, vec![0, 0, 0, 3, 3, 5]);
        assert_eq!(c.types, s.types);
        assert_eq!(c.static_collapsed(), c);
    }

    /// The rest term's gradients (both coordinates, and the deviation's standardised parameter
    /// `xi` with `sd = sd0 exp(log_sd xi)`) against central differences, Student-t and Gaussian.
    #[test]
    fn rest_term_gradients_match_finite_differences() {
        let sd0 = 0.004;
        for nu in [4.0, 0.0] {
            let cfg = dynamics::DynamicsConfig { rest_nu: nu, deviation_log_sd: 0.8, ..Default::default() };
            let log_sd = cfg.deviation_log_sd;
            for (qa, qb, xi) in [(0.01, 0.013, 0.2), (-0.2, -0.15, -1.1), (0.3, 0.3 + 1e-4, 0.7)] {
                let f = |qa: f64, qb: f64, xi: f64| {
                    let mut g = (vec![0.0; 2], 0.0);
                    rest_term(&[qa, qb], 0, 1, sd0 * (log_sd * xi).exp(), &cfg, &mut g.0, &mut g.1)
                };
                let mut g = (vec![0.0; 2], 0.0);
                rest_term(&[qa, qb], 0, 1, sd0 * (log_sd * xi).exp(), &cfg, &mut g.0, &mut g.1);
                let h = 1e-7;
                let num = [
                    (f(qa + h, qb, xi) - f(qa - h, qb, xi)) / (2.0 * h),
                    (f(qa, qb + h, xi) - f(qa, qb - h, xi)) / (2.0 * h),
                    (f(qa, qb, xi + h) - f(qa, qb, xi - h)) / (2.0 * h),
                ];
                for (k, (a, n)) in [g.0[0], g.0[1], g.1].iter().zip(num).enumerate() {
                    assert!((a - n).abs() <= 1e-5 * (1.0 + n.abs()), "nu {nu}, ({qa}, {qb}, {xi}), slot {k}: {a} vs {n}");
                }
            }
        }
    }
}
