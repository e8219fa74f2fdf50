//! Benchmarks (`cargo bench`): the physics forward simulation and its gradient, the kinematic
//! posterior of a real track, the dynamic posterior of a 3-part cabinet after one window,
//! whole replays, model criticism against the posterior it criticises, and the posterior
//! predictive of `bom predict`. Speed is measured here and by
//! `bom replay --timing`, never in tests.

use std::hint::black_box;
use std::path::PathBuf;

use bom::config::Config;
use bom::inference::svi;
use bom::model::likelihood::Evidence;
use bom::model::physics::{Articulation, Body, IntegrationParameters, JointKind, Wrench};
use bom::model::Real;
use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::{Matrix3, Vector3};
use num_dual::DualSVec64;

/// A cabinet with two doors (3 parts), lifted into the scalar type with the doors' damping,
/// friction and mass as the variables `x` (6 of them).
fn cabinet<T: Real>(x: &[T; 6]) -> Articulation<T> {
    let v = |a: f64, b: f64, c: f64| Vector3::new(T::from(a), T::from(b), T::from(c));
    let inertia = |m: T| Matrix3::from_diagonal(&v(0.08, 0.05, 0.03)) * m;
    let door = |side: f64, d: T, f: T, m: T| Body {
        parent: Some(0),
        joint: JointKind::Revolute,
        axis: v(0.0, 0.0, side),
        point: v(0.4 * side, -0.3, 0.8),
        mass: m,
        com: v(0.2 * side, -0.32, 0.8),
        inertia: inertia(m),
        damping: d,
        friction: f,
        stiffness: T::from(0.0),
        rest: T::from(0.0),
    };
    Articulation {
        bodies: vec![
            Body {
                parent: None,
                joint: JointKind::Rigid,
                axis: v(0.0, 0.0, 1.0),
                point: v(0.0, 0.0, 0.0),
                mass: T::from(8.0),
                com: v(0.0, 0.0, 0.8),
                inertia: inertia(T::from(8.0)),
                damping: T::from(0.0),
                friction: T::from(0.0),
                stiffness: T::from(0.0),
                rest: T::from(0.0),
            },
            door(1.0, x[0], x[1], x[2]),
            door(-1.0, x[3], x[4], x[5]),
        ],
    }
}

fn simulate<T: Real>(x: &[T; 6]) -> T {
    let a = cabinet(x);
    let p = IntegrationParameters::default();
    let push = |t: f64| {
        let f = if t < 1.5 { 6.0 } else { 0.0 };
        vec![Wrench {
            body: 1,
            point: Vector3::new(T::from(0.05), T::from(-0.33), T::from(0.8)),
            force: Vector3::new(T::from(0.0), T::from(-f), T::from(0.0)),
            torque: Vector3::zeros(),
        }]
    };
    let zero = vec![T::from(0.0); 3];
    // One 3 s window at 30 Hz.
    a.simulate(&zero, &zero, 90, &p, push)[89][1]
}

fn physics(c: &mut Criterion) {
    let x = [2.0, 1.0, 1.2, 2.0, 1.0, 1.2];
    c.bench_function("physics: 3-part cabinet, 3 s window, forward simulation (f64)", |b| b.iter(|| simulate(black_box(&x))));
    type D = DualSVec64<6>;
    let xd: [D; 6] = std::array::from_fn(|i| D::from_re(x[i]).derivative(i));
    c.bench_function("physics: same, with the gradient over 6 kinodynamic parameters (dual numbers)", |b| {
        b.iter(|| simulate(black_box(&xd)))
    });
}

/// A bundled bag replayed (tracks, geometry, windows) and decoded (its wrenches), for building
/// dynamic-mode evidence.
fn replayed(bag: &str, cfg: &Config) -> (bom::pipeline::Run, bom::input::Recording) {
    let bag = PathBuf::from(bag);
    let run = bom::pipeline::replay(std::slice::from_ref(&bag), cfg).expect("bundled bag");
    let mut diag = bom::diagnostics::Diagnostics::default();
    let rec = bom::input::decode_recording(&[bom::input::read_bag(&bag, &mut diag).expect("bundled bag")], &cfg.topics, &cfg.fixed_frame, &mut diag);
    (run, rec)
}

