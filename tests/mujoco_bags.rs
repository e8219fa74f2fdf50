//! The MuJoCo interaction bags (bags/mujoco, made by bags/generate): they decode with bom's reader
//! (and, in .ci/run, with rosbags), carry ground truth and 200 Hz wrenches, and in every
//! interaction the pushed part really moves while the static parts stay put. On the same replays,
//! model criticism names the undeclared effect of every bag that has one and adds none elsewhere.

mod common;

use std::path::PathBuf;

use bom::config::Config;
use bom::diagnostics::Diagnostics;
use bom::input::{self, CloudFrame};
use nalgebra::Point3;

fn bags() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir("bags/mujoco").unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "mcap")).collect();
    v.sort();
    v
}

/// `bags/mujoco/<name>.mcap` and its replay under `cfg`.
fn replay_bag(name: &str, cfg: &Config) -> (PathBuf, bom::pipeline::Run) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("bags/mujoco/{name}.mcap"));
    let run = bom::pipeline::replay(std::slice::from_ref(&path), cfg).expect("replay");
    (path, run)
}

fn part_points(c: &CloudFrame, label: u32) -> Vec<Point3<f64>> {
    c.points.iter().zip(&c.labels).filter(|(_, l)| **l == label).map(|(p, _)| *p).collect()
}

/// How far the surface `a` sits from the surface `b` [m]: a translation-only trimmed ICP (five
/// rounds; each moves `a` by the mean vector to the nearest points of `b` over the half of the
/// pairs that are closest), so surfaces revealed or hidden by a moving door, which have no
/// counterpart, do not count.
fn shift(a: &[Point3<f64>], b: &[Point3<f64>]) -> f64 {
    let mut t = nalgebra::Vector3::zeros();
    for _ in 0..5 {
        let mut v: Vec<nalgebra::Vector3<f64>> = a
            .iter()
            .map(|p| {
                let q = p + t;
                b.iter().min_by(|x, y| (*x - q).norm().total_cmp(&(*y - q).norm())).unwrap() - q
            })
            .collect();
        v.sort_by(|x, y| x.norm().total_cmp(&y.norm()));
        let kept = &v[..v.len() / 2];
        t += kept.iter().sum::<nalgebra::Vector3<f64>>() / kept.len() as f64;
    }
    t.norm()
}

/// A part's points over the clouds within `half` seconds of `t` (the clouds keep a random subset
/// of each part's points, so one frame samples a surface too sparsely to compare).
fn points_near(clouds: &[CloudFrame], t: f64, half: f64, label: u32) -> Vec<Point3<f64>> {
    clouds.iter().filter(|c| (c.stamp - t).abs() <= half).flat_map(|c| part_points(c, label)).collect()
}

