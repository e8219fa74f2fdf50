//! Perception stage: segmented clouds (fixed frame) to per-part poses relative to a reference
//! configuration, each with its uncertainty, and per-part geometry (centre of mass, inertia per
//! kilogram, observable rotation axes, surface points).
//!
//! Per frame and part ([`Perception::observe`]):
//! 1. **Points**: at most `max_points` (an even subsample), each weighted `boundary_weight` where
//!    a point of another part lies within `boundary_m` (segmentation swaps labels along part
//!    boundaries, and a part hidden by another ends where the other begins), else 1; with
//!    `edge_weight` set (off by default), a point on its part's own outline as seen from the
//!    cloud's viewpoint, where the other part lies behind or flush and hides nothing, weighs
//!    `edge_weight`: a flat panel sliding in its own plane is located there by nothing else.
//! 2. **Pose** by registration against the part's surface model ([`registration`]): the rigid
//!    motion `T_t` from the part's reference configuration (its first observed frame) to now, with
//!    the model growing as new surfaces come into view.
//! 3. **Uncertainty**: the covariance of the pose from the registration's Gauss-Newton matrix,
//!    scaled by `registration_cov_scale` (neighbouring points of a depth image do not err
//!    independently), expressed as the covariance of the part's anchor point and of its rotation,
//!    plus the floors `com_sd_floor_m` and `rotation_sd_floor_rad`.
//!
//! Per part, at any time ([`Perception::geometry`]): the centre of mass of the part's model in the
//! reference configuration — the centroid of its convex hull where the model spans a volume
//! (parry3d mass properties), else its mean — its inertia per kilogram (the hull's, else the
//! points' second moment, as for a thin shell), and which rotations its shape makes observable: a
//! rotation about a principal axis is observable only if the spreads along the other two axes
//! differ by `orientation_min_ratio` (nothing about a cube, not the spin of a square plate), or
//! where its surface normals pin it (`orientation_min_information`: a cube's faces, a slab's edges;
//! never a sphere's spin).

pub mod geometry;
pub mod registration;

use std::collections::BTreeMap;

use kiddo::{KdTree, SquaredEuclidean};
use nalgebra::{Isometry3, Matrix3, Matrix3x6, Matrix6, Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::input::{CloudFrame, WrenchSample};
use crate::parallel;
use registration::{FramePoints, Tracker};

/// Perception settings (`perception` section of the config).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct PerceptionConfig {
    /// Fewer points than this and the part is treated as not seen in that frame.
    pub min_points: usize,
    /// At most this many points per part and frame are registered (an even subsample).
    pub max_points: usize,
    /// A frame that shows fewer points of a part than this fraction of the most seen of it in
    /// one frame (before the subsample) is not registered: the part is treated as not seen (a
    /// sliver constrains the pose in too few directions, and grows the model at a wrong pose).
    /// 0 (the default): off; measured on the corpus and not landed — a panel sliding behind
    /// another shows less of itself exactly while it moves (README "Generalization", stop 77).
    pub min_seen_fraction: f64,
    /// Minimum smallest principal standard deviation for a model's convex hull \[m\].
    pub min_thickness_m: f64,
    /// Isolated model points — those whose mean distance to this many nearest model points is
    /// an outlier ([`geometry::isolated_free`]) — are left out of the convex hull that gives a
    /// part's centre of mass (the point the likelihood tracks and the physics accelerates),
    /// inertia and volume. 0 (the default): the hull of every model point; measured on the
    /// corpus, README "Generalization" (stop 52).
    pub hull_outlier_neighbours: usize,
    /// Floor of the standard deviation of a part's position \[m\].
    pub com_sd_floor_m: f64,
    /// Floor of the standard deviation of a part's rotation \[rad\].
    pub rotation_sd_floor_rad: f64,
    /// Ratio between principal spreads for a rotation to be observable.
    pub orientation_min_ratio: f64,
    /// A rotation axis is also observable where the model's surface normals pin it: its
    /// point-to-plane information ([`geometry::rotation_information`]) is at least this share of
    /// the model's mean squared distance from its centre of mass (1 for a surface whose every
    /// normal is square to its radius; 0 for a sphere's spin, or a flat plate's about its
    /// normal). Where this gives more axes than `orientation_min_ratio`, its axes are used. 0: off
    /// (the spreads alone, as before stop 105). Set once at 0.1, before any run (README, "Stop 105").
    pub orientation_min_information: f64,
    /// Registration covariance multiplier (errors of neighbouring depth pixels are correlated).
    pub registration_cov_scale: f64,
    /// Model resolution: one model point per voxel of this size \[m\].
    pub voxel_m: f64,
    /// Each new model point is projected once onto the robust least-squares plane of the model
    /// points within this radius \[m\] when it is an inlier of it (moving least squares, see
    /// [`registration::Smoothing`]). 0 (the default): off; measured on the corpus, README
    /// "Generalization".
    pub smoothing_radius_m: f64,
    /// Range of the point-to-plane scale of the Cauchy kernel, which is estimated per frame from
    /// the residuals (the depth noise) \[m\].
    pub point_sd_min_m: f64,
    pub point_sd_max_m: f64,
    /// Weight of the point-to-point term, and its scale as a multiple of the point-to-plane scale
    /// (at least one voxel: model points are that far apart).
    pub point_to_point_weight: f64,
    pub point_to_point_ratio: f64,
    /// Correspondence gates: coarse (first half of the iterations), fine (second half, costs) \[m\].
    pub match_gate_m: f64,
    pub fine_gate_m: f64,
    pub icp_iterations: usize,
    /// Points within this distance of another part's points ...
    pub boundary_m: f64,
    /// ... count with this weight and never grow the model ...
    pub boundary_weight: f64,
    /// ... unless the point lies on its own part's outline as seen from the cloud's viewpoint
    /// (no point of the other part in front of this part's surface there: the other part is
    /// behind it or flush with it, so it hides nothing of this one): then the point counts with
    /// this weight, and with weight 1 grows the model. 0 (the default: measured on the corpus,
    /// README "Generalization"): every point near another part counts `boundary_weight`, as
    /// without a viewpoint.
    pub edge_weight: f64,
    /// A candidate model point must be seen in this many frames to join the model.
    pub confirm_frames: usize,
    /// During its first frames, while still in its reference pose, a part's points join its model
    /// without confirmation.
    pub initial_frames: usize,
    pub max_model_points: usize,
    /// Surface points closer than this to another part touch it (contact prior on trees) \[m\].
    pub contact_range_m: f64,
    /// Cost of moving away from the previous pose, and of returning to the reference pose
    /// \[nats\].
    pub move_penalty_nats: f64,
    pub reference_penalty_nats: f64,
    /// Cost of moving away from the previous pose for the part that the applied wrench pushes
    /// in this frame, when the move takes the part's point at the contact along the force
    /// ([`PushGate`], `Tracker::update`) \[nats\]; `move_penalty_nats` is the cap. The default,
    /// equal to `move_penalty_nats`, is off: measured on the corpus and not landed (README,
    /// "Generalization", stop 76).
    ///
    /// Why it exists: `move_penalty_nats` is the prior log-odds against a part moving in a given
    /// frame, right for a part nothing touches (about a 1% test of a 6-DOF pose fitted to noise)
    /// and blind to a part that a push moves a little in every frame — a slowly turning flap's
    /// 150 points gain 2-5 nats a frame, and its track never leaves the reference (README,
    /// "Generalization", stop 49). While the robot pushes a part, that part moving is what is
    /// expected; every other part keeps the full penalty, so a static case does not wander along
    /// the directions its surfaces leave loose (what lowering `move_penalty_nats` for every part
    /// did).
    pub push_move_penalty_nats: f64,
    /// Cost of moving a pose when a frame is registered again against the final model.
    pub refine_penalty_nats: f64,
    /// Register each part also from its pose moved with each larger part ([`carrier_starts`]): a
    /// part rides a part larger than itself (a hatch or a latch its door, a box its drawer) and
    /// moves with it, so when it is barely seen (a sliver), comes back after a gap, or its
    /// carrier swings faster than its own constant-velocity prediction follows, its own last
    /// pose is the wrong start. The carrier's motion in the same cloud places it. The moved pose
    /// is a hypothesis of no own motion (no move penalty, like staying where it was), and an ICP
    /// start; the registration cost still chooses. The parts of a cloud are then registered one
    /// after another, larger models first. Off by default: on `tune` it turns 3 parts right,
    /// on `validation` it costs parts in the episode bags (README "Generalization", stop 85).
    pub carrier_starts: bool,
    /// The scale \[m\] of the distance between the robot's contact point and the material point
    /// of the pushed part it touched when the push began, as a term of the pushed part's
    /// registration ([`registration::Hand`], `Tracker::update`); 0: off, the default. Why: the
    /// hand moves with what it pushes, and the robot's kinematics know where it is, while a small
    /// part (a hatch in a door) or one seen edge-on registers with cm-scale lag along the
    /// directions its visible surface leaves loose (`tune`'s `obj045` hatch: 86 mm behind the
    /// hand; with the hand at 5 mm, 15 mm). The hand does not enter the registration's
    /// information, so perception's reported covariance does not claim the hand's precision.
    /// Measured at 0.005 with `model.contact_sd_m` 0.005: it helps `tune` at every seed and
    /// costs `validation` calls, so it is off (README "Generalization", stop 96); alone, it gains
    /// nothing clear on `tune` and costs `validation` calls too (stop 97): its anchor, one
    /// frame's pose of the touched part, can be a centimetre off on a thin part.
    pub hand_sd_m: f64,
}

