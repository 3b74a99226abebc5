//! Diagnostic: the turns the tracker mixes (`symmetry::near_symmetric_turns`) and the
//! off-centre half turns a view confuses (`symmetry::confusable_turns`) of each mesh given.
//!
//! cargo run --release --example turn_list -- MESH.ply [MESH.ply ...]

use pregrasp::mesh::Mesh;
use pregrasp::symmetry::{confusable_turns, near_symmetric_turns};
use pregrasp::tracker::TrackerConfig;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let config = TrackerConfig::default();
    for path in std::env::args().skip(1) {
        let mesh = Mesh::load(std::path::Path::new(&path))?;
        let d = mesh.diameter_m();
        let t0 = Instant::now();
        let turns = near_symmetric_turns(&mesh, config.turn_max_distance_rel * d);
        let t1 = t0.elapsed().as_secs_f64();
        let t0 = Instant::now();
        let conf = confusable_turns(&mesh, 0.02 * d, 0.0);
        let t2 = t0.elapsed().as_secs_f64();
        println!(
            "{path}: diameter {:.1} mm, {} mixed turns ({t1:.2} s), confusable ({t2:.2} s):",
            d * 1e3,
            turns.len()
        );
        for q in &turns {
            let a = q.axis().map_or(nalgebra::Vector3::z(), |a| a.into_inner());
            println!(
                "  mixed {:5.1} deg about ({:+.3}, {:+.3}, {:+.3})",
                q.angle().to_degrees(),
                a.x,
                a.y,
                a.z
            );
        }
        for t in &conf {
            let a = t.rotation.axis().map_or(nalgebra::Vector3::z(), |a| a.into_inner());
            let shift = t.origin_shift(&nalgebra::UnitQuaternion::identity());
            println!(
                "  confusable about ({:+.3}, {:+.3}, {:+.3}) through ({:+.1}, {:+.1}, {:+.1}) mm: trimmed {:.2} mm, origin shift {:.1} mm",
                a.x,
                a.y,
                a.z,
                t.centre_m.x * 1e3,
                t.centre_m.y * 1e3,
                t.centre_m.z * 1e3,
                t.trimmed_distance_m * 1e3,
                shift.norm() * 1e3
            );
        }
    }
    Ok(())
}
