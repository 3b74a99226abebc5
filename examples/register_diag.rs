//! How well does the depth registration of `tracker::register` place an object, and does the
//! information it claims cover what it leaves? An evaluation-only diagnostic: the true pose of
//! generated frames is moved by an error (per axis, Gaussian of the given size, in the object's
//! frame, the same for every camera of a frame), registered in each view, and the views are
//! combined by their information as the filter combines them.
//!
//! ```text
//! cargo run --release --example register_diag -- DATA [ERROR_M=0.01] [MAX_RANGE_M=inf] [ROT_ERROR_DEG=0] [MIN_RANGE_M=0]
//! ```
//!
//! Prints per sequence and overall: the error before and after (median), and the median of the
//! squared Mahalanobis distance of what is left under the claimed information (a calibrated
//! 3-D Gaussian gives 2.37; the information scale that would calibrate it is 2.37 / median).
//! `ROT_ERROR_DEG` also turns the hypothesis by that much about a random axis (a track's top
//! mode is a few degrees off); `HALF_TURN_AXIS=x,y,z` instead turns it half a turn about that
//! axis of the object (a near-symmetry's confusion). Nothing here reaches the filter.

use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use pregrasp::dataset::{Sequence, find_sequences};
use pregrasp::tracker::register::{RegistrationConfig, register_translation};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

fn arg(i: usize, default: f64) -> anyhow::Result<f64> {
    Ok(match std::env::args().nth(i) {
        Some(s) => s.parse()?,
        None => default,
    })
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mid = v.len() / 2;
    v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    v[mid]
}