impl Default for PerceptionConfig {
    fn default() -> Self {
        PerceptionConfig {
            min_points: 8,
            max_points: 400,
            min_seen_fraction: 0.0,
            min_thickness_m: 0.005,
            hull_outlier_neighbours: 0,
            com_sd_floor_m: 0.003,
            rotation_sd_floor_rad: 0.02,
            orientation_min_ratio: 1.3,
            orientation_min_information: 0.1,
            registration_cov_scale: 4.0,
            voxel_m: 0.008,
            smoothing_radius_m: 0.0,
            point_sd_min_m: 0.0005,
            point_sd_max_m: 0.02,
            point_to_point_weight: 0.3,
            point_to_point_ratio: 3.3,
            match_gate_m: 0.1,
            fine_gate_m: 0.02,
            icp_iterations: 20,
            boundary_m: 0.02,
            boundary_weight: 0.0,
            edge_weight: 0.0,
            confirm_frames: 3,
            initial_frames: 10,
            max_model_points: 6000,
            contact_range_m: 0.015,
            move_penalty_nats: 8.0,
            reference_penalty_nats: 0.0,
            refine_penalty_nats: 2.0,
            push_move_penalty_nats: 8.0,
            carrier_starts: false,
            hand_sd_m: 0.0,
        }
    }
}

/// One part seen in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PartObservation {
    /// Header stamp \[s\].
    pub stamp: f64,
    /// Rigid motion of the part from its reference configuration to this frame (fixed frame).
    pub pose: Isometry3<f64>,
    /// The part's anchor (the centroid of its first observed points) moved by `pose` \[m\], fixed
    /// frame: a material point of the part, for measuring its speed.
    pub com: Point3<f64>,
    /// Covariance of `pose` as of a small increment `(w, u)` in the reference configuration
    /// (`y -> y + w x y + u`; rad², m²), floors included.
    pub pose_cov: Matrix6<f64>,
    /// The registration's share of `pose_cov`, without the floors: what this frame's points
    /// say (zero for the reference frame). The model's likelihood of positions adds its own
    /// inferred noise to this instead of the floors ([`crate::model::likelihood::Evidence::new`]).
    pub registration_cov: Matrix6<f64>,
    /// Fraction of the points matched to the part's model.
    pub matched: f64,
    /// Points used.
    pub points: usize,
    /// Points dropped as strays (first frame) or beyond the subsample.
    pub outliers: usize,
}

/// Per-part observation tracks, by label, in time order.
pub type PartTracks = BTreeMap<u32, Vec<PartObservation>>;

/// Geometry of one part in its reference configuration (fixed frame).
#[derive(Debug, Clone, PartialEq)]
pub struct PartGeometry {
    /// Centre of mass \[m\]: the convex-hull centroid of the model (without its isolated points
    /// when `hull_outlier_neighbours` > 0), or its mean when flat.
    pub com: Vector3<f64>,
    /// Rotational inertia about `com` per kilogram (m²), fixed-frame axes.
    pub unit_inertia: Matrix3<f64>,
    /// Hull volume (m³), 0 for flat or tiny models.
    pub volume: f64,
    /// Unit rotation axes whose rotations the shape makes observable (0 to 3 principal axes).
    pub rotation_axes: Vec<Vector3<f64>>,
    /// Root-mean-square distance of the model points from `com` \[m\].
    pub radius: f64,
    /// Model surface points \[m\] (for distances between parts).
    pub points: Vec<Vector3<f64>>,
    /// Mean of the model points \[m\]: the centre of the seen surface, where the weight of a
    /// thin part (a door, lid or flap) acts. The hull centroid `com` is the centre of a solid
    /// filling the hull, which a few stray points far off a panel turn into a wedge (on the
    /// effects corpus's `tune` split, revolute parts' hull centroids lie a median 0.14 m from
    /// the centroid of their first clouds, up to 0.34 m along the panel's normal, where the
    /// model points' mean lies within 0.015 m of its plane on all but one: README, issue 25,
    /// stop 117).
    pub centroid: Vector3<f64>,
}

#[derive(Debug)]
struct PartState {
    tracker: Tracker,
    anchor: Vector3<f64>,
    /// The registered frames' points and weights, by stamp, with the hand on the part if any,
    /// for [`Perception::refine`].
    frames: Vec<KeptFrame>,
    /// The most points (before the subsample) seen of the part in one frame.
    most_seen: usize,
    /// The part's registered poses (reference -> fixed frame) by stamp \[s\], oldest first
    /// (its first frame at the identity), for the other parts' [`carrier_starts`]; as many as
    /// `frames` keeps where a frame limit bounds it.
    history: Vec<(f64, Isometry3<f64>)>,
    /// Stamp of the last registered frame with a push on the part \[s\] (`None`: without one).
    last_push: Option<f64>,
}

/// One registered frame of a part kept for [`Perception::refine`]: stamp \[s\], points \[m\]
/// (fixed frame), their weights, and the hand on the part in that frame, if any.
type KeptFrame = (f64, Vec<Vector3<f64>>, Vec<f64>, Option<registration::Hand>);

/// Neighbours of a model point that give its normal in [`geometry::rotation_information`].
const NORMAL_NEIGHBOURS: usize = 10;

/// A part registered again more than this long after its last pushed frame \[s\] starts a new
/// touch ([`PerceptionConfig::hand_sd_m`]): the push it was touched in has ended out of view.
const HAND_GAP_S: f64 = 0.5;

/// Stateful perception: one tracker per part label.
#[derive(Debug, Default)]
pub struct Perception {
    pub config: PerceptionConfig,
    parts: BTreeMap<u32, PartState>,
    /// Registered frames kept per part for [`Perception::refine`] (`None`: all, for replay).
    frame_limit: Option<usize>,
}

impl Perception {
    pub fn new(config: PerceptionConfig) -> Self {
        Perception { config, parts: BTreeMap::new(), frame_limit: None }
    }

    /// Keep only the newest `n` registered frames per part for [`Perception::refine`], so that a
    /// live node's memory stays bounded; older frames keep the poses they were given.
    pub fn with_frame_limit(mut self, n: usize) -> Self {
        self.frame_limit = Some(n);
        self
    }

    /// Observe every part of one cloud; parts with fewer than `min_points` points, or whose points
    /// match neither their model nor any pose, are not reported for this frame.
    pub fn observe(&mut self, cloud: &CloudFrame, push: Option<&Push>) -> Vec<(u32, PartObservation)> {
        let mut parts = split_parts(cloud, &self.config);
        mark_pushed(&mut parts, cloud, push, &self.config);
        self.observe_split(cloud.stamp, parts)
    }