#[test]
fn every_bag_decodes_and_every_push_moves_its_part() {
    let bags = bags();
    assert!(bags.len() >= 11, "{} bags", bags.len());
    let cfg = Config::new();
    let mut objects = std::collections::BTreeSet::new();
    let (mut declared, mut undeclared) = (0, 0);
    for bag in &bags {
        let name = bag.file_stem().unwrap().to_string_lossy().to_string();
        let mut diag = Diagnostics::default();
        let read = input::read_bag(bag, &mut diag).unwrap();
        let gt = read.ground_truth.clone().unwrap_or_else(|| panic!("{name}: no bom_ground_truth"));
        let rec = input::decode_recording(&[read], &cfg.topics, &cfg.fixed_frame, &mut diag);
        assert_eq!(diag.total(), 0, "{name}: {:?}", diag.counts());
        let span = rec.wrenches.last().unwrap().stamp - rec.wrenches[0].stamp;
        let rate = (rec.wrenches.len() - 1) as f64 / span;
        assert!((rate - 200.0).abs() < 5.0, "{name}: wrench rate {rate:.1} Hz");
        let cloud_rate = (rec.clouds.len() - 1) as f64 / (rec.clouds.last().unwrap().stamp - rec.clouds[0].stamp);
        assert!((cloud_rate - 30.0).abs() < 2.0, "{name}: cloud rate {cloud_rate:.1} Hz");
        if name.contains("undeclared") {
            assert!(gt.effects.is_empty(), "{name}: effects must be undeclared");
            undeclared += 1;
        } else if !gt.effects.is_empty() {
            declared += 1;
        }
        objects.insert(name.split('_').next().unwrap().to_string());

        let run = common::replay(std::slice::from_ref(bag));
        criticism_finds_the_undeclared_effect(&name, &run);
        let mut worst_static: f64 = 0.0;
        assert!(run.windows.len() >= 3, "{name}: {} interaction windows", run.windows.len());
        assert_eq!(run.mode, "dynamic");
        let last_cloud = rec.clouds.last().unwrap().stamp;
        for (k, w) in run.windows.iter().enumerate() {
            let pushed = w.pushed_part.unwrap_or_else(|| panic!("{name}: window {w:?} without a pushed part"));
            let gt_part = gt.parts.iter().find(|p| p.label == pushed).unwrap();
            assert_ne!(gt_part.joint, "rigid", "{name}: pushed part {pushed} is rigid");
            // The pushed part moves at least 3 cm (a material point) or turns 5 degrees (a door
            // pushed against a spring turns least: 7.5 degrees in MuJoCo's own record).
            let obs: Vec<_> = run.tracks[&pushed].iter().filter(|o| w.contains(o.stamp)).collect();
            let first = obs.first().unwrap();
            let moved = obs.iter().map(|o| (o.com - first.com).norm()).fold(0.0, f64::max);
            let turned = obs.iter().map(|o| first.pose.rotation.angle_to(&o.pose.rotation).to_degrees()).fold(0.0, f64::max);
            // Rotation counts for revolute joints only.
            let turned = if gt_part.joint == "revolute" { turned } else { 0.0 };
            assert!(moved >= 0.03 || turned >= 5.0, "{name}: part {pushed} moved {moved:.3} m, turned {turned:.1} deg in {w:?}");
            println!("{name:36} part {pushed}: moved {moved:.3} m, turned {turned:5.1} deg");
            // Static parts stay within noise: the surface after the push is shifted from the one
            // before it no more than two slices of the rest before it are from each other (depth
            // noise and the per-frame point subsampling set that level), plus 5 mm: a door that
            // moves also changes which parts of its neighbours are visible and how boundary
            // pixels are labelled, well inside the camera's depth noise (8 mm at 1.8 m).
            for p in gt.parts.iter().filter(|p| p.joint == "rigid" && p.parent == 0) {
                let before = points_near(&rec.clouds, w.start - 0.085, 0.085, p.label);
                let earlier = points_near(&rec.clouds, w.start - 0.255, 0.085, p.label);
                // After the push: at rest again, just before the next window (or the recording's
                // end), however long the window's margin after the force.
                let rest_end = run.windows.get(k + 1).map_or(last_cloud, |n| n.start);
                let after = points_near(&rec.clouds, rest_end - 0.085, 0.085, p.label);
                if before.len() > 20 && earlier.len() > 20 && after.len() > 20 {
                    let (noise, d) = (shift(&earlier, &before), shift(&after, &before));
                    assert!(d <= noise + 0.005, "{name}: static part {} moved: surface shift {d:.4} m, noise level {noise:.4} m", p.label);
                    worst_static = worst_static.max(d - noise);
                }
            }
        }
        println!("{name:36} static parts: largest surface shift above the noise level {worst_static:+.4} m");
    }
    assert!(objects.len() >= 6, "objects: {objects:?}");
    assert!(declared >= 2 && undeclared >= 3, "{declared} bags with declared effects, {undeclared} with undeclared");
}

/// The undeclared effect of a bag (by its name), if it has one.
fn undeclared_effect(name: &str) -> Option<&'static str> {
    [("drawer_limit_undeclared", "joint_limit"), ("hingecabinet_spring_undeclared", "spring"), ("slidecabinet_gravity_undeclared", "gravity")]
        .into_iter()
        .find(|(bag, _)| *bag == name)
        .map(|(_, effect)| effect)
}

/// `bags/effects/obj033_procedural.mcap` (the effects corpus's `tune` split): a door whose range
/// was narrowed so that its pushes reach both stops (undeclared), a drawer carrying a box lid that
/// the camera never sees, and a slider. The fourth push is on the box lid; the seen part nearest
/// the hand is the drawer, whose points all lie 0.1 m or more from it
/// ([`bom::model::likelihood::WindowEvidence::hand_off`]). The measured wrench did not act on the
/// drawer as the physics applies it, so criticism neither fits nor predicts the drawer on that
/// window: the door's stops are named and nothing is added to the drawer. (Before stop 102 the
/// drawer got a joint limit, held-out RMSE 8.1 -> 2.2 mm, +46.7 nats: a false alarm. The same
/// happened to `obj092` of the `validation` split, a drawer with an unseen box lid.)
#[test]
fn a_push_on_an_unseen_part_is_not_held_against_the_part_nearest_it() {
    let run = common::replay(&[PathBuf::from("bags/effects/obj033_procedural.mcap")]);
    let ev = bom::pipeline::final_evidence(&run, &Config::new());
    let drawer = ev.parts.iter().position(|p| p.label == 3).expect("the drawer is seen");
    let off: Vec<(usize, Option<usize>)> = ev.windows.iter().enumerate().filter(|(_, w)| w.hand_off).map(|(i, w)| (i, w.pushed)).collect();
    assert_eq!(off, [(3, Some(drawer))], "windows whose hand is off the part they were given to");
    for f in &run.findings {
        println!("obj033 criticism: part {} {}: held-out RMSE {:.4} -> {:.4} m, {:+.1} nats", f.part, f.name(), f.rmse_before_m, f.rmse_after_m, f.evidence_nats);
    }
    let added: Vec<(u32, &str)> = run.findings.iter().filter(|f| f.effect.is_some()).map(|f| (f.part, f.name())).collect();
    assert_eq!(added, [(2, "joint_limit")], "effects added");
}

