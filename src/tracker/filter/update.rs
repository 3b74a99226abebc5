//! The measurement update of one track: crops and codes per view, the coarse-to-fine matched
//! set (see [`crate::tracker::sparse`]), the fused update of the histograms and the weights,
//! estimates and resampling.

use super::{MAP_REUSE_RAD, TrackState, Tracker, normalise, weight_exponent};
use crate::geometry::Pose;
use crate::tracker::bins::flat_of_matrix;
use crate::tracker::observation::{ViewEvidence, ViewImage, box_loglik, encode_particles, view_evidence};
use crate::tracker::sparse::{Lattice, RotationState, fused_max, fused_row, fused_update, map_bins, match_rows};
use crate::tracker::{CameraFrame, StepReport, TrackStatus};
use nalgebra::{Matrix3, Point3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

/// One view's codes of a track's particles, with what the update needs of the view.
struct Encoded {
    camera: String,
    codes: Vec<f32>,
    valid: Vec<bool>,
    central_depth: Vec<f32>,
    positions_in_view_m: Vec<Vector3<f64>>,
    /// Histogram bin `b` (frame H) reads the view's codebook bin `bin(q * R_b)`.
    q: UnitQuaternion<f64>,
    /// The cached map of the grid (`u32::MAX` where not yet computed) and the rotation it maps
    /// by (the cache's, within `MAP_REUSE_RAD` of `q`).
    dense_map: Option<(Arc<Vec<u32>>, UnitQuaternion<f64>)>,
    /// The object's diameter in pixels at the particles' mean depth.
    size_px: f32,
    /// The object's mean silhouette in pixels there.
    area_px: f32,
    /// Its crops are centred on a detector's box and matched against the box-centred codes.
    box_centred: bool,
    /// What its evidence updates (`ObservationConfig::near_box_rotation`).
    role: Role,
}

/// What a view's evidence updates: a view is usually encoded once for both; with
/// `ObservationConfig::near_box_rotation` a near view is encoded twice, its crop aimed at the
/// detector's box for the rotation and a crop at each particle for the weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    Both,
    Rotation,
    Weights,
}

impl Encoded {
    /// This view's evidence from its similarities on the matched set (`sim`, moved into the
    /// evidence when the view sees the object) and each particle's best similarity and bin.
    fn evidence(
        &self,
        codebook: &crate::tracker::Codebook,
        sim: &mut Vec<f32>,
        best: &(Vec<f32>, Vec<u32>),
        config: &crate::tracker::observation::ObservationConfig,
    ) -> Option<ViewEvidence> {
        view_evidence(
            codebook,
            sim,
            &best.0,
            &best.1,
            &self.valid,
            &self.central_depth,
            &self.positions_in_view_m,
            config,
            self.box_centred,
        )
        .map(|mut ev| {
            let s = crate::tracker::observation::size_strength(self.size_px, self.area_px, config);
            ev.k *= s;
            ev.floor *= s;
            ev
        })
    }
}

/// Sorted union of the sorted lists `a`, `b` and the range `slice` (wrapping at `nb`); with
/// each output's slot in `a` (`u32::MAX`: none) and the output index of each element of `b`.
fn merge(a: &[u32], b: &[u32], slice: (usize, usize), nb: usize) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
    let (s0, len) = slice;
    let len = len.min(nb);
    let ranges: Vec<(usize, usize)> = if len == 0 {
        Vec::new()
    } else if s0 + len <= nb {
        vec![(s0, s0 + len)]
    } else {
        vec![(0, s0 + len - nb), (s0, nb)]
    };
    let next_slice = |x: usize| -> Option<usize> {
        ranges
            .iter()
            .filter_map(|(lo, hi)| {
                let c = x.max(*lo);
                (c < *hi).then_some(c)
            })
            .min()
    };
    let mut out = Vec::with_capacity(a.len() + b.len() + len);
    let mut slots = Vec::with_capacity(out.capacity());
    let mut b_index = vec![0u32; b.len()];
    let (mut i, mut j) = (0, 0);
    let mut x = 0usize;
    loop {
        let ca = a.get(i).map(|v| *v as usize);
        let cb = b.get(j).map(|v| *v as usize);
        let cs = next_slice(x);
        let Some(m) = [ca, cb, cs].into_iter().flatten().min() else {
            break;
        };
        let slot = if ca == Some(m) {
            i += 1;
            (i - 1) as u32
        } else {
            u32::MAX
        };
        if cb == Some(m) {
            b_index[j] = out.len() as u32;
            j += 1;
        }
        out.push(m as u32);
        slots.push(slot);
        x = m + 1;
    }
    (out, slots, b_index)
}

/// One track's update in a step, run beside the other tracks' (it reads the tracker's models
/// and settings and writes only its own track): everything up to the resampling, which draws
/// from the tracker's one random stream and so follows in track order.
struct TrackUpdate<'a> {
    config: &'a super::TrackerConfig,
    /// The world's down direction in the reference frame (for the support prior).
    down_reference: Option<Vector3<f64>>,
    models: &'a [super::Model],
    camera_names: &'a [String],
    stamp_ns: i64,
    state: &'a mut TrackState,
    track: &'a mut crate::tracker::Track,
    /// Similarity buffers reused between views (back to the tracker's pool after the update).
    sims: Vec<Vec<f32>>,
}

