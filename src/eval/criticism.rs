//! Scoring model criticism against the undeclared effects of a corpus (issue 25): which effects
//! were named for the right part, with what parameter error and held-out error ratio, and which
//! added effects are false alarms.
//!
//! The truth is the manifest's per-object `effects` list, as `bags/generate/effects_corpus.py`
//! writes it (also in each bag's `bom_undeclared_effects` metadata record): per effect the part
//! label, `kind` (`spring`, `joint_limit`, `gravity`, `quadratic_damping`, `extra_friction`),
//! whether it is the object's `primary` effect, how many pushes moved the part, and its parameters
//! in MuJoCo's joint coordinate along the ground truth's axis (`q_start` at the first frame).
//!
//! Rules:
//! - an effect is *scorable* when the part was pushed at least twice (criticism holds one push out
//!   of a refit to the others: with one push there is nothing to hold out) and, for a stop, when it
//!   was reached (`hit`); `extra_friction` is Coulomb friction, which the base model has: the right
//!   outcome is no added effect on that part (`absorbed`);
//! - *named*: criticism's final findings hold an effect of that kind for that part;
//! - the parameter error is relative for a spring's stiffness and a quadratic damping coefficient
//!   (`|est - true| / true`), and absolute in joint units (rad or m) for a stop's position, the
//!   truth mapped to bom's coordinate: `sign(axis_bom . axis_true) (q - q_start)`, bom's coordinate
//!   being zero at the part's first observed frame;
//! - a *false alarm* is an added effect whose kind acts on no part of that label in the truth; an
//!   *effect-free object* is one with no scorable effect of any kind (`none` objects and stops never
//!   reached).

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::median;
use crate::criticism::Finding;
use crate::inference::Posterior;
use crate::input::GroundTruth;
use crate::model::effects::EffectKind;

/// One undeclared effect of a corpus object (see the module docs).
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
pub struct TrueEffect {
    pub part: u32,
    pub kind: String,
    #[serde(default)]
    pub primary: bool,
    #[serde(default)]
    pub pushes: u32,
    #[serde(default)]
    pub q_start: Option<f64>,
    #[serde(default)]
    pub stiffness: Option<f64>,
    #[serde(default)]
    pub rest_position: Option<f64>,
    #[serde(default)]
    pub lower: Option<f64>,
    #[serde(default)]
    pub upper: Option<f64>,
    /// A stop: whether the recording reached it (absent: reached).
    #[serde(default)]
    pub hit: Option<bool>,
    #[serde(default)]
    pub coefficient: Option<f64>,
}

impl TrueEffect {
    /// Whether criticism can be asked to find this effect (module docs).
    pub fn scorable(&self) -> bool {
        self.pushes >= 2 && self.hit != Some(false) && self.kind != "extra_friction"
    }

    /// Extra Coulomb friction on a part pushed at least twice: the base model should absorb it.
    pub fn absorbable(&self) -> bool {
        self.kind == "extra_friction" && self.pushes >= 2
    }
}

/// One true effect against criticism's final findings.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct EffectScore {
    pub part: u32,
    pub kind: String,
    pub primary: bool,
    pub named: bool,
    pub rmse_before_m: Option<f64>,
    pub rmse_after_m: Option<f64>,
    /// Relative (stiffness, coefficient) or absolute (stop position, rad or m) error.
    pub param_error: Option<f64>,
    /// Whether the parameter is within the tolerance (25%; a stop within 1 cm or 0.05 rad).
    pub param_ok: Option<bool>,
    /// Whether the true parameter lies in the finding's 90% interval (for a stop: every true stop
    /// in the interval of one estimated stop).
    pub in_interval: Option<bool>,
}

/// An effect criticism added.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct AddedEffect {
    pub part: u32,
    pub effect: String,
    pub rmse_before_m: f64,
    pub rmse_after_m: f64,
    pub evidence_nats: f64,
    /// Whether an effect of this kind acts on this part in the truth.
    pub true_effect: bool,
}