    /// Register the parts of one cloud (split by [`split_parts`]). Without
    /// [`carrier_starts`](PerceptionConfig::carrier_starts) each part alone; with it, the parts
    /// from the largest model to the smallest, each also started from its pose moved with every
    /// larger part as that part moved since the part's own last registration, this cloud's
    /// registration of the larger part included ([`carrier_starts`]).
    fn observe_split(&mut self, stamp: f64, mut parts: Vec<SplitPart>) -> Vec<(u32, PartObservation)> {
        let cfg = &self.config;
        let mut extents = BTreeMap::new();
        if cfg.carrier_starts {
            extents = self.parts.iter().map(|(l, s)| (*l, s.tracker.model.extent())).collect();
            // Larger first (a stable sort: labels break ties), parts new in this cloud last.
            parts.sort_by(|a, b| {
                let (ea, eb) = (extents.get(&a.label).copied().unwrap_or(0.0), extents.get(&b.label).copied().unwrap_or(0.0));
                eb.total_cmp(&ea)
            });
        }
        let mut out = Vec::new();
        for part in parts {
            let label = part.label;
            let starts = carrier_starts(&self.parts, &extents, label, stamp, cfg);
            let state = self.parts.remove(&label);
            let (state, obs) = observe_part(state, stamp, part, &starts, cfg, self.frame_limit);
            self.parts.insert(label, state);
            out.extend(obs.map(|o| (label, o)));
        }
        out.sort_by_key(|(l, _)| *l);
        out
    }

