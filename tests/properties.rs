//! Property tests (issue 27): the decoders' round trips (encode -> decode -> equal) and the stages
//! that order messages in time — the per-topic stamp clock, the windows and the TF buffer — under
//! arbitrary stamp orders, gaps and duplicates.

use bom::config::Config;
use bom::diagnostics::Diagnostics;
use bom::input::pointcloud::{decode, encode_xyzl};
use bom::input::{StampGuard, StampLimits, TfBuffer, WrenchSample};
use bom::msgs::{
    decode_cdr, encode_cdr, Header, PointCloud2, PointField, Quaternion, TFMessage, Time, Transform, TransformStamped, Vector3, Wrench,
    WrenchStamped,
};
use bom::windows::{force_windows, motion_windows, Window, WindowConfig};
use nalgebra::{Isometry3, Point3};
use proptest::prelude::*;

fn time() -> impl Strategy<Value = Time> {
    (any::<i32>(), 0u32..1_000_000_000).prop_map(|(sec, nanosec)| Time { sec, nanosec })
}

fn header() -> impl Strategy<Value = Header> {
    (time(), "[a-z_/]{0,12}").prop_map(|(stamp, frame_id)| Header { stamp, frame_id })
}

fn vector() -> impl Strategy<Value = Vector3> {
    (-1e6..1e6f64, -1e6..1e6f64, -1e6..1e6f64).prop_map(|(x, y, z)| Vector3 { x, y, z })
}

fn transform() -> impl Strategy<Value = TransformStamped> {
    (header(), "[a-z_]{1,8}", vector(), (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)).prop_map(|(header, child, t, (x, y, z, w))| {
        TransformStamped { header, child_frame_id: child, transform: Transform { translation: t, rotation: Quaternion { x, y, z, w } } }
    })
}

fn cloud() -> impl Strategy<Value = PointCloud2> {
    (
        header(),
        0u32..4,
        0u32..64,
        proptest::collection::vec(("[a-z]{1,6}", 0u32..64, 1u8..=8, 0u32..3), 0..6),
        any::<bool>(),
        0u32..64,
        0u32..4096,
        proptest::collection::vec(any::<u8>(), 0..512),
        any::<bool>(),
    )
        .prop_map(|(header, height, width, fields, is_bigendian, point_step, row_step, data, is_dense)| PointCloud2 {
            header,
            height,
            width,
            fields: fields.into_iter().map(|(name, offset, datatype, count)| PointField { name, offset, datatype, count }).collect(),
            is_bigendian,
            point_step,
            row_step,
            data,
            is_dense,
        })
}

