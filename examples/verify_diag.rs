//! Does the mode verification prefer the true pose over its half turns? An evaluation-only
//! diagnostic: the scorer of `tracker::verify` is handed the ground truth of generated frames
//! (placed with an error of the given size, as a track's mean is) beside the truth turned by
//! 180 degrees about each object axis, and counts how often the truth scores higher.
//!
//! ```text
//! cargo run --release --example verify_diag -- DATA [PLACEMENT_ERROR_M=0.01] [PLACEMENT_SIGMA_M=0.01] [MAX_RANGE_M=inf] [DEPTH_SIGMA_PER_M=0.02] [USE_BOX=1]
//! ```
//!
//! `DATA` is one sequence or a folder of them (`pregrasp generate`); frames 0, 10, ..., 90 of
//! every camera. `PLACEMENT_SIGMA_M` is the scorer's placement spread (0: no slide); with
//! `USE_BOX` 1 the object's visible box bounds the pixels it must explain (as the track's
//! detection does in the filter).
//! Environment: `TURN_DEG` (the turns' angle, 180), `REGISTER=1` (each hypothesis registered to
//! the depth first), `MAX_SIDE`, `PPO` and `OCC` (the scorer's crop side, pixels per observation
//! and occluder truncation), `ROT_ERR_DEG` (the hypotheses' rotation error), `EDGE=1` (also the
//! colour image's gradients on each hypothesis's contours). Nothing here reaches the filter.

use nalgebra::{UnitQuaternion, Vector3};
use pregrasp::dataset::{Sequence, find_sequences};
use pregrasp::geometry::Pose;
use pregrasp::tracker::verify::{DepthView, VerificationConfig, score_hypotheses};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

fn arg(i: usize, default: f64) -> anyhow::Result<f64> {
    Ok(match std::env::args().nth(i) {
        Some(s) => s.parse()?,
        None => default,
    })
}