    /// Observe a whole recording, then [`refine`](Self::refine) the poses: the same tracks as
    /// [`observe`](Self::observe) on every cloud in turn, computed with the clouds split by part
    /// in parallel, then every part's tracker run over its frames on a thread of its own (the
    /// trackers are independent given the split) or, with
    /// [`carrier_starts`](PerceptionConfig::carrier_starts), the parts registered cloud after
    /// cloud (a part's starts read the larger parts' registrations of the same cloud).
    pub fn observe_all(&mut self, clouds: &[CloudFrame], pushes: &[Option<Push>]) -> PartTracks {
        let split: Vec<Vec<SplitPart>> = {
            let cfg = &self.config;
            parallel::map(parallel::resolve_threads(0), clouds.len(), |j| {
                let mut parts = split_parts(&clouds[j], cfg);
                mark_pushed(&mut parts, &clouds[j], pushes.get(j).and_then(|c| c.as_ref()), cfg);
                parts
            })
        };
        let mut tracks = PartTracks::new();
        if self.config.carrier_starts {
            for (c, parts) in clouds.iter().zip(split) {
                for (label, o) in self.observe_split(c.stamp, parts) {
                    tracks.entry(label).or_default().push(o);
                }
            }
            self.refine(&mut tracks);
            return tracks;
        }
        let cfg = &self.config;
        // Every part's frames in time order.
        let mut per_part: BTreeMap<u32, Vec<(f64, SplitPart)>> = BTreeMap::new();
        for (c, parts) in clouds.iter().zip(split) {
            for part in parts {
                per_part.entry(part.label).or_default().push((c.stamp, part));
            }
        }
        let limit = self.frame_limit;
        let owned: Vec<_> = per_part.into_iter().map(|(label, frames)| (label, self.parts.remove(&label), frames)).collect();
        let tracked: Vec<_> = std::thread::scope(|sc| {
            let jobs: Vec<_> = owned
                .into_iter()
                .map(|(label, mut state, frames)| {
                    sc.spawn(move || {
                        let mut track = Vec::new();
                        for (stamp, part) in frames {
                            let (s, obs) = observe_part(state.take(), stamp, part, &[], cfg, limit);
                            state = Some(s);
                            track.extend(obs);
                        }
                        (label, state, track)
                    })
                })
                .collect();
            jobs.into_iter().map(|j| j.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect()
        });
        for (label, state, track) in tracked {
            if let Some(state) = state {
                self.parts.insert(label, state);
            }
            if !track.is_empty() {
                tracks.insert(label, track);
            }
        }
        self.refine(&mut tracks);
        tracks
    }

    /// Register every frame of `tracks` again against the part models as they are now. A frame
    /// registered early met a model that still lacked the surfaces seen later (a door's far edge,
    /// a cabinet's inside); the complete model removes the bias that left, which a
    /// track's later frames do not have. A pose moves only where that explains the points better
    /// by more than `refine_penalty_nats`. Parts are refined in parallel (independent).
    pub fn refine(&self, tracks: &mut PartTracks) {
        std::thread::scope(|sc| {
            for (label, obs) in tracks.iter_mut() {
                let Some(state) = self.parts.get(label) else { continue };
                let cfg = &self.config;
                sc.spawn(move || refine_part(state, obs, cfg));
            }
        });
        // The registered tracks, one line a frame (`BOM_LOG=bom::perception=trace`): what the
        // likelihood is given, to be checked against a recorder's true joint positions.
        if tracing::enabled!(tracing::Level::TRACE) {
            for (label, obs) in tracks.iter() {
                let Some(state) = self.parts.get(label) else { continue };
                for o in obs {
                    let (axis, angle) = o.pose.rotation.axis_angle().map_or((Vector3::x(), 0.0), |(a, t)| (a.into_inner(), t));
                    let shift = o.com.coords - state.anchor;
                    tracing::trace!(
                        "part {label} at {:.3} s: rotation {angle:.4} rad about [{:.3}, {:.3}, {:.3}], anchor moved [{:.4}, {:.4}, {:.4}] m, {} points, {:.2} matched",
                        o.stamp, axis.x, axis.y, axis.z, shift.x, shift.y, shift.z, o.points, o.matched
                    );
                }
            }
        }
    }

    /// Geometry of every part seen so far, from its current model.
    pub fn geometry(&self) -> BTreeMap<u32, PartGeometry> {
        self.parts.iter().map(|(l, s)| (*l, part_geometry(&s.tracker.model.points, &self.config))).collect()
    }
}

/// One part's points in one cloud, subsampled, with their weights (`boundary_weight` near
/// another part's points).
struct SplitPart {
    label: u32,
    points: Vec<Vector3<f64>>,
    weights: Vec<f64>,
    /// Points dropped beyond the subsample.
    dropped: usize,
    /// The push acting on this part in this frame, if any ([`PushGate`]).
    push: Option<Push>,
}

/// Split a cloud by part label (label 0 is not in `cloud`), subsample each part to `max_points`
/// and weigh points near another part ([`outline_weight`]); parts with fewer than `min_points`
/// points are left out.
fn split_parts(cloud: &CloudFrame, cfg: &PerceptionConfig) -> Vec<SplitPart> {
    let mut by_label: BTreeMap<u32, Vec<Vector3<f64>>> = BTreeMap::new();
    for (p, l) in cloud.points.iter().zip(&cloud.labels) {
        by_label.entry(*l).or_default().push(p.coords);
    }
    let mut dropped: BTreeMap<u32, usize> = BTreeMap::new();
    for (l, pts) in by_label.iter_mut() {
        if pts.len() > cfg.max_points {
            let n = pts.len();
            *pts = (0..cfg.max_points).map(|i| pts[i * n / cfg.max_points]).collect();
            dropped.insert(*l, n - cfg.max_points);
        }
    }
    // Points of every part in one tree (items index `flat`), to find points near another part.
    let mut all: KdTree<f64, 3> = KdTree::new();
    let mut flat: Vec<(Vector3<f64>, u32)> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for (l, pts) in &by_label {
        for p in pts {
            // Exact duplicates add nothing and a k-d tree bucket holds few of them.
            if seen.insert((p.x.to_bits(), p.y.to_bits(), p.z.to_bits())) {
                all.add(&[p.x, p.y, p.z], flat.len() as u64);
                flat.push((*p, *l));
            }
        }
    }
    let viewpoint = cloud.viewpoint.map(|v| v.coords).filter(|_| cfg.edge_weight > 0.0);
    let r2 = cfg.boundary_m * cfg.boundary_m;
    by_label
        .into_iter()
        .filter(|(_, pts)| pts.len() >= cfg.min_points)
        .map(|(label, points)| {
            // With a viewpoint, the part's own points in a tree of their own, for its local surface.
            let seen_from = viewpoint.map(|v| {
                let mut own: KdTree<f64, 3> = KdTree::new();
                for (i, p) in points.iter().enumerate() {
                    own.add(&[p.x, p.y, p.z], i as u64);
                }
                (v, own)
            });
            let weights = points
                .iter()
                .map(|p| {
                    let near = all.within_unsorted::<SquaredEuclidean>(&[p.x, p.y, p.z], r2);
                    let others: Vec<Vector3<f64>> = near.iter().map(|n| flat[n.item as usize]).filter(|(_, l)| *l != label).map(|(q, _)| q).collect();
                    match &seen_from {
                        _ if others.is_empty() => 1.0,
                        Some((v, own)) => outline_weight(p, &others, &points, own, v, cfg),
                        None => cfg.boundary_weight,
                    }
                })
                .collect();
            SplitPart { label, points, weights, dropped: dropped.get(&label).copied().unwrap_or(0), push: None }
        })
        .collect()
}

/// Neighbours of a point on its own part that give the part's local surface.
const OUTLINE_NEIGHBOURS: usize = 8;

/// Weight of point `p` of a part whose neighbourhood (within `boundary_m`) holds the points
/// `others` of other parts, seen from `viewpoint` (fixed frame): `edge_weight` if `p` lies on
/// its own part's outline, else `boundary_weight`.
///
/// Where two parts meet in a depth image, the nearer surface's boundary is its own edge (an
/// occluding contour) and the farther one's is only where the nearer one starts to hide it (an
/// occluded contour), which moves with the occluder, not with the part. So `p` counts as its
/// part's outline when it lies on its part's local surface (the plane of its
/// `OUTLINE_NEIGHBOURS` nearest points, normal turned to the viewpoint) and no point of another
/// part near it lies in front of that surface; both within three times the neighbourhood's own
/// scatter about its plane (the depth noise, at least one voxel). A flat panel is located in its
/// own plane by nothing but that outline; points where segmentation swaps labels along a
/// boundary lie on one of the two surfaces, flush or behind, and are not taken for occluders.
fn outline_weight(p: &Vector3<f64>, others: &[Vector3<f64>], points: &[Vector3<f64>], own: &KdTree<f64, 3>, viewpoint: &Vector3<f64>, cfg: &PerceptionConfig) -> f64 {
    let nb: Vec<Vector3<f64>> = own.nearest_n::<SquaredEuclidean>(&[p.x, p.y, p.z], OUTLINE_NEIGHBOURS).iter().map(|n| points[n.item as usize]).collect();
    if nb.len() < 5 {
        return cfg.boundary_weight;
    }
    let (n, _) = geometry::normal_of(&nb);
    let mean = nb.iter().sum::<Vector3<f64>>() / nb.len() as f64;
    let n = if n.dot(&(viewpoint - mean)) < 0.0 { -n } else { n };
    // Scatter about the plane, three of its parameters fitted.
    let scatter = (nb.iter().map(|x| n.dot(&(x - mean)).powi(2)).sum::<f64>() / (nb.len() - 3) as f64).sqrt();
    let tol = (3.0 * scatter).max(cfg.voxel_m);
    let on_surface = n.dot(&(p - mean)).abs() <= tol;
    let hidden = others.iter().any(|q| n.dot(&(q - mean)) > tol);
    if on_surface && !hidden { cfg.edge_weight } else { cfg.boundary_weight }
}

/// Observe one part in one frame: a part seen for the first time gets its tracker (its inlier
/// points away from other parts are its first model, and the frame its reference); otherwise
/// its tracker registers the points. Returns the part's state and the observation, if any.
fn observe_part(
    state: Option<PartState>,
    stamp: f64,
    part: SplitPart,
    starts: &[Isometry3<f64>],
    cfg: &PerceptionConfig,
    frame_limit: Option<usize>,
) -> (PartState, Option<PartObservation>) {
    let SplitPart { points: pts, weights, dropped, push, .. } = part;
    let Some(mut state) = state else {
        let pts3: Vec<Point3<f64>> = pts.iter().map(|p| Point3::from(*p)).collect();
        let keep = geometry::inliers(&pts3);
        let clean: Vec<Vector3<f64>> = keep.iter().filter(|&&i| weights[i] >= 1.0).map(|&i| pts[i]).collect();
        let clean = if clean.len() >= cfg.min_points { clean } else { keep.iter().map(|&i| pts[i]).collect() };
        let anchor = clean.iter().sum::<Vector3<f64>>() / clean.len().max(1) as f64;
        let tracker = Tracker::new(&clean, cfg);
        let obs = observation(stamp, Isometry3::identity(), None, anchor, cfg, clean.len(), pts.len() - clean.len() + dropped, 1.0);
        let history = vec![(stamp, Isometry3::identity())];
        return (PartState { tracker, anchor, frames: Vec::new(), most_seen: pts.len() + dropped, history, last_push: None }, Some(obs));
    };
    let seen = pts.len() + dropped;
    state.most_seen = state.most_seen.max(seen);
    // A sliver of a part (a panel turning edge-on, a hatch sliding out of view) constrains its
    // pose in too few directions: registered, it slides or turns along the free ones, and the
    // points it then adds to the model make the wrong pose fit later frames too.
    if (seen as f64) < cfg.min_seen_fraction * state.most_seen as f64 {
        tracing::trace!("a part at {stamp:.3} s shows {seen} of its most seen {} points: not registered (perception.min_seen_fraction)", state.most_seen);
        return (state, None);
    }
    // A push that ended while the part was out of view: the next one touches anew.
    if state.last_push.is_some_and(|s| stamp - s > HAND_GAP_S) {
        state.tracker.touch = None;
    }
    let Some(reg) = state.tracker.update(&FramePoints { points: &pts, weights: &weights, hand: None }, push.as_ref(), starts, cfg) else { return (state, None) };
    let obs = observation(stamp, reg.pose, Some(&reg.information), state.anchor, cfg, pts.len(), dropped, reg.matched);
    state.last_push = push.map(|_| stamp);
    state.frames.push((stamp, pts, weights, reg.hand));
    if cfg.carrier_starts {
        state.history.push((stamp, reg.pose));
    }
    if let Some(n) = frame_limit {
        if state.frames.len() > n {
            let excess = state.frames.len() - n;
            state.frames.drain(..excess);
        }
        if state.history.len() > n {
            let excess = state.history.len() - n;
            state.history.drain(..excess);
        }
    }
    (state, Some(obs))
}

/// ICP starts for part `label` from the motion of every larger part (the carrier hypotheses of
/// [`PerceptionConfig::carrier_starts`]; a part rides a part larger than itself: a hatch or a
/// latch its door, a box its drawer). For a part `j` whose model is larger (`extents`: the
/// models' bounding-box diagonals before this cloud) and which is registered in this cloud (at
/// `stamp`), with poses `T_j(s)` (reference -> fixed frame), the part's last pose `T_p` at stamp
/// `t` moved as `j` moved since then: `T_j(stamp) T_j(t)⁻¹ T_p`, where `T_j(t)` is `j`'s pose at
/// or before `t`. A carrier not registered in this cloud says nothing about now and gives no
/// start; nor does one that moved the part's anchor by less than 1 mm and turned it by less
/// than 1 mrad (the tracker's own start). Empty when the option is off or the part is new.
fn carrier_starts(parts: &BTreeMap<u32, PartState>, extents: &BTreeMap<u32, f64>, label: u32, stamp: f64, cfg: &PerceptionConfig) -> Vec<Isometry3<f64>> {
    let mut out = Vec::new();
    if !cfg.carrier_starts {
        return out;
    }
    let Some(me) = parts.get(&label) else { return out };
    let Some(&(t, pose)) = me.history.last() else { return out };
    let mine = extents.get(&label).copied().unwrap_or(0.0);
    for (j, other) in parts {
        if *j == label || extents.get(j).is_none_or(|e| *e <= mine) {
            continue;
        }
        let h = &other.history;
        let Some(&(s_now, now)) = h.last() else { continue };
        if s_now != stamp {
            continue;
        }
        let k = h.partition_point(|(s, _)| *s <= t);
        let Some(&(_, then)) = k.checked_sub(1).map(|k| &h[k]) else { continue };
        let start = now * then.inverse() * pose;
        let anchor = Point3::from(me.anchor);
        let moved = (start * anchor - pose * anchor).norm();
        let turned = (start.rotation * pose.rotation.inverse()).angle();
        if moved >= 1e-3 || turned >= 1e-3 {
            out.push(start);
        }
    }
    out
}

/// [`Perception::refine`] of one part's track.
fn refine_part(state: &PartState, obs: &mut [PartObservation], cfg: &PerceptionConfig) {
    let mut frames = state.frames.iter().peekable();
    for o in obs.iter_mut() {
        while frames.peek().is_some_and(|f| f.0 < o.stamp) {
            frames.next();
        }
        let Some((_, pts, w, hand)) = frames.peek().filter(|f| f.0 == o.stamp) else { continue };
        if let Some(reg) = state.tracker.refine(&FramePoints { points: pts, weights: w, hand: *hand }, &o.pose, cfg) {
            *o = observation(o.stamp, reg.pose, Some(&reg.information), state.anchor, cfg, o.points, o.outliers, reg.matched);
        }
    }
}

/// The observation of a registered frame, its pose covariance from the registration's
/// Gauss-Newton matrix (`None`: the reference frame itself, known up to the floors).
#[allow(clippy::too_many_arguments)]
fn observation(
    stamp: f64,
    pose: Isometry3<f64>,
    information: Option<&Matrix6<f64>>,
    anchor: Vector3<f64>,
    cfg: &PerceptionConfig,
    points: usize,
    outliers: usize,
    matched: f64,
) -> PartObservation {
    let (fr, fp) = (cfg.rotation_sd_floor_rad.powi(2), cfg.com_sd_floor_m.powi(2));
    // The floors describe a rotation about the part's anchor and a shift of it: in the pose's
    // (rotation about the origin, translation) coordinates that rotation also moves the origin by
    // `anchor x w`. Floored about the origin instead, the rotation floor would turn into a
    // position sd of `floor * |anchor|` (1 cm for a part 0.5 m from the fixed frame's origin),
    // hiding small motions of parts far from the origin.
    let mut lever = Matrix6::<f64>::identity();
    lever.fixed_view_mut::<3, 3>(3, 0).copy_from(&registration::skew(&anchor));
    let mut pose_cov = lever * Matrix6::from_diagonal(&nalgebra::Vector6::new(fr, fr, fr, fp, fp, fp)) * lever.transpose();
    let mut registration_cov = Matrix6::zeros();
    if let Some(a) = information {
        // Regularised inverse: an unconstrained direction gets a large but finite variance.
        let reg = a + Matrix6::identity() * (1e-9 * a.trace().max(1e-12) + 1.0);
        registration_cov = reg.try_inverse().unwrap_or_else(Matrix6::identity) * cfg.registration_cov_scale;
        pose_cov += registration_cov;
    }
    PartObservation { stamp, pose, com: pose * Point3::from(anchor), pose_cov, registration_cov, matched, points, outliers }
}

impl PartObservation {
    /// Covariance \[m²\] (fixed frame) of the position of the material point `c` (reference
    /// configuration): a small increment `(w, u)` moves it by `R (c x w - u)`.
    pub fn position_cov(&self, c: &Vector3<f64>) -> Matrix3<f64> {
        self.position_cov_of(&self.pose_cov, c)
    }