/// Criticism's score on one object.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CriticismRow {
    pub category: Option<String>,
    pub effects: Vec<EffectScore>,
    pub added: Vec<AddedEffect>,
    /// `extra_friction` parts (scorable pushes) left without an added effect.
    pub absorbed: Vec<(u32, bool)>,
    /// No scorable true effect on the object.
    pub effect_free: bool,
    pub false_alarms: usize,
    /// Added effects whose held-out error did not fall.
    pub after_not_below_before: usize,
}

/// Score criticism's final `findings` of one object against its `truth`.
pub fn score(truth: &[TrueEffect], category: Option<&str>, findings: &[Finding], post: Option<&Posterior>, gt: Option<&GroundTruth>) -> CriticismRow {
    let added: Vec<AddedEffect> = findings
        .iter()
        .filter(|f| f.effect.is_some())
        .map(|f| AddedEffect {
            part: f.part,
            effect: f.name().to_string(),
            rmse_before_m: f.rmse_before_m,
            rmse_after_m: f.rmse_after_m,
            evidence_nats: f.evidence_nats,
            true_effect: truth.iter().any(|t| t.part == f.part && t.kind == f.name() && t.hit != Some(false)),
        })
        .collect();
    let sign = |part: u32| -> f64 {
        let est = post.and_then(|p| p.joints.iter().find(|j| j.child == part)).and_then(|j| j.axis.as_ref()).map(|a| a.direction);
        let tru = gt.and_then(|g| g.parts.iter().find(|p| p.label == part)).and_then(|p| p.axis_direction).map(Vector3::from);
        match (est, tru) {
            (Some(e), Some(t)) if e.dot(&t) < 0.0 => -1.0,
            _ => 1.0,
        }
    };
    let effects = truth
        .iter()
        .filter(|t| t.scorable())
        .map(|t| {
            let f = findings.iter().find(|f| f.part == t.part && f.effect.is_some() && f.name() == t.kind);
            let param = |name: &str| f.and_then(|f| f.params.iter().find(|(n, _)| n == name).map(|x| x.1));
            let interval = |name: &str| f.and_then(|f| f.intervals.iter().find(|(n, _)| n == name).map(|x| x.1));
            let inside = |name: &str, v: Option<f64>| Some(interval(name).zip(v).is_some_and(|([lo, hi], v)| lo <= v && v <= hi)).filter(|_| f.is_some());
            let (param_error, param_ok, in_interval) = match t.kind.as_str() {
                "spring" => with(rel(param("stiffness"), t.stiffness), inside("stiffness", t.stiffness)),
                "quadratic_damping" => with(rel(param("coefficient"), t.coefficient), inside("coefficient", t.coefficient)),
                "joint_limit" => {
                    let s = sign(t.part);
                    let q0 = t.q_start.unwrap_or(0.0);
                    let revolute = gt.and_then(|g| g.parts.iter().find(|p| p.label == t.part)).is_some_and(|p| p.joint == "revolute");
                    let est: Vec<f64> = ["lower", "upper"].iter().filter_map(|n| param(n)).collect();
                    // The true stops in bom's coordinate (module docs).
                    let stops: Vec<f64> = [t.lower, t.upper].iter().flatten().map(|&q| s * (q - q0)).collect();
                    let errs: Vec<f64> = stops.iter().map(|v| est.iter().map(|e| (e - v).abs()).fold(f64::INFINITY, f64::min)).collect();
                    let covered = stops.iter().all(|&v| ["lower", "upper"].iter().filter_map(|n| interval(n)).any(|[lo, hi]| lo <= v && v <= hi));
                    if f.is_none() || errs.is_empty() {
                        (None, None, None)
                    } else {
                        let worst = errs.iter().cloned().fold(0.0, f64::max);
                        (Some(worst), Some(worst <= if revolute { 0.05 } else { 0.01 }), Some(covered))
                    }
                }
                _ => (None, None, None),
            };
            EffectScore {
                part: t.part,
                kind: t.kind.clone(),
                primary: t.primary,
                named: f.is_some(),
                rmse_before_m: f.map(|f| f.rmse_before_m),
                rmse_after_m: f.map(|f| f.rmse_after_m),
                param_error,
                param_ok,
                in_interval,
            }
        })
        .collect();
    let absorbed = truth
        .iter()
        .filter(|t| t.absorbable())
        .map(|t| (t.part, !added.iter().any(|a| a.part == t.part)))
        .collect();
    CriticismRow {
        category: category.map(str::to_string),
        effect_free: !truth.iter().any(|t| t.scorable() || t.absorbable()),
        false_alarms: added.iter().filter(|a| !a.true_effect).count(),
        after_not_below_before: added.iter().filter(|a| a.rmse_after_m >= a.rmse_before_m).count(),
        effects,
        added,
        absorbed,
    }
}

