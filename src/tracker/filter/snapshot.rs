//! Tracks started from a caller's prior, and compact snapshots of the tracker's state.
//!
//! # Priors
//! A planner that already believes something about an object (the last map, a previous
//! visit, a human's click) starts a track with [`Tracker::start_track`]: translation
//! particles from an isotropic Gaussian around the given position, and every particle's
//! rotation histogram a Gaussian in the geodesic angle to the given rotation (or uniform when
//! no rotation is given), floored like every prior. The particles belong to the reference
//! camera's component; other cameras add their components from their first detections,
//! exactly as for a track started from a detection (the track stays `initialising` until the
//! first evidence).
//!
//! # Snapshots
//! A full state is `bins x particles` floats (84 MB for 110 particles on the full grid), too
//! much to write every few seconds. A [`TrackerSnapshot`] keeps every particle's position,
//! source and weight exactly, and of the rotation only the particle-weighted *mixture*
//! histogram, sparse (the bins that hold all but [`SNAPSHOT_DROPPED_MASS`] of the mass): a
//! few hundred kB at most. Restoring gives every particle that mixture (floored): the
//! correlation between a particle's position and its rotation is lost, the marginal rotation
//! distribution, the translation mixture and the estimate are kept. A snapshot taken on one
//! grid restores onto another (the coarse codebook comes first after a restart): each stored
//! bin's mass moves to the nearest bin of the new grid.

use super::{Disagreement, TrackState, Tracker};
use crate::geometry::{Pose, ray_rotation};
use crate::tracker::bins::GridTables;
use crate::tracker::sparse::RotationState;
use crate::tracker::{RobotOdometry, Track, TrackStatus, TrackerError};
use nalgebra::{UnitQuaternion, Vector3};
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

/// Version of [`TrackerSnapshot`]'s layout.
pub const SNAPSHOT_VERSION: u32 = 1;
/// Share of a track's rotation mass a snapshot may leave out (its smallest bins).
pub const SNAPSHOT_DROPPED_MASS: f64 = 1e-4;

/// What a caller believes about an object, in the reference frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackPrior {
    /// Mean pose (the rotation is used only with `rotation_std_rad`).
    pub reference_from_object: Pose,
    /// Isotropic standard deviation of the position, per axis.
    pub translation_std_m: f64,
    /// Standard deviation of the rotation's geodesic angle; `None`: any rotation.
    pub rotation_std_rad: Option<f64>,
}

/// One track in a snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackSnapshot {
    pub track: Track,
    /// Step of the grid the histograms were on.
    pub grid_step_deg: u32,
    pub positions_m: Vec<[f64; 3]>,
    /// Source camera of each particle.
    pub sources: Vec<String>,
    pub weights: Vec<f64>,
    pub reference_from_hist: Pose,
    /// Previous rotation estimate (histogram frame), as x, y, z, w.
    pub rotation_xyzw: Option<[f64; 4]>,
    /// The particle-weighted mixture histogram, sparse: (flat bin, mass), masses sum to ~1.
    pub rotation_bins: Vec<(u32, f32)>,
}

/// The tracker's state in a compact form (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackerSnapshot {
    pub version: u32,
    pub stamp_ns: i64,
    pub next_id: u64,
    pub world_from_reference: Pose,
    pub last_odometry: Option<RobotOdometry>,
    pub tracks: Vec<TrackSnapshot>,
}

