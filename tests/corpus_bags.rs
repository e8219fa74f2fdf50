//! Tune-split objects of the randomized corpus (`bags/corpus/`, README "Generalization"): three
//! with a tree that one of BOM-SVI's initial structures gets wrong (`bom::inference::svi::fit`),
//! where every joint type and parent must come out right, an episode with a light push, and a
//! door pushed only through its latch, whose kinodynamics need the latch's mass; and two objects
//! recorded as separate episodes, replayed together without wrenches; and one whose lid got a
//! spurious effect while criticism read hinges off their centre of mass; and an adroit door whose
//! parents need the hand's contact firm along its push (`model.contact_firm`).

use std::path::PathBuf;

use bom::config::Config;

/// Replay `bags` with `cfg` and score the posterior against the bags' ground truth: the run, its
/// metrics and the summary table (for failure messages).
fn evaluated(bags: &[PathBuf], cfg: &Config) -> (bom::pipeline::Run, bom::eval::Metrics, String) {
    let run = bom::pipeline::replay(bags, cfg).expect("replay");
    let truth = run.ground_truth.as_ref().expect("ground truth");
    let m = bom::eval::evaluate(truth, run.posterior.as_ref().expect("posterior"), false);
    let table = bom::output::table::render(&run);
    (run, m, table)
}

fn replay(name: &str) -> (bom::eval::Metrics, String) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("bags/corpus/{name}.mcap"));
    let (_, m, table) = evaluated(std::slice::from_ref(&path), &Config::new());
    (m, table)
}

/// Every scored part of `m` whose label `keep` accepts has the right joint type and parent.
fn assert_right(name: &str, m: &bom::eval::Metrics, table: &str, keep: impl Fn(u32) -> bool) {
    for p in m.per_part.iter().filter(|p| keep(p.label)) {
        assert!(p.joint_correct && p.parent_correct, "{name}: part {} (true {} on {}) called {:?} on {:?}\n{table}", p.label, p.true_joint, p.true_parent, p.estimated_joint, p.estimated_parent);
    }
}

fn all_right(name: &str) {
    let (m, table) = replay(name);
    assert_right(name, &m, &table, |_| true);
}

/// The default configuration without the wrench topic (kinematic mode).
fn kinematic() -> Config {
    let mut cfg = Config::new();
    cfg.topics.wrench = "/no_wrench".into();
    cfg
}

/// A drawer carrying a lidded box, and a door: the lid turns while the drawer is out. Only the
/// start that charges each coordinate by its own frame's observations hangs the lid on the drawer
/// as a revolute joint (from the BIC start it stays prismatic at P = 1.00).
///
/// Ignored since issue 25: it passed only while criticism adopted a spurious quadratic damping on
/// the drawer (held-out error 0.56 of the base model's, which the adoption rule of 0.5 no longer
/// accepts); with criticism off, or without that effect, the lid is called prismatic on the case.
/// A known failure (README, "Model criticism on objects and effects it was not tuned on"); run it
/// with `cargo test --release --test corpus_bags -- --ignored`.
#[test]
#[ignore = "issue 25: the lid was right only with a spurious effect on the drawer (README)"]
fn a_lid_on_a_drawer_is_revolute_on_the_drawer() {
    all_right("obj075_procedural");
}

/// A door, and a sliding panel carrying a flap: the flap rides the panel and turns 4.5 degrees.
/// Only the BIC start hangs it on the panel as a revolute joint (from the other it becomes
/// prismatic on the fixed frame, riding the panel's rail); the fit with the higher ELBO is kept.
#[test]
fn a_flap_on_a_slider_is_revolute_on_the_slider() {
    all_right("obj096_procedural");
}

/// Two drawers on parallel rails and a door, pushed in separate windows of one recording. Hung
/// from the second drawer, the first one's prismatic coordinate cancels the second's motion,
/// which the kinematics cannot tell from hanging it on the case (both initial structures hang it
/// from the other drawer); the physics can, as the pushed drawer would drag the other through
/// the joint's damping. The flatter runner-up
/// start (`structure::InitialStructure::runner_up`) hangs it from the case and wins on the ELBO.
#[test]
fn a_drawer_beside_a_drawer_hangs_from_the_case() {
    all_right("obj057_procedural");
}

