//! Output stage: the human summary, the JSON summary (contract section 5), the ROS messages of
//! contract section 2, the output bag and the figures of model criticism.

pub mod bag;
pub mod json;
pub mod messages;
pub mod plot;
pub mod table;

pub use bag::BagWriter;

use std::path::Path;

use crate::prediction::{PredictConfig, PredictiveModel, Scene};

use crate::config::Config;
use crate::msgs::Time;
use crate::pipeline::Run;


/// Write the output topics of a replay to an MCAP bag: `/bom/object_model` and `/bom/markers`
/// after every update (stamped at the end of the window that triggered it),
/// `/bom/model_criticism` after every update with findings, and
/// `/bom/predicted_part_poses` for every cloud frame after the first, predicted (as the node does)
/// from the posterior current at that time, the state up to the frame before and the wrench;
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
        // Frames: every stamp at which some part was seen; each predicted from the state up to
        // the frame before it (the node's predictor, `crate::prediction`).
        let scene = Scene { tracks: &run.tracks, geometry: &run.geometry, wrenches: &run.wrenches, windows: &run.windows };
        let models: Vec<PredictiveModel> = run.updates.iter().map(|u| PredictiveModel::from_posterior(&u.posterior, &u.criticism.findings)).collect();
        let pcfg = PredictConfig { draws: 0, ..cfg.prediction };
        let stamps = scene.stamps();
        for pair in stamps.windows(2) {
            let (prev, t) = (pair[0], pair[1]);
            let k = run.updates.iter().rposition(|u| u.stamp <= t).unwrap_or(0);
            if run.updates[k].posterior.joints.len() != first.posterior.joints.len() {
                continue;
            }
            let target = t + cfg.prediction.look_ahead_s;
            let Ok(pred) = crate::prediction::predict(&models[k], &scene, prev, &[target], &pcfg, &cfg.model) else { continue };
            let stamp = Time::from_seconds(target);
            let msg = messages::pose_array(&pred.poses(0), stamp, frame);
            w.write("/bom/predicted_part_poses", "geometry_msgs/msg/PoseArray", stamp.nanos(), &msg).map_err(err)?;
        }
    }
    w.finish().map_err(err)
}
