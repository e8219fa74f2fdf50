//! Two tune-split objects of the randomized corpus (`bags/corpus/`, README "Generalization"),
//! each a nested chain whose tree one of BOM-SVI's two initial structures gets wrong
//! (`bom::inference::svi::fit`): every joint type and parent must come out right.

use std::path::PathBuf;

use bom::config::Config;

fn replay(name: &str) -> (bom::eval::Metrics, String) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("bags/corpus/{name}.mcap"));
    let run = bom::pipeline::replay(std::slice::from_ref(&path), &Config::new()).expect("replay");
    let truth = run.ground_truth.as_ref().expect("ground truth");
    let m = bom::eval::evaluate(truth, run.posterior.as_ref().expect("posterior"), false);
    (m, bom::output::table::render(&run))
}

fn all_right(name: &str) {
    let (m, table) = replay(name);
    for p in &m.per_part {
        assert!(p.joint_correct && p.parent_correct, "{name}: part {} (true {} on {}) called {:?} on {:?}\n{table}", p.label, p.true_joint, p.true_parent, p.estimated_joint, p.estimated_parent);
    }
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
