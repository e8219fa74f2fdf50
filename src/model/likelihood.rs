//! The observation model and the prior on joint coordinates.
//!
//! - [`Evidence`]: the observed part poses on a common time grid (cloud frames inside the
//!   interaction windows, thinned), as the position of each part's centre of mass and its rotation,
//!   with their covariances (positions: the registration's alone, perception's floors left out,
//!   `sigma` stands for them; rotations: perception's, floors included).
//! - [`log_likelihood_position`]: the Gaussian likelihood of eq. 2 for one part's centre of mass
//!   and frame, covariance `Sigma_registration + sigma^2 I` with `sigma` inferred;
//!   [`log_likelihood_rotation`] adds the rotation about each axis the part's shape makes
//!   observable, with variance `sd_perception^2 + sigma_r^2`, `sigma_r` inferred too.
//! - [`coordinate_prior`]: the expected log random-walk prior of a joint-coordinate chain under a
//!   mean-field Gaussian guide, analytic with its gradient.

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Matrix3, Vector3};
use statrs::statistics::{Data, Median};

use super::effects::EffectSet;
use super::{c, Displacement, ModelConfig, Real};
use crate::input::WrenchSample;
use crate::perception::{geometry, PartGeometry, PartObservation, PartTracks};
use crate::windows::Window;

/// A position observation: the centre of mass \[m\] (fixed frame) and its registration's
/// covariance as eigenvectors (columns of `basis`) and variances \[m²\].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionObs {
    pub y: Vector3<f64>,
    pub basis: Matrix3<f64>,
    pub var: Vector3<f64>,
}

/// A rotation observation: the part's rotation since the reference frame (fixed frame) and, per
/// observable axis (unit, fixed frame, at this frame), the perception variance \[rad²\].
#[derive(Debug, Clone, PartialEq)]
pub struct RotationObs {
    pub r: Matrix3<f64>,
    pub axes: Vec<(Vector3<f64>, f64)>,
}

impl RotationObs {
    /// The error of a predicted rotation `r` (fixed frame) against the observed one, to first
    /// order: the vector \[rad\] of the skew part of `e = r R_obs^T`, the quantity
    /// [`log_likelihood_rotation`] projects on each observable axis.
    pub fn error(&self, r: &Matrix3<f64>) -> Vector3<f64> {
        let e = r * self.r.transpose();
        Vector3::new(e[(2, 1)] - e[(1, 2)], e[(0, 2)] - e[(2, 0)], e[(1, 0)] - e[(0, 1)]) * 0.5
    }
}

/// An observation of the pushed part's material point at the contact (dynamic mode,
/// [`Grid::contact_sd_m`]): while the robot pushes, the contact frame's origin (the contract's
/// point of application, its pose from `/tf`, i.e. the robot's own kinematics) moves with the
/// part it pushes. `x` is that material point in the part's reference configuration \[m\], fixed
/// frame, placed by perception's poses of the part at the push's start (see
/// `contact_observations`); `obs.y` is where the contact is at this grid frame
/// \[m\], fixed frame, with isotropic variance `contact_sd_m^2`. The likelihood is eq. 2's for
/// this point, Student-t like the centre of mass's ([`log_likelihood_position`], no inferred
/// noise added), or with `firm` Gaussian along the push ([`log_likelihood_contact`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactObs {
    pub x: Vector3<f64>,
    /// With `firm`, `obs.basis`'s first column is the force's direction at this frame.
    pub obs: PositionObs,
    /// Gaussian along the push, Student-t across it ([`Grid::contact_firm`], where the frame's
    /// force has a direction).
    pub firm: bool,
}

/// One part's observations on the grid.
#[derive(Debug, Clone)]
pub struct PartSeries {
    /// Part label (>= 1).
    pub label: u32,
    /// Perceived centre of mass in the part's reference configuration \[m\]: the configuration
    /// of its first observation, to which perception registers every later one (a single noisy
    /// frame of the evidence grid would make a poor reference).
    pub com0: Vector3<f64>,
    /// Per grid frame: the observed centre of mass, or None (not seen).
    pub obs: Vec<Option<PositionObs>>,
    /// Per grid frame: the observed rotation, where the part's shape makes one observable.
    pub rot: Vec<Option<RotationObs>>,
    /// Per grid frame: the part's observed displacement from its reference configuration (the
    /// registration's pose, whether or not its rotation is observable).
    pub disp: Vec<Option<Isometry3<f64>>>,
    /// Per grid frame: the contact point observed on this part while it is pushed ([`ContactObs`];
    /// empty, or all None, where off or not pushed).
    pub contact: Vec<Option<ContactObs>>,
    /// Root-mean-square radius of the part about its centre of mass \[m\].
    pub radius: f64,
    /// Extent of the part: the 98th percentile of its model points' distances from `com0` \[m\]
    /// (a percentile, so that a few stray points do not set it); 0 when unknown.
    pub reach: f64,
    /// Rotational inertia about the centre of mass per kilogram (m²), fixed frame, reference
    /// configuration; and the hull volume (m³, 0 when flat).
    pub unit_inertia: Matrix3<f64>,
    pub volume: f64,
    /// Where the part's weight acts, from `com0` \[m\], fixed frame, reference configuration:
    /// the mean of perception's model points less the hull centroid
    /// ([`crate::perception::PartGeometry::centroid`]); zero when unknown. Only the gravity
    /// effect uses it; the tracked point, the inertia and the path coordinate stay at `com0`.
    pub weight_offset: Vector3<f64>,
}

impl PartSeries {
    /// The contact observation at grid frame `t`, if any.
    pub fn contact_at(&self, t: usize) -> Option<&ContactObs> {
        self.contact.get(t).and_then(Option::as_ref)
    }

    /// Whether anything observes the part at grid frame `t`: its centre of mass, its rotation or
    /// the contact.
    pub fn observed_at(&self, t: usize) -> bool {
        self.obs[t].is_some() || self.rot[t].is_some() || self.contact_at(t).is_some()
    }

    /// Add the part's log-likelihood at grid frame `t` (eq. 2, Student-t with `nu` degrees of
    /// freedom) to `ll`: its centre of mass at `com` \[m\] (fixed frame), its rotation `disp.r`
    /// where observable, and the hand's contact point where observed (its material point moved
    /// by `disp`, the part's displacement from its reference configuration), all of it moved
    /// further by `moved` where given (the part's subtree re-attached under another parent).
    /// `sigma` \[m\] and `rot_sigma` \[rad\] are the inferred noise scales. Terms are added in
    /// that order, one at a time, so that a sum over frames does not depend on the caller.
    #[allow(clippy::too_many_arguments)]
    pub fn add_frame_log_likelihood(&self, ll: &mut f64, t: usize, disp: &Displacement<f64>, com: &Vector3<f64>, moved: Option<&Displacement<f64>>, sigma: f64, rot_sigma: f64, nu: f64) {
        if let Some(o) = &self.obs[t] {
            *ll += log_likelihood_position(o, &moved.map_or(*com, |d| d.apply(com)), sigma, nu);
        }
        if let Some(o) = &self.rot[t] {
            *ll += log_likelihood_rotation(o, &moved.map_or(disp.r, |d| d.r * disp.r), rot_sigma, nu);
        }
        if let Some(co) = self.contact_at(t) {
            let x = disp.apply(&co.x);
            *ll += log_likelihood_contact(co, &moved.map_or(x, |d| d.apply(&x)), nu);
        }
    }
}