    /// Covariance \[rad²\] of the rotation vector of the rotation error, fixed frame.
    pub fn rotation_cov(&self) -> Matrix3<f64> {
        let r = self.pose.rotation.to_rotation_matrix().into_inner();
        r * self.pose_cov.fixed_view::<3, 3>(0, 0).into_owned() * r.transpose()
    }

    /// [`Self::position_cov`] of the registration alone (no floors).
    pub fn registration_position_cov(&self, c: &Vector3<f64>) -> Matrix3<f64> {
        self.position_cov_of(&self.registration_cov, c)
    }

    fn position_cov_of(&self, cov: &Matrix6<f64>, c: &Vector3<f64>) -> Matrix3<f64> {
        let r = self.pose.rotation.to_rotation_matrix().into_inner();
        let mut j = Matrix3x6::<f64>::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&registration::skew(c));
        j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-Matrix3::identity()));
        r * (j * cov * j.transpose()) * r.transpose()
    }
}

/// Geometry of a part's model (see [`PartGeometry`]).
pub fn part_geometry(points: &[Vector3<f64>], cfg: &PerceptionConfig) -> PartGeometry {
    let p3: Vec<Point3<f64>> = points.iter().map(|p| Point3::from(*p)).collect();
    let pr = geometry::principal(&p3);
    let mass_properties = |pts: &[Point3<f64>]| match geometry::hull_properties(pts, cfg.min_thickness_m) {
        Some(h) => (h.centroid, h.unit_inertia, h.volume),
        None => {
            // A thin shell: the inertia of the points themselves, tr(C) I - C per kilogram.
            let pr = geometry::principal(pts);
            let c = pr.axes * Matrix3::from_diagonal(&Vector3::from(pr.variances)) * pr.axes.transpose();
            (pr.mean, Matrix3::identity() * c.trace() - c, 0.0)
        }
    };
    let keep = geometry::isolated_free(&p3, cfg.hull_outlier_neighbours);
    let (com, unit_inertia, volume) =
        if keep.len() == p3.len() { mass_properties(&p3) } else { mass_properties(&keep.iter().map(|&i| p3[i]).collect::<Vec<_>>()) };
    let v = pr.variances;
    let r = cfg.orientation_min_ratio;
    // Rotation about principal axis k is observable if the spreads along the other two differ.
    let observable = [v[1] > r * v[2], v[0] > r * v[2], v[0] > r * v[1]];
    let mut rotation_axes: Vec<Vector3<f64>> = (0..3).filter(|&k| observable[k] && v[2] >= 0.0).map(|k| pr.axes.column(k).into_owned()).collect();
    let mean_r2 = points.iter().map(|p| (p - com).norm_squared()).sum::<f64>() / points.len().max(1) as f64;
    // The surfaces' own say: the eigen-axes of the point-to-plane information about rotations
    // that hold at least `orientation_min_information` of the mean squared radius. Where they
    // are more axes than the spreads give, they replace them (stop 105: a near-square slab's spin,
    // pinned by its top and side faces, while a sphere pins nothing).
    if cfg.orientation_min_information > 0.0 && v[2] >= 0.0 {
        let e = geometry::rotation_information(points, &com, NORMAL_NEIGHBOURS).symmetric_eigen();
        if mean_r2 > 0.0 {
            let axes: Vec<Vector3<f64>> =
                (0..3).filter(|&k| e.eigenvalues[k] >= cfg.orientation_min_information * mean_r2).map(|k| e.eigenvectors.column(k).into_owned()).collect();
            if axes.len() > rotation_axes.len() {
                rotation_axes = axes;
            }
        }
    }
    let radius = mean_r2.sqrt();
    let centroid = if points.is_empty() { com } else { points.iter().sum::<Vector3<f64>>() / points.len() as f64 };
    PartGeometry { com, unit_inertia, volume, rotation_axes, radius, points: points.to_vec(), centroid }
}

/// Give the push (if one acts) to the part of `cloud` nearest its contact point; nothing while
/// both its users are off (the push prior, `push_move_penalty_nats` not below
/// `move_penalty_nats`, and the hand, `hand_sd_m` 0), so that they cost no search.
fn mark_pushed(parts: &mut [SplitPart], cloud: &CloudFrame, push: Option<&Push>, cfg: &PerceptionConfig) {
    let Some(push) = push.filter(|_| cfg.push_move_penalty_nats < cfg.move_penalty_nats || cfg.hand_sd_m > 0.0) else { return };
    let Some((label, d)) = nearest_part(cloud, &push.point) else { return };
    if tracing::enabled!(tracing::Level::TRACE) {
        // The runner-up part's distance: how sure this cloud's attribution is.
        let second = cloud.points.iter().zip(&cloud.labels).filter(|(_, l)| **l != label).map(|(p, _)| (p - push.point).norm()).fold(f64::INFINITY, f64::min);
        tracing::trace!("push at {:.3} s goes to part {label}: contact {:.1} mm from it, {:.1} mm from the next part", cloud.stamp, d * 1e3, second * 1e3);
    }
    for part in parts.iter_mut().filter(|p| p.label == label) {
        part.push = Some(*push);
    }
}

/// The applied wrench at a cloud, as the tracker's motion prior uses it
/// ([`PerceptionConfig::push_move_penalty_nats`]): the contact point \[m\] and force \[N\],
/// fixed frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Push {
    pub point: Point3<f64>,
    pub force: Vector3<f64>,
}