impl TrackUpdate<'_> {
    /// The update of the track with this step's views (see the module docs), up to its
    /// resampling ([`Tracker::finish_update`]); whether any view had evidence of it.
    fn update(&mut self, views: &[(&CameraFrame, Pose, usize)], report: &mut StepReport) -> bool {
        let mi = self.state.model;
        let codebook = self.models[mi].codebook.clone();
        let tables = self.models[mi].tables.clone();
        let lattice = self.models[mi].lattice.clone();
        let n = self.state.n();
        let nb = tables.grid.len();
        let kd = codebook.code_dim();
        let obs_cfg = self.config.observation;
        let matching = self.config.matching;
        // the registration's narrower floor holds for the step that registered only
        self.state.registered = None;
        let mean_ref = self.state.set(&tables, self.config.spread).mean_position();
        let reference_from_hist = self.state.reference_from_hist;
        let mean_hist = reference_from_hist
            .inverse_transform_point(&Point3::from(mean_ref))
            .coords;
        let mut in_some_image = false;

        // 1. crops and codes of every view that has a usable crop
        let mut encoded: Vec<Encoded> = Vec::new();
        // each view's box term per particle (the detector's box of the object, where it has one)
        let mut box_logs: Vec<Vec<f32>> = Vec::new();
        for (frame, view_from_ref, _ci) in views {
            let positions: Vec<Vector3<f64>> = self
                .state
                .positions
                .iter()
                .map(|p| (view_from_ref * Point3::from(*p)).coords)
                .collect();
            let mean_view = (view_from_ref * Point3::from(mean_ref)).coords;
            // the detector's box of the object nearest the track: its box term and, where the
            // object is small, the centre its crops are aimed at
            let object_box = crate::tracker::observation::nearest_box(
                &frame.intrinsics,
                &frame.detections,
                &self.models[mi].name,
                &mean_view,
                obs_cfg.detection_box.unwrap_or_default().sigma_rel,
            );
            if let Some(cfg) = &obs_cfg.detection_box {
                let mut l = vec![0f32; n];
                box_loglik(&frame.intrinsics, object_box, &positions, cfg, &mut l);
                box_logs.push(l);
            }
            if let Some(uv) = frame.intrinsics.project(&Point3::from(mean_view))
                && frame.intrinsics.contains(uv)
            {
                in_some_image = true;
            }
            let img = ViewImage {
                intrinsics: &frame.intrinsics,
                depth: &frame.depth,
                color: frame.color.as_ref(),
            };
            let size_px = crate::tracker::observation::object_size_px(&codebook, &frame.intrinsics, mean_view.z) as f32;
            // box codes only with the table to match them against (without it, as if off)
            let box_codes = obs_cfg.box_codes && codebook.box_table.is_some();
            let aimed = (size_px < obs_cfg.box_crops_below_px && (box_codes || self.models[mi].box_centred))
                .then_some(object_box)
                .flatten()
                .map(|(centre, _)| crate::tracker::observation::box_aimed(&frame.intrinsics, centre, &positions));
            // a near view aimed at the box as well, for the rotation alone
            let also_aimed = if aimed.is_none() && box_codes && obs_cfg.near_box_rotation {
                // not where something nearer hides part of the object: its box is the visible part's
                let side_rel = obs_cfg.detection_box.unwrap_or_default().sigma_rel;
                object_box
                    .filter(|(centre, sigma)| {
                        !crate::tracker::observation::box_hides_object(
                            &frame.depth,
                            *centre,
                            sigma / side_rel,
                            mean_view.z,
                            codebook.diameter_m,
                        )
                    })
                    .map(|(centre, _)| crate::tracker::observation::box_aimed(&frame.intrinsics, centre, &positions))
            } else {
                None
            };
            let q = crate::geometry::ray_rotation(&mean_view).inverse()
                * view_from_ref.rotation
                * reference_from_hist.rotation
                * crate::geometry::ray_rotation(&mean_hist);
            let area_px = crate::tracker::observation::object_area_px(
                self.models[mi].silhouette_m2,
                &frame.intrinsics,
                mean_view.z,
            ) as f32;
            let mut passes = vec![(
                aimed,
                if also_aimed.is_some() {
                    Role::Weights
                } else {
                    Role::Both
                },
            )];
            if let Some(a) = also_aimed {
                passes.push((Some(a), Role::Rotation));
            }
            let last = passes.len() - 1;
            let mut positions = positions;
            for (i, (crop_at, role)) in passes.into_iter().enumerate() {
                let box_centred = crop_at.is_some() && box_codes;
                let (codes, valid, central_depth, crops_s, encoding_s) =
                    encode_particles(&codebook, &img, crop_at.as_deref().unwrap_or(&positions));
                report.timings.crops_s += crops_s;
                report.timings.encoding_s += encoding_s;
                if !valid.iter().any(|v| *v) {
                    continue;
                }
                encoded.push(Encoded {
                    camera: frame.camera.clone(),
                    codes,
                    valid,
                    central_depth,
                    // copied only for a view encoded twice
                    positions_in_view_m: if i == last {
                        std::mem::take(&mut positions)
                    } else {
                        positions.clone()
                    },
                    q,
                    dense_map: None,
                    size_px,
                    box_centred,
                    area_px,
                    role,
                });
            }
        }

        // 2. the matched set: lattice, active bins, this step's slice (or every bin)
        let t0 = Instant::now();
        let slice = if matching.dense {
            (0, nb)
        } else {
            let len = nb.div_ceil(matching.slice_steps.max(1));
            let s = &mut *self.state;
            let start = s.slice_cursor % nb;
            s.slice_cursor = (start + len) % nb;
            (start, len)
        };
        let (mut bins, mut slots, lattice_rows) = merge(&self.state.rot.active, &lattice.points, slice, nb);
        // the support prior's factor of every matched bin, for the track's ray in `H`
        let support = self.models[mi]
            .support
            .as_ref()
            .zip(self.down_reference)
            .map(|(prior, down_ref)| {
                let down_hist = reference_from_hist.rotation.inverse() * down_ref;
                let ray = crate::geometry::ray_rotation(&mean_hist)
                    .to_rotation_matrix()
                    .into_inner();
                (prior, ray, down_hist)
            });
        let mut support_factors: Option<Vec<f32>> = support
            .as_ref()
            .map(|(prior, ray, down)| prior.factors(&tables, &bins, ray, down));
        // bin maps: a cached map of the grid where the camera's rotation held still
        for e in &mut encoded {
            e.dense_map = self.cached_map(&e.camera, &e.q, matching.dense, &tables, &bins);
        }
        let map_of = |e: &Encoded, bins: &[u32]| -> Vec<u32> {
            match &e.dense_map {
                Some((m, cq)) => {
                    let qm = cq.to_rotation_matrix().into_inner();
                    bins.iter()
                        .map(|b| match m[*b as usize] {
                            u32::MAX => flat_of_matrix(&tables.grid, &(qm * tables.matrix(*b as usize))) as u32,
                            v => v,
                        })
                        .collect()
                }
                None if e.q.angle() < 1e-9 => bins.to_vec(),
                None => map_bins(&tables, &e.q, bins),
            }
        };
        let mut maps: Vec<Vec<u32>> = encoded.iter().map(|e| map_of(e, &bins)).collect();
        report.timings.fusion_s += t0.elapsed().as_secs_f64();

        // 3. similarities on the matched set
        let t0 = Instant::now();
        let mut sims: Vec<Vec<f32>> = Vec::with_capacity(encoded.len());
        let mut best: Vec<(Vec<f32>, Vec<u32>)> = Vec::with_capacity(encoded.len());
        for (e, map) in encoded.iter().zip(&maps) {
            let mut sim = self.sims.pop().unwrap_or_default();
            best.push(match_rows(
                &e.codes,
                codebook.table(e.box_centred),
                n,
                kd,
                map,
                &mut sim,
            ));
            sims.push(sim);
        }
        report.timings.matching_s += t0.elapsed().as_secs_f64();

        // 4. refinement: the fine bins of the best lattice cells not yet matched
        if !matching.dense && matching.refine_cells > 0 && !encoded.is_empty() {
            let t0 = Instant::now();
            let provisional: Vec<ViewEvidence> = encoded
                .iter()
                .zip(&best)
                .zip(sims.iter_mut())
                .filter_map(|((e, b), sim)| {
                    let mut copy = std::mem::take(sim);
                    match e.evidence(&codebook, &mut copy, b, &obs_cfg) {
                        Some(ev) => Some(ev),
                        None => {
                            *sim = copy;
                            None
                        }
                    }
                })
                .collect();
            let refine = if provisional.is_empty() {
                Vec::new()
            } else {
                let refs: Vec<&ViewEvidence> = provisional.iter().collect();
                let s = &self.state;
                refine_bins(
                    &lattice,
                    &refs,
                    &lattice_rows,
                    &bins,
                    &slots,
                    &s.rot,
                    &tables,
                    n,
                    &matching,
                    support_factors.as_deref(),
                )
            };
            // the similarities go back to their views (in the same order as the evidence)
            let mut it = provisional.into_iter();
            for sim in sims.iter_mut() {
                if sim.is_empty()
                    && let Some(ev) = it.next()
                {
                    *sim = ev.sim;
                }
            }
            report.timings.fusion_s += t0.elapsed().as_secs_f64();
            if !refine.is_empty() {
                let t0 = Instant::now();
                let first = bins.len();
                if let (Some(f), Some((prior, ray, down))) = (support_factors.as_mut(), support.as_ref()) {
                    f.extend(prior.factors(&tables, &refine, ray, down));
                }
                bins.extend_from_slice(&refine);
                slots.extend(std::iter::repeat_n(u32::MAX, refine.len()));
                for (k, e) in encoded.iter().enumerate() {
                    let extra = map_of(e, &refine);
                    let mut more = Vec::new();
                    let (mx, arg) = match_rows(&e.codes, codebook.table(e.box_centred), n, kd, &extra, &mut more);
                    sims[k].extend_from_slice(&more);
                    maps[k].extend(extra);
                    for p in 0..n {
                        if mx[p] > best[k].0[p] {
                            best[k].0[p] = mx[p];
                            best[k].1[p] = arg[p];
                        }
                    }
                    debug_assert_eq!(sims[k].len(), (first + refine.len()) * n);
                }
                report.timings.matching_s += t0.elapsed().as_secs_f64();
            }
        }
        report.matched_bins += bins.len();

        // 5. each view's evidence (gate, strength, c_max over the matched bins, depth check)
        let t0 = Instant::now();
        let mut evidence: Vec<ViewEvidence> = Vec::new();
        let mut evidence_view: Vec<usize> = Vec::new();
        let mut seen_by = Vec::new();
        let mut best_sim = f32::NEG_INFINITY;
        // each particle's log-likelihood of its position: the views' depth checks and boxes
        let mut position_log = vec![0f32; n];
        let mut roles: Vec<Role> = Vec::new();
        for (k, ((e, b), mut sim)) in encoded.iter().zip(&best).zip(sims).enumerate() {
            match e.evidence(&codebook, &mut sim, b, &obs_cfg) {
                Some(ev) => {
                    best_sim = best_sim.max(ev.best_similarity);
                    if !seen_by.contains(&e.camera) {
                        seen_by.push(e.camera.clone());
                    }
                    if e.role != Role::Rotation {
                        for (d, l) in position_log.iter_mut().zip(&ev.depth_log) {
                            *d += l;
                        }
                    }
                    evidence.push(ev);
                    evidence_view.push(k);
                    roles.push(e.role);
                }
                None => self.sims.push(sim),
            }
        }
        for l in &box_logs {
            for (d, b) in position_log.iter_mut().zip(l) {
                *d += b;
            }
        }
        report.timings.likelihoods_s += t0.elapsed().as_secs_f64();
        if matching.audit && !evidence.is_empty() {
            let outside = self.audit_matched_set(&encoded, &evidence, &evidence_view, &bins, &tables, &codebook);
            report.audited += 1;
            report.audit_outside += usize::from(outside);
        }

        let t0 = Instant::now();
        let track = &mut *self.track;
        track.stamp_ns = self.stamp_ns;
        track.seen_by = seen_by.clone();
        track.best_similarity = best_sim.is_finite().then_some(best_sim as f64);
        let had_evidence = !evidence.is_empty();
        if had_evidence {
            // the histograms' evidence, and the weights' (they differ where a near view was
            // encoded twice: the histograms take the crops aimed at the box)
            let without = |skip: Role| -> Vec<&ViewEvidence> {
                evidence
                    .iter()
                    .zip(&roles)
                    .filter(|(_, r)| **r != skip)
                    .map(|(e, _)| e)
                    .collect()
            };
            let refs = without(Role::Weights);
            let floor_rel = self.config.prior_floor_rel as f32;
            let s = &self.state;
            let sf = support_factors.as_deref();
            // the fused posterior of `refs` on the matched bins, each particle's marginal (matched
            // and unmatched bins), the per-particle max it is scaled by, and the unmatched volume
            let fuse = |refs: &[&ViewEvidence]| {
                // per particle max of the fused log-likelihood, for exp's range; with floored
                // views the sum cannot go below `floor * views` (exp of that is well inside
                // f32), so the pass is skipped and 0 (the largest possible value) used
                let worst = obs_cfg.loglik_floor * refs.len() as f32;
                let fmax = if worst > -80.0 {
                    vec![0f32; n]
                } else {
                    fused_max(refs, bins.len(), n)
                };
                let (post, sums) = fused_update(&bins, &slots, refs, &s.rot, &tables, floor_rel, &fmax, sf);
                // the bins left out: each at its lattice cell's likelihood, on the prior's floor
                let (unmatched, v_unmatched) = if matching.dense {
                    (vec![0.0; n], 0.0)
                } else {
                    unmatched_mass(
                        &lattice,
                        refs,
                        &lattice_rows,
                        &bins,
                        &s.rot,
                        &tables,
                        floor_rel,
                        &fmax,
                        sf,
                    )
                };
                let marginal: Vec<f64> = sums.iter().zip(&unmatched).map(|(a, b)| a + b).collect();
                (post, marginal, unmatched, fmax, v_unmatched)
            };
            let (mut post, marginal, unmatched, fmax, v_unmatched) = fuse(&refs);
            // the weights' own fusion only where a near view was encoded twice (its posterior,
            // computed alongside, is not used)
            let weights_fused = roles
                .iter()
                .any(|r| *r != Role::Both)
                .then(|| fuse(&without(Role::Rotation)));
            let (marginal_w, fmax_w) = match &weights_fused {
                Some((_, m, _, f, _)) => (m.as_slice(), f.as_slice()),
                None => (marginal.as_slice(), fmax.as_slice()),
            };
            // new log weights: old + (log marginal (Eq. 7) + position terms) tempered by the number
            // of views (see `TrackerConfig::view_weight_tempering`)
            let alpha = weight_exponent(seen_by.len(), self.config.view_weight_tempering);
            let s = &mut *self.state;
            let mut logw: Vec<f64> = (0..n)
                .map(|p| {
                    s.weights[p].max(1e-300).ln()
                        + alpha * (marginal_w[p].max(1e-300).ln() + fmax_w[p] as f64 + position_log[p] as f64)
                })
                .collect();
            let m = logw.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            for v in &mut logw {
                *v = (*v - m).exp();
            }
            s.weights = logw;
            normalise(&mut s.weights);
            // the posterior: the matched bins, and the unmatched mass spread as the new floor
            let inv: Vec<f32> = marginal
                .iter()
                .map(|v| if *v > 0.0 { (1.0 / v) as f32 } else { 0.0 })
                .collect();
            post.par_chunks_mut(n).for_each(|row| {
                for (v, k) in row.iter_mut().zip(&inv) {
                    *v *= k;
                }
            });
            let floors: Vec<f32> = unmatched
                .iter()
                .zip(&marginal)
                .map(|(u, m)| {
                    if v_unmatched > 0.0 && *m > 0.0 {
                        (u / (m * v_unmatched)) as f32
                    } else {
                        0.0
                    }
                })
                .collect();
            s.rot = RotationState {
                active: bins,
                values: post,
                floors,
                column_of: (0..n as u32).collect(),
            };
        }
        // the similarity buffers go back to the pool for the next view, track and step
        self.sims.extend(evidence.into_iter().map(|ev| ev.sim));
        report.timings.fusion_s += t0.elapsed().as_secs_f64();
        super::floor_components(&mut *self.state, self.config.min_component_weight);

        // status
        let track = &mut *self.track;
        if had_evidence && best_sim >= self.config.lost_similarity {
            track.weak_steps = 0;
            if track.status == TrackStatus::Initialising {
                track.status = TrackStatus::Tracking;
            }
        } else if in_some_image {
            track.weak_steps += 1;
            if track.weak_steps >= self.config.lost_after_steps && track.status != TrackStatus::Lost {
                track.status = TrackStatus::Lost;
                report.tracks_lost.push(track.id);
            }
        }

        // estimates
        let t0 = Instant::now();
        self.refresh_estimate();
        report.timings.estimates_s += t0.elapsed().as_secs_f64();
        if had_evidence {
            let t0 = Instant::now();
            if self.verify_modes(views, &seen_by) {
                report.verified += 1;
                self.refresh_estimate();
            }
            report.timings.verification_s += t0.elapsed().as_secs_f64();
            let t0 = Instant::now();
            if self.register_translation(views, &seen_by) {
                report.registered += 1;
                self.refresh_estimate();
            }
            report.timings.registration_s += t0.elapsed().as_secs_f64();
        }

        had_evidence
    }

    /// Whether the heaviest particle's fused log-likelihood over the whole grid peaks outside
    /// the matched `bins` (the views' evidence as matched; only views with evidence count).
    #[allow(clippy::too_many_arguments)]
    fn audit_matched_set(
        &self,
        encoded: &[Encoded],
        evidence: &[ViewEvidence],
        evidence_view: &[usize],
        bins: &[u32],
        tables: &crate::tracker::bins::GridTables,
        codebook: &crate::tracker::Codebook,
    ) -> bool {
        let s = &self.state;
        let Some(p) = (0..s.n()).max_by(|a, b| s.weights[*a].total_cmp(&s.weights[*b])) else {
            return false;
        };
        let kd = codebook.code_dim();
        let nb = tables.grid.len();
        let mut fused = vec![0f32; nb];
        for (ev, k) in evidence.iter().zip(evidence_view) {
            let e = &encoded[*k];
            let code = &e.codes[p * kd..(p + 1) * kd];
            let sims: Vec<f32> = (0..nb)
                .into_par_iter()
                .with_min_len(4096)
                .map_init(
                    || vec![0f32; kd],
                    |row, b| {
                        codebook.table(e.box_centred).row_into(b, row);
                        row.iter().zip(code).map(|(a, b)| a * b).sum()
                    },
                )
                .collect();
            let map = tables.pull_map(&e.q);
            fused.par_iter_mut().zip(&map).for_each(|(f, m)| {
                *f += crate::tracker::observation::view_loglik(sims[*m as usize], ev.inv_best[p], ev.k, ev.floor);
            });
        }
        let best = (0..nb).max_by(|a, b| fused[*a].total_cmp(&fused[*b])).unwrap_or(0) as u32;
        !bins.contains(&best)
    }

    /// The cached bin map of `camera` and the rotation it maps by, when the camera's rotation
    /// `q` held still since the last step (`None`: map the bins needed by `q`). A cached map is
    /// filled where `needed` asks (and kept for the next steps): the whole grid's map of the
    /// cached rotation as the dense reference builds it, computed only where it is read.
    fn cached_map(
        &mut self,
        camera: &str,
        q: &UnitQuaternion<f64>,
        dense: bool,
        tables: &crate::tracker::bins::GridTables,
        needed: &[u32],
    ) -> Option<(Arc<Vec<u32>>, UnitQuaternion<f64>)> {
        if q.angle() < 1e-9 {
            return None;
        }
        let cache = &mut self.state.map_cache;
        let entry = cache.iter_mut().find(|(c, _, _)| c == camera);
        let (cq, map) = match entry {
            Some((_, cq, map)) if cq.angle_to(q) < MAP_REUSE_RAD => {
                let map = map.get_or_insert_with(|| Arc::new(vec![u32::MAX; tables.grid.len()]));
                (*cq, map)
            }
            Some((_, cq, map)) => {
                *cq = *q;
                *map = dense.then(|| Arc::new(tables.pull_map(q)));
                return map.clone().map(|m| (m, *q));
            }
            None => {
                let map = dense.then(|| Arc::new(tables.pull_map(q)));
                cache.push((camera.to_string(), *q, map.clone()));
                return map.map(|m| (m, *q));
            }
        };
        let missing: Vec<u32> = needed
            .iter()
            .filter(|b| map[**b as usize] == u32::MAX)
            .copied()
            .collect();
        if !missing.is_empty() {
            let values = map_bins(tables, &cq, &missing);
            let m = Arc::make_mut(map);
            for (b, v) in missing.iter().zip(values) {
                m[*b as usize] = v;
            }
        }
        Some((map.clone(), cq))
    }

    /// When two or more rotation modes of the track each hold at least
    /// `VerificationConfig::min_mode_mass`, renders the heaviest few into every view that saw
    /// the object, scores them against its depth ([`crate::tracker::verify`]) and scales each
    /// mode's bins (those nearer to it than to the other modes, within twice the modes' merge
    /// angle) by `exp(score - best score)`. Returns whether it did.
    fn verify_modes(&mut self, views: &[(&CameraFrame, Pose, usize)], seen_by: &[String]) -> bool {
        let cfg = self.config.verification;
        let Some(est) = self.state.estimate.as_ref() else {
            return false;
        };
        // shares of the modes' mass (the modes cluster the heaviest bins only)
        let total: f64 = est.rotation_modes.iter().map(|m| m.mass).sum();
        let modes: Vec<UnitQuaternion<f64>> = est
            .rotation_modes
            .iter()
            .filter(|m| total > 0.0 && m.mass / total >= cfg.min_mode_mass)
            .take(cfg.max_modes)
            .map(|m| {
                let [x, y, z, w] = m.rotation_xyzw;
                UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z))
            })
            .collect();
        if modes.len() < 2 {
            return false;
        }
        let mean_ref = est.reference_from_object.translation;
        let mi = self.state.model;
        let model = &self.models[mi];
        let mut total = vec![0.0; modes.len()];
        let mut scored = false;
        // the cameras whose direction to the track turned enough since they last verified it
        let min_turn = cfg.min_view_change_deg.to_radians();
        let hist_from_ref = self.state.reference_from_hist.inverse();
        let mean_hist = hist_from_ref * Point3::from(mean_ref.vector);
        let mut fresh: Vec<(String, Vector3<f64>)> = Vec::new();
        for (frame, view_from_ref, _) in views.iter().filter(|v| seen_by.contains(&v.0.camera)) {
            // the object's diameter in pixels at the track's mean: far crops are not verified
            let depth_m = (view_from_ref * Point3::from(mean_ref.vector)).z;
            if depth_m <= 0.0
                || crate::tracker::observation::object_size_px(&model.codebook, &frame.intrinsics, depth_m)
                    < cfg.min_object_px
            {
                continue;
            }
            let camera_hist = hist_from_ref * (view_from_ref.inverse() * Point3::origin());
            let Some(dir) = (camera_hist - mean_hist).try_normalize(1e-9) else {
                continue;
            };
            let last = self
                .state
                .verified_from
                .iter()
                .find(|(c, _)| c == &frame.camera)
                .map(|(_, d)| *d);
            if min_turn <= 0.0 || last.is_none_or(|d| d.angle(&dir) >= min_turn) {
                fresh.push((frame.camera.clone(), dir));
            }
        }
        for (frame, view_from_ref, _) in views.iter().filter(|v| fresh.iter().any(|(c, _)| c == &v.0.camera)) {
            // the track's own detection in this view bounds the pixels its object may explain
            let object_box = frame
                .detections
                .iter()
                .find(|d| d.object == model.name && self.detection_holds(frame, d, view_from_ref))
                .map(|d| d.bbox_xywh_px);
            let mut poses: Vec<Pose> = modes
                .iter()
                .map(|q| view_from_ref * Pose::from_parts(mean_ref, *q))
                .collect();
            if cfg.register_modes {
                let rotation_var = model.tables.grid.step_rad().powi(2) / 12.0;
                crate::tracker::verify::register_hypotheses(
                    &model.mesh,
                    &frame.intrinsics,
                    &frame.depth,
                    &mut poses,
                    model.codebook.diameter_m,
                    rotation_var,
                    &self.config.registration,
                );
            }
            let view = crate::tracker::verify::DepthView {
                intrinsics: &frame.intrinsics,
                depth: &frame.depth,
                object_box_px: object_box,
            };
            if let Some(s) = crate::tracker::verify::score_hypotheses(
                &model.mesh,
                &view,
                &poses,
                model.codebook.diameter_m,
                est.translation_std_m / 3f64.sqrt(),
                &cfg,
            ) {
                for (t, v) in total.iter_mut().zip(s) {
                    *t += v;
                }
                scored = true;
            }
        }
        if !scored {
            return false;
        }
        let s = &mut *self.state;
        for (camera, dir) in fresh {
            match s.verified_from.iter_mut().find(|(c, _)| *c == camera) {
                Some(entry) => entry.1 = dir,
                None => s.verified_from.push((camera, dir)),
            }
        }
        let best = total.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let factors: Vec<f32> = total.iter().map(|t| (t - best).exp() as f32).collect();
        // each active bin's rotation in the reference frame, through the mean's ray as the
        // estimate's modes are
        let tables = model.tables.clone();
        let radius = 2.0 * self.config.estimate.mode_merge_rad;
        let s = &mut *self.state;
        let mean_hist = s
            .reference_from_hist
            .inverse_transform_point(&Point3::from(mean_ref.vector))
            .coords;
        let to_ref = s.reference_from_hist.rotation * crate::geometry::ray_rotation(&mean_hist);
        let nc = s.rot.n_cols();
        let grid = &tables.grid;
        let scale: Vec<f32> = s
            .rot
            .active
            .par_iter()
            .map(|b| {
                let r = to_ref * grid.rotation(grid.unflat(*b as usize));
                let (k, a) = modes
                    .iter()
                    .map(|m| m.angle_to(&r))
                    .enumerate()
                    .min_by(|x, y| x.1.total_cmp(&y.1))
                    .unwrap_or((0, f64::INFINITY));
                if a < radius { factors[k] } else { 1.0 }
            })
            .collect();
        for (row, f) in s.rot.values.chunks_mut(nc.max(1)).zip(&scale) {
            for v in row {
                *v *= f;
            }
        }
        s.rot.renormalise(&tables);
        true
    }

    /// When the registration is on (and the track's top rotation mode holds at least
    /// `RegistrationConfig::min_mode_share` of its modes' mass), registers the object at the track's mean and that mode to the depth
    /// of every view that saw it ([`crate::tracker::register`]) and moves the
    /// particles by a Kalman update towards the views' registered positions, counting the
    /// other cameras' newest fits too while they are young (`carry_max_age_s`). Returns
    /// whether it did.
    fn register_translation(&mut self, views: &[(&CameraFrame, Pose, usize)], seen_by: &[String]) -> bool {
        let cfg = self.config.registration;
        if cfg.information_scale <= 0.0 {
            return false;
        }
        let Some(est) = self.state.estimate.as_ref() else {
            return false;
        };
        let total: f64 = est.rotation_modes.iter().map(|m| m.mass).sum();
        let Some(top) = est.rotation_modes.first() else {
            return false;
        };
        if total <= 0.0 || top.mass / total < cfg.min_mode_share {
            return false;
        }
        let [x, y, z, w] = top.rotation_xyzw;
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
        let mean_ref = est.reference_from_object.translation;
        let model = &self.models[self.state.model];
        let diameter_m = model.codebook.diameter_m;
        // the rotation's error: the estimate's rotation-vector covariance (object frame) plus
        // the grid's quantisation (a uniform bin's variance per axis)
        let bin_var = model.tables.grid.step_rad().powi(2) / 12.0;
        // (modulo the object's near-symmetric turns, which leave the surface in place)
        let rotation_cov = self
            .state
            .surface_rotation_cov
            .unwrap_or_else(|| Matrix3::from_fn(|r, c| est.covariance_6x6[r + 3][c + 3]))
            + Matrix3::identity() * bin_var;
        // per view: the registered position and its information, both in the reference frame
        let mut fits: Vec<(Vector3<f64>, Matrix3<f64>)> = Vec::new();
        let mut fresh: Vec<super::CarriedFit> = Vec::new();
        // the views' fits are independent: side by side, taken in view order
        let seen: Vec<&(&CameraFrame, Pose, usize)> = views.iter().filter(|v| seen_by.contains(&v.0.camera)).collect();
        let regs: Vec<_> = seen
            .par_iter()
            .map(|(frame, view_from_ref, _)| {
                let pose = view_from_ref * Pose::from_parts(mean_ref, q);
                crate::tracker::register::register_translation(
                    &model.mesh,
                    &frame.intrinsics,
                    &frame.depth,
                    &pose,
                    diameter_m,
                    &rotation_cov,
                    &cfg,
                )
            })
            .collect();
        for ((frame, view_from_ref, _), reg) in seen.into_iter().zip(regs) {
            let Some(reg) = reg else {
                continue;
            };
            let r = view_from_ref.rotation.inverse().to_rotation_matrix();
            let target = mean_ref.vector + r * reg.delta_m;
            let info = r.matrix() * reg.information * r.matrix().transpose() * cfg.information_scale;
            tracing::trace!(
                camera = %frame.camera,
                inliers = reg.inliers,
                noise_rel = reg.noise_rel,
                std_mm = ?reg.information.symmetric_eigen().eigenvalues.map(|l| 1e3 / l.max(1e-12).sqrt()),
                "registered"
            );
            fits.push((target, info));
            fresh.push(super::CarriedFit {
                camera: frame.camera.clone(),
                stamp_ns: self.stamp_ns,
                target,
                information: info,
            });
        }
        // the other cameras' newest fits, while young enough; this step's replace their own
        let max_age_ns = (cfg.carry_max_age_s.max(0.0) * 1e9) as i64;
        let stamp_ns = self.stamp_ns;
        let kept = &mut self.state.carried_fits;
        kept.retain(|f| {
            (0..=max_age_ns).contains(&(stamp_ns - f.stamp_ns)) && !fresh.iter().any(|g| g.camera == f.camera)
        });
        fits.extend(kept.iter().map(|f| (f.target, f.information)));
        kept.extend(fresh);
        if fits.is_empty() {
            return false;
        }
        // a Kalman update of every particle by the registered positions, per source camera's
        // component with that component's spread as the prior: the reported cloud moves and
        // narrows along what the depth fixes. The filter keeps its own positions: a cloud
        // narrowed there crops every particle alike, and the rotation histograms, which the
        // crops' spread keeps apart, turned confidently wrong on the tuning set (mugs, bananas)
        let h: Matrix3<f64> = fits.iter().map(|f| f.1).sum();
        tracing::trace!(
            fits = fits.len(),
            std_mm = ?h.symmetric_eigen().eigenvalues.map(|l| 1e3 / l.max(1e-12).sqrt()),
            "registration combined"
        );
        let b: Vector3<f64> = fits.iter().map(|f| f.1 * f.0).sum();
        self.state.registered = Some(super::Registered {
            information: h,
            target: b,
            positions: Vec::new(),
        });
        move_registered(self.state, self.config.spread);
        true
    }

    /// Recomputes a track's estimate from its particles.
    fn refresh_estimate(&mut self) {
        let tables = self.models[self.state.model].tables.clone();
        let status = self.track.status;
        let est = {
            let s = &self.state;
            let set = s.reported_set(&tables, self.config.spread);
            let mean = set.mean_position();
            let mean_hist = s
                .reference_from_hist
                .inverse_transform_point(&Point3::from(mean))
                .coords;
            let (tcov, tstd) = set.translation_covariance();
            let mixture = set.mixture();
            let mut summary = crate::tracker::estimate::summarise_rotation(
                &tables.grid,
                &mixture,
                &mean_hist,
                s.rotation.as_ref(),
                &self.config.estimate,
                &self.models[s.model].turns,
            );
            let surface_cov = summary.surface_covariance;
            let rotation_hist = summary.rotation;
            let to_ref = s.reference_from_hist.rotation;
            summary.rotation = to_ref * rotation_hist;
            for m in &mut summary.modes {
                let q = to_ref
                    * UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                        m.rotation_xyzw[3],
                        m.rotation_xyzw[0],
                        m.rotation_xyzw[1],
                        m.rotation_xyzw[2],
                    ));
                let v = q.quaternion();
                m.rotation_xyzw = [v.i, v.j, v.k, v.w];
            }
            let mut cov6 = [[0.0; 6]; 6];
            for r in 0..3 {
                for c in 0..3 {
                    cov6[r][c] = tcov[(r, c)];
                    cov6[r + 3][c + 3] = summary.covariance[(r, c)];
                }
            }
            let est = crate::tracker::Estimate {
                reference_from_object: Pose::from_parts(nalgebra::Translation3::from(mean), summary.rotation),
                translation_std_m: tstd,
                components: set.components(self.camera_names),
                rotation_modes: summary.modes,
                rotation_entropy: summary.entropy,
                covariance_6x6: cov6,
                status,
                stamp_ns: self.stamp_ns,
            };
            (est, rotation_hist, surface_cov)
        };
        self.state.rotation = Some(est.1);
        self.state.estimate = Some(est.0);
        self.state.surface_rotation_cov = Some(est.2);
    }

    fn detection_holds(&self, frame: &CameraFrame, det: &crate::tracker::Detection, view_from_ref: &Pose) -> bool {
        super::recovery::detection_holds(self.state, self.models, self.config, frame, det, view_from_ref)
    }
}

