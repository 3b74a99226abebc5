//! Diagnostic (never part of the decision): how much pose error each object's best grasp
//! survives, with the tracker taken out of the question.
//!
//! Every YCB object named stands upright on the table at its model frame's orientation; pose
//! samples are drawn around that pose with Gaussian translation (`t` mm per axis) and rotation
//! (`r` degrees per axis of the rotation vector), and the decision plans its grasp on the true
//! pose and checks it on the samples, as the service does. Printed per noise level: the raw
//! success rate of the chosen grasp, its label and the share of samples each test fails. With
//! `--shift`, the chosen grasp at 3 mm is also moved across the pads (gripper y) and along the
//! approach (gripper z) in steps of 4 and 10 mm: a grasp whose rate climbs there is placed off
//! its robust spot by the candidate generator.
//!
//! cargo run --release --example grasp_diag -- [--shift] OBJECT... (e.g. 025_mug 011_banana)

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use pregrasp::geometry::{Pose, PoseSamples};
use pregrasp::grasp::{Decision, DecisionQuery, Grasp, GraspObject, Gripper, SupportPlane, decide};
use pregrasp::mesh::Mesh;

/// (translation std in m, rotation std in rad) of the samples.
const NOISE: [(f64, f64); 5] = [(0.0, 0.0), (0.003, 0.0), (0.0, 0.0524), (0.005, 0.0873), (0.01, 0.1745)];

fn failing(d: &Decision) -> String {
    d.reasons
        .iter()
        .map(|r| format!("{:?} {:.3}", r.test, r.failure_share))
        .collect::<Vec<_>>()
        .join(", ")
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let shift = args.iter().any(|a| a == "--shift");
    let gripper = Gripper::default_parallel_jaw();
    let table = SupportPlane {
        normal: [0.0, 0.0, 1.0],
        point_m: [0.0, 0.0, 0.0],
    };
    let models = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/ycb");
    for name in args.iter().filter(|a| !a.starts_with("--")) {
        let object = GraspObject::new(&Mesh::load(&models.join(format!("{name}.ply")))?)?;
        let (lo, _) = object.extent_along(&Vector3::z());
        let truth = Pose::from_parts(Translation3::new(0.6, 0.1, -lo), UnitQuaternion::identity());
        let query = DecisionQuery {
            n_samples: 1000,
            threshold: 0.9,
            grasp: None,
            support_plane: Some(table),
            translation_std_m: None,
            reference_sees: true,
        };
        for (t, r) in NOISE {
            let d = decide(
                &object,
                &gripper,
                &truth,
                &PoseSamples::gaussian(&truth, [t; 3], [r; 3], 1000, 1),
                &query,
            )?;
            println!(
                "{name} t {:.0} mm r {:.0} deg: p {:.3} [{}] {}",
                t * 1e3,
                r.to_degrees(),
                d.p_success_raw,
                d.grasp.label,
                failing(&d)
            );
        }
        if shift {
            let s = PoseSamples::gaussian(&truth, [0.003; 3], [0.0; 3], 1000, 1);
            let d = decide(&object, &gripper, &truth, &s, &query)?;
            for dy_mm in [-8.0, -4.0, 0.0, 4.0, 8.0] {
                let mut row = String::new();
                for dz_mm in [-10.0, 0.0, 10.0] {
                    let mut pose = d.grasp.object_from_gripper;
                    pose.translation.vector += pose.rotation * Vector3::new(0.0, dy_mm, dz_mm) * 1e-3;
                    let q = DecisionQuery {
                        grasp: Some(Grasp::from_pose(&object, pose, "shifted")),
                        ..query.clone()
                    };
                    let e = decide(&object, &gripper, &truth, &s, &q)?;
                    row += &format!("  dz {dz_mm:+.0}: {:.3}", e.p_success_raw);
                }
                println!("  {} moved dy {dy_mm:+.0} mm:{row}", d.grasp.label);
            }
        }
    }
    Ok(())
}