impl Tracker {
    /// Starts a track of model `object` from a prior; returns its id. The estimate is
    /// available at once.
    pub fn start_track(&mut self, object: &str, prior: &TrackPrior) -> Result<u64, TrackerError> {
        let mi = self
            .models
            .iter()
            .position(|m| m.name == object)
            .ok_or_else(|| TrackerError::Config(format!("no model {object:?} in the tracker")))?;
        let t = prior.reference_from_object.translation.vector;
        let finite = t.iter().all(|v| v.is_finite())
            && prior
                .reference_from_object
                .rotation
                .coords
                .iter()
                .all(|v| v.is_finite());
        if !(finite && prior.translation_std_m.is_finite() && prior.translation_std_m >= 0.0) {
            return Err(TrackerError::Config(
                "prior: non-finite pose or bad translation std".into(),
            ));
        }
        if let Some(r) = prior.rotation_std_rad
            && !(r.is_finite() && r > 0.0)
        {
            return Err(TrackerError::Config(format!(
                "prior: rotation std must be > 0, got {r}"
            )));
        }
        let ci = self
            .camera_names
            .iter()
            .position(|c| c == &self.reference)
            .ok_or_else(|| TrackerError::UnknownCamera(self.reference.clone()))?;
        let externals = self
            .cameras
            .iter()
            .filter(|(name, m)| *name != &self.reference && matches!(m, crate::tracker::CameraMount::Stationary { .. }))
            .count();
        let n = if self.config.only_reference_camera {
            self.config.particles_from_robot_camera
        } else {
            self.config.particles_from_robot_camera + externals * self.config.particles_per_external_camera
        };
        let normal = Normal::new(0.0, prior.translation_std_m).map_err(|e| TrackerError::Config(e.to_string()))?;
        let positions: Vec<Vector3<f64>> = (0..n)
            .map(|_| {
                t + Vector3::new(
                    normal.sample(&mut self.rng),
                    normal.sample(&mut self.rng),
                    normal.sample(&mut self.rng),
                )
            })
            .collect();
        let tables = self.models[mi].tables.clone();
        let grid = tables.grid;
        // histograms live in H = the reference frame now; allocentric through the mean's ray
        let column: Vec<f32> = match prior.rotation_std_rad {
            None => (0..grid.len()).map(|b| tables.volume(b) as f32).collect(),
            Some(sigma) => {
                let sigma = sigma.max(0.5 * grid.step_rad());
                let allo = ray_rotation(&t).inverse() * prior.reference_from_object.rotation;
                let floor = self.config.prior_floor_rel;
                (0..grid.len())
                    .map(|b| {
                        let a = grid.rotation(grid.unflat(b)).angle_to(&allo);
                        (tables.volume(b) * ((-0.5 * a * a / (sigma * sigma)).exp()).max(floor)) as f32
                    })
                    .collect()
            }
        };
        let id = self.next_id;
        self.next_id += 1;
        self.tracks.push(Track {
            id,
            object: object.to_string(),
            status: TrackStatus::Initialising,
            stamp_ns: self.stamp_ns,
            best_similarity: None,
            weak_steps: 0,
            seen_by: Vec::new(),
            reference_seen: true,
            reinitialised: None,
        });
        let state = state_from_column(
            mi,
            &tables,
            positions,
            vec![ci; n],
            vec![1.0 / n as f64; n],
            &column,
            Pose::identity(),
            None,
        );
        self.states.push(state);
        let ti = self.states.len() - 1;
        self.refresh_estimate(ti);
        Ok(id)
    }

    /// Re-bins every track of model `name` onto that model's new grid (a finer codebook
    /// arrived): each track goes through its compact snapshot, so it keeps its particles,
    /// weights and marginal rotation instead of restarting. Returns the tracks that could not
    /// be carried over (declared lost, their particles dropped).
    pub(super) fn carry_tracks_to_new_grid(&mut self, carried: Vec<TrackSnapshot>) -> Vec<u64> {
        let mut failed = Vec::new();
        for t in carried {
            if let Err(e) = self.restore_track(&t) {
                tracing::warn!("track {} not carried to the new grid: {e}", t.track.id);
                if let Some(i) = self.index_of(t.track.id) {
                    self.tracks[i].status = TrackStatus::Lost;
                    let st = &mut self.states[i];
                    st.positions.clear();
                    st.sources.clear();
                    st.weights.clear();
                    st.rot.clear();
                    st.map_cache.clear();
                }
                failed.push(t.track.id);
            }
        }
        failed
    }

    /// Snapshots of the tracks of model `mi` (before its grid changes).
    pub(super) fn snapshots_of_model(&self, mi: usize) -> Vec<TrackSnapshot> {
        (0..self.tracks.len())
            .filter(|&i| self.states[i].model == mi && self.states[i].n() > 0)
            .map(|i| self.track_snapshot(i))
            .collect()
    }

    /// Stops tracking `track_id`; false when there is no such track.
    pub fn remove_track(&mut self, track_id: u64) -> bool {
        match self.index_of(track_id) {
            Some(i) => {
                self.tracks.remove(i);
                self.states.remove(i);
                true
            }
            None => false,
        }
    }

    /// A compact snapshot of every track (see the module docs).
    pub fn snapshot(&self) -> TrackerSnapshot {
        let tracks = (0..self.tracks.len())
            .filter(|&i| self.states[i].n() > 0)
            .map(|i| self.track_snapshot(i))
            .collect();
        TrackerSnapshot {
            version: SNAPSHOT_VERSION,
            stamp_ns: self.stamp_ns,
            next_id: self.next_id,
            world_from_reference: self.world_from_reference,
            last_odometry: self.last_odometry,
            tracks,
        }
    }

    /// The compact snapshot of track `i` (index into `tracks`).
    fn track_snapshot(&self, i: usize) -> TrackSnapshot {
        let (track, s) = (&self.tracks[i], &self.states[i]);
        let tables = &self.models[s.model].tables;
        let mixture = s.reported_set(tables, self.config.spread).mixture();
        let total: f64 = mixture.iter().sum();
        let mut bins: Vec<(u32, f32)> = mixture
            .iter()
            .enumerate()
            .filter(|(_, m)| **m > 0.0)
            .map(|(b, m)| (b as u32, (*m / total.max(1e-300)) as f32))
            .collect();
        bins.sort_by(|a, b| b.1.total_cmp(&a.1));
        let mut kept = 0.0f64;
        let keep = bins
            .iter()
            .take_while(|(_, m)| {
                let more = kept < 1.0 - SNAPSHOT_DROPPED_MASS;
                kept += *m as f64;
                more
            })
            .count();
        bins.truncate(keep.max(1));
        bins.sort_by_key(|(b, _)| *b);
        TrackSnapshot {
            track: track.clone(),
            grid_step_deg: tables.grid.step_deg(),
            positions_m: s.positions.iter().map(|p| [p.x, p.y, p.z]).collect(),
            sources: s.sources.iter().map(|c| self.camera_names[*c].clone()).collect(),
            weights: s.weights.clone(),
            reference_from_hist: s.reference_from_hist,
            rotation_xyzw: s.rotation.map(|q| [q.i, q.j, q.k, q.w]),
            rotation_bins: bins,
        }
    }

