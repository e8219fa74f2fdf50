//! The kinematic BOM on clean synthetic motions: the posterior must be confident and right.

mod common;

use common::*;

#[test]
fn straight_line_is_prismatic() {
    let dir = tempfile::tempdir().unwrap();
    let bag = trajectory_bag(dir.path(), "line", 3.0, 0.002, |s| [0.4 + 0.3 * s, -0.2 + 0.1 * s, 0.8]);
    let p = type_probs(&replay(&[bag]));
    println!("line: P(rigid, prismatic, revolute) = {p:?}");
    assert!(p[1] >= 0.95, "P(prismatic) = {:.3} ({p:?})", p[1]);
}

#[test]
fn sixty_degree_arc_is_revolute_with_the_right_axis() {
    let dir = tempfile::tempdir().unwrap();
    // Handle 0.4 m from a vertical hinge at (0.5, 0.2).
    let bag = trajectory_bag(dir.path(), "arc", 3.0, 0.002, |s| {
        let a = s * std::f64::consts::FRAC_PI_3;
        [0.5 + 0.4 * a.cos(), 0.2 + 0.4 * a.sin(), 0.9]
    });
    let run = replay(&[bag]);
    let p = type_probs(&run);
    println!("arc: P(rigid, prismatic, revolute) = {p:?}");
    assert!(p[2] >= 0.95, "P(revolute) = {:.3} ({p:?})", p[2]);
    let axis = run.posterior.as_ref().unwrap().joints[0].axis.clone().unwrap();
    assert!(axis.direction.z.abs() > 0.99, "axis {}", axis.direction);
    let point = axis.point.unwrap();
    assert!(((point.x - 0.5).powi(2) + (point.y - 0.2).powi(2)).sqrt() < 0.02, "point {point}");
}

#[test]
fn still_part_is_rigid() {
    let dir = tempfile::tempdir().unwrap();
    let bag = trajectory_bag(dir.path(), "still", 3.0, 0.002, |_| [0.3, 0.1, 0.7]);
    let run = replay(&[bag]);
    let p = type_probs(&run);
    println!("still: P(rigid, prismatic, revolute) = {p:?}");
    assert!(p[0] >= 0.95, "P(rigid) = {:.3} ({p:?})", p[0]);
}