/// When a cloud is pushed: its stamp's last wrench sample (at or before it, as a node has the
/// samples when the cloud arrives) is at most `max_age_s` old and its force is above `force_n`
/// \[N\]; that sample's contact point goes to the part of the cloud nearest it (contract section
/// 1's rule for the pushed part, applied to the one cloud).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PushGate {
    pub force_n: f64,
    pub max_age_s: f64,
}

impl PushGate {
    /// The push acting at `t`, from `wrenches` in time order.
    pub fn push(&self, wrenches: &[WrenchSample], t: f64) -> Option<Push> {
        let end = wrenches.partition_point(|w| w.stamp <= t);
        let w = wrenches[..end].last()?;
        (t - w.stamp <= self.max_age_s && w.force.norm() > self.force_n).then_some(Push { point: w.point, force: w.force })
    }
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

/// The pushed part of one push, from every cloud seen while it lasts (contract section 1: "the
/// pushed part is the one whose points lie nearest to the contact point").
///
/// The contact point stays on the pushed part's surface for the whole push, while the hand that
/// pushes hides that part from the camera in some clouds — often in the one nearest the push's
/// first sample, where a single cloud then names a neighbour (`obj006` of the effects corpus: a
/// flap's push given to the drawer below it, whose nearest point was 21 cm from the contact).
/// So each cloud of the push gives every part seen in it the distance \[m\] from the contact
/// point at that cloud's stamp to the part's nearest point, and the part with the smallest
/// median of those distances, over the clouds it is seen in, is the pushed one (ties: the part
/// seen in more clouds, then the lower label).
///
/// At most [`ContactVotes::MAX_CLOUDS`] clouds are kept (a push held that long has long named
/// its part); later ones are ignored.
#[derive(Debug, Clone, Default)]
pub struct ContactVotes {
    /// Label -> the nearest point's distance \[m\] in each cloud the part is seen in.
    distances: BTreeMap<u32, Vec<f64>>,
    clouds: usize,
}

impl ContactVotes {
    /// Clouds kept per push (about 8 s of a 30 Hz camera).
    pub const MAX_CLOUDS: usize = 256;

    /// Add `cloud` with the contact point `point` \[m, fixed frame\] at its stamp. Non-finite
    /// distances (a NaN point that got through) are skipped.
    pub fn add(&mut self, cloud: &CloudFrame, point: &Point3<f64>) {
        if self.clouds >= Self::MAX_CLOUDS {
            return;
        }
        let mut nearest: BTreeMap<u32, f64> = BTreeMap::new();
        for (p, l) in cloud.points.iter().zip(&cloud.labels) {
            let d = (p - point).norm();
            if d.is_finite() {
                let e = nearest.entry(*l).or_insert(f64::INFINITY);
                *e = e.min(d);
            }
        }
        if nearest.is_empty() {
            return;
        }
        self.clouds += 1;
        for (l, d) in nearest {
            self.distances.entry(l).or_default().push(d);
        }
    }

    /// Clouds added.
    pub fn clouds(&self) -> usize {
        self.clouds
    }

    /// The pushed part: the smallest median distance (`None` before any cloud).
    pub fn part(&self) -> Option<u32> {
        let median = |v: &[f64]| {
            let mut s = v.to_vec();
            s.sort_by(f64::total_cmp);
            let n = s.len();
            if n % 2 == 1 { s[n / 2] } else { 0.5 * (s[n / 2 - 1] + s[n / 2]) }
        };
        self.distances
            .iter()
            .map(|(l, v)| (*l, median(v), v.len()))
            .min_by(|a, b| a.1.total_cmp(&b.1).then(b.2.cmp(&a.2)).then(a.0.cmp(&b.0)))
            .map(|(l, _, _)| l)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The push gate: a cloud is pushed while its stamp's last wrench sample (never a later one:
    /// a node does not have it yet) is recent and above the force threshold, at that sample's
    /// contact point.
    #[test]
    fn a_push_acts_while_the_last_sample_is_strong() {
        let w = |t: f64, f: f64, x: f64| WrenchSample { stamp: t, point: Point3::new(x, 0.0, 0.0), force: Vector3::new(0.0, f, 0.0), torque: Vector3::zeros() };
        // Light contact, a push of 2 N from 1.0 to 2.0 s moving along x, released, a later push.
        let mut ws: Vec<WrenchSample> = (0..10).map(|k| w(0.5 + 0.05 * k as f64, 0.3, 0.0)).collect();
        ws.extend((0..=100).map(|k| w(1.0 + 0.01 * k as f64, 2.0, 0.001 * k as f64)));
        ws.extend((1..=30).map(|k| w(2.0 + 0.05 * k as f64, 0.0, 0.1)));
        ws.push(w(5.0, 3.0, 0.7));
        let gate = PushGate { force_n: 0.5, max_age_s: 0.3 };
        let at = |t: f64| gate.push(&ws, t).map(|p| p.point.x);
        assert_eq!(at(0.9), None, "a light touch is no push");
        assert_eq!(at(1.0), Some(0.0));
        let mid = at(1.505).expect("pushing");
        assert!((mid - 0.05).abs() < 1e-9, "the last sample at or before the cloud: {mid}");
        assert_eq!(gate.push(&ws, 1.5).map(|p| p.force), Some(Vector3::new(0.0, 2.0, 0.0)));
        assert_eq!(at(2.03), Some(0.1), "the last sample, 2.0 s, still pushes");
        assert_eq!(at(2.06), None, "released");
        assert_eq!(at(4.99), None, "the next push has not been received");
        assert_eq!(at(5.0), Some(0.7));
        assert_eq!(at(5.31), None, "the stream stopped: its last sample is stale");
        assert_eq!(gate.push(&[], 1.0), None);
    }

    /// Only the part nearest the push's contact point gets the push, so only its tracker uses the
    /// push's motion prior.
    #[test]
    fn the_part_at_the_contact_point_is_the_pushed_one() {
        let cloud = CloudFrame {
            stamp: 1.0,
            points: vec![Point3::new(0.0, 0.0, 0.0), Point3::new(0.01, 0.0, 0.0), Point3::new(0.5, 0.0, 0.0), Point3::new(0.51, 0.0, 0.0)],
            labels: vec![1, 1, 2, 2],
            viewpoint: None,
        };
        let cfg = PerceptionConfig { min_points: 1, push_move_penalty_nats: 4.0, ..PerceptionConfig::default() };
        let mut parts = split_parts(&cloud, &cfg);
        let push = Push { point: Point3::new(0.48, 0.0, 0.0), force: Vector3::new(-1.0, 0.0, 0.0) };
        mark_pushed(&mut parts, &cloud, Some(&push), &cfg);
        let pushed: Vec<(u32, bool)> = parts.iter().map(|p| (p.label, p.push.is_some())).collect();
        assert_eq!(pushed, [(1, false), (2, true)]);
        for (push, cfg) in [(None, cfg.clone()), (Some(&push), PerceptionConfig { min_points: 1, hand_sd_m: 0.0, ..PerceptionConfig::default() })] {
            let mut parts = split_parts(&cloud, &cfg);
            mark_pushed(&mut parts, &cloud, push, &cfg);
            assert!(parts.iter().all(|p| p.push.is_none()), "no push, or both the prior and the hand off");
        }
        // The hand in the registration needs the push too, the prior off or not.
        let cfg = PerceptionConfig { min_points: 1, hand_sd_m: 0.005, ..PerceptionConfig::default() };
        let mut parts = split_parts(&cloud, &cfg);
        mark_pushed(&mut parts, &cloud, Some(&push), &cfg);
        assert_eq!(parts.iter().map(|p| (p.label, p.push.is_some())).collect::<Vec<_>>(), [(1, false), (2, true)]);
    }

    /// A hatch (label 3) in a door (label 2) is hidden while the door turns by 1 rad about its
    /// hinge, then seen again, first as a sliver (two rows of its points, five clouds), then
    /// whole. Its own tracker starts from where it was last seen, 30 cm away and turned the
    /// wrong way, and the sliver leaves the turn unresolved; with `carrier_starts` the door's
    /// motion since then places it, and it comes back turned with the door, online and offline
    /// alike.
    #[test]
    fn a_hatch_seen_again_after_its_door_turned_moves_with_the_door() {
        // Reference geometry (door closed): a wavy door panel in the plane y = 0 from x = 0.05 to
        // 0.45 m, and a hatch in front of it with a bump, so that every rotation shows.
        let door: Vec<Vector3<f64>> = (0..600)
            .map(|k| {
                let (x, z) = (0.05 + 0.4 * (k % 20) as f64 / 19.0, 0.6 * (k / 20) as f64 / 29.0);
                Vector3::new(x, 0.01 * (12.0 * x).sin() * (9.0 * z).cos(), z)
            })
            .collect();
        let hatch: Vec<Vector3<f64>> = (0..144)
            .map(|k| {
                let (u, v) = ((k % 12) as f64 / 11.0 - 0.5, (k / 12) as f64 / 11.0 - 0.5);
                Vector3::new(0.35 + 0.1 * u, -0.02 - 0.015 * (1.0 - 4.0 * (u * u + v * v)).max(0.0) - 0.01 * u, 0.3 + 0.1 * v)
            })
            .collect();
        let turn = |k: usize| 1.0 * ((k as f64 - 15.0) / 15.0).clamp(0.0, 1.0);
        let cloud = |k: usize| {
            let r = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::z_axis(), turn(k));
            let mut points: Vec<Point3<f64>> = door.iter().map(|p| Point3::from(r * p)).collect();
            let mut labels = vec![2; door.len()];
            if !(16..=30).contains(&k) {
                let n = if (31..36).contains(&k) { 24 } else { hatch.len() };
                points.extend(hatch[..n].iter().map(|p| Point3::from(r * p)));
                labels.extend(vec![3; n]);
            }
            CloudFrame { stamp: k as f64 / 30.0, points, labels, viewpoint: None }
        };
        let clouds: Vec<CloudFrame> = (0..46).map(cloud).collect();
        // The hatch's rotation relative to the door at every cloud that shows both (truth: none).
        let relative = |tracks: &PartTracks| -> Vec<f64> {
            tracks[&3]
                .iter()
                .filter_map(|h| tracks[&2].iter().find(|d| d.stamp == h.stamp).map(|d| (d.pose.rotation.inverse() * h.pose.rotation).angle()))
                .collect()
        };
        let cfg = PerceptionConfig { carrier_starts: true, ..PerceptionConfig::default() };
        let offline = Perception::new(cfg.clone()).observe_all(&clouds, &vec![None; clouds.len()]);
        let mut online = Perception::new(cfg);
        let mut streamed = PartTracks::new();
        for c in &clouds {
            for (label, o) in online.observe(c, None) {
                streamed.entry(label).or_default().push(o);
            }
        }
        online.refine(&mut streamed);
        for (how, tracks) in [("offline", &offline), ("online", &streamed)] {
            let rel = relative(tracks);
            assert_eq!(rel.len(), 31, "{how}: the hatch is registered in all 31 clouds that show it");
            let worst = rel.iter().copied().fold(0.0, f64::max);
            assert!(worst < 0.01, "{how}: the hatch turns with its door (worst {worst:.3} rad)");
            let last = tracks[&3].last().expect("seen at the end");
            assert!((last.pose.rotation.angle() - 1.0).abs() < 0.02, "{how}: the hatch turned 1 rad");
        }
        // Its own tracker alone does not find it (why the option exists).
        let alone = Perception::new(PerceptionConfig { carrier_starts: false, ..PerceptionConfig::default() }).observe_all(&clouds, &vec![None; clouds.len()]);
        let worst = relative(&alone).iter().copied().fold(0.0, f64::max);
        assert!(worst > 0.1, "without carrier starts the hatch comes back turned off its door: {worst:.3} rad");
    }

