//! A buffer of `/tf` and `/tf_static` transforms, tf2-style, on the `transforms` crate (frame tree,
//! chains of transforms, SLERP/linear interpolation in time, static edges valid at all times).
//!
//! Chosen over writing our own: `transforms` 2.3 is maintained, forbids unsafe code, validates every
//! input transform and reports an unknown frame or a stamp outside the buffered interval as a typed
//! error, which is what the contract asks for. This module only converts ROS messages in and
//! nalgebra isometries out, and normalises frame names (a leading `/` is dropped, as tf2 does).

use nalgebra::{Isometry3, Quaternion as NQuat, Translation3, UnitQuaternion};
use transforms::geometry::{Quaternion, Transform, Vector3};
use transforms::time::{Stamp, Timestamp};
use transforms::Registry;

use crate::msgs::{TFMessage, Time};

/// Why a transform was rejected or a lookup failed.
#[derive(Debug, thiserror::Error)]
pub enum TfError {
    #[error("transform '{parent}' -> '{child}' rejected: {why}")]
    Rejected { parent: String, child: String, why: String },
    #[error("no transform from '{target}' to '{source_frame}' at t={stamp:.3} s: {why}")]
    Lookup {
        target: String,
        source_frame: String,
        stamp: f64,
        why: String,
        /// The chain is known and a frame on it has transforms up to a time before `stamp` only:
        /// its transform at `stamp` has not come *yet* (latency), as opposed to an unknown frame,
        /// disconnected frames or a stamp before the buffered interval.
        late: bool,
    },
}

/// Time-stamped transforms between frames.
pub struct TfBuffer {
    registry: Registry,
}

impl Default for TfBuffer {
    fn default() -> Self {
        Self::new()
    }
}

fn frame(name: &str) -> &str {
    name.strip_prefix('/').unwrap_or(name)
}

impl TfBuffer {
    pub fn new() -> Self {
        TfBuffer { registry: Registry::new() }
    }

    /// A buffer that forgets dynamic transforms older than `max_age` behind the newest one (for
    /// the live node; static transforms never expire).
    pub fn with_cache(max_age: std::time::Duration) -> Self {
        TfBuffer { registry: Registry::with_max_age(max_age) }
    }

    /// Add every transform of a `tf2_msgs/TFMessage`; `is_static` for `/tf_static`. Returns one
    /// error per rejected transform (non-finite values, a quaternion far from unit norm, a frame
    /// that is its own parent, a frame re-parented); the others are kept.
    pub fn add(&mut self, msg: &TFMessage, is_static: bool) -> Vec<TfError> {
        let mut errors = Vec::new();
        for t in &msg.transforms {
            let (parent, child) = (frame(&t.header.frame_id), frame(&t.child_frame_id));
            let r = t.transform.rotation;
            let n = (r.x * r.x + r.y * r.y + r.z * r.z + r.w * r.w).sqrt();
            let reject = |why: String| TfError::Rejected { parent: parent.into(), child: child.into(), why };
            // Real publishers send slightly denormalised quaternions; renormalise those, reject the rest.
            if !(n.is_finite() && (0.9..1.1).contains(&n)) {
                errors.push(reject(format!("rotation quaternion has norm {n}")));
                continue;
            }
            let tr = t.transform.translation;
            let stamp = if is_static { Stamp::Static } else { Stamp::At(Timestamp::from_nanos(t.header.stamp.nanos())) };
            let made = Transform::new(
                parent,
                child,
                Vector3::new(tr.x, tr.y, tr.z),
                Quaternion { w: r.w / n, x: r.x / n, y: r.y / n, z: r.z / n },
                stamp,
            );
            match made {
                Ok(tf) => {
                    if let Err(e) = self.registry.add_transform(tf) {
                        errors.push(reject(e.to_string()));
                    }
                }
                Err(e) => errors.push(reject(e.to_string())),
            }
        }
        errors
    }

    /// The pose of `source` in `target` at `stamp`: maps `source` coordinates to `target` ones.
    ///
    /// # Errors
    /// [`TfError::Lookup`] for an unknown frame, frames not connected, or a stamp outside the
    /// buffered interval of a dynamic transform on the chain (no extrapolation; `late` when the
    /// stamp is after it).
    pub fn lookup(&self, target: &str, source: &str, stamp: Time) -> Result<Isometry3<f64>, TfError> {
        let (target, source) = (frame(target), frame(source));
        if target == source {
            return Ok(Isometry3::identity());
        }
        let asked = Timestamp::from_nanos(stamp.nanos());
        let t = self
            .registry
            .get_transform(target, source, asked)
            .map_err(|e| {
                let late = matches!(&e, transforms::errors::RegistryError::NotFoundAt { covered: Some((_, end)), .. } if *end < asked);
                TfError::Lookup { target: target.into(), source_frame: source.into(), stamp: stamp.seconds(), why: e.to_string(), late }
            })?;
        let (p, q) = (t.translation(), t.rotation());
        Ok(Isometry3::from_parts(
            Translation3::new(p.x, p.y, p.z),
            UnitQuaternion::from_quaternion(NQuat::new(q.w, q.x, q.y, q.z)),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Transform as RosTf, TransformStamped, Vector3 as V};

    fn tf(parent: &str, child: &str, sec: i32, x: f64, yaw: f64) -> TransformStamped {
        TransformStamped {
            header: Header { stamp: Time { sec, nanosec: 0 }, frame_id: parent.into() },
            child_frame_id: child.into(),
            transform: RosTf {
                translation: V { x, y: 0.0, z: 0.0 },
                rotation: crate::msgs::Quaternion { x: 0.0, y: 0.0, z: (yaw / 2.0).sin(), w: (yaw / 2.0).cos() },
            },
        }
    }

    #[test]
    fn chains_interpolates_and_reports_errors() {
        let mut b = TfBuffer::new();
        assert!(b.add(&TFMessage { transforms: vec![tf("world", "base", 0, 1.0, std::f64::consts::FRAC_PI_2)] }, true).is_empty());
        let dynamic = TFMessage { transforms: vec![tf("/base", "camera", 10, 0.0, 0.0), tf("base", "camera", 12, 2.0, 0.0)] };
        assert!(b.add(&dynamic, false).is_empty());
        // At t=11 the camera is 1 m along base x, which is world y; base sits at world x=1.
        let iso = b.lookup("world", "camera", Time { sec: 11, nanosec: 0 }).unwrap();
        let p = iso * nalgebra::Point3::origin();
        assert!((p - nalgebra::Point3::new(1.0, 1.0, 0.0)).norm() < 1e-9, "{p}");
        assert!(b.lookup("world", "camera", Time { sec: 20, nanosec: 0 }).is_err());
        let e = b.lookup("world", "nowhere", Time { sec: 11, nanosec: 0 }).unwrap_err().to_string();
        assert!(e.contains("nowhere"), "{e}");
        let mut bad = tf("world", "x", 0, 0.0, 0.0);
        bad.transform.rotation.w = 0.0;
        assert_eq!(b.add(&TFMessage { transforms: vec![bad] }, false).len(), 1);
    }
}
