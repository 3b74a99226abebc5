//! Diagnostic (scoring only, never part of the filter): how well each camera's own observation
//! model ranks the true orientation of a sequence's target, frame by frame.
//!
//! For every `--stride`-th frame and every camera that sees the target, it crops at the true
//! position (and a 3 x 3 x 3 grid of 1 cm offsets around it, as the particles would), matches
//! against the codebook and reports the geodesic and symmetry-aware error of the view's own best
//! bin, the rank of the true bin, and the view's evidence strength. Then it pulls every view's
//! log-likelihood into the robot camera's frame with the tracker's own bin maps, sums them as
//! the filter does (Eq. 6), and reports the evidence for the truth: the log of the posterior
//! mass of the true bin's 3 x 3 x 3 neighbourhood over that of a uniform prior (nats), and per
//! view that evidence against the same for the truth's best near-symmetric turn (the tracker's
//! turns; `vs turn`, positive where the view prefers the truth).
//!
//! - `--offset-cm X`: crops X cm off the truth (along the world's (1, 1, 1), or `--offset-dir
//!   x,y,z`; `--offset-in object` takes that direction in the object's frame), as a particle a
//!   little off would see the object.
//! - `--dump FILE`: per view one JSON line (`FILE.jsonl`) and the similarities at the true
//!   position to every bin (`FILE.f32`), for calibrating the likelihood offline.
//!
//! cargo run --release --example view_diag -- DATA_DIR [--grid 10] [--stride 5] [--cache DIR] [--models DIR] [--offset-cm X] [--offset-dir x,y,z] [--offset-in object] [--dump FILE]