/// How the evidence grid is built from the cloud stamps (see [`Evidence::new`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    /// Least time between grid frames \[s\], unless a window would then keep fewer than
    /// `min_frames`; and the most grid frames.
    pub min_dt_s: f64,
    pub min_frames: usize,
    pub max_frames: usize,
    /// Dynamic mode: stamps up to this long after a window \[s\] (and before the next window)
    /// join the grid, at the window's spacing, as *rest frames*: observed like any frame, but
    /// outside the physics window, their coordinates tied to its last one
    /// ([`WindowEvidence::rest`]). Why: a part's pose at rest after a push shows its joint's
    /// displacement over many frames at once, without asking the physics to predict how the
    /// joint settles (extending the window further, `windows.margin_after_s` 1.0 s, did that and
    /// biased damping and friction; the default 0.7 s covers a heavy door's coast, so that rest
    /// frames begin once the part has stopped).
    pub rest_after_s: f64,
    /// Dynamic mode: stamps up to this long before a window \[s\] (and after the previous window
    /// and its rest frames) join the grid, at the window's spacing, as *rest frames before* it,
    /// their coordinates tied to the window's first one ([`WindowEvidence::rest_before`]). Why:
    /// the window opens only `windows.margin_before_s` ahead of the force, so a part that a push
    /// moved and that then stayed put showed its old pose in a few frames only, which a rigid
    /// joint's Student-t likelihood takes for outliers (issue 24, class 1: a drawer pushed 2.5 cm
    /// was called rigid with P = 1.00); where the part rested before the push is as much
    /// evidence of its joint's displacement as where it rests after. Off by default (0): at
    /// 0.5 s it helped joint types on the corpus but cost two shipped bags their criticism and
    /// physics results (README, "Generalization").
    pub rest_before_s: f64,
    /// A break in the clouds longer than this \[s\] between two windows cuts the tie between
    /// them (dynamic mode, [`WindowEvidence::continues`]): separate episodes, such as the bags of an
    /// interaction dataset, often start from a reset object, and nothing unobserved is known to
    /// have stayed where it was.
    pub max_unobserved_s: f64,
    /// Integration step of the physics in dynamic mode \[s\].
    pub step_s: f64,
    /// Dynamic mode: the sd \[m\] of the contact point as an observation of the pushed part's
    /// material point ([`ContactObs`]); 0: the contact is not observed (only the physics uses it).
    /// Why: the robot's hand moves with what it pushes. A drawer at 50 N s/m pushed 2.5 cm showed
    /// its motion in ten frames, which a rigid joint's Student-t
    /// likelihood took for outliers (issue 24, class 1), while the hand's own track said where the
    /// drawer's front went in every one of them.
    pub contact_sd_m: f64,
    /// [`ContactObs::firm`] for every contact observation (`model.contact_firm`).
    pub contact_firm: bool,
    /// The least force \[N\] at which the hand counts as touching the part (the window's closing
    /// threshold, `windows.force_close_n`): while the force ramps up and after release the contact
    /// frame need not be on the part.
    pub contact_force_n: f64,
    /// Surface points closer than this to another part count as touching it \[m\]; each model
    /// point stands for a `voxel_m` square of surface.
    pub contact_range_m: f64,
    pub voxel_m: f64,
}

/// One interaction window in dynamic mode: its grid frames and the measured wrench resampled on
/// the physics' integration steps, which start at the window's first grid frame.
#[derive(Debug, Clone, PartialEq)]
pub struct WindowEvidence {
    /// Grid frames of the window, in time order.
    pub frames: Vec<usize>,
    /// Rest frames after the window ([`Grid::rest_after_s`]), in time order: no force acts, and
    /// the joint's coordinate there deviates from the window's last by the physics' deviation
    /// scale.
    pub rest: Vec<usize>,
    /// Rest frames before the window ([`Grid::rest_before_s`]), in time order: the joint's
    /// coordinate there deviates from the window's first by the physics' deviation scale.
    pub rest_before: Vec<usize>,
    /// Integration step at the stamp of each of `frames` (0 for the first).
    pub frame_substep: Vec<usize>,
    /// The pushed part (index into [`Evidence::parts`]), if known.
    pub pushed: Option<usize>,
    /// Whether the object was watched without a break (no gap in the clouds over
    /// [`Grid::max_unobserved_s`]) since the previous window: only then does the joint start this
    /// window where the previous one left it. False for the first window.
    pub continues: bool,
    /// Whether the push's contact lies [`CONTACT_REACH_M`] or more from every point of the pushed
    /// part's model (reference configuration) at the first pushing frame where the part is seen:
    /// the hand is on something else, often a part the camera never sees (a box lid inside a
    /// drawer), and the measured wrench does not act on the pushed part as the physics applies
    /// it. False when not pushed or unknown.
    pub hand_off: bool,
    /// Integration step \[s\].
    pub h: f64,
    /// Per integration step: force \[N\], torque \[N·m\] and point of application \[m\], fixed frame
    /// (linearly interpolated between wrench stamps, zero outside them).
    pub force: Vec<Vector3<f64>>,
    pub torque: Vec<Vector3<f64>>,
    pub point: Vec<Vector3<f64>>,
}

/// Observations of all parts on a common time grid.
#[derive(Debug, Clone)]
pub struct Evidence {
    /// Grid stamps \[s\].
    pub times: Vec<f64>,
    /// Whether a grid frame starts a new window (the first frame always does).
    pub window_start: Vec<bool>,
    /// Parts in label order.
    pub parts: Vec<PartSeries>,
    /// Contact area between parts `i` and `k` \[m²\] (contact prior on trees): the surface of
    /// each part's model within `contact_range` of the other's, averaged over both directions, at
    /// the first grid frame in which both are seen; 0 if never seen together.
    pub contact: Vec<Vec<f64>>,
    /// Dynamic mode: the windows with their wrenches (empty in kinematic mode).
    pub windows: Vec<WindowEvidence>,
    /// Per part: the effects on its joint beyond damping and friction — declared by the recording
    /// (`bom_ground_truth` effects) or adopted by model criticism — which the physics includes
    /// with their parameters inferred.
    pub effects: Vec<EffectSet>,
}