impl Tracker {
    /// Updates every track that has particles with this step's views: the tracks side by side,
    /// as many at a time as there are threads (each track's update is the same arithmetic as
    /// alone; more at once would hold more tracks' matching buffers for no more speed), then in
    /// track order their resampling.
    pub(super) fn update_tracks(&mut self, views: &[(&CameraFrame, Pose, usize)], report: &mut StepReport) {
        let down_reference = self.down_in_reference();
        let order: Vec<usize> = (0..self.states.len()).filter(|&ti| self.states[ti].n() > 0).collect();
        let pool = std::mem::take(&mut self.sims);
        let jobs: Vec<TrackUpdate> = self
            .states
            .iter_mut()
            .zip(self.tracks.iter_mut())
            .filter(|(s, _)| s.n() > 0)
            .map(|(state, track)| TrackUpdate {
                config: &self.config,
                down_reference,
                models: &self.models,
                camera_names: &self.camera_names,
                stamp_ns: self.stamp_ns,
                state,
                track,
                sims: Vec::new(),
            })
            .collect();
        // as many workers as threads, each taking the next track when it is done with one: at
        // most that many tracks' buffers at once, and no core idle while a track is left
        let n_jobs = jobs.len();
        let workers = rayon::current_num_threads().clamp(1, n_jobs.max(1));
        let jobs: Vec<Mutex<TrackUpdate>> = jobs.into_iter().map(Mutex::new).collect();
        let results: Vec<Mutex<Option<(StepReport, bool)>>> = (0..n_jobs).map(|_| Mutex::new(None)).collect();
        let next = AtomicUsize::new(0);
        let pool = Mutex::new(pool);
        rayon::scope(|scope| {
            for _ in 0..workers {
                scope.spawn(|_| {
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        if i >= n_jobs {
                            break;
                        }
                        let mut job = lock(&jobs[i]);
                        job.sims = {
                            let mut p = lock(&pool);
                            (0..views.len()).map_while(|_| p.pop()).collect()
                        };
                        let mut r = StepReport::default();
                        let had_evidence = job.update(views, &mut r);
                        lock(&pool).append(&mut job.sims);
                        *lock(&results[i]) = Some((r, had_evidence));
                    }
                });
            }
        });
        drop(jobs);
        self.sims = pool.into_inner().unwrap_or_else(|p| p.into_inner());
        let done: Vec<(StepReport, bool)> = results
            .into_iter()
            .map(|r| {
                r.into_inner()
                    .unwrap_or_else(|p| p.into_inner())
                    .expect("every track is updated")
            })
            .collect();
        for (ti, (r, had_evidence)) in order.into_iter().zip(done) {
            report.absorb(r);
            self.finish_update(ti, had_evidence, report);
        }
    }

    /// A track's update after [`TrackUpdate::update`]: resampling within components, then the
    /// bins that went back to the floor.
    fn finish_update(&mut self, ti: usize, had_evidence: bool, report: &mut StepReport) {
        let matching = self.config.matching;
        let tables = self.models[self.states[ti].model].tables.clone();
        let t0 = Instant::now();
        if had_evidence {
            self.resample(ti);
            let spread = self.config.spread;
            move_registered(&mut self.states[ti], spread);
        }
        if !matching.dense {
            let rule = matching.prune_rule(self.config.prior_floor_rel);
            self.states[ti].rot.prune(&tables, &rule);
        } else if had_evidence {
            // the dense reference keeps every bin, in order
            let s = &mut self.states[ti];
            sort_active(&mut s.rot);
        }
        report.active_bins += self.states[ti].rot.active.len();
        report.timings.resampling_s += t0.elapsed().as_secs_f64();
    }

    /// Recomputes a track's estimate from its particles.
    pub(super) fn refresh_estimate(&mut self, ti: usize) {
        TrackUpdate {
            config: &self.config,
            down_reference: None,
            models: &self.models,
            camera_names: &self.camera_names,
            stamp_ns: self.stamp_ns,
            state: &mut self.states[ti],
            track: &mut self.tracks[ti],
            sims: Vec::new(),
        }
        .refresh_estimate();
    }

    /// Systematic resampling inside each source camera's component: the component keeps its
    /// particle count and its weight (spread evenly over its new particles); copies of one
    /// ancestor share its histogram column.
    fn resample(&mut self, ti: usize) {
        use rand::Rng;
        let s = &mut self.states[ti];
        let n = s.n();
        let mut src_idx: Vec<usize> = Vec::with_capacity(n);
        let mut new_w: Vec<f64> = Vec::with_capacity(n);
        let cams = components(&s.sources);
        let mut new_sources = Vec::with_capacity(n);
        for c in cams {
            let idx: Vec<usize> = (0..n).filter(|&i| s.sources[i] == c).collect();
            let wc: f64 = idx.iter().map(|&i| s.weights[i]).sum();
            let m = idx.len();
            let u0 = self.rng.random::<f64>() / m as f64;
            let mut acc = 0.0;
            let mut j = 0;
            for k in 0..m {
                let u = (u0 + k as f64 / m as f64) * wc;
                while j + 1 < m && acc + s.weights[idx[j]] < u {
                    acc += s.weights[idx[j]];
                    j += 1;
                }
                src_idx.push(idx[j]);
                new_w.push(wc / m as f64);
                new_sources.push(c);
            }
        }
        let spread = self.config.spread;
        let kernels: Vec<Kernel> = components(&s.sources)
            .into_iter()
            .map(|c| {
                let (mean, cov) = crate::tracker::estimate::component_moments(&s.positions, &s.weights, &s.sources, c);
                let h2 = spread.bandwidth * spread.bandwidth;
                let chol = (h2 > 0.0)
                    .then(|| (cov * h2 + nalgebra::Matrix3::identity() * 1e-12).cholesky())
                    .flatten()
                    .map(|c| c.l());
                (c, mean, chol, spread.extra(&mean, &cov, None))
            })
            .collect();
        let shrink = (1.0 - (spread.bandwidth * spread.bandwidth).min(1.0)).sqrt();
        let std_normal = rand_distr::StandardNormal;
        let mut positions: Vec<Vector3<f64>> = src_idx.iter().map(|&i| s.positions[i]).collect();
        for (p, c) in positions.iter_mut().zip(&new_sources) {
            let Some((_, mean, chol, extra)) = kernels.iter().find(|k| k.0 == *c) else {
                continue;
            };
            let z = Vector3::from_fn(|_, _| rand_distr::Distribution::<f64>::sample(&std_normal, &mut self.rng));
            let e = Vector3::from_fn(|_, _| rand_distr::Distribution::<f64>::sample(&std_normal, &mut self.rng));
            if let Some(l) = chol {
                *p = mean + (*p - mean) * shrink + l * z;
            }
            *p += extra.draw(&e);
        }
        s.positions = positions;
        s.rot.resample(&src_idx);
        s.weights = new_w;
        s.sources = new_sources;
        normalise(&mut s.weights);
    }
}