    /// Restores the tracker-wide part of a snapshot (robot pose, odometry, time, ids); call
    /// before [`Tracker::restore_track`].
    pub fn restore_frame(&mut self, snapshot: &TrackerSnapshot) -> Result<(), TrackerError> {
        if snapshot.version != SNAPSHOT_VERSION {
            return Err(TrackerError::Config(format!(
                "snapshot version {} (this build reads {SNAPSHOT_VERSION})",
                snapshot.version
            )));
        }
        self.stamp_ns = self.stamp_ns.max(snapshot.stamp_ns);
        self.next_id = self.next_id.max(snapshot.next_id);
        self.world_from_reference = snapshot.world_from_reference;
        if self.last_odometry.is_none() {
            self.last_odometry = snapshot.last_odometry;
        }
        Ok(())
    }

    /// Restores one track of a snapshot; its model must have been added. A track with the
    /// same id is replaced.
    pub fn restore_track(&mut self, t: &TrackSnapshot) -> Result<(), TrackerError> {
        let bad = |why: &str| TrackerError::Config(format!("snapshot of track {}: {why}", t.track.id));
        let mi = self
            .models
            .iter()
            .position(|m| m.name == t.track.object)
            .ok_or_else(|| bad(&format!("no model {:?}", t.track.object)))?;
        let n = t.positions_m.len();
        if n == 0 || t.sources.len() != n || t.weights.len() != n {
            return Err(bad("particle arrays of different lengths"));
        }
        let sources = t
            .sources
            .iter()
            .map(|c| {
                self.camera_names
                    .iter()
                    .position(|n| n == c)
                    .ok_or_else(|| bad(&format!("unknown camera {c:?}")))
            })
            .collect::<Result<Vec<usize>, _>>()?;
        let finite = t.positions_m.iter().flatten().all(|v| v.is_finite())
            && t.weights.iter().all(|w| w.is_finite() && *w >= 0.0);
        if !finite || t.weights.iter().sum::<f64>() <= 0.0 {
            return Err(bad("non-finite positions or weights"));
        }
        let tables = self.models[mi].tables.clone();
        let grid = tables.grid;
        let from = crate::geometry::RotationGrid::new(t.grid_step_deg).map_err(|e| bad(&e.to_string()))?;
        let floor = self.config.prior_floor_rel;
        let mut column: Vec<f64> = (0..grid.len()).map(|b| floor * tables.volume(b)).collect();
        for (b, m) in &t.rotation_bins {
            let b = *b as usize;
            if b >= from.len() || !m.is_finite() || *m < 0.0 {
                return Err(bad("rotation bin out of range or negative"));
            }
            let to = if from == grid {
                b
            } else {
                grid.flat_of(&from.rotation(from.unflat(b)))
            };
            column[to] += *m as f64;
        }
        let column: Vec<f32> = column.into_iter().map(|v| v as f32).collect();
        let positions = t.positions_m.iter().map(|p| Vector3::new(p[0], p[1], p[2])).collect();
        let rotation = t
            .rotation_xyzw
            .map(|q| UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2])));
        let mut state = state_from_column(
            mi,
            &tables,
            positions,
            sources,
            t.weights.clone(),
            &column,
            t.reference_from_hist,
            rotation,
        );
        super::normalise(&mut state.weights);
        match self.index_of(t.track.id) {
            Some(i) => {
                self.tracks[i] = t.track.clone();
                self.states[i] = state;
            }
            None => {
                self.tracks.push(t.track.clone());
                self.states.push(state);
            }
        }
        self.next_id = self.next_id.max(t.track.id + 1);
        let ti = self.index_of(t.track.id).unwrap_or(self.states.len() - 1);
        self.refresh_estimate(ti);
        Ok(())
    }
}

/// A track state whose particles all carry `column` (normalised) as their histogram.
#[allow(clippy::too_many_arguments)] // the parts of a track state, each from its own source
fn state_from_column(
    model: usize,
    tables: &GridTables,
    positions: Vec<Vector3<f64>>,
    sources: Vec<usize>,
    weights: Vec<f64>,
    column: &[f32],
    reference_from_hist: Pose,
    rotation: Option<UnitQuaternion<f64>>,
) -> TrackState {
    let n = positions.len();
    TrackState {
        model,
        positions,
        sources,
        weights,
        rot: RotationState::from_column(tables, column, n),
        rotation,
        estimate: None,
        reference_from_hist,
        map_cache: Vec::new(),
        slice_cursor: 0,
        disagreement: Disagreement::default(),
        verified_from: Vec::new(),
        registered: None,
        carried_fits: Vec::new(),
        surface_rotation_cov: None,
    }
}