/// The reported joint-type probabilities of dynamic mode (`inference.coarsen: report`, README
/// "Generalization", stop 53) temper the fit's comparison and leave the fit alone: on the same
/// bag, the rate-0.1 report keeps every most probable type and parent of the frames-independent
/// report (`coarsen: kinematic`, stop 52's default), its log-odds are a tenth of the rate-1
/// report's wherever those are below the 300-nat floor, and the flap whose type flips with the
/// seed (revolute by 25.6 nats at seed 0, README "Stop 52") is no longer reported sure. The
/// other starts' fits, which end in other structures here, raise alternatives on the same scale
/// (`svi::fit`, README "Stop 69") and never above a call: each part's call and parent stay its
/// most probable type and parent.
#[test]
fn reported_type_probabilities_temper_the_fit_and_keep_its_calls() {
    use bom::inference::svi::Coarsen;
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bags/corpus/obj096_procedural.mcap");
    let run = |coarsen: Coarsen, rate: f64| {
        let mut cfg = Config::new();
        cfg.inference.coarsen = coarsen;
        cfg.inference.report_rate = rate;
        let run = bom::pipeline::replay(std::slice::from_ref(&path), &cfg).expect("replay");
        run.posterior.expect("posterior").joints
    };
    let (plain, one, tenth) = (run(Coarsen::Kinematic, 1.0), run(Coarsen::Report, 1.0), run(Coarsen::Report, 0.1));
    assert_eq!(plain.len(), 4);
    let top = |p: &[f64; 3]| (0..3).max_by(|&a, &b| p[a].total_cmp(&p[b])).unwrap();
    for ((a, b), c) in plain.iter().zip(&one).zip(&tenth) {
        assert_eq!((a.child, a.parent, a.map_type), (c.child, c.parent, c.map_type), "part {}", a.child);
        assert_eq!((b.parent, b.map_type), (c.parent, c.map_type), "part {}", a.child);
        assert_eq!(top(&a.type_probs), top(&c.type_probs), "part {}: {:?} -> {:?}", a.child, a.type_probs, c.type_probs);
        for j in [a, b, c] {
            assert_eq!(top(&j.type_probs), j.map_type.index(), "part {}: call {:?}, {:?}", j.child, j.map_type, j.type_probs);
            let p_call = j.parent_probs.iter().find(|x| x.0 == j.parent).expect("the parent's probability").1;
            assert!(j.parent_probs.iter().all(|x| x.1 <= p_call), "part {}: parent {}, {:?}", j.child, j.parent, j.parent_probs);
        }
        let t = top(&b.type_probs);
        for k in (0..3).filter(|&k| k != t) {
            let (gap1, gap01) = ((b.type_probs[t] / b.type_probs[k]).ln(), (c.type_probs[t] / c.type_probs[k]).ln());
            if gap1 < 299.0 {
                assert!((gap01 - 0.1 * gap1).abs() < 1e-6 * gap1.max(1.0), "part {} type {k}: {gap1} nats at rate 1, {gap01} at 0.1", a.child);
            }
        }
    }
    let flap = tenth.iter().find(|j| j.child == 4).expect("the flap");
    assert!(flap.type_probs.iter().all(|&p| p < 0.95), "flap reported sure: {:?}", flap.type_probs);
}

