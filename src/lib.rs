//! # bom — Bayesian Object Models for ROS 2
//!
//! bom turns segmented part point clouds (and, in dynamic mode, the wrench a robot applied)
//! into a posterior over an articulated object's kinematic tree, joint types and screw axes:
//! the Bayesian object models of Gothoskar et al. (CoRL 2022), fitted online by SVI.
//!
//! Data flows one way, one module per stage:
//! [`input`] (bags, topics) -> [`perception`] (clouds to part centres and poses) -> [`windows`]
//! -> [`model`] (priors, tree sampler, physics, effects, likelihood, the log density) ->
//! [`inference`] (SVI, NUTS) ->
//! [`criticism`] (held-out residuals, missing effects) -> [`prediction`] (posterior predictive
//! part motion under a wrench) -> [`output`] (summary table, JSON, ROS
//! messages, bags, plots). [`pipeline`] wires the stages for
//! `bom replay`; [`import`] makes bags from articulation track logs.
//!
//! ```no_run
//! use bom::{config::Config, pipeline};
//! let cfg = Config::default();
//! let run = pipeline::replay(&["bags/sturm/cabinet_one_001.mcap".into()], &cfg).unwrap();
//! for j in &run.posterior.as_ref().unwrap().joints {
//!     println!("part {}: {:?} p={:?}", j.child, j.map_type, j.type_probs);
//! }
//! ```

// Numeric code: `!(x > 0.0)` is meant — it also rejects NaN, which `x <= 0.0` would let through;
// and index loops run over several parallel arrays (coordinates, frames, parts) at once.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod config;
pub mod criticism;
pub mod diagnostics;
pub mod eval;
pub mod import;
pub mod inference;
pub mod input;
pub mod model;
pub mod msgs;
pub mod node;
pub mod output;
pub mod parallel;
pub mod perception;
pub mod pipeline;
pub mod prediction;
pub mod windows;
