//! Rigid joint (URDF `fixed`): the child moves with its parent.
//!
//! Standardised parameters (all `N(0, 1)` a priori, paper §3.2), shared as the first block by
//! every joint type:
//! - `xi[0..3]`: reference centre of mass `com = com0 + com_sd_m * xi[0..3]` \[m\], `com0` the
//!   perceived centre of mass at the reference frame (paper: "each node has a center-of-mass
//!   parameter");
//! - `xi[3]`: position noise `sigma = noise_median_m * exp(noise_log_sd * xi[3])` \[m\];
//! - `xi[4]`: rotation noise `sigma_r = rotation_noise_median_rad * exp(rotation_noise_log_sd * xi[4])`
//!   \[rad\] (positions and rotations err differently: a partial view biases them separately).
//!
//! No joint coordinate; the displacement is the identity.

/// Number of standardised parameters of a rigid joint.
pub const NUM_PARAMS: usize = 5;