/// One episode of tune object 45: its hatch (prismatic on a door) is pushed with at most 0.87 N,
/// below `windows.force_open_n`, and slides out. The push is a window on the hatch (before stop
/// 55 no window opened: the whole recording was used as one, with a warning, and no part was
/// pushed), and the hatch is prismatic.
#[test]
fn a_light_push_that_moves_a_hatch_is_a_window_on_it() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bags/corpus/obj045_ep3_light_push.mcap");
    let cfg = Config::new();
    let run = bom::pipeline::replay(std::slice::from_ref(&path), &cfg).expect("replay");
    assert_eq!(run.diagnostics.total(), 0, "{:?}", run.diagnostics.counts());
    assert_eq!(run.windows.len(), 1, "{:?}", run.windows);
    assert_eq!(run.windows[0].pushed_part, Some(3), "{:?}", run.windows);
    let hatch = run.posterior.as_ref().expect("posterior").joints.iter().find(|j| j.child == 3).expect("the hatch");
    assert_eq!(hatch.map_type, bom::model::JointType::Prismatic, "{:?}", hatch.type_probs);
}

/// A door pushed only through the latch it carries (tune object 24: five pushes on the latch,
/// which turn the door about its hinge with up to 2.9 N m). The latch's mass enters the door's
/// physics (its locked subtree) while the latch's own pushes barely weigh it; fitted one block at
/// a time it stayed near the prior's 1 kg at the door's far edge and the door took the error
/// (damping and friction 0.95 and 0.81 off the truth, relative). The reported fit of the coupled
/// subtree's blocks together (README "Stop 59") puts both within a third of the truth (0.12 and
/// 0.07 when written), and the door's 90% intervals hold it.
#[test]
fn a_door_pushed_through_its_latch_is_identified_with_the_latch() {
    let (m, table) = replay("obj024_procedural");
    let door = m.per_part.iter().find(|p| p.label == 2).expect("the door");
    assert!(door.joint_correct && door.parent_correct, "{table}");
    for (name, e) in [("damping", door.damping_rel_error), ("friction", door.friction_rel_error)] {
        let e = e.expect("a movable door has kinodynamics");
        assert!(e < 1.0 / 3.0, "door {name} relative error {e:.2}: {door:?}\n{table}");
    }
    assert_eq!((door.damping_covered, door.friction_covered), (Some(true), Some(true)), "{door:?}");
}

/// Tune object 81 recorded as two separate episodes (each bag from the reset object, stamps 300 s
/// apart: a lid turned in the first, a door in the second), replayed together without their
/// wrenches (kinematic mode, as a dataset without force data is). The lid's registration jitters
/// to the end of its episode, so before stop 66 its motion period stayed open across the break in
/// the clouds and one window covered both episodes and the gap: its evidence, thinned to
/// `min_dt_s` over 303 s, kept a handful of frames of each push, and the lid came out rigid at
/// P = 0.999. A break longer than `windows.max_unobserved_s` now ends a window: two windows, and
/// every part right.
#[test]
fn separate_episodes_without_wrenches_are_separate_windows() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bags/corpus");
    let bags = [dir.join("obj081_ep1.mcap"), dir.join("obj081_ep2.mcap")];
    let (run, m, table) = evaluated(&bags, &kinematic());
    assert_eq!(run.mode, "kinematic");
    assert_eq!(run.windows.len(), 2, "{:?}", run.windows);
    assert!(run.windows[0].end < 10.0 && run.windows[1].start > 290.0, "a window spans the break: {:?}", run.windows);
    assert_right("obj081 episodes", &m, &table, |_| true);
}

/// Tune object 9 recorded as four separate episodes (a door, a latch in it, a drawer carrying a
/// box with a lid; the drawer pulled 18 cm in the fourth episode only), replayed together without
/// their wrenches. After three windows without the drawer moving, the warm start's type factor
/// was sure of rigid, the comparison weight `n_eff / n` taken under that rigid fit of a moving
/// part collapsed (0.067), and the drawer stayed rigid at P = 0.96 after the window that moved it
/// (fitted afresh on all four, it is prismatic). In kinematic mode a part the previous fit called
/// rigid that the start structure of all windows calls movable now takes its type factor from the
/// data (`svi::fit`'s warm start). The lid is never seen apart from the box and is not scored.
#[test]
fn a_part_first_moved_in_a_later_episode_is_not_kept_rigid() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bags/corpus");
    let bags: Vec<PathBuf> = (1..=4).map(|k| dir.join(format!("obj009_ep{k}.mcap"))).collect();
    let (run, m, table) = evaluated(&bags, &kinematic());
    assert_eq!(run.windows.len(), 4, "{:?}", run.windows);
    assert_right("obj009 episodes", &m, &table, |label| label <= 4);
}