impl Evidence {
    /// Build the grid from perception tracks and windows: every stamp at which some part was
    /// seen inside a window, thinned so that kept stamps are at least `min_dt` seconds apart and
    /// then evenly to at most `max_frames`. Parts never seen inside a window are left out.
    ///
    /// Why thin in time: tracking errors of real recordings are correlated over a fraction of a
    /// second (jumps, slow drifts), while eq. 2 treats frames as independent; at 30 Hz it would
    /// count one drift as dozens of independent observations and prefer any curve that follows
    /// it (a large-radius arc over a straight slide). Keeping frames `min_dt` apart makes the
    /// independence assumption hold approximately, as in coarsened posteriors (Miller & Dunson,
    /// JASA 2019), and leaves the Occam factor of the richer joint type visible.
    ///
    /// A short window would keep too few frames that way: the spacing in each window is at most
    /// its duration / `min_frames`.
    ///
    /// With wrenches (dynamic mode), each window's measured wrench is resampled on the physics'
    /// integration steps; `effects` gives the effects on each part's joint by label (absent: none).
    pub fn new(
        tracks: &PartTracks,
        geometry: &BTreeMap<u32, PartGeometry>,
        windows: &[Window],
        wrenches: &[WrenchSample],
        effects: &BTreeMap<u32, EffectSet>,
        grid: &Grid,
    ) -> Evidence {
        let (min_dt, min_frames, max_frames) = (grid.min_dt_s, grid.min_frames, grid.max_frames);
        // The window of a stamp, rest frames after it included (dynamic mode only).
        let dynamic_mode = !wrenches.is_empty();
        let rest_after = if dynamic_mode { grid.rest_after_s.max(0.0) } else { 0.0 };
        let rest_before = if dynamic_mode { grid.rest_before_s.max(0.0) } else { 0.0 };
        let physics_window = |t: f64| windows.iter().position(|w| w.contains(t));
        let after_window = |t: f64| windows.iter().position(|w| t > w.end && t <= w.end + rest_after);
        // Rest after a window takes a stamp before rest before the next one does.
        let window_of = |t: f64| {
            physics_window(t).or_else(|| after_window(t)).or_else(|| windows.iter().position(|w| t < w.start && t >= w.start - rest_before))
        };
        let mut stamps: BTreeMap<u64, usize> = BTreeMap::new();
        let key = |t: f64| (t * 1e9).round() as u64;
        for obs in tracks.values() {
            for o in obs {
                if window_of(o.stamp).is_some() {
                    stamps.insert(key(o.stamp), 0);
                }
            }
        }
        // Thinning restarts where a window's physics begins, so that its frames do not depend on
        // the rest frames before it.
        let group_of = |t: f64| window_of(t).map(|w| (w, t < windows[w].start));
        let mut all: Vec<u64> = Vec::new();
        for &k in stamps.keys() {
            let new_window = all.last().is_some_and(|&l| group_of(l as f64 * 1e-9) != group_of(k as f64 * 1e-9));
            let dt = window_of(k as f64 * 1e-9)
                .map(|w| min_dt.min((windows[w].end - windows[w].start) / min_frames.max(1) as f64))
                .unwrap_or(min_dt);
            if all.last().is_none_or(|&l| new_window || (k - l) as f64 * 1e-9 >= dt - 1e-6) {
                all.push(k);
            }
        }
        let keep: Vec<u64> = if all.len() > max_frames.max(2) {
            let m = max_frames.max(2);
            (0..m).map(|i| all[i * (all.len() - 1) / (m - 1)]).collect()
        } else {
            all
        };
        let index: BTreeMap<u64, usize> = keep.iter().enumerate().map(|(i, k)| (*k, i)).collect();
        let times: Vec<f64> = keep.iter().map(|k| *k as f64 * 1e-9).collect();
        let window_start = (0..times.len())
            .map(|i| i == 0 || window_of(times[i]) != window_of(times[i - 1]))
            .collect();
        let mut parts = Vec::new();
        // Each part's model points, for the contact areas.
        let mut models: Vec<&[Vector3<f64>]> = Vec::new();
        for (&label, obs) in tracks {
            let Some(geo) = geometry.get(&label) else { continue };
            let seen: Vec<(usize, &PartObservation)> =
                obs.iter().filter_map(|o| index.get(&key(o.stamp)).map(|&i| (i, o))).collect();
            if seen.is_empty() {
                continue;
            }
            let mut series = vec![None; times.len()];
            let mut rot = vec![None; times.len()];
            for &(i, o) in &seen {
                let y = (o.pose * nalgebra::Point3::from(geo.com)).coords;
                // The position's covariance from the registration, without perception's floors:
                // the likelihood's own noise (`sigma`, inferred per part and joint type) stands for
                // what registration does not see. The floors (3 mm, and 0.02 rad about the part's
                // anchor, which a deep drawer's centre of mass 0.3 m behind its front turns into
                // 6 mm) were several times the scatter of the corpus's tracks (that drawer at rest:
                // about 1.5 mm), which flattened the likelihood until a rigid joint took a 2.5 cm
                // push for noise (issue 24, class 1). Rotations keep the floor: registration's spin
                // errors are systematic (README, `adroit_door`'s latch creeping over pushes in which
                // it does not turn), and without it that latch's axis went from 2.9 to 3.5 degrees.
                let e = o.registration_position_cov(&geo.com).symmetric_eigen();
                series[i] = Some(PositionObs { y, basis: e.eigenvectors, var: e.eigenvalues.map(|v| v.max(0.0)) });
                if !geo.rotation_axes.is_empty() {
                    let r = o.pose.rotation.to_rotation_matrix().into_inner();
                    let cov = o.rotation_cov();
                    let axes = geo.rotation_axes.iter().map(|a| {
                        let a = r * a;
                        (a, (a.transpose() * cov * a)[0].max(0.0))
                    });
                    rot[i] = Some(RotationObs { r, axes: axes.collect() });
                }
            }
            let mut poses = vec![None; times.len()];
            for &(i, o) in &seen {
                poses[i] = Some(o.pose);
            }
            models.push(&geo.points);
            let extent = reach(&geo.points, &geo.com);
            tracing::trace!("part {label}: com0 {:.3?}, reach {extent:.3} m, rms radius {:.3} m", geo.com.as_slice(), geo.radius);
            parts.push(PartSeries {
                label,
                com0: geo.com,
                obs: series,
                rot,
                disp: poses,
                contact: vec![None; times.len()],
                radius: geo.radius.max(1e-3),
                reach: extent,
                unit_inertia: geo.unit_inertia,
                volume: geo.volume,
                weight_offset: geo.centroid - geo.com,
            });
        }
        let disps: Vec<&[Option<Isometry3<f64>>]> = parts.iter().map(|p: &PartSeries| p.disp.as_slice()).collect();
        let contact = geometry::contact_areas(&disps, &models, grid.contact_range_m, grid.voxel_m);
        let labels: Vec<u32> = parts.iter().map(|p| p.label).collect();
        let mut dynamic: Vec<WindowEvidence> = if wrenches.is_empty() {
            Vec::new()
        } else {
            windows
                .iter()
                .enumerate()
                .filter_map(|(w, win)| {
                    let frames: Vec<usize> = (0..times.len()).filter(|&i| physics_window(times[i]) == Some(w)).collect();
                    let rest: Vec<usize> =
                        (0..times.len()).filter(|&i| physics_window(times[i]).is_none() && after_window(times[i]) == Some(w)).collect();
                    let rest_before: Vec<usize> = (0..times.len())
                        .filter(|&i| physics_window(times[i]).is_none() && after_window(times[i]).is_none() && window_of(times[i]) == Some(w))
                        .collect();
                    let pushed = win.pushed_part.and_then(|l| labels.iter().position(|&x| x == l));
                    window_evidence(&times, frames, rest, rest_before, pushed, wrenches, grid.step_s)
                })
                .collect()
        };
        let mut seen: Vec<f64> = tracks.values().flat_map(|obs| obs.iter().map(|o| o.stamp)).collect();
        seen.sort_by(|a, b| a.total_cmp(b));
        for w in 1..dynamic.len() {
            let (a, b) = (times[*dynamic[w - 1].frames.last().expect("a window has frames")], times[dynamic[w].frames[0]]);
            dynamic[w].continues = longest_gap(&seen, a, b) <= grid.max_unobserved_s;
        }
        for (w, win) in dynamic.iter_mut().enumerate() {
            let Some(p) = win.pushed else { continue };
            win.hand_off = hand_off(&parts[p], models[p], win, grid);
            if win.hand_off {
                tracing::debug!("window {w}: the hand is {CONTACT_REACH_M} m or more from every point of part {}, the part nearest it", parts[p].label);
            }
        }
        if grid.contact_sd_m > 0.0 {
            for (w, win) in dynamic.iter().enumerate() {
                let Some(p) = win.pushed else { continue };
                contact_observations(&mut parts[p], models[p], win, grid);
                // Only for the log: how far the hand is from perception's track.
                if !tracing::enabled!(tracing::Level::DEBUG) {
                    continue;
                }
                let part = &parts[p];
                let gaps: Vec<f64> = win
                    .frames
                    .iter()
                    .filter_map(|&f| part.contact_at(f).zip(part.disp[f]).map(|(c, pose)| (c.obs.y - (pose * nalgebra::Point3::from(c.x)).coords).norm() * 1e3))
                    .collect();
                let n = win.frames.iter().filter(|&&f| part.contact_at(f).is_some()).count();
                tracing::debug!("window {w}: the contact observes part {} in {n} grid frames; off perception's track by {:.1?} mm", part.label, gaps);
            }
        }
        let effects = labels.iter().map(|l| effects.get(l).copied().unwrap_or_default()).collect();
        Evidence { times, window_start, parts, contact, windows: dynamic, effects }
    }