/// `bags/effects/t300000_obj045_procedural.mcap` (`effects_corpus.py --seed 300000 --tune-only
/// --only 45`, a corpus for choosing settings only): one door on a hinge tilted 12.8 degrees,
/// 0.27 kg, whose undeclared weight swings it open onto its undeclared stop once a push lets
/// go. Criticism names gravity with the stop, and gravity cuts the held-out error to a third of
/// the stop's alone. Before stop 118 the Laplace refits of criticism took damping and friction
/// from a grid centred on the priors' medians even where the start (a converged fit's) was
/// better, so gravity with the stop was fitted in a friction-held basin (ELBO 108.7 nats, where
/// the mode near the truth reaches 123.4) and the stop with quadratic damping (117.1) was adopted
/// instead (`laplace::coarse_grid_or_start`).
#[test]
fn a_tilted_door_falling_onto_its_stop_is_given_gravity() {
    let run = common::replay(&[PathBuf::from("bags/effects/t300000_obj045_procedural.mcap")]);
    for f in &run.findings {
        println!("t300000_obj045 criticism: part {} {}: held-out RMSE {:.4} -> {:.4} m, {:+.1} nats, {:?}", f.part, f.name(), f.rmse_before_m, f.rmse_after_m, f.evidence_nats, f.params);
    }
    let added: Vec<(u32, &str)> = run.findings.iter().filter(|f| f.effect.is_some()).map(|f| (f.part, f.name())).collect();
    assert!(added.iter().all(|a| *a == (2, "gravity") || *a == (2, "joint_limit")), "effects added: {added:?}");
    let gravity = run.findings.iter().find(|f| f.part == 2 && f.name() == "gravity").expect("gravity on the door");
    assert!(gravity.rmse_after_m <= gravity.rmse_before_m / 3.0, "held-out RMSE {:.4} -> {:.4} m", gravity.rmse_before_m, gravity.rmse_after_m);
}

/// Model criticism on one bag's replay: with an undeclared effect, that effect and no other is
/// added (on one part or more: the recorder's spring acts on both doors of the hinge cabinet) and
/// cuts the held-out error to a third; without one, no effect is added. (The hinge springs got to
/// 0.58 and 0.38 of the base's error only, while their bag pushed each door twice, both times
/// further open: a refit to the one push left moves along a ridge of stiffness, rest and
/// friction. The bag now pushes each door three times, the last one back towards closed.)
fn criticism_finds_the_undeclared_effect(name: &str, run: &bom::pipeline::Run) {
    let added: Vec<_> = run.findings.iter().filter(|f| f.effect.is_some()).collect();
    for f in &run.findings {
        println!("{name:36} criticism: part {} {}: held-out RMSE {:.4} -> {:.4} m, {:+.1} nats", f.part, f.name(), f.rmse_before_m, f.rmse_after_m, f.evidence_nats);
    }
    match undeclared_effect(name) {
        Some(effect) => {
            let names: Vec<_> = added.iter().map(|f| f.name()).collect();
            assert!(!added.is_empty() && names.iter().all(|n| *n == effect), "{name}: effects added: {names:?}");
            for f in &added {
                assert!(f.rmse_after_m <= f.rmse_before_m / 3.0, "{name}: part {}: held-out RMSE {:.4} -> {:.4} m", f.part, f.rmse_before_m, f.rmse_after_m);
                // Every parameter has a 90% interval around its median (issue 25).
                assert_eq!(f.intervals.len(), f.params.len(), "{name}: part {}: intervals {:?}", f.part, f.intervals);
                for ((n, v), (m, [lo, hi])) in f.params.iter().zip(&f.intervals) {
                    assert!(n == m && lo <= v && v <= hi && lo < hi, "{name}: part {}: {n} {v} in [{lo}, {hi}]", f.part);
                }
            }
            // Where in the pushes the base model's error lies (issue 25): a restoring force
            // (spring, gravity) acts hardest once the push lets go, so where it dominates the
            // error, the part errs more at rest than while pushed.
            if matches!(effect, "spring" | "gravity") {
                let worst = added.iter().max_by(|a, b| a.rmse_before_m.total_cmp(&b.rmse_before_m)).expect("a finding");
                let p = bom::criticism::Phases::of(&worst.before);
                println!("{name:36} part {}: base error by phase {p:?}", worst.part);
                assert!(p.rmse_rest_m > p.rmse_push_m, "{name}: part {}: {p:?}", worst.part);
            }
        }
        None => assert!(added.is_empty(), "{name}: false alarm: {:?}", added.iter().map(|f| f.name()).collect::<Vec<_>>()),
    }
}

