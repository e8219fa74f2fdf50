//! Two readings of every hinge's coordinate in a bag, frame by frame: off the part's observed
//! centre of mass ([`bom::model::track_coordinate`]) and what the collapsed fit and model
//! criticism take ([`bom::model::observed_coordinate`]: off the observed turn where the part's
//! shape shows it). `bags/generate/hinge_readings.py` sets both against the recorder's joint
//! positions (README, "Stop 72").
//!
//! ```sh
//! cargo run --release --example hinge_readings -- BAG [CONFIG]
//! ```
//!
//! Replays BAG with the default configuration (or CONFIG) and prints, for every part the posterior
//! calls revolute, one line per grid frame at which it is seen: `label stamp_s q_com_m q_read_m
//! radius_m` (coordinates in metres of path, 0 at the part's reference configuration, the parent's
//! displacement taken out). Exit code 2 on bad arguments, 3 when the bag cannot be replayed.

use std::path::PathBuf;

use bom::config::Config;
use bom::criticism::residuals::part_transforms;
use bom::model::{observed_coordinate, track_coordinate, Displacement, JointType};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(bag) = args.first().map(PathBuf::from) else {
        eprintln!("usage: hinge_readings BAG [CONFIG]");
        std::process::exit(2);
    };
    let cfg = match args.get(1) {
        Some(path) => match Config::load(std::path::Path::new(path)) {
            Ok(cfg) => cfg,
            Err(e) => {
                eprintln!("error: {path}: {e}");
                std::process::exit(2);
            }
        },
        None => Config::new(),
    };
    let run = match bom::pipeline::replay(std::slice::from_ref(&bag), &cfg) {
        Ok(run) => run,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(3);
        }
    };
    let Some(post) = run.posterior.as_ref() else {
        eprintln!("error: {}: no posterior", bag.display());
        std::process::exit(3);
    };
    let ev = bom::pipeline::final_evidence(&run, &cfg);
    let transforms = part_transforms(post, ev.len());
    println!("# label stamp_s q_com_m q_read_m radius_m");
    for (i, part) in ev.parts.iter().enumerate() {
        let j = &post.joints[i];
        if j.map_type != JointType::Revolute {
            continue;
        }
        let p = &j.mean_params[j.map_type.index()];
        for (t, o) in part.obs.iter().enumerate() {
            let Some(o) = o else { continue };
            let pre = if j.parent_index == 0 { Displacement::identity() } else { transforms[j.parent_index - 1][t] };
            let from_com = track_coordinate(p, &pre.inverse_apply(&o.y));
            let read = observed_coordinate(p, &pre, &o.y, part.rot[t].as_ref());
            println!("{} {:.4} {:.6} {:.6} {:.4}", part.label, ev.times[t], from_com, read, p.radius);
        }
    }
}
