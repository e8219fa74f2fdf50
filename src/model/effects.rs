//! Effects beyond viscous damping and Coulomb friction: physics terms that a joint may need and
//! the base model lacks, each with its own priors. A recording may declare them (contract section
//! 3, `effects`); model criticism ([`crate::criticism`]) adds the ones the residuals call for.
//!
//! | effect | force on the joint coordinate `q` | latent parameters (prior) |
//! |---|---|---|
//! | `spring` | `-k (q - rest)` | stiffness `k` (log-normal), rest position (normal around the reference configuration) |
//! | `joint_limit` | `-k_c w softplus((q - q_lim) / w)` beyond an upper stop (mirrored for a lower one) | per stop (lower, upper or both) its position (normal around an anchor), one contact stiffness `k_c` (log-normal) |
//! | `gravity` | the moment (force) of the subtree's weights about (along) the axis, each acting at the centre of its part's seen surface ([`crate::model::dynamics::JointInWindow::weight_com`]) | none: the fixed frame's gravity vector and the part's mass, already latent |
//! | `quadratic_damping` | `-c q' \|q'\|`: the drag of a fluid or a soft-close damper | coefficient `c` (log-normal) |
//!
//! Parameters are standardised like the base kinodynamic ones (paper §3.2: `xi ~ N(0, 1)` mapped
//! to the physical scale) and follow the base four in [`crate::model::dynamics::decode`]'s layout,
//! in the order of the table.

use serde::{Deserialize, Serialize};

/// Kinds of effects, in the order of their parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EffectKind {
    Spring,
    JointLimit,
    Gravity,
    QuadraticDamping,
}

impl EffectKind {
    pub const ALL: [EffectKind; 4] = [EffectKind::Spring, EffectKind::JointLimit, EffectKind::Gravity, EffectKind::QuadraticDamping];

    /// The name in the contract (`bom_ground_truth` effects, JSON `criticism`).
    pub fn name(self) -> &'static str {
        match self {
            EffectKind::Spring => "spring",
            EffectKind::JointLimit => "joint_limit",
            EffectKind::Gravity => "gravity",
            EffectKind::QuadraticDamping => "quadratic_damping",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        EffectKind::ALL.into_iter().find(|k| k.name() == s)
    }
}

/// The joint's stops in the model: on each side that has one, the anchor its position prior is
/// centred on [m of centre-of-mass path from the reference configuration].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LimitSpec {
    pub lower: Option<f64>,
    pub upper: Option<f64>,
}

impl LimitSpec {
    /// Number of stops (0, 1 or 2).
    pub fn sides(&self) -> usize {
        self.lower.is_some() as usize + self.upper.is_some() as usize
    }
}

/// The effects on one part's joint.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EffectSet {
    pub spring: bool,
    pub limit: Option<LimitSpec>,
    pub gravity: bool,
    pub quadratic_damping: bool,
}

impl EffectSet {
    /// Number of latent parameters the effects add (after the base four).
    pub fn num_params(&self) -> usize {
        2 * self.spring as usize + self.limit.map_or(0, |l| l.sides() + 1) + self.quadratic_damping as usize
    }

    /// Each present effect's kind with the number of standardised parameters it adds, in the
    /// layout of [`crate::model::dynamics::decode`] after the base four (spring: stiffness, rest;
    /// joint limit: each stop's position, then the contact stiffness; gravity: none; quadratic
    /// damping: its coefficient). The lengths sum to [`EffectSet::num_params`].
    pub fn param_blocks(&self) -> Vec<(EffectKind, usize)> {
        self.kinds()
            .into_iter()
            .map(|k| {
                let len = match k {
                    EffectKind::Spring => 2,
                    EffectKind::JointLimit => self.limit.map_or(0, |l| l.sides() + 1),
                    EffectKind::Gravity => 0,
                    EffectKind::QuadraticDamping => 1,
                };
                (k, len)
            })
            .collect()
    }

    /// Whether any effect is present.
    pub fn any(&self) -> bool {
        *self != EffectSet::default()
    }

    /// This set with one more effect (`limit` for a joint limit).
    pub fn with(mut self, kind: EffectKind, limit: Option<LimitSpec>) -> Self {
        match kind {
            EffectKind::Spring => self.spring = true,
            EffectKind::JointLimit => self.limit = limit.or(self.limit),
            EffectKind::Gravity => self.gravity = true,
            EffectKind::QuadraticDamping => self.quadratic_damping = true,
        }
        self
    }

    /// This set without `kind`.
    pub fn without(mut self, kind: EffectKind) -> Self {
        match kind {
            EffectKind::Spring => self.spring = false,
            EffectKind::JointLimit => self.limit = None,
            EffectKind::Gravity => self.gravity = false,
            EffectKind::QuadraticDamping => self.quadratic_damping = false,
        }
        self
    }

    /// The kinds present, in parameter order.
    pub fn kinds(&self) -> Vec<EffectKind> {
        let mut k = Vec::new();
        if self.spring {
            k.push(EffectKind::Spring);
        }
        if self.limit.is_some() {
            k.push(EffectKind::JointLimit);
        }
        if self.gravity {
            k.push(EffectKind::Gravity);
        }
        if self.quadratic_damping {
            k.push(EffectKind::QuadraticDamping);
        }
        k
    }
}

/// Priors of the effects (`model.dynamics.effects` in the config). Medians per joint type are
/// `[prismatic, revolute]` in the joint's units.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct EffectsConfig {
    /// Spring stiffness (N/m, N·m/rad) and the prior sd of its rest position around the reference
    /// configuration [m of path].
    pub spring_median: [f64; 2],
    pub spring_log_sd: f64,
    pub spring_rest_sd_m: f64,
    /// Joint stop: contact stiffness (N/m, N·m/rad), prior sd of its position around the anchor
    /// [m of path] and the contact width [m of path].
    pub limit_stiffness_median: [f64; 2],
    pub limit_stiffness_log_sd: f64,
    pub limit_position_sd_m: f64,
    pub limit_width_m: f64,
    /// Gravity in the fixed frame (m/s²; REP 103: z up).
    pub gravity: [f64; 3],
    /// Quadratic damping coefficient (N·s²/m², N·m·s²/rad²).
    pub quadratic_damping_median: [f64; 2],
    pub quadratic_damping_log_sd: f64,
}

impl Default for EffectsConfig {
    fn default() -> Self {
        EffectsConfig {
            spring_median: [10.0, 1.0],
            spring_log_sd: 1.5,
            spring_rest_sd_m: 0.3,
            limit_stiffness_median: [2000.0, 200.0],
            limit_stiffness_log_sd: 1.5,
            limit_position_sd_m: 0.05,
            limit_width_m: 0.002,
            gravity: [0.0, 0.0, -9.81],
            quadratic_damping_median: [50.0, 0.5],
            quadratic_damping_log_sd: 1.5,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_parameters_count() {
        for k in EffectKind::ALL {
            assert_eq!(EffectKind::parse(k.name()), Some(k));
        }
        assert_eq!(EffectKind::parse("magnet"), None);
        let all = EffectKind::ALL.into_iter().fold(EffectSet::default(), |s, k| s.with(k, Some(LimitSpec { lower: Some(-0.1), upper: Some(0.1) })));
        assert_eq!(all.num_params(), 6);
        assert_eq!(all.kinds(), EffectKind::ALL.to_vec());
        assert!(!EffectSet::default().any());
    }
}