/// Rest frames (`inference.rest_after_s`, 0.5 s by default since stop 22, and
/// `inference.rest_before_s`, off by default): in dynamic mode grid frames up to that long
/// after each window join the evidence, outside the physics window and without starting a new
/// one, and frames up to that long before it (not already resting after the previous window); the
/// physics windows keep exactly the frames and wrench they have without them, and kinematic mode
/// (no wrench) gets none. With them `adroit_door`'s latch axis
/// comes out within 3.5 degrees of the truth and the bag's median axis angle within 2 (without:
/// 4.5-4.9 and 2.3-2.5, with windows 0.5 s past the force), rest frames before included.
#[test]
fn rest_frames_follow_each_window_outside_the_physics() {
    use bom::model::likelihood::{Evidence, Grid};
    use std::collections::BTreeMap;
    let mut cfg = Config::new();
    cfg.inference.rest_after_s = 0.5;
    cfg.inference.rest_before_s = 0.5;
    let (path, run) = replay_bag("adroit_door", &cfg);
    let mut diag = Diagnostics::default();
    let bag = input::read_bag(&path, &mut diag).expect("bag");
    let truth = bag.ground_truth.clone().expect("ground truth");
    let rec = input::decode_recording(&[bag], &cfg.topics, &cfg.fixed_frame, &mut diag);
    let grid = bom::pipeline::grid(&cfg);
    let no_rest = Grid { rest_after_s: 0.0, rest_before_s: 0.0, ..grid };
    let build = |wrenches: &[bom::input::WrenchSample], g: &Grid| Evidence::new(&run.tracks, &run.geometry, &run.windows, wrenches, &BTreeMap::new(), g);
    let (ev, ev0) = (build(&rec.wrenches, &grid), build(&rec.wrenches, &no_rest));
    assert_eq!(ev.windows.len(), run.windows.len());
    let mut before = 0;
    for (w, (we, we0)) in ev.windows.iter().zip(&ev0.windows).enumerate() {
        assert!(!we.rest.is_empty(), "window {w}: no rest frames");
        assert!(we0.rest.is_empty() && we0.rest_before.is_empty());
        before += we.rest_before.len();
        let start = run.windows[w].start;
        for &r in &we.rest_before {
            assert!(ev.times[r] < start && ev.times[r] >= start - grid.rest_before_s - 1e-9, "window {w}: rest frame before at {}", ev.times[r]);
            assert!(!we.frames.contains(&r) && !ev.windows.iter().any(|x| x.rest.contains(&r)));
        }
        let end = run.windows[w].end;
        for &r in &we.rest {
            assert!(ev.times[r] > end && ev.times[r] <= end + grid.rest_after_s + 1e-9, "window {w}: rest frame at {}", ev.times[r]);
            assert!(!ev.window_start[r] && !we.frames.contains(&r));
        }
        let stamps = |e: &Evidence, f: &[usize]| f.iter().map(|&k| e.times[k]).collect::<Vec<f64>>();
        assert_eq!(stamps(&ev, &we.frames), stamps(&ev0, &we0.frames), "window {w}");
        assert_eq!((&we.force, &we.frame_substep), (&we0.force, &we0.frame_substep));
    }
    assert!(before > 0, "no rest frames before any window");
    assert_eq!(build(&[], &grid).times, build(&[], &no_rest).times, "kinematic mode");
    let m = bom::eval::evaluate(&truth, run.posterior.as_ref().expect("posterior"), false);
    let latch = m.per_part.iter().find(|p| p.label == 3).and_then(|p| p.axis_angle_deg).expect("latch axis");
    assert!(latch < 3.5 && m.axis_angle_deg.is_some_and(|a| a < 2.0), "latch {latch:.2} deg, bag {:?}", m.axis_angle_deg);
}