proptest! {
    /// CDR, as bags and DDS carry every input type: encode -> decode -> equal.
    #[test]
    fn cdr_round_trips(h in header(), f in vector(), t in vector(), tfs in proptest::collection::vec(transform(), 0..5), c in cloud()) {
        let w = WrenchStamped { header: h, wrench: Wrench { force: f, torque: t } };
        prop_assert_eq!(decode_cdr::<WrenchStamped>(&encode_cdr(&w).unwrap()).unwrap(), w);
        let m = TFMessage { transforms: tfs };
        prop_assert_eq!(decode_cdr::<TFMessage>(&encode_cdr(&m).unwrap()).unwrap(), m);
        prop_assert_eq!(decode_cdr::<PointCloud2>(&encode_cdr(&c).unwrap()).unwrap(), c.clone());
        // Any prefix of a message is an error, never a panic.
        let bytes = encode_cdr(&c).unwrap();
        for cut in [0, 3, 4, bytes.len() / 2, bytes.len().saturating_sub(1)] {
            let _ = decode_cdr::<PointCloud2>(&bytes[..cut]);
        }
    }

    /// A cloud of labelled points: encode -> PointCloud2 -> decode gives the points (as f32) and
    /// labels back, label-0 points left out; an arbitrary layout decodes or errs, never panics.
    #[test]
    fn pointcloud_round_trips(pts in proptest::collection::vec(((-100.0..100.0f64, -100.0..100.0f64, -100.0..100.0f64), 0u32..5), 0..200), c in cloud()) {
        let points: Vec<[f64; 3]> = pts.iter().map(|((x, y, z), _)| [*x, *y, *z]).collect();
        let labels: Vec<u32> = pts.iter().map(|(_, l)| *l).collect();
        let got = decode(&encode_xyzl(Header::default(), &points, &labels), u64::MAX, f64::INFINITY).unwrap();
        let want: Vec<([f64; 3], u32)> =
            points.iter().zip(&labels).filter(|(_, l)| **l > 0).map(|(p, l)| (p.map(|v| v as f32 as f64), *l)).collect();
        prop_assert_eq!(got.points.iter().copied().zip(got.labels.iter().copied()).collect::<Vec<_>>(), want);
        if let Ok(lp) = decode(&c, 10_000, 1e3) {
            prop_assert_eq!(lp.points.len(), lp.labels.len());
            prop_assert!(lp.points.len() as u64 <= c.width as u64 * c.height as u64);
        }
    }

    /// The per-topic clock under arbitrary stamps: every message is either released once or
    /// counted as dropped, and without clock resets the released stamps never go back.
    #[test]
    fn stamp_guard_releases_or_counts_every_message(stamps in proptest::collection::vec(prop_oneof![0.0..100.0f64, 1e5..1e6f64, Just(5.0)], 0..200), reset in 1u32..20) {
        for reset_messages in [reset, u32::MAX] {
            let mut g = StampGuard::new(StampLimits { jump_s: 1.0, reset_messages });
            let mut diag = Diagnostics::default();
            let mut released = Vec::new();
            for (i, &t) in stamps.iter().enumerate() {
                released.extend(g.push("/t", t, i, &mut diag));
            }
            released.extend(g.flush());
            let mut ids: Vec<usize> = released.iter().map(|(_, i)| *i).collect();
            ids.sort();
            ids.dedup();
            prop_assert_eq!(ids.len(), released.len(), "a message released twice");
            let resets = diag.counts().get("/t: clock reset").copied().unwrap_or(0);
            prop_assert_eq!(released.len() as u64 + diag.total() - resets, stamps.len() as u64, "{:?}", diag.counts());
            if resets == 0 {
                prop_assert!(released.windows(2).all(|w| w[0].0 <= w[1].0), "{:?}", released);
            }
        }
    }

    /// Windows from wrenches and tracks with arbitrary stamp orders, gaps and duplicates: sorted,
    /// disjoint, at least `min_duration_s` long and inside the data's span.
    #[test]
    fn windows_are_sorted_disjoint_and_inside_the_data(samples in proptest::collection::vec((0.0..60.0f64, 0.0..5.0f64), 0..300), shuffle in any::<bool>()) {
        let cfg = WindowConfig::default();
        let mut samples = samples;
        if !shuffle {
            samples.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        let wrenches: Vec<WrenchSample> = samples
            .iter()
            .map(|&(t, f)| WrenchSample { stamp: t, point: Point3::origin(), force: nalgebra::Vector3::new(f, 0.0, 0.0), torque: nalgebra::Vector3::zeros() })
            .collect();
        let check = |ws: &[Window], lo: f64, hi: f64| -> Result<(), TestCaseError> {
            for w in ws {
                prop_assert!(w.end - w.start >= cfg.min_duration_s - 1e-9 && w.start >= lo - 1e-9 && w.end <= hi + 1e-9, "{:?}", ws);
            }
            prop_assert!(ws.windows(2).all(|p| p[0].end < p[1].start), "{:?}", ws);
            Ok(())
        };
        check(&force_windows(&wrenches, [], &cfg, 0.0, 60.0), 0.0, 60.0)?;
        let track: Vec<_> = samples
            .iter()
            .map(|&(t, x)| bom::perception::PartObservation {
                stamp: t,
                pose: Isometry3::translation(x * 0.1, 0.0, 0.0),
                com: Point3::new(x * 0.1, 0.0, 0.0),
                pose_cov: nalgebra::Matrix6::identity() * 1e-6,
                registration_cov: nalgebra::Matrix6::identity() * 1e-6,
                matched: 1.0,
                points: 10,
                outliers: 0,
            })
            .collect();
        let (lo, hi) = samples.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), s| (a.min(s.0), b.max(s.0)));
        let ws = motion_windows([track.as_slice()], &cfg);
        if !shuffle {
            check(&ws, lo, hi)?;
            // Light pushes (between the two force thresholds) under which the track moves.
            check(&force_windows(&wrenches, [track.as_slice()], &cfg, 0.0, 60.0), 0.0, 60.0)?;
        }
    }

    /// The TF buffer under arbitrary stamps (out of order, duplicated, far apart): lookups succeed
    /// or err, and every isometry they give is proper (unit rotation, finite).
    #[test]
    fn tf_lookups_are_proper_isometries(stamps in proptest::collection::vec((0i32..100, 0u32..1_000_000_000), 1..40), yaw in -3.0..3.0f64, at in (0i32..110, 0u32..1_000_000_000)) {
        let mut tf = TfBuffer::new();
        let rot = Quaternion { x: 0.0, y: 0.0, z: (yaw / 2.0).sin(), w: (yaw / 2.0).cos() };
        let fixed = TransformStamped {
            header: Header { stamp: Time::default(), frame_id: "world".into() },
            child_frame_id: "base".into(),
            transform: Transform { translation: Vector3 { x: 1.0, y: 0.0, z: 0.0 }, rotation: rot },
        };
        let _ = tf.add(&TFMessage { transforms: vec![fixed] }, true);
        for (k, &(sec, nanosec)) in stamps.iter().enumerate() {
            let m = TransformStamped {
                header: Header { stamp: Time { sec, nanosec }, frame_id: "base".into() },
                child_frame_id: "camera".into(),
                transform: Transform { translation: Vector3 { x: k as f64, y: 0.0, z: 0.0 }, rotation: rot },
            };
            let _ = tf.add(&TFMessage { transforms: vec![m] }, false);
        }
        let t = Time { sec: at.0, nanosec: at.1 };
        for (a, b) in [("world", "camera"), ("camera", "world"), ("world", "base"), ("base", "nowhere")] {
            if let Ok(iso) = tf.lookup(a, b, t) {
                prop_assert!((iso.rotation.norm() - 1.0).abs() < 1e-9 && iso.translation.vector.iter().all(|v| v.is_finite()));
            }
        }
        prop_assert!(tf.lookup("world", "base", t).is_ok());
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// Any prefix of a real bag reads as a prefix of its messages (a truncated recording keeps
    /// what came before the cut, in order, byte for byte), or errs when not one record is whole.
    #[test]
    fn a_cut_bag_reads_as_a_prefix_of_its_messages(cut in 0.0..1.0f64) {
        let bytes = std::fs::read("bags/mujoco/drawer.mcap").unwrap();
        let limits = bom::input::InputLimits::default();
        let full = bom::input::read_mcap(&bytes, "full", &limits, &mut Diagnostics::default()).unwrap().messages;
        let n = (bytes.len() as f64 * cut) as usize;
        if let Ok(part) = bom::input::read_mcap(&bytes[..n], "cut", &limits, &mut Diagnostics::default()) {
            prop_assert!(part.messages.len() <= full.len());
            for (a, b) in part.messages.iter().zip(&full) {
                prop_assert!(a.topic == b.topic && a.log_time == b.log_time && a.data == b.data);
            }
        }
    }
}