fn main() -> anyhow::Result<()> {
    let dir = std::env::args()
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("usage: verify_diag DATA [error_m] [sigma_m] [max_range_m] [depth_sigma]"))?;
    let error_m = arg(2, 0.01)?;
    let placement_sigma_m = arg(3, 0.01)?;
    let max_range_m = arg(4, f64::INFINITY)?;
    let config = VerificationConfig {
        depth_sigma_m: arg(5, VerificationConfig::default().depth_sigma_m)?,
        max_side_px: std::env::var("MAX_SIDE").map_or(Ok(VerificationConfig::default().max_side_px), |s| s.parse())?,
        occlusion_truncation: std::env::var("OCC")
            .map_or(Ok(VerificationConfig::default().occlusion_truncation), |s| s.parse())?,
        pixels_per_observation: std::env::var("PPO")
            .map_or(Ok(VerificationConfig::default().pixels_per_observation), |s| s.parse())?,
        ..VerificationConfig::default()
    };
    let use_box = arg(6, 1.0)? > 0.0;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let normal = Normal::new(0.0, 1.0)?;
    // `TURN_DEG` (default 180): the turns' angle; `REGISTER=1`: every hypothesis is first
    // registered to the view's depth over its translation, as `register_modes` does
    let turn_rad = std::env::var("TURN_DEG")
        .map_or(Ok(180.0), |s| s.parse::<f64>())?
        .to_radians();
    let register = std::env::var("REGISTER").is_ok_and(|s| s == "1");
    let turns = [Vector3::x(), Vector3::y(), Vector3::z()].map(|a| UnitQuaternion::from_scaled_axis(a * turn_rad));
    let (mut all_wins, mut all_n) = ([0usize; 3], 0usize);
    // the truth's lead over its turn about z, per view (nats)
    let mut leads_z: Vec<f64> = Vec::new();
    let mut edge_leads: Vec<f64> = Vec::new();
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
        let (mut wins, mut n) = ([0usize; 3], 0usize);
        for (camera, stream) in &seq.cameras {
            for f in (0..100u32).step_by(10) {
                let (Some(meta), Some(gts)) = (stream.frames.get(&f), stream.gt.get(&f)) else {
                    continue;
                };
                let Some(gt) = gts.iter().find(|g| g.obj_id == obj) else {
                    continue;
                };
                if gt.camera_from_object.translation.z > max_range_m {
                    continue;
                }
                let mut placed = gt.camera_from_object;
                placed.translation.vector += Vector3::from_fn(|_, _| normal.sample(&mut rng) * error_m);
                // `ROT_ERR_DEG`: each hypothesis's rotation off by about this much (a mode's mean)
                let rot_err = std::env::var("ROT_ERR_DEG")
                    .map_or(0.0, |s| s.parse::<f64>().unwrap_or(0.0))
                    .to_radians();
                placed.rotation *= UnitQuaternion::from_scaled_axis(
                    Vector3::from_fn(|_, _| normal.sample(&mut rng)) * (rot_err / 3f64.sqrt()),
                );
                let mut hypotheses = vec![placed];
                hypotheses.extend(
                    turns
                        .iter()
                        .map(|q| Pose::from_parts(placed.translation, placed.rotation * q)),
                );
                // the detector's box: BOP's visible box as the generator's detections are
                let gi = gts.iter().position(|g| g.obj_id == obj).unwrap_or(0);
                let object_box = if use_box {
                    stream
                        .gt_info
                        .get(&f)
                        .and_then(|v| v.get(gi))
                        .and_then(|i| i.bbox_visib)
                        .map(|[x, y, w, h]| [x as f64, y as f64, w as f64, h as f64])
                } else {
                    None
                };
                let depth = seq.load_depth(camera, f)?;
                if register {
                    pregrasp::tracker::verify::register_hypotheses(
                        &mesh,
                        &meta.intrinsics,
                        &depth,
                        &mut hypotheses,
                        diameter_m,
                        (5f64.to_radians()).powi(2) / 12.0,
                        &pregrasp::tracker::register::RegistrationConfig::default(),
                    );
                }
                let view = DepthView {
                    intrinsics: &meta.intrinsics,
                    depth: &depth,
                    object_box_px: object_box,
                };
                let Some(s) = score_hypotheses(&mesh, &view, &hypotheses, diameter_m, placement_sigma_m, &config)
                else {
                    continue;
                };
                n += 1;
                for k in 0..3 {
                    wins[k] += usize::from(s[0] > s[k + 1]);
                }
                leads_z.push(s[0] - s[3]);
                // `EDGE=1`: the colour image's gradients on each hypothesis's rendered contours
                if std::env::var("EDGE").is_ok_and(|s| s == "1")
                    && let (Some(rgb), Some(b)) = (seq.load_rgb(camera, f)?, object_box)
                {
                    let e: Vec<f64> = hypotheses
                        .iter()
                        .map(|h| edge_score(&mesh, &meta.intrinsics, &rgb, *h, b))
                        .collect();
                    edge_leads.push(e[0] - e[3]);
                }
            }
        }
        println!(
            "{} {target}: the truth beats its x / y / z half turn in {} / {} / {} of {n} views",
            seq_dir.display(),
            wins[0],
            wins[1],
            wins[2]
        );
        for k in 0..3 {
            all_wins[k] += wins[k];
        }
        all_n += n;
    }
    println!(
        "all: {} / {} / {} of {all_n} ({:.2} of the comparisons)",
        all_wins[0],
        all_wins[1],
        all_wins[2],
        all_wins.iter().sum::<usize>() as f64 / (3 * all_n).max(1) as f64
    );
    edge_leads.sort_by(f64::total_cmp);
    if !edge_leads.is_empty() {
        let q = |p: f64| edge_leads[((edge_leads.len() as f64 - 1.0) * p).round() as usize];
        println!(
            "edges: the truth's lead over its z turn: 10th percentile {:.3}, median {:.3}, 90th {:.3}; ahead in {} of {}",
            q(0.1),
            q(0.5),
            q(0.9),
            edge_leads.iter().filter(|l| **l > 0.0).count(),
            edge_leads.len()
        );
    }
    leads_z.sort_by(f64::total_cmp);
    let q = |p: f64| {
        leads_z
            .get(((leads_z.len() as f64 - 1.0) * p).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "the truth's lead over its z turn, nats: 10th percentile {:.1}, median {:.1}, 90th {:.1}",
        q(0.1),
        q(0.5),
        q(0.9)
    );
    Ok(())
}