/// The positions the track reports with this step's registration: each source camera's
/// component updated by it (a Kalman update with the component's spread as the prior),
/// after the registration and again after resampling.
fn move_registered(s: &mut TrackState, spread: super::SpreadConfig) {
    let Some((h, b)) = s.registered.as_ref().map(|r| (r.information, r.target)) else {
        return;
    };
    let mut moved = s.positions.clone();
    for c in components(&s.sources) {
        let (mean, cov) = crate::tracker::estimate::component_moments(&s.positions, &s.weights, &s.sources, c);
        let prior = cov + spread.extra(&mean, &cov, None).cov();
        let Some(gain) = prior.try_inverse().and_then(|p_inv| (p_inv + h).try_inverse()) else {
            continue;
        };
        for (p, src) in moved.iter_mut().zip(&s.sources) {
            if *src == c {
                *p += gain * (b - h * *p);
            }
        }
    }
    if let Some(r) = s.registered.as_mut() {
        r.positions = moved;
    }
}

/// One component's regularisation kernel: its camera, mean, the Cholesky factor of `h^2 S`
/// (none without shrinkage) and the standard deviation its floor adds.
type Kernel = (
    usize,
    Vector3<f64>,
    Option<nalgebra::Matrix3<f64>>,
    crate::tracker::estimate::FloorExtra,
);