fn inference(c: &mut Criterion) {
    let cfg = Config::new();
    let bag: PathBuf = "bags/sturm/left_door_001.mcap".into();
    let run = bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).expect("bundled bag");
    let ev = Evidence::new(&run.tracks, &run.geometry, &run.windows, &[], &Default::default(), &bom::pipeline::grid(&cfg));
    let mut g = c.benchmark_group("inference");
    g.sample_size(20);
    g.bench_function("kinematic BOM-SVI posterior, real door track (left_door_001)", |b| {
        b.iter(|| svi::fit(black_box(&ev), &cfg.model, &cfg.inference, None))
    });
    // Dynamic mode: the posterior of a 3-part cabinet (two doors) after its first interaction
    // window, from its recorded wrenches (the "3-part object after one window").
    let (run3, rec) = replayed("bags/mujoco/hingecabinet.mcap", &cfg);
    let springs = run3.ground_truth.as_ref().map(bom::pipeline::declared_effects).unwrap_or_default();
    let ev3 = Evidence::new(&run3.tracks, &run3.geometry, &run3.windows[..1], &rec.wrenches, &springs, &bom::pipeline::grid(&cfg));
    g.sample_size(10);
    g.bench_function("dynamic BOM-SVI posterior, 3-part hinge cabinet, first window", |b| {
        b.iter(|| svi::fit(black_box(&ev3), &cfg.model, &cfg.inference, None))
    });
    // The "one 3 s window": the first window (1.65 s: one push and its margins) runs on
    // to 3 s after its start, into the rest and the first 0.3 s of the next push (on the other
    // door, which then starts to move).
    let mut long = run3.windows[0];
    long.end = long.start + 3.0;
    let ev3l = Evidence::new(&run3.tracks, &run3.geometry, &[long], &rec.wrenches, &springs, &bom::pipeline::grid(&cfg));
    g.bench_function("dynamic BOM-SVI posterior, 3-part hinge cabinet, one 3 s window", |b| {
        b.iter(|| svi::fit(black_box(&ev3l), &cfg.model, &cfg.inference, None))
    });
    g.bench_function("bom replay, real door track (left_door_001)", |b| {
        b.iter(|| bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).unwrap())
    });
    g.finish();
}

/// BOM-NUTS (issue 26): one evaluation of the log density and its gradient on the drawer and
/// microwave bags (dynamic mode, 2 parts, 4 windows; centred and non-centred coordinates), which times the
/// number of leapfrog steps is a dynamic run's cost, and the whole sampler with its defaults
/// (4 chains x 1000 + 1000) on a real door track (kinematic mode). The dynamic run itself is
/// minutes long and is timed by `bom replay bags/mujoco/drawer.mcap --inference nuts --timing`.
fn nuts(c: &mut Criterion) {
    use bom::inference::nuts::{self, NutsConfig};
    use bom::model::density::{Density, NonCentred, Structure};
    use rand::SeedableRng;
    let cfg = Config::new();
    let mut g = c.benchmark_group("nuts");
    // A prismatic and a revolute joint: a revolute window's gradient costs about twice a
    // prismatic one's (its generalised force and inertia turn with the axis and hinge point).
    for bag in ["drawer", "microwave"] {
        let run = bom::pipeline::replay(&[PathBuf::from(format!("bags/mujoco/{bag}.mcap"))], &cfg).expect("bundled bag");
        let ev = bom::pipeline::final_evidence(&run, &cfg);
        let fitted = svi::fit(&ev, &cfg.model, &cfg.inference, None).expect("a fit");
        let joints = &fitted.posterior.joints;
        let structure = Structure { parent: joints.iter().map(|j| j.parent_index).collect(), types: joints.iter().map(|j| j.map_type).collect() };
        for (name, non_centred) in [("centred", false), ("non-centred", true)] {
            let nc = NonCentred::new(Density::new(&ev, &cfg.model, structure.clone()), non_centred);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
            let y = nc.from_model(&nuts::start_from_guide(nc.density(), &fitted.guide, &mut rng));
            let mut grad = vec![0.0; y.len()];
            g.bench_function(format!("log density and gradient, {bag} (2 parts, 4 windows), {name}"), |b| b.iter(|| nc.log_density(black_box(&y), &mut grad)));
        }
    }
    // A nested chain: the door on the slider (4 parts), where the slider's kinematic parameters
    // reach the door's physics by forward differences (`density::cross_physics_differences`).
    let run = bom::pipeline::replay(&[PathBuf::from("bags/mujoco/slide_microwave.mcap")], &cfg).expect("bundled bag");
    let ev = bom::pipeline::final_evidence(&run, &cfg);
    let fitted = svi::fit(&ev, &cfg.model, &cfg.inference, None).expect("a fit");
    let joints = &fitted.posterior.joints;
    let structure = Structure { parent: joints.iter().map(|j| j.parent_index).collect(), types: joints.iter().map(|j| j.map_type).collect() };
    let nc = NonCentred::new(Density::new(&ev, &cfg.model, structure), true);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let y = nc.from_model(&nuts::start_from_guide(nc.density(), &fitted.guide, &mut rng));
    let mut grad = vec![0.0; y.len()];
    g.bench_function("log density and gradient, slide_microwave (4 parts, door on slider), non-centred", |b| b.iter(|| nc.log_density(black_box(&y), &mut grad)));
    let bag: PathBuf = "bags/sturm/left_door_001.mcap".into();
    let run = bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).expect("bundled bag");
    let ev = bom::pipeline::final_evidence(&run, &cfg);
    let fitted = svi::fit(&ev, &cfg.model, &cfg.inference, None).expect("a fit");
    g.sample_size(10);
    g.bench_function("BOM-NUTS posterior (4 x 1000 + 1000), real door track (left_door_001)", |b| {
        b.iter(|| nuts::sample(black_box(&ev), &cfg.model, &fitted, &NutsConfig::default()).expect("NUTS runs"))
    });
    g.finish();
}