use nalgebra::{UnitQuaternion, Vector3};
use pregrasp::dataset::{Sequence, find_sequences};
use pregrasp::eval::metrics::Symmetries;
use pregrasp::geometry::{RotationGrid, ray_rotation};
use pregrasp::mesh::Mesh;
use pregrasp::render::Renderer;
use pregrasp::symmetry::near_symmetric_turns_cached;
use pregrasp::tracker::bins::GridTables;
use pregrasp::tracker::observation::{ViewImage, evidence_strength, observe_view, view_loglik};
use pregrasp::tracker::{Codebook, CodebookConfig, TrackerConfig};
use std::collections::BTreeMap;
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let data = PathBuf::from(args.get(1).ok_or_else(|| anyhow::anyhow!("usage: view_diag DATA"))?);
    let opt = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let grid_deg: u32 = opt("--grid").map_or(Ok(10), |s| s.parse())?;
    let offset_cm: f64 = opt("--offset-cm").map_or(Ok(0.0), |s| s.parse())?;
    let off_dir: Vec<f64> = opt("--offset-dir")
        .unwrap_or_else(|| "1,1,1".into())
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    anyhow::ensure!(off_dir.len() == 3, "--offset-dir takes x,y,z");
    let off_world = Vector3::new(off_dir[0], off_dir[1], off_dir[2]).normalize() * offset_cm * 0.01;
    // `--offset-in object`: the offset's direction is in the object's frame, not the world's
    let off_in_object = opt("--offset-in").as_deref() == Some("object");
    let stride: usize = opt("--stride").map_or(Ok(5), |s| s.parse())?;
    let cache = opt("--cache").map(PathBuf::from);
    let models = opt("--models").map(PathBuf::from);
    let mut dump = match opt("--dump") {
        Some(p) => Some((
            std::io::BufWriter::new(std::fs::File::create(format!("{p}.jsonl"))?),
            std::io::BufWriter::new(std::fs::File::create(format!("{p}.f32"))?),
        )),
        None => None,
    };
    let grid = RotationGrid::new(grid_deg)?;
    let tables = GridTables::new(grid);
    let renderer = Renderer::new()?;
    let mut books: BTreeMap<String, (Codebook, Symmetries, Vec<UnitQuaternion<f64>>)> = BTreeMap::new();
    // per (object, camera): [sum of ln(L(truth) / L(best turn of the truth)), frames, frames the turn wins]
    let mut swaps: BTreeMap<(String, String), [f64; 3]> = BTreeMap::new();
    // per (object, camera): [sum geodesic, sum symmetric, count, sum strength, sum rank]
    let mut totals: BTreeMap<(String, String), [f64; 5]> = BTreeMap::new();
    // per object: (sum of the fused evidence for the truth, frames)
    let mut fused_totals: BTreeMap<String, (f64, f64)> = BTreeMap::new();
    let obs = {
        let mut o = TrackerConfig::default().observation;
        o.gate_similarity = 0.0;
        o
    };
    for seq_dir in find_sequences(&data)? {
        let seq = Sequence::open(&seq_dir)?;
        let Some(target) = seq.rig.target.clone() else { continue };
        let Some(obj) = seq.rig.object_by_name(&target) else {
            continue;
        };
        let obj_id = obj.obj_id;
        if !books.contains_key(&target) {
            let mesh = match &models {
                Some(d) => Mesh::load(&d.join(format!("{target}.ply")))?,
                None => seq.load_mesh(&target)?,
            };
            let cb = Codebook::load_or_build(&renderer, &mesh, grid, &CodebookConfig::default(), cache.as_deref())?;
            let mut turns = near_symmetric_turns_cached(
                &mesh,
                TrackerConfig::default().turn_max_distance_rel * mesh.diameter_m(),
            );
            // EXTRA_TURNS="x,y,z,deg;...": compare the truth against these turns of it as well
            if let Ok(s) = std::env::var("EXTRA_TURNS") {
                for t in s.split(';').filter(|t| !t.is_empty()) {
                    let v: Vec<f64> = t.split(',').map(str::parse).collect::<Result<_, _>>()?;
                    anyhow::ensure!(v.len() == 4, "EXTRA_TURNS takes x,y,z,deg;...");
                    let axis = nalgebra::Unit::new_normalize(Vector3::new(v[0], v[1], v[2]));
                    turns.push(UnitQuaternion::from_axis_angle(&axis, v[3].to_radians()));
                }
            }
            books.insert(target.clone(), (cb, Symmetries::for_object(&target, &mesh), turns));
        }
        let (cb, sym, turns) = &books[&target];
        println!("== {} ({target})", seq_dir.display());
        for f in seq.frame_ids().into_iter().step_by(stride.max(1)) {
            let mut line = format!("frame {f:3}:");
            // (camera, camera_from_world, true position in the camera, log-likelihood per bin)
            let mut lls: Vec<(String, pregrasp::geometry::Pose, Vector3<f64>, Vec<f32>)> = Vec::new();
            for (cam, stream) in &seq.cameras {
                let Some(gt) = stream.gt.get(&f).and_then(|l| l.iter().find(|g| g.obj_id == obj_id)) else {
                    continue;
                };
                let visib = stream
                    .gt_info
                    .get(&f)
                    .and_then(|l| {
                        let i = stream.gt.get(&f)?.iter().position(|g| g.obj_id == obj_id)?;
                        l.get(i)?.visib_fract
                    })
                    .unwrap_or(1.0);
                if visib < 0.3 {
                    continue;
                }
                let meta = seq.frame(cam, f)?;
                let depth = seq.load_depth(cam, f)?;
                let color = seq.load_rgb(cam, f)?;
                let img = ViewImage {
                    intrinsics: &meta.intrinsics,
                    depth: &depth,
                    color: color.as_ref(),
                };
                let off_cam = if off_in_object {
                    gt.camera_from_object.rotation * off_world
                } else {
                    meta.camera_from_world.map_or(off_world, |c| c.rotation * off_world)
                };
                let t = gt.camera_from_object.translation.vector + off_cam;
                let mut positions = vec![t];
                for dx in -1..=1 {
                    for dy in -1..=1 {
                        for dz in -1..=1 {
                            if dx != 0 || dy != 0 || dz != 0 {
                                positions.push(t + Vector3::new(dx as f64, dy as f64, dz as f64) * 0.01);
                            }
                        }
                    }
                }
                let n = positions.len();
                let mut sim = Vec::new();
                let Some(ev) = observe_view(cb, &img, &positions, &obs, &mut sim) else {
                    continue;
                };
                // the view's best (particle, bin)
                let (mut bp, mut bb, mut bc) = (0, 0, f32::NEG_INFINITY);
                for b in 0..grid.len() {
                    for p in 0..n {
                        let c = ev.sim[b * n + p];
                        if ev.valid[p] && c > bc {
                            (bp, bb, bc) = (p, b, c);
                        }
                    }
                }
                let est = ray_rotation(&positions[bp]) * grid.rotation(grid.unflat(bb));
                let truth = gt.camera_from_object.rotation;
                let geo = est.angle_to(&truth).to_degrees();
                let symm = sym.error_deg(&est, &truth);
                let true_bin = grid.flat_of(&(ray_rotation(&t).inverse() * truth));
                let c_true = ev.sim[true_bin * n];
                let rank = (0..grid.len()).filter(|b| ev.sim[b * n] > c_true).count();
                let s = evidence_strength(ev.best_similarity, &TrackerConfig::default().observation);
                if let Some(cfw) = meta.camera_from_world
                    && ev.best_similarity >= TrackerConfig::default().observation.gate_similarity
                {
                    let o = TrackerConfig::default().observation;
                    let k = -0.5 / (o.sigma * o.sigma) * s;
                    let fl = o.loglik_floor * s;
                    let ll: Vec<f32> = (0..grid.len())
                        .map(|b| view_loglik(ev.sim[b * n], 1.0 / ev.best_similarity, k, fl))
                        .collect();
                    lls.push((cam.clone(), cfw, t, ll));
                }
                if let Some((meta_w, sim_w)) = dump.as_mut() {
                    use std::io::Write;
                    let row: Vec<f32> = (0..grid.len()).map(|b| ev.sim[b * n]).collect();
                    for v in &row {
                        sim_w.write_all(&v.to_le_bytes())?;
                    }
                    let side_px = meta.intrinsics.fx() * cb.crop_side_m() / t.z;
                    let diameter_px = meta.intrinsics.fx() * cb.diameter_m / t.z;
                    writeln!(
                        meta_w,
                        "{}",
                        serde_json::json!({"object": target, "camera": cam, "frame": f, "z": t.z,
                            "side_px": side_px, "diameter_px": diameter_px, "c_max": ev.best_similarity,
                            "c_true": c_true, "true_bin": true_bin, "visib": visib, "valid0": ev.valid[0]})
                    )?;
                }
                let e = totals.entry((target.clone(), cam.clone())).or_default();
                e[0] += geo;
                e[1] += symm;
                e[2] += 1.0;
                e[3] += s as f64;
                e[4] += rank as f64;
                line += &format!(
                    "  {cam} z {:.2} geo {geo:5.1} sym {symm:5.1} c {bc:.2}/{c_true:.2} rank {rank:5} s {s:.2}",
                    t.z
                );
            }
            // fused in the robot camera's frame at this frame (true pose: diagnostics only)
            let robot_cfw = seq
                .cameras
                .get(&seq.rig.reference_camera)
                .and_then(|c| c.frames.get(&f))
                .and_then(|m| m.camera_from_world);
            let robot_truth = pregrasp::eval::truth::objects_in_reference(&seq, f)
                .into_iter()
                .find(|o| o.obj_id == obj_id);
            if let (Some(rcfw), Some(rt)) = (robot_cfw, robot_truth)
                && !lls.is_empty()
            {
                let off_ref = if off_in_object {
                    rt.reference_from_object.rotation * off_world
                } else {
                    rcfw.rotation * off_world
                };
                let t_ref = rt.reference_from_object.translation.vector + off_ref;
                let true_ref = grid.flat_of(&(ray_rotation(&t_ref).inverse() * rt.reference_from_object.rotation));
                let mut fused = vec![0f32; grid.len()];
                for (c, cfw, t_v, ll) in &lls {
                    let view_from_ref = cfw * rcfw.inverse();
                    let q = ray_rotation(t_v).inverse() * view_from_ref.rotation * ray_rotation(&t_ref);
                    let map = tables.pull_map(&q);
                    let mapped: Vec<f32> = map.iter().map(|&m| ll[m as usize]).collect();
                    let g_true = gain(&grid, &tables, &mapped, true_ref);
                    line += &format!("  [{c}->ref gain {g_true:.1}]");
                    // the truth against its near-symmetric turns, in this view's own evidence
                    let turned: Vec<usize> = turns
                        .iter()
                        .map(|q| {
                            grid.flat_of(&(ray_rotation(&t_ref).inverse() * rt.reference_from_object.rotation * q))
                        })
                        .collect();
                    if !turned.is_empty() {
                        let g_turn = turned
                            .iter()
                            .map(|&b| gain(&grid, &tables, &mapped, b))
                            .fold(f64::NEG_INFINITY, f64::max);
                        line += &format!("(vs turn {:+.1})", g_true - g_turn);
                        let e = swaps.entry((target.clone(), c.clone())).or_default();
                        e[0] += g_true - g_turn;
                        e[1] += 1.0;
                        e[2] += f64::from(u8::from(g_turn > g_true));
                    }
                    for (d, v) in fused.iter_mut().zip(&mapped) {
                        *d += v;
                    }
                }
                let g = gain(&grid, &tables, &fused, true_ref);
                line += &format!("  FUSED gain {g:.1}");
                let e = fused_totals.entry(target.clone()).or_default();
                e.0 += g;
                e.1 += 1.0;
            }
            println!("{line}");
        }
    }
    println!("\nper object and camera: mean geodesic / symmetric error of the view's own best bin, strength, rank");
    for ((o, c), v) in &totals {
        println!(
            "{o:24} {c:6} n {:3} geo {:6.1} sym {:6.1} strength {:.2} rank {:7.0}",
            v[2],
            v[0] / v[2],
            v[1] / v[2],
            v[3] / v[2],
            v[4] / v[2]
        );
    }
    println!(
        "\nper object and camera: the truth against its best near-symmetric turn (mean nats, share of frames the turn wins)"
    );
    for ((o, c), v) in &swaps {
        println!(
            "{o:24} {c:6} n {:3} {:+6.2} nats, turn wins {:.2}",
            v[1],
            v[0] / v[1],
            v[2] / v[1]
        );
    }
    println!("\nper object: mean fused evidence for the truth (nats over a uniform prior)");
    for (o, (sum, n)) in &fused_totals {
        println!("{o:24} n {n:3} {:5.1}", sum / n);
    }
    Ok(())
}

/// Log of the posterior mass (uniform volume prior times `ll`) of the true bin's 3 x 3 x 3
/// neighbourhood, minus that of the uniform prior: nats of evidence for the truth.
fn gain(grid: &RotationGrid, tables: &GridTables, ll: &[f32], true_bin: usize) -> f64 {
    let m = ll.iter().cloned().fold(f32::NEG_INFINITY, f32::max) as f64;
    let post: Vec<f64> = ll
        .iter()
        .enumerate()
        .map(|(b, v)| tables.volume(b) * ((*v as f64) - m).exp())
        .collect();
    let total: f64 = post.iter().sum();
    let tb = grid.unflat(true_bin);
    let mut nb = grid.neighbours(tb);
    nb.push(tb);
    let p: f64 = nb.iter().map(|b| post[grid.flat(*b)]).sum::<f64>() / total;
    let u: f64 = nb.iter().map(|b| tables.volume(grid.flat(*b))).sum();
    (p / u).ln()
}
