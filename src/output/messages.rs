//! ROS messages of contract section 2 built from a posterior: `bom_msgs/ObjectModel`,
//! `visualization_msgs/MarkerArray` (joint axes as arrows, part centres of mass as spheres, text
//! "revolute 0.97"), `geometry_msgs/PoseArray`, and `bom_msgs/ModelCriticism` from model
//! criticism's findings.

use nalgebra::{Isometry3, Vector3};

use crate::criticism::Finding;
use crate::inference::{Estimate, Posterior};
use crate::msgs::{
    ColorRGBA, EffectFinding, Header, JointPosterior, Marker, MarkerArray, ModelCriticism, ObjectModel, ParameterEstimate, Pose, PoseArray, Quaternion,
    Time, Vector3 as V3,
};

fn v3(v: &Vector3<f64>) -> V3 {
    V3 { x: v.x, y: v.y, z: v.z }
}

fn unknown() -> ParameterEstimate {
    ParameterEstimate { known: false, median: f64::NAN, sd: f64::NAN, q05: f64::NAN, q95: f64::NAN }
}

fn estimate(e: Option<&Estimate>) -> ParameterEstimate {
    e.map(|e| ParameterEstimate { known: true, median: e.median, sd: e.sd, q05: e.q05, q95: e.q95 }).unwrap_or_else(unknown)
}

/// `bom_msgs/ObjectModel` of a posterior; `inference` names the algorithm that gave it (`svi`,
/// `nuts`). Kinodynamic parameters are unknown in kinematic mode and for rigid joints.
pub fn object_model(p: &Posterior, stamp: Time, fixed_frame: &str, mode: &str, num_windows: u32, inference: &str) -> ObjectModel {
    let joints = p
        .joints
        .iter()
        .map(|j| {
            let axis = j.axis.as_ref().filter(|_| j.map_type.movable());
            let kd = j.kinodynamics.as_ref().filter(|_| j.map_type.movable());
            JointPosterior {
                child: j.child as i32,
                parent: j.parent as i32,
                parent_candidates: j.parent_probs.iter().map(|(l, _)| *l as i32).collect(),
                parent_probs: j.parent_probs.iter().map(|(_, p)| *p).collect(),
                most_probable_type: j.map_type.name().into(),
                p_rigid: j.type_probs[0],
                p_prismatic: j.type_probs[1],
                p_revolute: j.type_probs[2],
                axis_direction: axis.map(|a| v3(&a.direction)).unwrap_or_default(),
                axis_direction_sd_deg: axis.map(|a| a.direction_sd_deg).unwrap_or(f64::NAN),
                axis_direction_q90_deg: axis.map(|a| a.direction_q90_deg).unwrap_or(f64::NAN),
                has_axis_point: axis.and_then(|a| a.point).is_some(),
                axis_point: axis.and_then(|a| a.point).map(|p| v3(&p)).unwrap_or_default(),
                axis_point_sd_m: axis.map(|a| a.point_sd_m).unwrap_or(f64::NAN),
                damping: estimate(kd.map(|k| &k.damping)),
                friction: estimate(kd.map(|k| &k.friction)),
                mass: estimate(kd.map(|k| &k.mass)),
            }
        })
        .collect();
    ObjectModel {
        header: Header { stamp, frame_id: fixed_frame.into() },
        mode: mode.into(),
        inference: inference.into(),
        runtime_s: p.runtime_s,
        elbo: p.elbo,
        num_windows,
        part_labels: p.joints.iter().map(|j| j.child as i32).collect(),
        joints,
    }
}

fn color(r: f32, g: f32, b: f32) -> ColorRGBA {
    ColorRGBA { r, g, b, a: 1.0 }
}

/// Markers for RViz and Foxglove: a DELETEALL first, then per part a sphere at the centre of
/// mass, an arrow along a movable joint's axis (through the axis point for revolute joints, the
/// centre of mass for prismatic ones) and a text with the most probable type and its probability.
pub fn markers(p: &Posterior, stamp: Time, fixed_frame: &str) -> MarkerArray {
    let header = Header { stamp, frame_id: fixed_frame.into() };
    let mut out = vec![Marker { header: header.clone(), ns: "bom".into(), action: Marker::DELETEALL, ..Default::default() }];
    for j in &p.joints {
        let params = &j.mean_params[j.map_type.index()];
        let com = params.com;
        let id = j.child as i32 * 10;
        out.push(Marker {
            header: header.clone(),
            ns: "bom/com".into(),
            id,
            type_: Marker::SPHERE,
            action: Marker::ADD,
            pose: Pose { position: v3(&com), orientation: Quaternion::default() },
            scale: V3 { x: 0.03, y: 0.03, z: 0.03 },
            color: color(0.2, 0.6, 1.0),
            ..Default::default()
        });
        let prob = j.type_probs[j.map_type.index()];
        out.push(Marker {
            header: header.clone(),
            ns: "bom/type".into(),
            id: id + 1,
            type_: Marker::TEXT_VIEW_FACING,
            action: Marker::ADD,
            pose: Pose { position: v3(&(com + Vector3::new(0.0, 0.0, 0.08))), orientation: Quaternion::default() },
            scale: V3 { x: 0.0, y: 0.0, z: 0.05 },
            color: color(1.0, 1.0, 1.0),
            text: format!("{} {:.2}", j.map_type.name(), prob),
            ..Default::default()
        });
        if let (Some(a), true) = (&j.axis, j.map_type.movable()) {
            let start = a.point.unwrap_or(com) - a.direction * 0.25;
            let end = a.point.unwrap_or(com) + a.direction * 0.25;
            out.push(Marker {
                header: header.clone(),
                ns: "bom/axis".into(),
                id: id + 2,
                type_: Marker::ARROW,
                action: Marker::ADD,
                pose: Pose::default(),
                scale: V3 { x: 0.01, y: 0.02, z: 0.03 },
                color: color(1.0, 0.4, 0.1),
                points: vec![v3(&start), v3(&end)],
                ..Default::default()
            });
        }
    }
    MarkerArray { markers: out }
}

/// `geometry_msgs/PoseArray` of predicted part poses, in `ObjectModel.part_labels` order.
pub fn pose_array(poses: &[Isometry3<f64>], stamp: Time, fixed_frame: &str) -> PoseArray {
    PoseArray {
        header: Header { stamp, frame_id: fixed_frame.into() },
        poses: poses
            .iter()
            .map(|iso| {
                let q = iso.rotation;
                Pose {
                    position: v3(&iso.translation.vector),
                    orientation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
                }
            })
            .collect(),
    }
}

/// `bom_msgs/ModelCriticism` of findings: per finding the part, the effect (or `unexplained`),
/// its parameters by name (joint units; the residual's diagnosis when unexplained) and the
/// held-out centre-of-mass RMSE before and after \[m\].
pub fn model_criticism(findings: &[Finding], stamp: Time, fixed_frame: &str) -> ModelCriticism {
    ModelCriticism {
        header: Header { stamp, frame_id: fixed_frame.into() },
        findings: findings
            .iter()
            .map(|f| EffectFinding {
                part: f.part as i32,
                effect: f.name().into(),
                param_names: f.params.iter().map(|(k, _)| k.clone()).collect(),
                param_values: f.params.iter().map(|(_, v)| *v).collect(),
                rmse_before_m: f.rmse_before_m,
                rmse_after_m: f.rmse_after_m,
            })
            .collect(),
    }
}