/// The posterior predictive (`bom predict`): a 3 s horizon of the nested `slide_microwave` (4
/// parts, the door revolute on the sliding microwave) from the start of its first push, at the
/// posterior medians and with a 100-draw band.
fn prediction(c: &mut Criterion) {
    use bom::prediction::{predict, PredictConfig, PredictiveModel, Scene};
    let cfg = Config::new();
    let bag = PathBuf::from("bags/mujoco/slide_microwave.mcap");
    let run = bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).expect("bundled bag");
    let model = PredictiveModel::from_posterior(run.posterior.as_ref().expect("a posterior"), &run.findings);
    let mut diag = bom::diagnostics::Diagnostics::default();
    let obs = bom::pipeline::observe(&[bag], &cfg, &mut diag).expect("bundled bag");
    let scene = Scene { tracks: &obs.tracks, geometry: &obs.geometry, wrenches: &obs.recording.wrenches, windows: &obs.windows };
    let from = obs.windows[0].start;
    let stamps: Vec<f64> = scene.stamps().into_iter().filter(|&t| t >= from && t <= from + 3.0).collect();
    let mut g = c.benchmark_group("predict");
    for draws in [0, 100] {
        let pcfg = PredictConfig { draws, ..PredictConfig::default() };
        g.bench_function(format!("3 s window, slide_microwave (4 parts), {draws} draws"), |b| {
            b.iter(|| predict(&model, &scene, from, black_box(&stamps), &pcfg, &cfg.model).expect("predicts"))
        });
    }
    g.finish();
}

/// `n` points on the surface of the box `lo`..`hi`, resampled per `frame` (a depth camera never
/// sees the same surface points twice), with ±1 mm of deterministic noise.
fn box_surface(lo: [f64; 3], hi: [f64; 3], n: usize, frame: usize) -> Vec<[f64; 3]> {
    let mut out = Vec::with_capacity(n);
    let (mut u, mut v) = (0.137 * frame as f64 % 1.0, 0.291 * frame as f64 % 1.0);
    for i in 0..n {
        // Low-discrepancy (golden-ratio) coordinates on the six faces.
        u = (u + 0.618_033_988_75).fract();
        v = (v + 0.754_877_666_25).fract();
        let face = i % 6;
        let (a, b) = ((face / 2 + 1) % 3, (face / 2 + 2) % 3);
        let mut p = [0.0; 3];
        p[face / 2] = if face % 2 == 0 { lo[face / 2] } else { hi[face / 2] };
        p[a] = lo[a] + u * (hi[a] - lo[a]);
        p[b] = lo[b] + v * (hi[b] - lo[b]);
        let noise = |k: usize| ((((i * 7 + k * 13 + frame * 31) * 2_654_435_761) % 2001) as f64 / 1000.0 - 1.0) * 1e-3;
        out.push([p[0] + noise(0), p[1] + noise(1), p[2] + noise(2)]);
    }
    out
}