fn with((e, ok): (Option<f64>, Option<bool>), inside: Option<bool>) -> (Option<f64>, Option<bool>, Option<bool>) {
    (e, ok, inside.filter(|_| e.is_some()))
}

fn rel(est: Option<f64>, truth: Option<f64>) -> (Option<f64>, Option<bool>) {
    match (est, truth) {
        (Some(e), Some(t)) if t != 0.0 => {
            let r = (e - t).abs() / t.abs();
            (Some(r), Some(r <= 0.25))
        }
        _ => (None, None),
    }
}

/// Per effect kind over a set of objects.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct KindScore {
    pub kind: String,
    /// Scorable primary effects of this kind, and how many were named.
    pub primary: usize,
    pub named: usize,
    /// Named with the held-out RMSE after at most a third of before.
    pub named_third: usize,
    pub ratio_median: Option<f64>,
    pub param_error_median: Option<f64>,
    pub param_ok: [usize; 2],
    /// Primary effects whose true parameter lies in the reported 90% interval / those scored.
    pub in_interval: [usize; 2],
    /// Secondary effects of this kind (e.g. the stop a gravity-loaded lid rests on), named / all.
    pub secondary: [usize; 2],
}

/// Criticism over a set of scored objects.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CriticismAggregate {
    pub objects: usize,
    pub per_kind: Vec<KindScore>,
    /// All scorable primary effects: named, and named with after <= before / 3.
    pub primary: usize,
    pub named: usize,
    pub named_third: usize,
    /// Effect-free objects, and those with at least one added effect.
    pub effect_free: usize,
    pub effect_free_alarmed: usize,
    /// False alarms on all objects (added effects of a kind the part lacks).
    pub false_alarms: usize,
    /// `extra_friction` parts: absorbed (no effect added) / all.
    pub absorbed: [usize; 2],
    /// Added effects whose held-out error did not fall (must be 0).
    pub after_not_below_before: usize,
}