    /// A part seen whole, then as a sliver (a fifth of its points: a panel turned edge-on), then
    /// whole again: with `min_seen_fraction` the sliver's frame is not registered and the part
    /// is reported again when it is back; off (the default), every frame is.
    #[test]
    fn a_sliver_of_a_part_is_not_registered_when_asked() {
        // A 20 x 20 grid on a box face, label 1; the sliver keeps its first 4 rows.
        let grid: Vec<Point3<f64>> =
            (0..400).map(|k| Point3::new(0.01 * (k % 20) as f64, 0.01 * (k / 20) as f64, 0.02 * ((k % 20) as f64 * 0.3).sin())).collect();
        let cloud = |t: f64, n: usize| CloudFrame { stamp: t, points: grid[..n].to_vec(), labels: vec![1; n], viewpoint: None };
        let frames = [cloud(0.0, 400), cloud(0.033, 400), cloud(0.067, 80), cloud(0.1, 400)];
        let seen = |cfg: PerceptionConfig| -> Vec<f64> {
            let mut perception = Perception::new(cfg);
            frames.iter().flat_map(|c| perception.observe(c, None)).map(|(_, o)| o.stamp).collect()
        };
        assert_eq!(seen(PerceptionConfig { min_seen_fraction: 0.3, ..PerceptionConfig::default() }), [0.0, 0.033, 0.1]);
        assert_eq!(seen(PerceptionConfig::default()), [0.0, 0.033, 0.067, 0.1]);
    }

    /// A flap (label 3) pushed while the hand hides it in the push's first cloud, where the drawer
    /// below it (label 4) is nearest the contact point; in the later clouds the flap carries the
    /// contact point. One cloud names the drawer, the push's clouds together the flap.
    #[test]
    fn the_clouds_of_a_push_name_the_part_the_hand_hides_at_first() {
        let patch = |c: Point3<f64>, label: u32| -> Vec<(Point3<f64>, u32)> {
            (0..9).map(|i| (c + Vector3::new((i % 3) as f64 * 0.01, (i / 3) as f64 * 0.01, 0.0), label)).collect()
        };
        let frame = |t: f64, flap_seen: bool, contact: Point3<f64>| {
            let mut pts = patch(Point3::new(0.0, 0.0, 0.5), 4);
            if flap_seen {
                pts.extend(patch(contact, 3));
            }
            CloudFrame { stamp: t, points: pts.iter().map(|p| p.0).collect(), labels: pts.iter().map(|p| p.1).collect(), viewpoint: None }
        };
        // The contact point moves with the flap, 20 cm above the drawer.
        let contact = |k: usize| Point3::new(0.0, 0.01 * k as f64, 0.7);
        let first = frame(0.0, false, contact(0));
        assert_eq!(nearest_part(&first, &contact(0)).map(|p| p.0), Some(4), "one cloud: the drawer");
        let mut votes = ContactVotes::default();
        assert_eq!(votes.part(), None);
        votes.add(&first, &contact(0));
        for k in 1..6 {
            votes.add(&frame(k as f64 / 30.0, k % 2 == 0, contact(k)), &contact(k));
        }
        assert_eq!(votes.clouds(), 6);
        assert_eq!(votes.part(), Some(3), "the push's clouds: the flap");
        // Bounded: clouds past the limit are not kept.
        for k in 0..ContactVotes::MAX_CLOUDS {
            votes.add(&first, &contact(k));
        }
        assert_eq!(votes.clouds(), ContactVotes::MAX_CLOUDS);
    }

    #[test]
    fn observability_follows_the_shape() {
        let cfg = PerceptionConfig::default();
        // A solid lattice cube (no surface whose normals could pin a turn): no rotation observable;
        // a flat square: all but its spin; a box: all.
        let lattice = |sx: f64, sy: f64, sz: f64| -> Vec<Vector3<f64>> {
            let mut v = Vec::new();
            for a in 0..5 {
                for b in 0..5 {
                    for c in 0..5 {
                        v.push(Vector3::new(sx * a as f64, sy * b as f64, sz * c as f64));
                    }
                }
            }
            v
        };
        assert_eq!(part_geometry(&lattice(0.01, 0.01, 0.01), &cfg).rotation_axes.len(), 0);
        let sq = part_geometry(&lattice(0.01, 0.01, 0.0), &cfg);
        assert_eq!(sq.rotation_axes.len(), 2);
        assert!(sq.rotation_axes.iter().all(|a| a.z.abs() < 1e-9), "{:?}", sq.rotation_axes);
        let bx = part_geometry(&lattice(0.04, 0.02, 0.01), &cfg);
        assert_eq!(bx.rotation_axes.len(), 3);
        // The spreads alone (the surfaces' test off) say the same of the cube and the square.
        let spreads = PerceptionConfig { orientation_min_information: 0.0, ..cfg.clone() };
        assert_eq!(part_geometry(&lattice(0.01, 0.01, 0.01), &spreads).rotation_axes.len(), 0);
        assert_eq!(part_geometry(&lattice(0.01, 0.01, 0.0), &spreads).rotation_axes.len(), 2);
        assert!(bx.volume > 0.0 && (bx.com - Vector3::new(0.08, 0.04, 0.02)).norm() < 1e-6);
    }