/// Perception as the node runs it: one cloud of a 4-part object (cabinet body, a door swinging
/// about a vertical hinge, a sliding drawer, a shelf) with 20,000 labelled points, decoded,
/// transformed and registered (tests/ros/throughput.py streams the same object over DDS).
fn perception(c: &mut Criterion) {
    use bom::input::pointcloud::encode_xyzl;
    use bom::msgs::{Header, Time};
    use bom::pipeline::online::Online;
    let n = 5000;
    let frames: Vec<_> = (0..90)
        .map(|k| {
            let parts = [
                box_surface([0.0, -0.4, 0.0], [0.4, 0.4, 0.8], n, k),
                box_surface([0.42, -0.4, 0.02], [0.44, 0.0, 0.78], n, k),
                box_surface([0.05, 0.02, 0.1], [0.41, 0.38, 0.3], n, k),
                box_surface([0.0, -0.4, 0.85], [0.4, 0.4, 0.88], n, k),
            ];
            let t = k as f64 / 30.0;
            let (a, slide) = (0.2 * t, 0.05 * t);
            let (ca, sa) = (a.cos(), a.sin());
            let mut pts = Vec::new();
            let mut labels = Vec::new();
            for (i, part) in parts.iter().enumerate() {
                for p in part {
                    let q = match i {
                        1 => {
                            let (x, y) = (p[0] - 0.43, p[1] + 0.4);
                            [0.43 + ca * x - sa * y, -0.4 + sa * x + ca * y, p[2]]
                        }
                        2 => [p[0] + slide, p[1], p[2]],
                        _ => *p,
                    };
                    pts.push(q);
                    labels.push(i as u32 + 1);
                }
            }
            encode_xyzl(Header { stamp: Time::from_seconds(t), frame_id: "world".into() }, &pts, &labels)
        })
        .collect();
    let cfg = Config::new();
    let mut g = c.benchmark_group("perception");
    g.sample_size(10);
    g.bench_function("node perception: 90 clouds of a 4-part object, 20,000 points each (3 s at 30 Hz)", |b| {
        b.iter(|| {
            let mut on = Online::new(&cfg);
            for f in &frames {
                black_box(on.cloud("/segmented_points", f));
            }
        })
    });
    g.finish();
}

/// Model criticism (issue 25: its time per posterior at most twice the posterior's own): the
/// dynamic posterior of `hingecabinet_spring_undeclared` over all six windows, and the criticism
/// of that posterior (held-out refits, then every candidate effect on both doors, whose
/// springs are undeclared: the costly case).
fn criticism(c: &mut Criterion) {
    let cfg = Config::new();
    let (run, rec) = replayed("bags/mujoco/hingecabinet_spring_undeclared.mcap", &cfg);
    let ev = Evidence::new(&run.tracks, &run.geometry, &run.windows, &rec.wrenches, &Default::default(), &bom::pipeline::grid(&cfg));
    let fitted = svi::fit(&ev, &cfg.model, &cfg.inference, None).expect("posterior");
    let mut g = c.benchmark_group("criticism");
    g.sample_size(10);
    g.bench_function("dynamic BOM-SVI posterior, hinge cabinet with undeclared springs, 6 windows", |b| {
        b.iter(|| svi::fit(black_box(&ev), &cfg.model, &cfg.inference, None))
    });
    g.bench_function("criticism of that posterior", |b| {
        b.iter(|| bom::criticism::criticise(black_box(&ev), &fitted.posterior, &Default::default(), &cfg.model.dynamics, &cfg.criticism))
    });
    g.finish();
}

criterion_group!(benches, physics, inference, nuts, perception, prediction, criticism);
criterion_main!(benches);