/// The physics against MuJoCo: at the recorder's true damping, friction and joint axis, the model's
/// simulation of each joint ([`bom::criticism::residuals::JointSeries::predict`]: from the window's
/// first frame at rest, under the measured wrench, with the replay's MAP tree) follows every push
/// the recording holds to within 2 cm of centre-of-mass path, and better than with damping and
/// friction both 1.5 times larger or smaller — for every joint on a part that stays put, on every
/// bag whose physics the base model covers (no effects, or only more friction). A units slip
/// (radians against metres of path), a wrong lever arm or a friction law that does not stop a joint
/// would break this; the criticism's held-out residuals stand on it. The mass is the fitted one:
/// the bag's is the MuJoCo body's, whose inertia (with the joint's armature) the observed hull
/// scaled by a mass does not reproduce (`adroit_door`'s door: 83 mm RMSE with the bag's mass, 6 mm
/// with the fitted one). The true axis, not the fitted one, because the fitted hinge of `microwave`
/// passes 5 cm from the true hinge point (the lines come closest far from the object, so
/// `axis_offset_m` reads 5 mm): the push's lever arm is then 10% short, the pushes are 22 mm off at
/// the true damping and friction, and the fit makes both about 10% low to match (README, known
/// limits).
#[test]
fn the_physics_at_the_true_parameters_follows_every_push() {
    use bom::criticism::residuals::{part_transforms, JointSeries};
    use bom::model::dynamics;
    use bom::model::effects::EffectSet;
    use nalgebra::Vector3;
    use std::collections::BTreeMap;
    let cfg = Config::new();
    let dyncfg = &cfg.model.dynamics;
    let mut checked = 0;
    for bag in bags() {
        let name = bag.file_stem().unwrap().to_string_lossy().to_string();
        let mut diag = Diagnostics::default();
        let read = input::read_bag(&bag, &mut diag).unwrap();
        let truth = read.ground_truth.clone().unwrap();
        if name.contains("undeclared") || !truth.effects.iter().all(|e| e["kind"] == "extra_friction") {
            continue;
        }
        let rec = input::decode_recording(&[read], &cfg.topics, &cfg.fixed_frame, &mut diag);
        let run = bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).expect("replay");
        let post = run.posterior.as_ref().expect("posterior");
        let ev = bom::model::likelihood::Evidence::new(&run.tracks, &run.geometry, &run.windows, &rec.wrenches, &BTreeMap::new(), &bom::pipeline::grid(&cfg));
        let transforms = part_transforms(post, ev.len());
        for i in 0..ev.parts.len() {
            let label = ev.parts[i].label;
            let gt = truth.parts.iter().find(|p| p.label == label).unwrap();
            let (Some(d), Some(f), Some(td)) = (gt.damping, gt.friction, gt.axis_direction) else { continue };
            // One joint is simulated with its parent held where the window starts: a joint on a
            // moving part (a latch on a door, which its pushes swing) is not one joint's physics.
            let mut node = gt.parent;
            let mut on_moving = false;
            for _ in 0..truth.parts.len() {
                let Some(p) = truth.parts.iter().find(|p| p.label == node) else { break };
                on_moving |= p.joint != "rigid";
                node = p.parent;
            }
            if on_moving {
                continue;
            }
            let Some(mut series) = JointSeries::new(&ev, post, &transforms, i, dyncfg) else { continue };
            let Some(kd) = post.joints[i].kinodynamics else { continue };
            // The true axis (in the reference configuration), moved by the parent's displacement at
            // each window's start as the fitted one is.
            let td = Vector3::from(td);
            let td = if td.dot(&series.params.direction) < 0.0 { -td } else { td };
            for jw in series.windows.iter_mut() {
                let pre = series.pre[jw.win.frames[0]];
                jw.joint.direction = pre.r * td;
                if let Some(tp) = gt.axis_point {
                    jw.joint.point = pre.apply(&Vector3::from(tp));
                }
            }
            // Standardised parameters (paper §3.2: xi ~ N(0, 1) mapped to the physical scale).
            let scales = dynamics::prior_scales(series.params.joint, dyncfg);
            let xi = |scale: f64| -> Vec<f64> {
                let v = [d * scale, f * scale, kd.mass.median];
                (0..3).map(|k| (v[k] / scales[k].0).ln() / scales[k].1).chain([0.0]).collect()
            };
            let rmse = |xi: &[f64]| {
                let (mut sq, mut n) = (0.0, 0);
                for (w, jw) in series.windows.iter().enumerate().filter(|(_, jw)| jw.pushed) {
                    let pred = series.predict(w, xi, EffectSet::default(), dyncfg);
                    for (k, &t) in jw.win.frames.iter().enumerate().skip(1) {
                        sq += (series.com_at(t, series.q[t]) - series.com_at(t, pred[k])).norm_squared();
                        n += 1;
                    }
                }
                (n > 0).then(|| (sq / n as f64).sqrt())
            };
            let (Some(at_truth), Some(up), Some(down)) = (rmse(&xi(1.0)), rmse(&xi(1.5)), rmse(&xi(1.0 / 1.5))) else { continue };
            println!("{name:24} part {label}: pushes within {at_truth:.4} m RMSE at the true damping and friction ({up:.4} m at 1.5 times, {down:.4} m at 1/1.5)");
            assert!(at_truth < 0.02 && at_truth < up && at_truth < down, "{name} part {label}: {at_truth:.4} m at the truth, {up:.4} / {down:.4} m at 1.5 / 1/1.5 times");
            checked += 1;
        }
    }
    assert!(checked >= 8, "{checked} joints checked");
}