/// The distinct source cameras of a track's particles, ascending.
fn components(sources: &[usize]) -> Vec<usize> {
    let mut cams = sources.to_vec();
    cams.sort_unstable();
    cams.dedup();
    cams
}

/// Sorts the active bins (with their values) ascending.
fn sort_active(rot: &mut RotationState) {
    if rot.active.windows(2).all(|w| w[0] < w[1]) {
        return;
    }
    let nc = rot.n_cols();
    let mut order: Vec<usize> = (0..rot.active.len()).collect();
    order.par_sort_unstable_by_key(|i| rot.active[*i]);
    let mut values = vec![0f32; rot.values.len()];
    values.par_chunks_mut(nc).zip(&order).for_each(|(dst, i)| {
        dst.copy_from_slice(&rot.values[i * nc..(i + 1) * nc]);
    });
    rot.active = order.iter().map(|i| rot.active[*i]).collect();
    rot.values = values;
}

/// Per particle and lattice cell, the log posterior density (up to a constant) at the cell's
/// lattice point: `ln(prior / volume) + f`, plus the log of the cell's support factor
/// (`support`, one per matched bin) when the support prior is on.
#[allow(clippy::too_many_arguments)]
fn refine_bins(
    lattice: &Lattice,
    views: &[&ViewEvidence],
    lattice_rows: &[u32],
    bins: &[u32],
    slots: &[u32],
    rot: &RotationState,
    tables: &crate::tracker::bins::GridTables,
    n: usize,
    matching: &super::MatchingConfig,
    support: Option<&[f32]>,
) -> Vec<u32> {
    let nc = rot.n_cols();
    // cells whose every fine bin is matched already need nothing
    let mut matched_in_cell = vec![0u32; lattice.points.len()];
    for b in bins {
        matched_in_cell[lattice.cell_of[*b as usize] as usize] += 1;
    }
    // the log prior density of a bin on the floor depends on its column and elevation row
    // only: taken once per pair (the same expression as per bin, so the same values)
    let per_row = tables.grid.n_azimuth() * tables.grid.n_inplane();
    let floor_ln: Vec<f32> = tables
        .elevation_volume
        .iter()
        .flat_map(|v| {
            let vol = *v as f32;
            rot.floors.iter().map(move |fl| ((fl * vol) / vol).max(1e-30).ln())
        })
        .collect();
    let mut scored: Vec<(f32, usize)> = lattice_rows
        .par_iter()
        .enumerate()
        .with_min_len(256)
        .filter(|(c, _)| (matched_in_cell[*c] as usize) < lattice.cell_bins[*c].len())
        .map(|(c, row)| {
            let i = *row as usize;
            let mut f = vec![0f32; n];
            fused_row(views, i, n, &mut f);
            let b = bins[i] as usize;
            let vol = tables.volume(b) as f32;
            let on_floor = &floor_ln[(b / per_row) * nc..(b / per_row + 1) * nc];
            let best = (0..n)
                .map(|p| {
                    let col = rot.column_of[p] as usize;
                    let ln_prior = if slots[i] == u32::MAX {
                        on_floor[col]
                    } else {
                        (rot.values[slots[i] as usize * nc + col] / vol).max(1e-30).ln()
                    };
                    ln_prior + f[p]
                })
                .fold(f32::NEG_INFINITY, f32::max);
            let best = best + support.map_or(0.0, |s| s[i].max(1e-30).ln());
            (best, c)
        })
        .collect();
    // a track without active bins (a new one) has no support to refine around: more cells
    let cells = if rot.active.is_empty() {
        4 * matching.refine_cells
    } else {
        matching.refine_cells
    };
    let k = cells.min(scored.len());
    if k == 0 {
        return Vec::new();
    }
    scored.select_nth_unstable_by(k - 1, |a, b| b.0.total_cmp(&a.0));
    scored.truncate(k);
    let mut matched = std::collections::HashSet::with_capacity(bins.len());
    for (c, _) in scored.iter().map(|(_, c)| (*c, ())) {
        for b in &lattice.cell_bins[c] {
            matched.insert(*b);
        }
    }
    for b in bins {
        matched.remove(b);
    }
    let mut out: Vec<u32> = matched.into_iter().collect();
    out.sort_unstable();
    out
}