/// The mean gradient magnitude of the grey image (over its mean inside the box grown by a
/// tenth) on the contours of `pose`'s render (its silhouette's outline and its depth steps over
/// 1 cm, the handle's ring in front of the body among them), each contour pixel reading the
/// largest gradient within one pixel.
fn edge_score(
    mesh: &pregrasp::mesh::Mesh,
    k: &pregrasp::camera::Intrinsics,
    rgb: &pregrasp::camera::ColorImage,
    pose: Pose,
    [bx, by, bw, bh]: [f64; 4],
) -> f64 {
    let (w, h) = (k.width as i64, k.height as i64);
    let x0 = ((bx - 0.1 * bw).floor() as i64).clamp(1, w - 2);
    let x1 = ((bx + 1.1 * bw).ceil() as i64).clamp(1, w - 2);
    let y0 = ((by - 0.1 * bh).floor() as i64).clamp(1, h - 2);
    let y1 = ((by + 1.1 * bh).ceil() as i64).clamp(1, h - 2);
    let grey = |x: i64, y: i64| {
        let [r, g, b] = rgb.data[(y * w + x) as usize];
        0.299 * r as f64 + 0.587 * g as f64 + 0.114 * b as f64
    };
    let grad = |x: i64, y: i64| {
        let gx = grey(x + 1, y - 1) + 2.0 * grey(x + 1, y) + grey(x + 1, y + 1)
            - grey(x - 1, y - 1)
            - 2.0 * grey(x - 1, y)
            - grey(x - 1, y + 1);
        let gy = grey(x - 1, y + 1) + 2.0 * grey(x, y + 1) + grey(x + 1, y + 1)
            - grey(x - 1, y - 1)
            - 2.0 * grey(x, y - 1)
            - grey(x + 1, y - 1);
        (gx * gx + gy * gy).sqrt()
    };
    let mut mean = 0.0;
    let mut count = 0.0;
    for y in y0..=y1 {
        for x in x0..=x1 {
            mean += grad(x, y);
            count += 1.0;
        }
    }
    let mean = (mean / count).max(1e-6);
    let d = pregrasp::render::raster::render(k, &[(mesh, pose)], 0.02, [0, 0, 0])
        .depth
        .data_m;
    let at = |x: i64, y: i64| d[(y * w + x) as usize];
    let (mut sum, mut n) = (0.0, 0.0);
    for y in y0.max(2)..=y1.min(h - 3) {
        for x in x0.max(2)..=x1.min(w - 3) {
            let z = at(x, y);
            if z <= 0.0 {
                continue;
            }
            let contour = [(1, 0), (-1, 0), (0, 1), (0, -1)].iter().any(|(dx, dy)| {
                let o = at(x + dx, y + dy);
                o <= 0.0 || (o - z).abs() > 0.01
            });
            if contour {
                let best = (-1..=1)
                    .flat_map(|dy| (-1..=1).map(move |dx| (dx, dy)))
                    .map(|(dx, dy)| grad(x + dx, y + dy))
                    .fold(0.0, f64::max);
                sum += best;
                n += 1.0;
            }
        }
    }
    if n > 0.0 { sum / n / mean } else { 0.0 }
}