/// The node's streaming pipeline fed clouds and wrenches with shuffled, duplicated and far-apart
/// stamps: no panic; closed windows stay sorted and disjoint; every dropped message is counted.
#[test]
fn online_stream_survives_arbitrary_stamp_orders() {
    use bom::pipeline::online::Online;
    use rand::{Rng, SeedableRng};
    let cfg = Config::new();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    for _case in 0..20 {
        let mut on = Online::new(&cfg);
        for k in 0..600 {
            let t = match rng.random_range(0..10) {
                0 => rng.random_range(0.0..1e6),
                1 => (k as f64 / 30.0) - rng.random_range(0.0..5.0),
                _ => k as f64 / 30.0,
            };
            let x = if (5.0..8.0).contains(&t) { 0.05 * (t - 5.0) } else { 0.0 };
            let pts: Vec<[f64; 3]> = (0..27).map(|i| [x + (i % 3) as f64 * 0.02, (i / 3 % 3) as f64 * 0.02, (i / 9) as f64 * 0.02]).collect();
            let c = encode_xyzl(Header { stamp: Time::from_seconds(t.max(0.0)), frame_id: "world".into() }, &pts, &[1; 27]);
            on.cloud("/segmented_points", &c);
            let f = if (5.0..6.0).contains(&t) { 5.0 } else { 0.0 };
            let w = WrenchStamped {
                header: Header { stamp: Time::from_seconds(t.max(0.0)), frame_id: "world".into() },
                wrench: Wrench { force: Vector3 { x: f, y: 0.0, z: 0.0 }, torque: Vector3::default() },
            };
            on.wrench("/applied_wrench", &w);
            on.close_windows();
        }
        on.flush();
        let ws = on.windows();
        assert!(ws.windows(2).all(|p| p[0].end <= p[1].start), "{ws:?}");
        assert!(on.diag.total() > 0, "shuffled stamps were not reported");
    }
}