/// Gravity where the weight acts: `bags/effects/obj015_procedural.mcap` (the effects corpus's
/// `tune` split, not in its shipped manifest) is a door on a hinge tilted 16.9 degrees, held shut
/// by its weight, pushed open twice and falling back shut, once from its open stop. At the bag's
/// true damping, friction and mass, with gravity and both stops (anchored where the door was seen
/// furthest each way), the door's physics follows all three windows when the weight acts at the
/// centre of the part's seen surface (the mean of its model points), and does not when it acts at
/// the hull centroid, which a few stray model points put 0.16 m off the door (README, issue 25,
/// stop 117: the weight's moment then pushes the closed door open). The value that criticism's
/// grids search on there equals the log posterior whose gradient its Newton steps follow.
#[test]
fn gravity_at_the_true_parameters_holds_a_tilted_door_shut() {
    use bom::criticism::residuals::{part_transforms, JointSeries};
    use bom::model::dynamics;
    use bom::model::effects::{EffectSet, LimitSpec};
    use std::collections::BTreeMap;
    let cfg = Config::new();
    let dyncfg = &cfg.model.dynamics;
    let bag = PathBuf::from("bags/effects/obj015_procedural.mcap");
    let mut diag = Diagnostics::default();
    let read = input::read_bag(&bag, &mut diag).unwrap();
    let truth = read.ground_truth.clone().unwrap();
    let rec = input::decode_recording(&[read], &cfg.topics, &cfg.fixed_frame, &mut diag);
    let run = bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).expect("replay");
    let post = run.posterior.as_ref().expect("posterior");
    let ev = bom::model::likelihood::Evidence::new(&run.tracks, &run.geometry, &run.windows, &rec.wrenches, &BTreeMap::new(), &bom::pipeline::grid(&cfg));
    let transforms = part_transforms(post, ev.len());
    let door = truth.parts.iter().find(|p| p.label == 3).unwrap();
    let (Some(d), Some(f), Some(m)) = (door.damping, door.friction, door.mass) else { panic!("the door's truth") };
    let i = ev.parts.iter().position(|p| p.label == 3).unwrap();
    let series = JointSeries::new(&ev, post, &transforms, i, dyncfg).expect("the door moves");
    let seen: Vec<f64> = series.windows.iter().flat_map(|jw| jw.win.frames.iter().map(|&t| series.q[t])).collect();
    let (lo, hi) = (seen.iter().copied().fold(f64::INFINITY, f64::min), seen.iter().copied().fold(f64::NEG_INFINITY, f64::max));
    let effects = EffectSet { gravity: true, limit: Some(LimitSpec { lower: Some(lo), upper: Some(hi) }), ..Default::default() };
    // Standardised parameters: the truth's damping, friction and mass; the stops at their
    // anchors with a stiff contact (two prior sds above the median).
    let scales = dynamics::prior_scales(series.params.joint, dyncfg);
    let v = [d, f, m];
    let xi: Vec<f64> = (0..3).map(|k| (v[k] / scales[k].0).ln() / scales[k].1).chain([0.0, 0.0, 0.0, 2.0]).collect();
    let rmse = |s: &JointSeries| {
        let (mut sq, mut n) = (0.0, 0);
        for (w, jw) in s.windows.iter().enumerate() {
            let pred = s.predict(w, &xi, effects, dyncfg);
            for (k, &t) in jw.win.frames.iter().enumerate().skip(1) {
                sq += (s.q[t] - pred[k]).powi(2);
                n += 1;
            }
        }
        (sq / n as f64).sqrt()
    };
    let at_surface = rmse(&series);
    let mut hull = series.clone();
    for jw in hull.windows.iter_mut() {
        jw.weight_com = jw.com;
    }
    let at_hull = rmse(&hull);
    println!("door: {} windows, RMSE {at_surface:.4} m with the weight at the seen surface's centre, {at_hull:.4} m at the hull centroid", series.windows.len());
    assert!(series.windows.len() >= 3 && series.windows.iter().filter(|jw| jw.pushed).count() >= 2);
    assert!(at_surface < 0.03, "{at_surface:.4} m of path at the true parameters");
    assert!(at_hull > 3.0 * at_surface, "hull centroid {at_hull:.4} m against {at_surface:.4} m");
    // The value criticism's grids search on (simulated in `f64`, stop 119) is the log posterior
    // whose gradient Newton's method follows (dual numbers as wide as the parameters, 7 here),
    // for the door's windows with these effects and with a spring too (9 parameters).
    let all = |_: usize| true;
    let sprung = EffectSet { spring: true, ..effects };
    for (set, x) in [(effects, xi.clone()), (sprung, xi[..4].iter().copied().chain([0.5, -0.2]).chain(xi[4..].iter().copied()).collect())] {
        let (value, with_gradient) = (series.log_posterior_value(&x, set, &all, dyncfg), series.log_posterior(&x, set, &all, dyncfg).0);
        assert!((value - with_gradient).abs() <= 1e-9 * with_gradient.abs().max(1.0), "{value} against {with_gradient}");
    }
}