fn main() -> anyhow::Result<()> {
    let dir = std::env::args()
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("usage: register_diag DATA [error_m] [max_range_m] [rot_error_deg]"))?;
    let error_m = arg(2, 0.01)?;
    let max_range_m = arg(3, f64::INFINITY)?;
    let rot_error = arg(4, 0.0)?.to_radians();
    let min_range_m = arg(5, 0.0)?;
    let config = RegistrationConfig::default();
    // HALF_TURN_AXIS=x,y,z: the hypothesis is the truth turned by half a turn about that object
    // axis (a near-symmetry's confusion) instead of `ROT_ERROR_DEG` about a random one
    let half_turn_axis: Option<Vector3<f64>> = match std::env::var("HALF_TURN_AXIS") {
        Ok(s) => {
            let v: Vec<f64> = s.split(',').map(str::parse).collect::<Result<_, _>>()?;
            anyhow::ensure!(v.len() == 3, "HALF_TURN_AXIS takes x,y,z");
            Some(Vector3::new(v[0], v[1], v[2]).normalize())
        }
        Err(_) => None,
    };
    let mut left_sum = Vector3::zeros();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let normal = Normal::new(0.0, 1.0)?;
    let (mut all_before, mut all_after, mut all_d2, mut all_view_d2) = (vec![], vec![], vec![], vec![]);
    let mut seconds = vec![];
    // per view: (noise share, error along the view's known directions before, after, Mahalanobis^2)
    let mut per_view: Vec<(f64, f64, f64, f64)> = vec![];
    for seq_dir in find_sequences(std::path::Path::new(&dir))? {
        let seq = Sequence::open(&seq_dir)?;
        let Some(target) = seq.rig.target.clone() else { continue };
        let obj = seq
            .rig
            .object_by_name(&target)
            .ok_or_else(|| anyhow::anyhow!("no {target} in the rig"))?
            .obj_id;
        let mesh = seq.load_mesh(&target)?;
        let diameter_m = mesh.diameter_m();
        let (mut before, mut after, mut d2s) = (vec![], vec![], vec![]);
        for f in (0..100u32).step_by(10) {
            // one error per frame, in the object's frame
            let err_obj = Vector3::from_fn(|_, _| normal.sample(&mut rng) * error_m);
            let axis = Vector3::from_fn(|_, _| normal.sample(&mut rng)).normalize();
            let turn = match &half_turn_axis {
                Some(a) => UnitQuaternion::from_scaled_axis(a * std::f64::consts::PI),
                None => UnitQuaternion::from_scaled_axis(axis * rot_error),
            };
            let (mut info_obj, mut b_obj) = (Matrix3::zeros(), Vector3::zeros());
            let mut views = 0;
            for (camera, stream) in &seq.cameras {
                let (Some(meta), Some(gts)) = (stream.frames.get(&f), stream.gt.get(&f)) else {
                    continue;
                };
                let Some(gt) = gts.iter().find(|g| g.obj_id == obj) else {
                    continue;
                };
                // the bounds are on the object's apparent diameter, pixels, when given negative
                let z = gt.camera_from_object.translation.z;
                let size_px = diameter_m * meta.intrinsics.fx() / z;
                let out = if max_range_m < 0.0 {
                    size_px < -max_range_m || size_px >= -min_range_m
                } else {
                    z > max_range_m || z < min_range_m
                };
                if out {
                    continue;
                }
                let r = gt.camera_from_object.rotation;
                let mut placed = gt.camera_from_object;
                placed.translation.vector += r * err_obj;
                placed.rotation = r * turn;
                let depth = seq.load_depth(camera, f)?;
                let t0 = std::time::Instant::now();
                let reg = register_translation(
                    &mesh,
                    &meta.intrinsics,
                    &depth,
                    &placed,
                    diameter_m,
                    &(Matrix3::identity() * (rot_error * rot_error / 3.0)),
                    &config,
                );
                seconds.push(t0.elapsed().as_secs_f64());
                let Some(reg) = reg else { continue };
                // into the object's frame: the correction and its information
                let rm = r.to_rotation_matrix();
                let d_obj = rm.inverse() * reg.delta_m;
                let h_obj = rm.matrix().transpose() * reg.information * rm.matrix();
                let left = err_obj + d_obj;
                all_view_d2.push(left.dot(&(h_obj * left)));
                // the directions this view claims to know to 5 mm
                let eig = h_obj.symmetric_eigen();
                let (mut b2, mut a2) = (0.0, 0.0);
                for j in 0..3 {
                    if eig.eigenvalues[j] > 1.0 / (0.005 * 0.005) {
                        let v = eig.eigenvectors.column(j);
                        b2 += v.dot(&err_obj).powi(2);
                        a2 += v.dot(&left).powi(2);
                    }
                }
                per_view.push((reg.noise_rel, b2.sqrt(), a2.sqrt(), left.dot(&(h_obj * left))));
                info_obj += h_obj;
                b_obj += h_obj * d_obj;
                views += 1;
            }
            if views == 0 {
                continue;
            }
            // the views combined: the information-weighted correction (pseudo-inverse)
            let eig = info_obj.symmetric_eigen();
            let mut d = Vector3::zeros();
            for j in 0..3 {
                let lam = eig.eigenvalues[j];
                if lam > 1e-9 {
                    let v = eig.eigenvectors.column(j);
                    d += v * (v.dot(&b_obj) / lam);
                }
            }
            let left = err_obj + d;
            left_sum += left;
            before.push(err_obj.norm());
            after.push(left.norm());
            d2s.push(left.dot(&(info_obj * left)));
        }
        println!(
            "{} {target}: error {:.4} -> {:.4} m (median of {}), Mahalanobis^2 median {:.2}",
            seq_dir.display(),
            median(before.clone()),
            median(after.clone()),
            before.len(),
            median(d2s.clone())
        );
        all_before.extend(before);
        all_after.extend(after);
        all_d2.extend(d2s);
    }
    let edges = [0.0, 0.02, 0.04, 0.06, 0.1, 0.15, 0.2, 0.3, 0.5, f64::INFINITY];
    for w in edges.windows(2) {
        let v: Vec<&(f64, f64, f64, f64)> = per_view.iter().filter(|p| p.0 >= w[0] && p.0 < w[1]).collect();
        if v.is_empty() {
            continue;
        }
        println!(
            "views with depth noise {:.2}-{:.2} of the diameter: {} views, error along their known directions {:.4} -> {:.4} m (median), Mahalanobis^2 median {:.2}",
            w[0],
            w[1],
            v.len(),
            median(v.iter().map(|p| p.1).collect()),
            median(v.iter().map(|p| p.2).collect()),
            median(v.iter().map(|p| p.3).collect())
        );
    }
    println!(
        "mean error left in the object's frame: {:+.4} {:+.4} {:+.4} m",
        left_sum.x / all_after.len().max(1) as f64,
        left_sum.y / all_after.len().max(1) as f64,
        left_sum.z / all_after.len().max(1) as f64
    );
    let within90 = all_d2.iter().filter(|d| **d <= 6.25).count() as f64 / all_d2.len().max(1) as f64;
    println!(
        "all: error {:.4} -> {:.4} m (median of {} frames; 90th percentile after {:.4}), Mahalanobis^2 median {:.2} (one view {:.2}), within the 90 % region {:.2}; {:.1} ms a view (median)",
        median(all_before.clone()),
        median(all_after.clone()),
        all_before.len(),
        {
            let mut v = all_after.clone();
            v.sort_by(|a, b| a.total_cmp(b));
            v.get(v.len() * 9 / 10).copied().unwrap_or(f64::NAN)
        },
        median(all_d2),
        median(all_view_d2),
        within90,
        1e3 * median(seconds)
    );
    Ok(())
}
