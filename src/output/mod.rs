//! Output stage: the human summary, the JSON summary (contract section 5), the ROS messages of
//! contract section 2, the output bag and the figures of model criticism.

pub mod bag;
pub mod json;
pub mod messages;
pub mod plot;
pub mod table;

pub use bag::BagWriter;

use std::path::Path;

use nalgebra::{UnitQuaternion, Vector3};

use crate::config::Config;
use crate::msgs::Time;
use crate::pipeline::Run;


/// Write the output topics of a replay to an MCAP bag: `/bom/object_model` and `/bom/markers`
/// after every update (stamped at the end of the window that triggered it),
/// `/bom/model_criticism` after every update with findings, and
/// `/bom/predicted_part_poses` for every cloud frame from the posterior current at that time;
/// frames before the first update, which the live node could not track yet, use the first
/// posterior so that the whole recording is tracked.
///
/// # Errors
/// A one-line description naming the file.
pub fn write_replay_bag(run: &Run, path: &Path, cfg: &Config) -> Result<(), String> {
    let err = |e: bag::WriteError| format!("{}: {e}", path.display());
    let mut w = BagWriter::create(path).map_err(err)?;
    let frame = &cfg.fixed_frame;
    for u in &run.updates {
        let stamp = Time::from_seconds(u.stamp);
        let model = messages::object_model(&u.posterior, stamp, frame, run.mode, u.num_windows as u32, "svi");
        w.write("/bom/object_model", "bom_msgs/msg/ObjectModel", stamp.nanos(), &model).map_err(err)?;
        let markers = messages::markers(&u.posterior, stamp, frame);
        w.write("/bom/markers", "visualization_msgs/msg/MarkerArray", stamp.nanos(), &markers).map_err(err)?;
        if !u.criticism.findings.is_empty() {
            let msg = messages::model_criticism(&u.criticism.findings, stamp, frame);
            w.write("/bom/model_criticism", "bom_msgs/msg/ModelCriticism", stamp.nanos(), &msg).map_err(err)?;
        }
    }
    // BOM-NUTS's posterior of the last update follows it, as in the node.
    if let (Some(_), Some(p), Some(last)) = (&run.sampler, &run.posterior, run.updates.last()) {
        let stamp = Time::from_seconds(last.stamp);
        let model = messages::object_model(p, stamp, frame, run.mode, last.num_windows as u32, "nuts");
        w.write("/bom/object_model", "bom_msgs/msg/ObjectModel", stamp.nanos(), &model).map_err(err)?;
    }
    if let Some(first) = run.updates.first() {
        // Frames: every stamp at which some part was seen.
        let mut stamps: Vec<f64> = run.tracks.values().flatten().map(|o| o.stamp).collect();
        stamps.sort_by(|a, b| a.total_cmp(b));
        stamps.dedup();
        let labels: Vec<u32> = first.posterior.joints.iter().map(|j| j.child).collect();
        // A part's frame is aligned with the fixed frame in its reference configuration.
        let reference = vec![UnitQuaternion::identity(); labels.len()];
        let mut coords = vec![0.0; labels.len()];
        let mut cursor: std::collections::BTreeMap<u32, usize> = labels.iter().map(|l| (*l, 0)).collect();
        for t in stamps {
            let u = run.updates.iter().rev().find(|u| u.stamp <= t).unwrap_or(first);
            if u.posterior.joints.len() != labels.len() {
                continue;
            }
            let observed: Vec<Option<Vector3<f64>>> = labels
                .iter()
                .map(|l| {
                    let obs = run.tracks.get(l)?;
                    let c = cursor.get_mut(l)?;
                    while *c < obs.len() && obs[*c].stamp < t {
                        *c += 1;
                    }
                    let com = run.geometry.get(l).map(|g| g.com).unwrap_or_default();
                    (*c < obs.len() && obs[*c].stamp == t).then(|| (obs[*c].pose * nalgebra::Point3::from(com)).coords)
                })
                .collect();
            let poses = u.posterior.predict_poses(&observed, &mut coords, &reference);
            let stamp = Time::from_seconds(t);
            let msg = messages::pose_array(&poses, stamp, frame);
            w.write("/bom/predicted_part_poses", "geometry_msgs/msg/PoseArray", stamp.nanos(), &msg).map_err(err)?;
        }
    }
    w.finish().map_err(err)
}