/// Criticism revises itself: an effect adopted earlier is measured again on all windows at every
/// later update and retracted when it no longer meets the adoption rule there (decisive ELBO
/// gain, held-out error cut to `max_error_ratio`). `microwave_spring` (its spring declared) with
/// quadratic damping adopted on its door, a wrong effect its first windows once took up (before
/// stop 104 the replay itself adopted it there, tracked with boundary points at weight 0.2, the
/// rule at `max_error_ratio` 0.8 and the hand's track off; with the rotational inertia scaled by
/// the mass, stop 104, it adopts nothing, so the test starts from the adopted effect, as the
/// drawer's below does): criticism on all four windows, default settings, must retract the
/// damping, report no finding whose error does not fall, and leave the refitted model with its
/// declared spring only (measured: the door's residual is then 5.7 mm, unexplained).
#[test]
fn an_effect_the_later_windows_refute_is_retracted() {
    use bom::model::effects::{EffectKind, EffectSet};
    use bom::pipeline::{criticise_update, declared_effects, fit_update, Effects, EvidenceSource};
    let cfg = Config::new();
    let (_, run) = replay_bag("microwave_spring", &cfg);
    let declared = declared_effects(run.ground_truth.as_ref().expect("ground truth"));
    let door = *declared.iter().find(|(_, e)| e.spring).expect("a declared spring").0;
    assert!(run.effects.get(&door).is_some_and(|e| !e.quadratic_damping), "replay itself keeps quadratic damping: {:?}", run.effects);
    let src = EvidenceSource { tracks: &run.tracks, geometry: &run.geometry, windows: &run.windows, wrenches: &run.wrenches };
    let damping = EffectSet::default().with(EffectKind::QuadraticDamping, None);
    let mut effects = Effects { declared: declared.clone(), adopted: [(door, damping)].into() };
    let (ev, fitted) = fit_update(src, &effects, &cfg, None).expect("a fit");
    let (criticism, refit) = criticise_update(src, &ev, &fitted, &mut effects, &cfg);
    for f in &criticism.findings {
        println!("part {}: {} (new {}): held-out RMSE {:.4} -> {:.4} m, {:+.1} nats", f.part, f.name(), f.new, f.rmse_before_m, f.rmse_after_m, f.evidence_nats);
    }
    assert!(criticism.retracted.contains(&(door, EffectKind::QuadraticDamping)), "the damping is kept: {:?}", criticism.retracted);
    for f in criticism.findings.iter().filter(|f| f.effect.is_some()) {
        assert!(f.rmse_after_m < f.rmse_before_m, "part {}: {} kept with held-out RMSE {:.4} -> {:.4} m", f.part, f.name(), f.rmse_before_m, f.rmse_after_m);
    }
    assert!(effects.all() == declared, "effects at the end: {:?}", effects.all());
    assert!(refit.is_some(), "no refit without the damping");
}

