//! Benchmarks (`cargo bench`): the physics forward simulation and its gradient, the kinematic
//! posterior of a real track, the dynamic posterior of a 3-part cabinet after one window, and
//! whole replays. Speed is measured here and by
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

fn inference(c: &mut Criterion) {
    let cfg = Config::new();
    let bag: PathBuf = "bags/sturm/left_door_001.mcap".into();
    let run = bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).expect("bundled bag");
    let ev = Evidence::new(&run.tracks, &run.geometry, &run.windows, &[], &[], &bom::pipeline::grid(&cfg));
    let mut g = c.benchmark_group("inference");
    g.sample_size(20);
    g.bench_function("kinematic BOM-SVI posterior, real door track (left_door_001)", |b| {
        b.iter(|| svi::fit(black_box(&ev), &cfg.model, &cfg.inference, None))
    });
    // Dynamic mode: the posterior of a 3-part cabinet (two doors) after its first interaction
    // window, from its recorded wrenches (the "3-part object after one window").
    let cab: PathBuf = "bags/mujoco/hingecabinet.mcap".into();
    let run3 = bom::pipeline::replay(std::slice::from_ref(&cab), &cfg).expect("bundled bag");
    let springs = run3.ground_truth.as_ref().map(bom::pipeline::declared_springs).unwrap_or_default();
    let mut diag = bom::diagnostics::Diagnostics::default();
    let rec = bom::input::decode_recording(&[bom::input::read_bag(&cab, &mut diag).expect("bundled bag")], &cfg.topics, &cfg.fixed_frame, &mut diag);
    let ev3 = Evidence::new(&run3.tracks, &run3.geometry, &run3.windows[..1], &rec.wrenches, &springs, &bom::pipeline::grid(&cfg));
    g.sample_size(10);
    g.bench_function("dynamic BOM-SVI posterior, 3-part hinge cabinet, first window", |b| {
        b.iter(|| svi::fit(black_box(&ev3), &cfg.model, &cfg.inference, None))
    });
    g.bench_function("bom replay, real door track (left_door_001)", |b| {
        b.iter(|| bom::pipeline::replay(std::slice::from_ref(&bag), &cfg).unwrap())
    });
    g.finish();
}

criterion_group!(benches, physics, inference);
criterion_main!(benches);