    /// Surfaces, not spreads (stop 105): the surface of a near-square slab (0.29 x 0.27 x 0.05 m,
    /// `obj082`'s slider) pins its spin with its edges though its face's spreads are within 1.3,
    /// and the surface of a sphere pins no rotation (the stand-in of `bom import-tracks`).
    #[test]
    fn surfaces_pin_a_slabs_spin_and_not_a_spheres() {
        let cfg = PerceptionConfig::default();
        let spreads = PerceptionConfig { orientation_min_information: 0.0, ..cfg.clone() };
        // Points on the six faces of a box, 1 cm apart.
        let (a, b, c) = (0.29, 0.27, 0.05);
        let mut slab = Vec::new();
        let steps = |l: f64| (0..=(l / 0.01).round() as usize).map(move |i| i as f64 * 0.01 - l / 2.0);
        for x in steps(a) {
            for y in steps(b) {
                slab.push(Vector3::new(x, y, -c / 2.0));
                slab.push(Vector3::new(x, y, c / 2.0));
            }
            for z in steps(c) {
                slab.push(Vector3::new(x, -b / 2.0, z));
                slab.push(Vector3::new(x, b / 2.0, z));
            }
        }
        for y in steps(b) {
            for z in steps(c) {
                slab.push(Vector3::new(-a / 2.0, y, z));
                slab.push(Vector3::new(a / 2.0, y, z));
            }
        }
        assert_eq!(part_geometry(&slab, &spreads).rotation_axes.len(), 2, "the spreads miss the spin");
        assert_eq!(part_geometry(&slab, &cfg).rotation_axes.len(), 3, "the slab's edges pin its spin");
        let pose = crate::import::TrackPose { position: Vector3::new(0.4, -0.2, 0.1), orientation: None, size: None };
        let sphere: Vec<Vector3<f64>> = crate::import::synthesize(&pose, 6).iter().map(|p| Vector3::new(p[0], p[1], p[2])).collect();
        assert_eq!(sphere.len(), 216);
        assert!(sphere.iter().all(|p| ((p - pose.position).norm() - 0.025).abs() < 1e-12));
        assert_eq!(part_geometry(&sphere, &cfg).rotation_axes.len(), 0, "a sphere pins no rotation");
    }

    /// A hatch 1.5 cm in front of a door panel, seen from in front: the hatch's points along
    /// its outline are its own edge (the door lies behind them) and count `edge_weight`; the
    /// door's points around the hatch are where the hatch starts to hide the door and count
    /// `boundary_weight`; without a viewpoint every point near the other part counts
    /// `boundary_weight`, as it did before the viewpoint was known.
    #[test]
    fn a_part_in_front_keeps_its_outline_and_the_one_behind_does_not() {
        use rand::{Rng, SeedableRng};
        // Every point kept (no subsample), so that both outlines are dense; outlines on.
        let cfg = PerceptionConfig { max_points: 5000, edge_weight: 1.0, ..PerceptionConfig::default() };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (mut points, mut labels) = (Vec::new(), Vec::new());
        let hatch = |x: f64, z: f64| (0.1..=0.25).contains(&x) && (0.2..=0.4).contains(&z);
        for i in 0..=40 {
            for k in 0..=60 {
                let (x, z) = (i as f64 * 0.01, k as f64 * 0.01);
                // 2 mm of depth noise; the hatch hides the door behind it.
                let noise = rng.random_range(-0.002..0.002);
                let (y, l) = if hatch(x, z) { (-0.015, 2) } else { (0.0, 1) };
                points.push(Point3::new(x, y + noise, z));
                labels.push(l);
            }
        }
        let cloud = |viewpoint| CloudFrame { stamp: 0.0, points: points.clone(), labels: labels.clone(), viewpoint };
        let near_other = |p: &Vector3<f64>, l: u32| points.iter().zip(&labels).any(|(q, m)| *m != l && (q.coords - p).norm() <= cfg.boundary_m);
        let weights_near = |parts: &[SplitPart], l: u32| -> Vec<f64> {
            let part = parts.iter().find(|s| s.label == l).expect("part");
            part.points.iter().zip(&part.weights).filter(|(p, _)| near_other(p, l)).map(|(_, w)| *w).collect()
        };
        let seen = split_parts(&cloud(Some(Point3::new(0.2, -1.5, 0.8))), &cfg);
        let (door, hatch_w) = (weights_near(&seen, 1), weights_near(&seen, 2));
        assert!(door.len() > 20 && hatch_w.len() > 20, "{} / {} points near the other part", door.len(), hatch_w.len());
        let share = |w: &[f64], v: f64| w.iter().filter(|x| **x == v).count() as f64 / w.len() as f64;
        assert!(share(&hatch_w, cfg.edge_weight) > 0.9, "hatch outline kept: {:.2}", share(&hatch_w, cfg.edge_weight));
        assert!(share(&door, cfg.boundary_weight) > 0.9, "door around the hatch dropped: {:.2}", share(&door, cfg.boundary_weight));
        let blind = split_parts(&cloud(None), &cfg);
        assert!(weights_near(&blind, 1).iter().chain(&weights_near(&blind, 2)).all(|w| *w == cfg.boundary_weight));
    }

    /// The floors are about the part's anchor: a part far from the fixed frame's origin is not
    /// less certain in position than one at the origin.
    #[test]
    fn covariance_floors_do_not_depend_on_the_origin() {
        let cfg = PerceptionConfig::default();
        for anchor in [Vector3::zeros(), Vector3::new(0.5, -2.0, 1.0)] {
            let o = observation(0.0, Isometry3::identity(), None, anchor, &cfg, 100, 0, 1.0);
            let sd = o.position_cov(&anchor).symmetric_eigen().eigenvalues.map(f64::sqrt);
            assert!(sd.iter().all(|s| (s - cfg.com_sd_floor_m).abs() < 1e-12), "anchor {anchor:?}: sd {sd:?}");
            // A point 0.1 m from the anchor: the rotation floor moves it by up to 0.1 * floor.
            let far = o.position_cov(&(anchor + Vector3::new(0.1, 0.0, 0.0))).symmetric_eigen().eigenvalues.map(f64::sqrt).max();
            let want = (cfg.com_sd_floor_m.powi(2) + (0.1 * cfg.rotation_sd_floor_rad).powi(2)).sqrt();
            assert!((far - want).abs() < 1e-9, "anchor {anchor:?}: {far} vs {want}");
            let r = o.rotation_cov().symmetric_eigen().eigenvalues.map(f64::sqrt);
            assert!(r.iter().all(|s| (s - cfg.rotation_sd_floor_rad).abs() < 1e-12));
        }
    }

    /// Isolated model points leave the centre of mass when asked to: a box's model with a few
    /// points 0.3 m behind it (segmentation's strays).
    #[test]
    fn isolated_model_points_can_leave_the_centre_of_mass() {
        let mut pts: Vec<Vector3<f64>> = Vec::new();
        for i in 0..25 {
            for j in 0..25 {
                for z in [0.0, -0.016] {
                    pts.push(Vector3::new(0.008 * i as f64, 0.008 * j as f64, z));
                }
            }
        }
        for k in 0..6 {
            pts.push(Vector3::new(0.03 * k as f64, 0.1, -0.3));
        }
        let truth = Vector3::new(0.096, 0.096, -0.008);
        let off = part_geometry(&pts, &PerceptionConfig::default());
        assert!((off.com - truth).norm() > 0.05, "{}", off.com);
        let cfg = PerceptionConfig { hull_outlier_neighbours: 8, ..PerceptionConfig::default() };
        let on = part_geometry(&pts, &cfg);
        assert!((on.com - truth).norm() < 0.005, "{}", on.com);
        assert!(on.volume < 0.5 * off.volume, "{} vs {}", on.volume, off.volume);
    }
}