/// Tune object 69 (1 case; 2 lid, revolute on a horizontal hinge; 3 drawer; 4 door; six pushes).
/// The structure corpus has no undeclared effect (gravity off, no springs), so any finding is a
/// false alarm. Criticism used to read the lid's coordinate off its centre of mass, which perception
/// places in the lid's own plane partly by its outline and which wandered there by centimetres:
/// the base model's held-out error on the lid was 32 mm, and a spring of 0.05 N m/rad was adopted
/// at +108.8 nats (held-out 32 -> 5.1 mm). A hinge's coordinate is now read off its observed turn
/// where the shape shows it (`bom::model::observed_coordinate`; README, "Stop 72"): the lid's
/// held-out error is under a centimetre and nothing is added to it. The drawer is not asserted:
/// criticism adds an effect to it at some config seeds (stop 78's binary: a joint limit at seed 1,
/// held-out 8.6 -> 2.8 mm; stop 79's: quadratic damping at seed 0 and the joint limit at seed 1;
/// none at seed 2) — issue 25's false alarms, open, counted by `bom eval --corpus
/// effects/manifest.json`.
#[test]
fn a_lid_read_off_its_turn_gets_no_effect() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bags/corpus/obj069_procedural.mcap");
    let (run, m, table) = evaluated(std::slice::from_ref(&path), &Config::new());
    let added: Vec<_> = run.findings.iter().filter(|f| f.effect.is_some()).map(|f| (f.part, f.name(), f.rmse_before_m, f.rmse_after_m)).collect();
    assert!(added.iter().all(|a| a.0 != 2), "false alarm on the lid: {added:?}\n{table}");
    // Whatever is added elsewhere must have lowered the held-out error (issue 25: never after >= before).
    assert!(added.iter().all(|a| a.3 < a.2), "an added effect whose held-out error did not fall: {added:?}\n{table}");
    let lid = run.updates.last().expect("an update").criticism.parts.iter().find(|p| p.label == 2).expect("the lid is criticised");
    assert!(lid.rmse_m < 0.01, "lid held-out RMSE {:.4} m\n{table}", lid.rmse_m);
    assert_right("obj069_procedural", &m, &table, |_| true);
}

/// Tune object 90, an adroit door (1 frame: rigid on world; 2 door: revolute on 1; 3 latch:
/// revolute on 2; four pushes), with `model.contact_firm` (off by default: README
/// "Generalization", stop 122). By default the door comes out hung from its latch at P = 1.00.
/// With the hand's contact Gaussian along its push — the hand cannot advance into a surface that
/// stays — every parent is right, and no joint type that is wrong is called at P >= 0.95 (the
/// door's type is a close call between revolute and prismatic here).
#[test]
fn a_firm_contact_hangs_the_door_on_its_frame() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bags/corpus/obj090_adroit_door.mcap");
    let mut cfg = Config::new();
    cfg.model.contact_firm = true;
    let (run, m, table) = evaluated(std::slice::from_ref(&path), &cfg);
    let joints = &run.posterior.as_ref().expect("posterior").joints;
    assert_eq!(m.per_part.len(), 3, "{table}");
    for p in &m.per_part {
        assert!(p.parent_correct, "part {} (on {}) hung from {:?}\n{table}", p.label, p.true_parent, p.estimated_parent);
        let j = joints.iter().find(|j| j.child == p.label).expect("every part has a joint");
        let top = j.type_probs.iter().copied().fold(0.0, f64::max);
        assert!(p.joint_correct || top < 0.95, "part {} (true {}) called {:?} at P = {top:.2}\n{table}", p.label, p.true_joint, p.estimated_joint);
    }
}