    /// Number of grid frames.
    pub fn len(&self) -> usize {
        self.times.len()
    }

    pub fn is_empty(&self) -> bool {
        self.times.is_empty()
    }
}

/// The contact observations of `part`, pushed in `win` ([`ContactObs`]): each run of the window's
/// grid frames with a force of at least `contact_force_n` and a finite contact point is one push,
/// and its frames observe one material point `x` (reference configuration), placed by perception's
/// pose of the part (`pose⁻¹ · contact`) while the part is still at rest:
/// - over the push's first frames, while the hand stays within `contact_sd_m` of where the push
///   began, the componentwise median of the carried contact, where two or more of those frames
///   have a pose; every frame of the push then observes `x`;
/// - otherwise the push's first frame with a pose alone places `x`, and the frames after it
///   observe it (stop 95's rule).
///
/// Why at rest: where the hand touches the part is not measured, and perception's registration
/// lags a moving part along the directions its surface leaves loose, so a point placed by poses
/// during the motion is shifted along the motion, and the hand then says the part stood elsewhere
/// before the push than the clouds say (stop 98: the median over a whole push added a false
/// gravity finding on `bags/corpus/obj057_procedural`, held-out error 5.8 mm against 2.5 with the
/// first-frame anchor). Why
/// a median of several frames: a single frame's registration of a small part can be off by
/// 0.07-0.10 rad (README, stop 97). A push whose material point lies farther than
/// [`CONTACT_REACH_M`] from every point of the part's model `points` (reference configuration)
/// ends the window's observations: the hand is not on this part.
fn contact_observations(part: &mut PartSeries, points: &[Vector3<f64>], win: &WindowEvidence, grid: &Grid) {
    let var = Vector3::repeat(grid.contact_sd_m * grid.contact_sd_m);
    // The runs of pushing grid frames with a finite contact point: one push each; per frame the
    // grid frame, the contact point and the force.
    type Run = Vec<(usize, Vector3<f64>, Vector3<f64>)>;
    let mut runs: Vec<Run> = vec![Vec::new()];
    for (k, &f) in win.frames.iter().enumerate() {
        let step = win.frame_substep[k];
        let (force, point) = (win.force.get(step), win.point.get(step));
        let (Some(force), Some(point)) = (force, point) else { break };
        // Written so that a NaN force does not count as a push.
        let pushing = force.norm() >= grid.contact_force_n;
        if !pushing || !point.iter().all(|v| v.is_finite()) {
            runs.push(Vec::new());
            continue;
        }
        runs.last_mut().expect("one run at least").push((f, *point, *force));
    }
    for run in runs {
        let Some(&(_, y0, _)) = run.first() else { continue };
        let carry = |&(f, y, _): &(usize, Vector3<f64>, Vector3<f64>)| part.disp[f].map(|pose| (pose.inverse() * nalgebra::Point3::from(y)).coords);
        let still: Vec<Vector3<f64>> = run.iter().take_while(|(_, y, _)| (y - y0).norm() < grid.contact_sd_m).filter_map(carry).collect();
        let (x, from) = if still.len() >= 2 {
            (Vector3::from_fn(|c, _| Data::new(still.iter().map(|u| u[c]).collect::<Vec<f64>>()).median()), 0)
        } else {
            let Some((k, x)) = run.iter().enumerate().find_map(|(k, e)| carry(e).map(|x| (k, x))) else { continue };
            (x, k + 1)
        };
        if !points.iter().any(|p| (p - x).norm_squared() <= CONTACT_REACH_M * CONTACT_REACH_M) {
            tracing::debug!("part {}: a push's contact is {CONTACT_REACH_M} m or more from its points; not observed", part.label);
            return;
        }
        for &(f, y, force) in &run[from..] {
            // The force's direction first; a force without one (`contact_force_n` 0) is not firm.
            let (basis, firm) = match force.try_normalize(1e-12) {
                Some(n) if grid.contact_firm => {
                    let t1 = n.cross(&if n.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
                    (Matrix3::from_columns(&[n, t1, n.cross(&t1)]), true)
                }
                _ => (Matrix3::identity(), false),
            };
            part.contact[f] = Some(ContactObs { x, obs: PositionObs { y, basis, var }, firm });
        }
    }
}

/// Whether the hand is off the pushed part in window `win` ([`WindowEvidence::hand_off`]): the
/// contact point at the first pushing grid frame where the part is seen, carried into the part's
/// reference configuration, lies [`CONTACT_REACH_M`] or more from every one of its model `points`.
/// False without model points or without such a frame.
fn hand_off(part: &PartSeries, points: &[Vector3<f64>], win: &WindowEvidence, grid: &Grid) -> bool {
    if points.is_empty() {
        return false;
    }
    for (k, &f) in win.frames.iter().enumerate() {
        let step = win.frame_substep[k];
        let (Some(force), Some(point)) = (win.force.get(step), win.point.get(step)) else { break };
        // Written so that a NaN force does not count as a push.
        if !(force.norm() >= grid.contact_force_n) || !point.iter().all(|v| v.is_finite()) {
            continue;
        }
        let Some(pose) = part.disp.get(f).copied().flatten() else { continue };
        let x = (pose.inverse() * nalgebra::Point3::from(*point)).coords;
        return !points.iter().any(|p| (p - x).norm_squared() <= CONTACT_REACH_M * CONTACT_REACH_M);
    }
    false
}

/// The farthest the contact may lie from the pushed part's model points for it to observe the
/// part \[m\]: a handle that the segmentation leaves out stands a few centimetres off the panel;
/// farther, the hand is on something else (the part nearest the contact is not always the one
/// touched: the hand can hide a flap).
pub const CONTACT_REACH_M: f64 = 0.1;

/// A window's wrench on the integration steps from its first grid frame to its last.
fn window_evidence(times: &[f64], frames: Vec<usize>, rest: Vec<usize>, rest_before: Vec<usize>, pushed: Option<usize>, wrenches: &[WrenchSample], h: f64) -> Option<WindowEvidence> {
    let (&first, &last) = (frames.first()?, frames.last()?);
    if frames.len() < 2 || h <= 0.0 {
        return None;
    }
    let t0 = times[first];
    let frame_substep: Vec<usize> = frames.iter().map(|&f| ((times[f] - t0) / h).round() as usize).collect();
    let n = ((times[last] - t0) / h).round() as usize + 1;
    let (force, torque, point) = wrench_on_steps(wrenches, t0, n, h);
    Some(WindowEvidence { frames, rest, rest_before, frame_substep, pushed, continues: false, hand_off: false, h, force, torque, point })
}

/// Force, torque and point of application per integration step ([`wrench_on_steps`]).
pub type WrenchSteps = (Vec<Vector3<f64>>, Vec<Vector3<f64>>, Vec<Vector3<f64>>);

/// The measured wrench on `n` integration steps `t0 + k h` \[s\]: force \[N\], torque \[N·m\] and
/// point of application \[m\], fixed frame, linearly interpolated between the stamps of
/// `wrenches` (sorted by stamp), zero outside them (the point then stays at the last sample's).
pub fn wrench_on_steps(wrenches: &[WrenchSample], t0: f64, n: usize, h: f64) -> WrenchSteps {
    let (mut force, mut torque, mut point) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
    if wrenches.is_empty() {
        return (vec![Vector3::zeros(); n], vec![Vector3::zeros(); n], vec![Vector3::zeros(); n]);
    }
    // The last sample at or before `t0` (a node keeps a long buffer).
    let mut j = wrenches.partition_point(|w| w.stamp <= t0).saturating_sub(1);
    for s in 0..n {
        let t = t0 + s as f64 * h;
        while j + 1 < wrenches.len() && wrenches[j + 1].stamp <= t {
            j += 1;
        }
        let (a, b) = (&wrenches[j], wrenches.get(j + 1));
        let sample = match b {
            Some(b) if a.stamp <= t && t <= b.stamp && b.stamp > a.stamp => {
                let u = (t - a.stamp) / (b.stamp - a.stamp);
                Some((a.force.lerp(&b.force, u), a.torque.lerp(&b.torque, u), a.point.coords.lerp(&b.point.coords, u)))
            }
            _ if (a.stamp - t).abs() < 1e-9 => Some((a.force, a.torque, a.point.coords)),
            _ => None,
        };
        let (f, tq, p) = sample.unwrap_or((Vector3::zeros(), Vector3::zeros(), a.point.coords));
        force.push(f);
        torque.push(tq);
        point.push(p);
    }
    (force, torque, point)
}

/// The longest time between consecutive stamps of `sorted` within `[a, b]`, the ends included \[s\].
fn longest_gap(sorted: &[f64], a: f64, b: f64) -> f64 {
    let lo = sorted.partition_point(|&t| t < a);
    let hi = sorted.partition_point(|&t| t <= b);
    let mut prev = a;
    let mut gap: f64 = 0.0;
    for &t in &sorted[lo..hi] {
        gap = gap.max(t - prev);
        prev = t;
    }
    gap.max(b - prev)
}

/// Log-density of a `dim`-variate Student-t with `nu` degrees of freedom (Gaussian when `nu` is
/// infinite or 0) at squared Mahalanobis distance `m2`, with `half_log_det = 0.5 log |Sigma|`.
#[inline]
pub(crate) fn log_student<T: Real>(m2: T, half_log_det: T, dim: usize, nu: f64) -> T {
    let d = dim as f64;
    if !(nu.is_finite() && nu > 0.0) {
        return -(m2 * 0.5) - half_log_det - c::<T>(0.5 * d * (2.0 * std::f64::consts::PI).ln());
    }
    -((m2 / nu + 1.0).ln() * (0.5 * (nu + d))) - half_log_det + student_norm(nu, d)
}

/// The Student-t's log normalising constant (without the covariance's determinant),
/// `lgamma((nu + d) / 2) - lgamma(nu / 2) - d/2 log(nu pi)`, remembered for the last `(nu, d)` of
/// the thread: `nu` is a setting, and two `lgamma`s a frame were a tenth of a log density's time.
#[inline]
fn student_norm(nu: f64, d: f64) -> f64 {
    thread_local! {
        static LAST: std::cell::Cell<(f64, f64, f64)> = const { std::cell::Cell::new((f64::NAN, f64::NAN, f64::NAN)) };
    }
    LAST.with(|last| {
        let (n, dd, v) = last.get();
        if n == nu && dd == d {
            return v;
        }
        let v = libm::lgamma(0.5 * (nu + d)) - libm::lgamma(0.5 * nu) - 0.5 * d * (nu * std::f64::consts::PI).ln();
        last.set((nu, d, v));
        v
    })
}

/// Log-likelihood of one part's centre of mass in one frame (eq. 2): covariance
/// `Sigma + sigma^2 I`, with the perception covariance `Sigma` given by its eigen-decomposition.
/// With `nu` finite, a multivariate Student-t with that covariance scale: the paper's Gaussian
/// when perception errs like Gaussian noise, but a registration that slips for a few frames
/// (depth images err in bursts) costs logarithmically instead of quadratically, and cannot force
/// a joint onto a static part.
#[inline]
pub fn log_likelihood_position<T: Real>(o: &PositionObs, x: &Vector3<T>, sigma: T, nu: f64) -> T {
    let s2 = sigma * sigma;
    let d = Vector3::new(c::<T>(o.y.x) - x.x, c::<T>(o.y.y) - x.y, c::<T>(o.y.z) - x.z);
    let (mut m2, mut hld) = (c::<T>(0.0), c::<T>(0.0));
    for k in 0..3 {
        let b = o.basis.column(k);
        let dk = d.x * b.x + d.y * b.y + d.z * b.z;
        let var = s2 + o.var[k];
        m2 += dk * dk / var;
        hld += var.ln() * 0.5;
    }
    log_student(m2, hld, 3, nu)
}

/// Log-likelihood of the hand's contact point `co` given where the part's touched material point
/// is, `x` \[m\], fixed frame. Without `co.firm` it is [`log_likelihood_position`] (Student-t,
/// no inferred noise). With it, the displacement along the push (`co.obs.basis`'s first column,
/// the force's direction) is Gaussian and the two across it a bivariate Student-t with `nu`
/// degrees of freedom: the hand may slip along the surface it pushes (and where it touches is
/// placed by perception's poses, which err), but it moves into the surface only as far as the
/// surface moves, so a hand that advances along its force while the clouds say the part stays
/// is evidence that the part moved, not an outlier (the arm's kinematics place the hand to
/// millimetres; perception can miss a motion along directions the part's visible surface leaves
/// loose, a drawer's sides sliding along themselves). With Gaussian noise (`nu` 0, as
/// `model.student_nu` 0 sets) the two forms are one density.
#[inline]
pub fn log_likelihood_contact<T: Real>(co: &ContactObs, x: &Vector3<T>, nu: f64) -> T {
    let o = &co.obs;
    if !co.firm {
        return log_likelihood_position(o, x, c(0.0), nu);
    }
    let d = Vector3::new(c::<T>(o.y.x) - x.x, c::<T>(o.y.y) - x.y, c::<T>(o.y.z) - x.z);
    let project = |k: usize| {
        let b = o.basis.column(k);
        d.x * b.x + d.y * b.y + d.z * b.z
    };
    let along = project(0);
    let gauss = log_student(along * along / o.var[0], c::<T>(0.5 * o.var[0].ln()), 1, f64::INFINITY);
    let (mut m2, mut hld) = (c::<T>(0.0), c::<T>(0.0));
    for k in 1..3 {
        let dk = project(k);
        m2 += dk * dk / o.var[k];
        hld += c::<T>(0.5 * o.var[k].ln());
    }
    gauss + log_student(m2, hld, 2, nu)
}

/// The 98th percentile of the distances of `points` from `centre` \[m\]; 0 for no points.
fn reach(points: &[Vector3<f64>], centre: &Vector3<f64>) -> f64 {
    let mut d: Vec<f64> = points.iter().map(|p| (p - centre).norm()).filter(|x| x.is_finite()).collect();
    if d.is_empty() {
        return 0.0;
    }
    d.sort_by(|a, b| a.total_cmp(b));
    d[((d.len() - 1) as f64 * 0.98).round() as usize]
}

/// Log-likelihood of a part's observed rotation given its predicted rotation `r` (fixed frame):
/// the rotation vector of the error `r R_obs^T` (its skew part, exact for small errors and
/// bounded for large ones) projected on each observable axis, variance `sd^2 + sigma_r^2` per
/// axis, Student-t with `nu` degrees of freedom as for positions.
#[inline]
pub fn log_likelihood_rotation<T: Real>(o: &RotationObs, r: &Matrix3<T>, sigma_r: T, nu: f64) -> T {
    if o.axes.is_empty() {
        return c(0.0);
    }
    // Off-diagonal entries of `e = r R_obs^T` only, summed in nalgebra's order (bit-identical).
    let ro = &o.r;
    let e = |i: usize, j: usize| r[(i, 0)] * ro[(j, 0)] + r[(i, 1)] * ro[(j, 1)] + r[(i, 2)] * ro[(j, 2)];
    let w = Vector3::new(e(2, 1) - e(1, 2), e(0, 2) - e(2, 0), e(1, 0) - e(0, 1)).map(|v| v * 0.5);
    let s2 = sigma_r * sigma_r;
    let (mut m2, mut hld) = (c::<T>(0.0), c::<T>(0.0));
    for (a, v) in &o.axes {
        let wk = w.x * a.x + w.y * a.y + w.z * a.z;
        let var = s2 + *v;
        m2 += wk * wk / var;
        hld += var.ln() * 0.5;
    }
    log_student(m2, hld, o.axes.len(), nu)
}

/// The prior of a joint coordinate `q` \[m\] at a window start that no continuity ties to an
/// earlier frame, in expectation under a Gaussian guide `N(m, s^2)`: a two-component mixture,
/// `p(q) = pi N(q; 0, s_r^2) + (1 - pi) N(q; 0, s_b^2)` with `pi = window_reset_prob`,
/// `s_r = window_reset_sd_m`, `s_b = window_start_sd_m`. Returns the value and its derivatives
/// with respect to `m` and `s` (`s = 0`: the log density at `m`).
///
/// The value is `log sum_c exp(log pi_c + E_q[log N_c(q)])`: the component taken as a discrete
/// latent with its posterior at the optimum, a lower bound of `E_q[log p(q)]` (Jensen), so the
/// ELBO stays a bound; exact when `s = 0`. `window_reset_prob` is clamped to `[0, 1]`; at 0 (the
/// default) this is the broad Gaussian alone, bit for bit.
///
/// Why: 0 is the part's reference configuration, its first observation, so the first frame is
/// there by construction, and interaction datasets reset the object between episodes (issue 24,
/// class 2). With the broad prior alone every such start costs a movable joint type about
/// `log(s_b / s)` nats (7 for a 1 mm guide against 1 m) that the rigid type does not pay: an
/// object recorded in 6 episodes charges each movable part some 40 nats. Measured on the corpus
/// with `inference.tol_type_nats` (README, "Why movable parts come out rigid at P = 1.00"): off
/// by default for now.
pub fn window_start_prior(m: f64, s: f64, cfg: &ModelConfig) -> (f64, f64, f64) {
    let ln2pi = (2.0 * std::f64::consts::PI).ln();
    let p = cfg.window_reset_prob.clamp(0.0, 1.0);
    let comps = [(p, cfg.window_reset_sd_m), (1.0 - p, cfg.window_start_sd_m)];
    let e = comps.map(|(p, sd)| {
        let var = sd * sd;
        if p > 0.0 { p.ln() - (m * m + s * s) / (2.0 * var) - 0.5 * (var.ln() + ln2pi) } else { f64::NEG_INFINITY }
    });
    let top = e[0].max(e[1]);
    let v = top + e.iter().map(|x| (x - top).exp()).sum::<f64>().ln();
    let (mut dm, mut ds) = (0.0, 0.0);
    for (x, &(_, sd)) in e.iter().zip(&comps) {
        let r = (x - v).exp();
        dm -= r * m / (sd * sd);
        ds -= r * s / (sd * sd);
    }
    (v, dm, ds)
}

/// Expected log prior `E_q[log p(q)]` of a joint-coordinate chain and its gradient with respect
/// to the guide means `m` and sds `s`.
///
/// Prior (kinematic mode): the first frame of every window by [`window_start_prior`] (0 is
/// the part's reference configuration, its first observation), and within a window increments `q_k - q_{k-1} ~ N(0, (v * dt_k)^2)`. The velocity scale `v` is itself
/// latent, `v = velocity_sd_mps * exp(velocity_log_sd * xi_v)` with `xi_v ~ N(0, 1)` and, in the
/// guide, `xi_v ~ N(vm, vs^2)`: a joint that barely moved is a joint with a small velocity scale,
/// not a joint that beat the odds of a fast random walk in every frame — with a fixed scale the
/// per-frame Occam factor declared such a part rigid with certainty. In dynamic mode the physics
/// prior ([`super::dynamics`]) takes the place of all of this.
///
/// Returns the value and its gradients with respect to `m`, `s`, `vm` and `vs`.
pub fn coordinate_prior(ev: &Evidence, m: &[f64], s: &[f64], vm: f64, vs: f64, cfg: &ModelConfig) -> (f64, Vec<f64>, Vec<f64>, f64, f64) {
    let n = ev.len();
    let (mut v, mut gm, mut gs) = (0.0, vec![0.0; n], vec![0.0; n]);
    let l = cfg.velocity_log_sd;
    // E[1 / v^2] and E[log v] under the guide of xi_v.
    let inv_v2 = (-2.0 * l * vm + 2.0 * l * l * vs * vs).exp() / cfg.velocity_sd_mps.powi(2);
    let log_v = cfg.velocity_sd_mps.ln() + l * vm;
    let (mut g_vm, mut g_vs) = (0.0, 0.0);
    let ln2pi = (2.0 * std::f64::consts::PI).ln();
    let mm = |k: usize| m[k];
    let ss = |k: usize| s[k];
    for k in 0..n {
        if ev.window_start[k] {
            let (l, dm, ds) = window_start_prior(mm(k), ss(k), cfg);
            v += l;
            gm[k] += dm;
            gs[k] += ds;
        } else {
            let dt = (ev.times[k] - ev.times[k - 1]).max(1e-3);
            // 1 / var = E[1 / v^2] / dt^2 and log var = 2 (E[log v] + log dt).
            let inv_var = inv_v2 / (dt * dt);
            let d = mm(k) - mm(k - 1);
            let sq = d * d + ss(k).powi(2) + ss(k - 1).powi(2);
            v += -sq * inv_var / 2.0 - (log_v + dt.ln()) - 0.5 * ln2pi;
            gm[k] -= d * inv_var;
            gm[k - 1] += d * inv_var;
            gs[k] -= ss(k) * inv_var;
            gs[k - 1] -= ss(k - 1) * inv_var;
            g_vm += sq * inv_var * l - l;
            g_vs -= sq * inv_var * 2.0 * l * l * vs;
        }
    }
    (v, gm, gs, g_vm, g_vs)
}

#[cfg(test)]
mod tests {
    use super::{contact_observations, hand_off, log_likelihood_contact, log_likelihood_position, longest_gap, window_start_prior, ContactObs, Grid, PartSeries, WindowEvidence};
    use crate::model::ModelConfig;
    use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};

    /// A part of `k` grid frames, nothing observed, with perception's poses `disp`.
    fn unobserved_part(k: usize, disp: Vec<Option<Isometry3<f64>>>) -> PartSeries {
        PartSeries {
            label: 2,
            com0: Vector3::zeros(),
            obs: vec![None; k],
            rot: vec![None; k],
            disp,
            contact: vec![None; k],
            radius: 0.1,
            reach: 0.1,
            unit_inertia: Matrix3::identity(),
            volume: 0.0,
            weight_offset: Vector3::zeros(),
        }
    }

    /// A window over every grid frame of a push on part 0, one integration step per frame: the
    /// force and the contact point at each.
    fn pushed_window(force: Vec<Vector3<f64>>, point: Vec<Vector3<f64>>) -> WindowEvidence {
        let k = force.len();
        WindowEvidence {
            frames: (0..k).collect(),
            rest: vec![],
            rest_before: vec![],
            frame_substep: (0..k).collect(),
            pushed: Some(0),
            continues: false,
            hand_off: false,
            h: 0.01,
            force,
            torque: vec![Vector3::zeros(); k],
            point,
        }
    }

    /// One integration step per grid frame, no rests; the contact at `contact_sd_m`.
    fn contact_grid(contact_sd_m: f64, contact_firm: bool) -> Grid {
        Grid {
            min_dt_s: 0.0,
            min_frames: 2,
            max_frames: 100,
            rest_after_s: 0.0,
            rest_before_s: 0.0,
            max_unobserved_s: 5.0,
            step_s: 0.01,
            contact_sd_m,
            contact_firm,
            contact_force_n: 0.5,
            contact_range_m: 0.01,
            voxel_m: 0.005,
        }
    }

    /// A push is one run of frames at or above the contact force; a frame below the force ends
    /// it. A push that moves the hand at once: its first frame with a pose of the part anchors
    /// the material point (the part's reference configuration) and observes nothing, each later
    /// frame observes it. A push that starts slowly: the median over the frames before the hand
    /// has moved `contact_sd_m` places the point, so that one frame's registration error does not
    /// move it, and every frame observes. A part far from the hand is not observed, and its
    /// window says the hand is off it ([`hand_off`]).
    #[test]
    fn contact_points_anchor_each_push_on_the_part() {
        let k = 8;
        // The part slides along x by 1 cm a frame and turns by 0.1 rad about z; unseen at frame 1.
        let pose = |t: usize| {
            Isometry3::from_parts(Translation3::new(0.01 * t as f64, 0.0, 0.0), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.1 * t as f64))
        };
        let mut part = unobserved_part(k, (0..k).map(|t| (t != 1).then(|| pose(t))).collect());
        let material = Vector3::new(0.3, 0.05, 0.1);
        let at = |t: usize| pose(t) * nalgebra::Point3::from(material);
        // One integration step per frame; force below 0.5 N at frames 0 and 5.
        let magnitude = [0.2, 2.0, 2.0, 2.0, 2.0, 0.1, 3.0, 3.0];
        let mut win = pushed_window(magnitude.iter().map(|&f| Vector3::new(f, 0.0, 0.0)).collect(), (0..k).map(|t| at(t).coords).collect());
        let grid = contact_grid(0.004, false);
        let near = [Vector3::new(0.3, 0.0, 0.1), Vector3::new(2.0, 0.0, 0.0)];
        // Whether the hand is on the part: judged at frame 2, the first pushed frame it is seen in.
        assert!(!hand_off(&part, &near, &win, &grid), "5 cm from a point of the part");
        assert!(hand_off(&part, &[Vector3::new(0.3, 0.2, 0.1), Vector3::new(2.0, 0.0, 0.0)], &win, &grid), "15 cm from every point");
        assert!(!hand_off(&part, &[], &win, &grid), "no model points: not known to be off");
        contact_observations(&mut part, &[], &win, &grid);
        assert!((0..k).all(|t| part.contact_at(t).is_none()), "no point of the part near the hand");
        contact_observations(&mut part, &near, &win, &grid);
        let seen: Vec<usize> = (0..k).filter(|&t| part.contact_at(t).is_some()).collect();
        // Frame 1 is pushed but unseen, so frame 2 anchors; frame 6 anchors the second push.
        assert_eq!(seen, [3, 4, 7]);
        for &t in &seen {
            let c = part.contact_at(t).unwrap();
            assert!((c.x - material).norm() < 1e-12, "frame {t}: material point {:?}", c.x);
            assert!((c.obs.y - at(t).coords).norm() < 1e-12);
            assert_eq!(c.obs.var, Vector3::repeat(0.004 * 0.004));
        }
        assert!(part.observed_at(3) && !part.observed_at(2), "the anchor observes nothing");
        // A slow start: the part (and the hand) still over frames 1-3 of the first push, then
        // moving; perception's pose at frame 2 turned by 0.1 rad (3 cm at the hand).
        let slow = |t: usize| pose(t.saturating_sub(3));
        part.disp = (0..k).map(|t| Some(slow(t))).collect();
        part.disp[2] = Some(slow(2) * Isometry3::rotation(Vector3::z() * 0.1));
        win.point = (0..k).map(|t| (slow(t) * nalgebra::Point3::from(material)).coords).collect();
        part.contact = vec![None; k];
        contact_observations(&mut part, &near, &win, &grid);
        let seen: Vec<usize> = (0..k).filter(|&t| part.contact_at(t).is_some()).collect();
        assert_eq!(seen, [1, 2, 3, 4, 7], "the slow push observes in every frame, the quick one after its anchor");
        for &t in &seen {
            let c = part.contact_at(t).unwrap();
            assert!((c.x - material).norm() < 1e-12, "frame {t}: material point {:?}", c.x);
        }
    }

    /// A firm contact ([`log_likelihood_contact`]): with the basis `contact_observations` builds
    /// from the force, a hand 10 cm ahead of the material point along its force costs the
    /// Gaussian's 200 nats (20 sds), 10 cm across the force the Student-t's few nats, and without
    /// `firm` both are the centre of mass's Student-t; with Gaussian noise (`nu` 0) the two forms
    /// are one density. Its derivative through dual numbers is that of its value.
    #[test]
    fn a_firm_contact_is_gaussian_along_the_push_only() {
        let sd = 0.005;
        let force = Vector3::new(1.0, 2.0, -0.5);
        let mut part = unobserved_part(3, vec![Some(Isometry3::identity()); 3]);
        let win = pushed_window(vec![force; 3], vec![Vector3::new(0.3, 0.0, 0.1); 3]);
        let grid = contact_grid(sd, true);
        contact_observations(&mut part, &[Vector3::new(0.3, 0.0, 0.1)], &win, &grid);
        let co: ContactObs = *part.contact_at(1).expect("the still push observes every frame");
        assert!(co.firm);
        let n = force.normalize();
        assert!((co.obs.basis.column(0) - n).norm() < 1e-12, "the force's direction first");
        assert!((co.obs.basis.transpose() * co.obs.basis - Matrix3::identity()).norm() < 1e-12, "orthonormal");
        let across = co.obs.basis.column(1).into_owned();
        let loose = ContactObs { firm: false, ..co };
        let at = |x: Vector3<f64>, c: &ContactObs, nu: f64| log_likelihood_contact(c, &x, nu);
        let y = co.obs.y;
        let (nu, d) = (4.0, 0.1);
        let drop = |dir: Vector3<f64>, c: &ContactObs| at(y, c, nu) - at(y - dir * d, c, nu);
        let gauss_drop = 0.5 * (d / sd).powi(2);
        assert!((drop(n, &co) - gauss_drop).abs() < 1e-9, "along the push: {} nats", drop(n, &co));
        assert!(drop(across, &co) > 1.0 && drop(across, &co) < 20.0, "across the push: {} nats", drop(across, &co));
        assert!(drop(n, &loose) < 20.0, "not firm: Student-t along the push too ({} nats)", drop(n, &loose));
        let off = y + Vector3::new(0.01, -0.02, 0.03);
        assert_eq!(at(off, &loose, nu), log_likelihood_position(&loose.obs, &off, 0.0, nu));
        assert!((at(off, &co, 0.0) - at(off, &loose, 0.0)).abs() < 1e-9, "Gaussian noise: one density");
        // The derivative along x through a dual number against central differences.
        let dual = log_likelihood_contact(&co, &Vector3::new(num_dual::Dual64::from(off.x).derivative(), off.y.into(), off.z.into()), nu);
        let h = 1e-6;
        let fd = (at(off + Vector3::x() * h, &co, nu) - at(off - Vector3::x() * h, &co, nu)) / (2.0 * h);
        assert!((dual.eps - fd).abs() < 1e-5 * fd.abs().max(1.0), "derivative {} against {fd}", dual.eps);
    }

    /// The window-start mixture: with `s = 0` it is the log of the mixture density, without the
    /// reset component the broad Gaussian's expectation, its derivatives are those of its value,
    /// and a start at the reference configuration costs a movable joint far less than the broad
    /// prior alone charged (the rigid type pays nothing there), one far from it about `log 2` more.
    #[test]
    fn window_start_mixture() {
        let cfg = ModelConfig { window_reset_prob: 0.5, ..ModelConfig::default() };
        let n = |x: f64, sd: f64| (-(x * x) / (2.0 * sd * sd)).exp() / (sd * (2.0 * std::f64::consts::PI).sqrt());
        for x in [0.0, 0.004, -0.03, 0.4] {
            let (v, _, _) = window_start_prior(x, 0.0, &cfg);
            let mix = cfg.window_reset_prob * n(x, cfg.window_reset_sd_m) + (1.0 - cfg.window_reset_prob) * n(x, cfg.window_start_sd_m);
            assert!((v - mix.ln()).abs() < 1e-9, "{v} vs {}", mix.ln());
        }
        let broad = ModelConfig { window_reset_prob: 0.0, ..cfg.clone() };
        let (m, s, var) = (0.2, 0.003, cfg.window_start_sd_m.powi(2));
        let (v, dm, ds) = window_start_prior(m, s, &broad);
        assert!((v - (-(m * m + s * s) / (2.0 * var) - 0.5 * (var * 2.0 * std::f64::consts::PI).ln())).abs() < 1e-12);
        assert!((dm + m / var).abs() < 1e-12 && (ds + s / var).abs() < 1e-12);
        for (m, s) in [(0.001, 0.002), (0.02, 0.004), (-0.3, 0.01)] {
            let (_, dm, ds) = window_start_prior(m, s, &cfg);
            let h = 1e-7;
            let fd_m = (window_start_prior(m + h, s, &cfg).0 - window_start_prior(m - h, s, &cfg).0) / (2.0 * h);
            let fd_s = (window_start_prior(m, s + h, &cfg).0 - window_start_prior(m, s - h, &cfg).0) / (2.0 * h);
            assert!((dm - fd_m).abs() < 1e-4 * (1.0 + fd_m.abs()), "{dm} vs {fd_m}");
            assert!((ds - fd_s).abs() < 1e-4 * (1.0 + fd_s.abs()), "{ds} vs {fd_s}");
        }
        // A guide 1 mm wide at the reference: the mixture against the broad prior alone.
        let gain = window_start_prior(0.0, 0.001, &cfg).0 - window_start_prior(0.0, 0.001, &broad).0;
        assert!(gain > 3.0, "{gain}");
        let loss = window_start_prior(0.4, 0.001, &broad).0 - window_start_prior(0.4, 0.001, &cfg).0;
        assert!((loss - 2f64.ln()).abs() < 0.01, "{loss}");
    }

    /// The break between two windows counts its ends: clouds every 1/30 s are no gap, a bag that
    /// ends 300 s before the next begins is one, and so is a stream that stops before `b`.
    #[test]
    fn longest_gap_between_windows() {
        let stream: Vec<f64> = (0..300).map(|k| k as f64 / 30.0).collect();
        assert!(longest_gap(&stream, 2.0, 5.0) < 0.04);
        let mut episodes = stream.clone();
        episodes.extend((0..300).map(|k| 310.0 + k as f64 / 30.0));
        assert!((longest_gap(&episodes, 9.0, 311.0) - (310.0 - 299.0 / 30.0)).abs() < 1e-9);
        assert!((longest_gap(&stream, 9.0, 20.0) - (20.0 - 299.0 / 30.0)).abs() < 1e-9);
        assert_eq!(longest_gap(&[], 1.0, 3.0), 2.0);
    }
}