/// Per particle, the posterior mass of the bins left out of the matched set, each taken at its
/// lattice cell's fused likelihood on the prior's floor; and the volume left out.
#[allow(clippy::too_many_arguments)]
fn unmatched_mass(
    lattice: &Lattice,
    views: &[&ViewEvidence],
    lattice_rows: &[u32],
    bins: &[u32],
    rot: &RotationState,
    tables: &crate::tracker::bins::GridTables,
    floor_rel: f32,
    fmax: &[f32],
    support: Option<&[f32]>,
) -> (Vec<f64>, f64) {
    let n = fmax.len();
    let mut left = lattice.cell_volume.clone();
    for b in bins {
        left[lattice.cell_of[*b as usize] as usize] -= tables.volume(*b as usize);
    }
    let lvl: Vec<f32> = rot
        .column_of
        .iter()
        .map(|c| rot.floors[*c as usize].max(floor_rel))
        .collect();
    let total: f64 = left.iter().map(|v| v.max(0.0)).sum();
    // fixed blocks of cells, summed in order: the same sums however the threads share them
    const BLOCK: usize = 256;
    let blocks: Vec<Vec<f64>> = lattice_rows
        .par_chunks(BLOCK)
        .enumerate()
        .map(|(k, rows)| {
            let (mut acc, mut f) = (vec![0f64; n], vec![0f32; n]);
            for (j, row) in rows.iter().enumerate() {
                let c = k * BLOCK + j;
                if left[c] <= 1e-15 {
                    continue;
                }
                fused_row(views, *row as usize, n, &mut f);
                let k = support.map_or(1.0, |s| f64::from(s[*row as usize]));
                for p in 0..n {
                    acc[p] += (lvl[p] as f64) * left[c] * k * crate::tracker::bins::fast_exp(f[p] - fmax[p]) as f64;
                }
            }
            acc
        })
        .collect();
    let mut mass = vec![0f64; n];
    for b in blocks {
        for (x, y) in mass.iter_mut().zip(b) {
            *x += y;
        }
    }
    (mass, total)
}

/// A mutex's guard, also after a panic elsewhere (the data is a track's own update).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merge_is_the_sorted_union_with_slots() {
        let a = vec![2u32, 5, 9];
        let b = vec![0u32, 5, 7];
        let (out, slots, b_index) = merge(&a, &b, (8, 4), 12);
        assert_eq!(out, vec![0, 2, 5, 7, 8, 9, 10, 11]);
        assert_eq!(slots, vec![u32::MAX, 0, 1, u32::MAX, u32::MAX, 2, u32::MAX, u32::MAX]);
        assert_eq!(b_index, vec![0, 2, 3]);
        // a slice that wraps around the end of the grid
        let (out, _, _) = merge(&[], &[5], (10, 4), 12);
        assert_eq!(out, vec![0, 1, 5, 10, 11]);
        let (out, _, _) = merge(&a, &b, (0, 0), 12);
        assert_eq!(out, vec![0, 2, 5, 7, 9]);
        let (out, _, _) = merge(&[], &[], (3, 2), 12);
        assert_eq!(out, vec![3, 4]);
    }
}