/// Aggregate per effect kind (see [`CriticismAggregate`]).
pub fn aggregate(rows: &[&CriticismRow]) -> CriticismAggregate {
    let kinds = EffectKind::ALL.map(EffectKind::name);
    let all: Vec<&EffectScore> = rows.iter().flat_map(|r| r.effects.iter()).collect();
    let third = |e: &EffectScore| e.named && matches!((e.rmse_before_m, e.rmse_after_m), (Some(b), Some(a)) if a <= b / 3.0);
    let per_kind = kinds
        .iter()
        .map(|&k| {
            let p: Vec<&&EffectScore> = all.iter().filter(|e| e.kind == k && e.primary).collect();
            let s: Vec<&&EffectScore> = all.iter().filter(|e| e.kind == k && !e.primary).collect();
            KindScore {
                kind: k.into(),
                primary: p.len(),
                named: p.iter().filter(|e| e.named).count(),
                named_third: p.iter().filter(|e| third(e)).count(),
                ratio_median: median(p.iter().filter_map(|e| Some(e.rmse_after_m? / e.rmse_before_m?)).collect()),
                param_error_median: median(p.iter().filter_map(|e| e.param_error).collect()),
                param_ok: [p.iter().filter(|e| e.param_ok == Some(true)).count(), p.iter().filter(|e| e.param_ok.is_some()).count()],
                in_interval: [p.iter().filter(|e| e.in_interval == Some(true)).count(), p.iter().filter(|e| e.in_interval.is_some()).count()],
                secondary: [s.iter().filter(|e| e.named).count(), s.len()],
            }
        })
        .collect();
    let prim: Vec<&&EffectScore> = all.iter().filter(|e| e.primary).collect();
    CriticismAggregate {
        objects: rows.len(),
        per_kind,
        primary: prim.len(),
        named: prim.iter().filter(|e| e.named).count(),
        named_third: prim.iter().filter(|e| third(e)).count(),
        effect_free: rows.iter().filter(|r| r.effect_free).count(),
        effect_free_alarmed: rows.iter().filter(|r| r.effect_free && !r.added.is_empty()).count(),
        false_alarms: rows.iter().map(|r| r.false_alarms).sum(),
        absorbed: [rows.iter().flat_map(|r| &r.absorbed).filter(|a| a.1).count(), rows.iter().map(|r| r.absorbed.len()).sum()],
        after_not_below_before: rows.iter().map(|r| r.after_not_below_before).sum(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn finding(part: u32, kind: EffectKind, params: &[(&str, f64)], before: f64, after: f64) -> Finding {
        Finding {
            part,
            effect: Some(kind),
            limit: None,
            params: params.iter().map(|(n, v)| (n.to_string(), *v)).collect(),
            // 90% intervals of +-10% around each estimate.
            intervals: params.iter().map(|(n, v)| (n.to_string(), [0.9 * v, 1.1 * v])).collect(),
            rmse_before_m: before,
            rmse_after_m: after,
            evidence_nats: 20.0,
            new: true,
            before: vec![],
            after: vec![],
        }
    }

    fn effect(part: u32, kind: &str, pushes: u32) -> TrueEffect {
        TrueEffect {
            part,
            kind: kind.into(),
            primary: true,
            pushes,
            q_start: Some(0.1),
            stiffness: Some(2.0),
            rest_position: None,
            lower: None,
            upper: Some(0.5),
            hit: None,
            coefficient: None,
        }
    }

    #[test]
    fn named_false_alarms_and_stops() {
        // A spring named on part 2 (stiffness 2.4 of 2.0: 20%), a stop on part 3 found 0.03 rad
        // off (the truth at 0.5 - 0.1 = 0.4 in bom's coordinate), a gravity effect on part 2
        // that does not act there.
        let truth = vec![effect(2, "spring", 3), effect(3, "joint_limit", 2), effect(4, "spring", 1)];
        let findings = vec![
            finding(2, EffectKind::Spring, &[("stiffness", 2.4)], 0.03, 0.005),
            finding(3, EffectKind::JointLimit, &[("upper", 0.43)], 0.02, 0.012),
            finding(2, EffectKind::Gravity, &[("mass", 1.0)], 0.03, 0.031),
        ];
        let row = score(&truth, Some("spring"), &findings, None, None);
        assert_eq!(row.effects.len(), 2, "the spring on a part pushed once is not scorable");
        assert!(row.effects[0].named && row.effects[0].param_ok == Some(true));
        assert!((row.effects[1].param_error.unwrap() - 0.03).abs() < 1e-12);
        // 2.0 is outside [2.16, 2.64]; 0.4 inside [0.387, 0.473].
        assert_eq!((row.effects[0].in_interval, row.effects[1].in_interval), (Some(false), Some(true)));
        assert_eq!(row.false_alarms, 1);
        assert_eq!(row.after_not_below_before, 1);
        assert!(!row.effect_free);
        let agg = aggregate(&[&row]);
        assert_eq!((agg.primary, agg.named, agg.named_third), (2, 2, 1));
    }
}