/// A wrong effect adopted on early windows does not survive all of them: `drawer_limit_undeclared`'s
/// drawer is stopped by an undeclared joint limit, and a spring partly stands in for it (in the
/// project's CI at stop 100 the node adopted one and kept it to the end: held-out RMSE 63 mm
/// without it, 24 mm with it, where replay's stops alone give 2.5 mm; the likely cause, the
/// node's topic order, is fixed: `tests/online.rs` `a_late_wrench_topic_changes_nothing`). On replay's evidence
/// of all four windows, starting from the spring adopted, criticism must retract it (the
/// adoption rule measured again) and adopt the stops, with the error falling, and the refitted
/// model must keep only the stops.
#[test]
fn a_wrong_effect_adopted_early_gives_way_to_the_stops() {
    use bom::model::effects::{EffectKind, EffectSet};
    use bom::pipeline::{criticise_update, fit_update, Effects, EvidenceSource};
    let cfg = Config::new();
    let (_, run) = replay_bag("drawer_limit_undeclared", &cfg);
    let drawer = 2;
    assert!(run.effects.get(&drawer).is_some_and(|e| e.limit.is_some()), "replay itself adopts no joint limit: {:?}", run.effects);
    let src = EvidenceSource { tracks: &run.tracks, geometry: &run.geometry, windows: &run.windows, wrenches: &run.wrenches };
    let spring = EffectSet::default().with(EffectKind::Spring, None);
    let mut effects = Effects { declared: Default::default(), adopted: [(drawer, spring)].into() };
    let (ev, fitted) = fit_update(src, &effects, &cfg, None).expect("a fit");
    let (criticism, refit) = criticise_update(src, &ev, &fitted, &mut effects, &cfg);
    for f in &criticism.findings {
        println!("part {}: {} (new {}): held-out RMSE {:.4} -> {:.4} m, {:+.1} nats", f.part, f.name(), f.new, f.rmse_before_m, f.rmse_after_m, f.evidence_nats);
    }
    assert!(criticism.retracted.contains(&(drawer, EffectKind::Spring)), "the spring is kept: {:?}", criticism.retracted);
    let limit = criticism.findings.iter().find(|f| f.part == drawer && f.effect == Some(EffectKind::JointLimit) && f.new).expect("a joint limit adopted");
    assert!(limit.rmse_after_m < 0.5 * limit.rmse_before_m, "{:.4} -> {:.4} m", limit.rmse_before_m, limit.rmse_after_m);
    let end = effects.adopted.get(&drawer).copied().unwrap_or_default();
    assert!(end.limit.is_some() && !end.spring, "effects at the end: {end:?}");
    assert!(refit.is_some(), "no refit with the new effects");
}

/// The contact point as an observation of the pushed part (`model.contact_sd_m`): on the shipped
/// bags without an undeclared effect, every window whose push moves its part gives the pushed
/// part contact observations, and the hand's recorded track agrees with perception's own track
/// of the material point it touches — the median distance between the observed contact and the
/// anchored material point carried by perception's pose of the part at the same frame is under
/// 1 cm on every bag (measured: 2.3-7.7 mm, the microwave's door the largest), while the contact
/// itself moved by 9.5-47 cm. A recorder whose contact
/// frame did not move with the part, a contact attached to the wrong part, or an anchor taken in
/// the wrong configuration would break this.
#[test]
fn the_hand_moves_with_the_part_it_pushes() {
    use bom::model::likelihood::Evidence;
    use std::collections::BTreeMap;
    let mut cfg = Config::new();
    cfg.model.contact_sd_m = 0.005;
    for name in ["drawer", "microwave", "slidecabinet", "hingecabinet", "adroit_door"] {
        let (path, run) = replay_bag(name, &cfg);
        let mut diag = Diagnostics::default();
        let bag = input::read_bag(&path, &mut diag).expect("bag");
        let rec = input::decode_recording(&[bag], &cfg.topics, &cfg.fixed_frame, &mut diag);
        let ev = Evidence::new(&run.tracks, &run.geometry, &run.windows, &rec.wrenches, &BTreeMap::new(), &bom::pipeline::grid(&cfg));
        let (mut gaps, mut travel) = (Vec::new(), 0.0f64);
        for (w, win) in ev.windows.iter().enumerate() {
            let Some(p) = win.pushed else { continue };
            let part = &ev.parts[p];
            let seen: Vec<usize> = win.frames.iter().copied().filter(|&f| part.contact_at(f).is_some()).collect();
            assert!(!seen.is_empty(), "{name}: window {w}: no contact observation of part {}", part.label);
            for f in seen {
                let (Some(c), Some(pose)) = (part.contact_at(f), part.disp[f]) else { continue };
                let anchored = (pose * Point3::from(c.x)).coords;
                gaps.push((c.obs.y - anchored).norm());
                travel = travel.max((c.obs.y - c.x).norm());
            }
        }
        gaps.sort_by(f64::total_cmp);
        let median = gaps[gaps.len() / 2];
        println!("{name:24} hand vs perception: median {:.1} mm over {} frames; the hand travels {:.0} mm", median * 1e3, gaps.len(), travel * 1e3);
        assert!(median < 0.01 && travel > 0.05, "{name}: contact vs perception median {median:.4} m over {} frames, travel {travel:.3} m", gaps.len());
    }
}
