//! The [`Tracker`]: one multi-view RBPF per tracked object instance.
//!
//! One step (all objects of the scene):
//! 1. Prediction: the robot camera's motion from odometry (odometry motion model per
//!    particle, the rotation prior re-binned once through a pull map), Brownian object motion,
//!    and the wrap-around blur of every histogram.
//! 2. Detections start tracks (or add a camera's component to a young track, or restart a
//!    track the filter declared lost) at the depth read in their box, leaving out what
//!    another, nearer detection covers ([`detection_centre`]).
//! 3. Update: per view, the evidence of [`observation`](super::observation) is pulled into the
//!    reference bins through one bin map per view and step and summed in log space (Eq. 6);
//!    the posterior is the prior (floored at `prior_floor_rel` times the bin's volume, times the
//!    support prior's factor when [`TrackerConfig::support`] is on) times the fused likelihood;
//!    the particle weight is multiplied by the marginal (Eq. 7), the depth term and, in every
//!    view with a detection of the object, the box term
//!    ([`ObservationConfig::detection_box`](super::observation::ObservationConfig)).
//! 4. Component weights are floored (`min_component_weight`) so that Eq. 2's mixture stays a
//!    mixture; estimates (with the depth registration's positions when it is on, see
//!    [`RegistrationConfig`]); resampling *within* each source camera's component
//!    (systematic), so each camera keeps its share of particles.
//!
//! Lost tracks: when the best similarity stays below `lost_similarity` for `lost_after_steps`
//! steps while the track's mean lies inside some camera's image, the track is `Lost`; the next
//! detection of its model restarts it. An object inside no camera's image keeps its prior
//! (its uncertainty grows with the motion noise).

mod recovery;
mod snapshot;
mod update;
pub use snapshot::{SNAPSHOT_VERSION, TrackPrior, TrackSnapshot, TrackerSnapshot};

use crate::camera::Intrinsics;
use crate::geometry::{Pose, PoseSamples};
use crate::mesh::Mesh;
use crate::tracker::bins::{GridTables, gaussian_kernel};
use crate::tracker::codebook::Codebook;
pub use crate::tracker::estimate::SpreadConfig;
use crate::tracker::estimate::{EstimateConfig, ParticleSet};
use crate::tracker::motion::{OdometryNoise, brownian, move_with_odometry};
use crate::tracker::observation::ObservationConfig;
pub use crate::tracker::register::RegistrationConfig;
use crate::tracker::sparse::{BlurWork, Lattice, RotationState};
pub use crate::tracker::verify::VerificationConfig;
use crate::tracker::{
    CameraFrame, CameraMount, Detection, Estimate, ParticleView, ReinitReason, Reinitialisation, RobotOdometry,
    StepReport, Track, TrackStatus, TrackerError,
};
use nalgebra::{UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use recovery::Disagreement;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

/// Configuration of the tracker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackerConfig {
    pub particles_per_external_camera: usize,
    pub particles_from_robot_camera: usize,
    /// Single-view baseline: use only the reference camera's frames.
    pub only_reference_camera: bool,
    pub observation: ObservationConfig,
    pub estimate: EstimateConfig,
    /// Best similarity below which a step counts as weak evidence.
    pub lost_similarity: f32,
    pub lost_after_steps: u32,
    pub brownian_sigma_m: f64,
    pub odometry_noise: OdometryNoise,
    pub blur_radius_bins: usize,
    pub blur_sigma_bins: f64,
    /// A lighter blur for tracks near the reference camera; `None`: `blur_sigma_bins`
    /// everywhere.
    #[serde(default)]
    pub near_blur: Option<NearBlur>,
    /// Prior floor per bin, relative to the bin's share of a uniform distribution.
    pub prior_floor_rel: f64,
    pub min_component_weight: f64,
    /// Initial pixel jitter as a share of the detection box side.
    pub init_uv_jitter_rel: f64,
    /// Initial depth jitter (m) plus this share of the object's diameter.
    pub init_depth_sigma_m: f64,
    /// A detection belongs to a track when the track's mean projects inside its box grown by
    /// this share of its side.
    pub association_margin_rel: f64,
    /// A detection that matches no track of its object opens a new track only while the
    /// object has fewer tracks than this that are not lost (0: no limit, every unmatched
    /// detection is a new instance; 1 by default, as the service runs). A lost track is restarted first either way. With a limit,
    /// two cameras whose first detections disagree on the position (or a track that drifted
    /// out of its detection's box) cannot duplicate a single object.
    #[serde(default)]
    pub max_tracks_per_object: usize,
    /// The particle weights' update (Eq. 7: old weight times the marginal of the fused
    /// histogram, times the depth term) is raised to the power `1 / views^t` with `t` this
    /// value and `views` the number of views with evidence in the step; 0 is the paper's plain
    /// product. The rotation histograms still multiply every view (Eq. 6): only the weights
    /// that pick translation particles are tempered.
    ///
    /// Why: the observation model's sharpness was tuned for one view (PoseRBPF), and the
    /// views' errors in the translation direction are not independent (a crop a centimetre off
    /// the object matches worse in every view at once), so a plain product of the views leaves
    /// almost no effective particles. With `t = 1` the weights are as peaked as one view's (the
    /// single-view filter is unchanged). Measurements: `docs/decisions.md`
    /// ("Tracker: decisions moved from the code").
    #[serde(default = "default_view_weight_tempering")]
    pub view_weight_tempering: f64,
    /// What each step matches and keeps of the rotation grid.
    #[serde(default)]
    pub matching: MatchingConfig,
    /// How resampling keeps the translation particles apart.
    #[serde(default)]
    pub spread: SpreadConfig,
    /// When the cameras' detections disagree with a track, part of it starts again.
    #[serde(default)]
    pub recovery: RecoveryConfig,
    /// Competing rotation modes checked against the depth images.
    #[serde(default)]
    pub verification: VerificationConfig,
    /// The translation registered to the views' depth narrows what the track reports.
    #[serde(default)]
    pub registration: RegistrationConfig,
    /// Each step, this share of every histogram's mass above its floor moves to the object's
    /// near-symmetric turns (`turn_max_distance_rel`): a view cannot be trusted to tell a pose
    /// from a turn that moves the surface by a few millimetres, so the turn keeps some mass
    /// until the evidence against it outweighs the move. 0: off. The default, 0.02 on the
    /// turns within 1.6 % of the diameter (the banana's end swap, the boxes', the can's and
    /// the bottles' half turns), was chosen on the tuning seeds and kept the truth likelier on
    /// every held-out seed (`docs/decisions.md`, "Turn mixing switched on with its map of four
    /// tuning sets").
    #[serde(default = "default_turn_share")]
    pub turn_share: f64,
    /// A turn by 90 or 180 degrees about an object axis, or the best half turn about any axis,
    /// is near-symmetric when it moves the mesh's surface by less than this share of the
    /// object's diameter on average (`symmetry::near_symmetric_turns`).
    #[serde(default = "default_turn_max_distance_rel")]
    pub turn_max_distance_rel: f64,
    /// Twins: each step a few particles jump to the pose an off-centre confusable turn makes
    /// of theirs, rotation and position together. On by default; `null` switches them off.
    #[serde(default = "default_twins")]
    pub twins: Option<TwinConfig>,
    /// The support prior: the object rests on a stable face of its hull or a face of its
    /// bounding box, its turn about the vertical free ([`crate::tracker::support`]); applied
    /// when the scene's support surface is known ([`Tracker::set_support_normal`]). `None`: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub support: Option<crate::tracker::support::SupportConfig>,
    pub seed: u64,
}

/// A confusable turn this near a turn that turn mixing already moves mass to gets no twins:
/// on the tuning set the banana's end swap with both lost 0.7 nats of the truth's
/// log-likelihood (`docs/decisions.md`, "Twins for the mug's turned body").
const TWIN_MIXED_TURN_RAD: f64 = 10.0 * std::f64::consts::PI / 180.0;

/// Twin particles for the joint modes a view confuses with the truth
/// (`symmetry::confusable_turns`): the mug's body turned about its own axis shows the handle on
/// the other side and sits two centimetres off, so the rotation histograms alone can never
/// carry the track from one to the other (the particles near the truth hold the turned
/// histogram of their ancestors, and the views weigh them down). Each step, `share` of a
/// track's particles (at least one) per turn move to their turned pose: the position shifted
/// by the turn's offset at the particle's top bin, the histogram turned. The views then weigh
/// the twins as any particle, so a twin at the truth takes over within a few steps, and twins
/// the views reject are resampled away (`docs/decisions.md`, "Twins for the mug's turned
/// body"). Only the mug among the YCB objects has such a turn within `max_trimmed_rel`; the
/// bottles' and the drill's lie within `near_max_trimmed_rel` where it is named.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TwinConfig {
    /// Share of a track's particles that jump per turn and step.
    pub share: f64,
    /// Turns whose trimmed surface distance is below this share of the object's diameter.
    pub max_trimmed_rel: f64,
    /// Turns that shift the object's origin by at least this (m); those that shift it less
    /// are turn mixing's (`turn_share`).
    pub min_shift_m: f64,
    /// Twins only for a track whose last rotation entropy is below this share of the
    /// uniform's: the shift's direction follows the particle's rotation, and twins of a
    /// rotation the track does not know scatter its positions by the shift at random.
    #[serde(default = "default_twin_max_entropy_rel")]
    pub max_entropy_rel: f64,
    /// Turns whose trimmed surface distance lies between `max_trimmed_rel` and this share of
    /// the diameter get twins only in a step where a view sees the object at least
    /// `near_min_object_px` across (0: no such turns). Such a turn (the bottles upside down
    /// and slid along their axis) moves the surface by millimetres: a far view cannot tell it
    /// from the truth, so its twins there only make the top mode a coin, while near they are
    /// the way off a wrong face the far views chose.
    #[serde(default, skip_serializing_if = "crate::tracker::observation::is_zero")]
    pub near_max_trimmed_rel: f64,
    /// See `near_max_trimmed_rel`: the object's size (pixels, [`crate::tracker::observation::object_size_px`])
    /// at the track's mean in the nearest view of the step that holds the mean in its image.
    #[serde(default, skip_serializing_if = "crate::tracker::observation::is_zero")]
    pub near_min_object_px: f64,
}

fn default_twin_max_entropy_rel() -> f64 {
    0.75
}

impl Default for TwinConfig {
    fn default() -> Self {
        Self {
            share: 0.05,
            max_trimmed_rel: 0.012,
            min_shift_m: 0.005,
            max_entropy_rel: default_twin_max_entropy_rel(),
            near_max_trimmed_rel: 0.0,
            near_min_object_px: 0.0,
        }
    }
}

/// The rotation blur of a track that is near and well explained. The blur is process noise
/// that lets a wrong mode go while the views are far and their codes ambiguous; where a near
/// view's codes match the crop closely (the generated sequences) a full bin of it widens every
/// histogram past the error, while where they match it poorly (the real clip) the codes leave
/// the rotation open and the full blur keeps it so (`docs/decisions.md`, "A lighter blur for
/// near, well-matched tracks"). The sigma goes from [`TrackerConfig::blur_sigma_bins`] to
/// `sigma_bins` by the product of two ramps: the distance of the track's mean from the
/// reference camera (1 at `full_m` and nearer, 0 at `until_m` and further) and the track's
/// best similarity of the last step (0 at `from_similarity` and below, 1 at
/// `full_similarity` and above).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NearBlur {
    pub sigma_bins: f64,
    pub full_m: f64,
    pub until_m: f64,
    pub from_similarity: f64,
    pub full_similarity: f64,
}

/// 0 at `zero` and below, 1 at `full` and above (`full >= zero`), linear between; a step at
/// `full` when the two are equal.
fn ramp(x: f64, zero: f64, full: f64) -> f64 {
    if full <= zero {
        return f64::from(u8::from(x >= full));
    }
    ((x - zero) / (full - zero)).clamp(0.0, 1.0)
}

impl NearBlur {
    /// The blur's sigma for a track at `distance_m` whose last step matched at best at
    /// `best_similarity` (`None`: unseen, the far sigma), given the far sigma.
    pub fn sigma_at(&self, distance_m: f64, best_similarity: Option<f64>, far_sigma_bins: f64) -> f64 {
        let near = ramp(-distance_m, -self.until_m, -self.full_m);
        let close = best_similarity.map_or(0.0, |c| ramp(c, self.from_similarity, self.full_similarity));
        far_sigma_bins + near * close * (self.sigma_bins - far_sigma_bins)
    }
}

fn default_turn_share() -> f64 {
    0.02
}

fn default_turn_max_distance_rel() -> f64 {
    0.016
}

fn default_twins() -> Option<TwinConfig> {
    Some(TwinConfig::default())
}

/// Recovery when the cameras disagree with a track (augmented Monte Carlo localisation's
/// random particles, made deterministic): when, for `steps` steps in a row, at least two
/// views' detection-derived positions agree with each other and lie outside the track's 99 %
/// region (its particle covariance plus the detection's own uncertainty), and no more views
/// support the track than disagree, the disagreeing views' components are spawned again from
/// their detections. The rotation state is left alone (the new particles take the track's
/// rotation belief). After a recovery the track waits `cooldown_steps` before the next one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RecoveryConfig {
    /// Steps in a row of disagreement before the particles are spawned again (0: never).
    pub steps: u32,
    pub cooldown_steps: u32,
    /// Chi-square bound of the region (3 degrees of freedom: 11.34 for 99 %).
    pub region_chi2: f64,
}

impl Default for RecoveryConfig {
    fn default() -> Self {
        Self {
            steps: 5,
            cooldown_steps: 10,
            region_chi2: 11.34,
        }
    }
}

/// What a step matches and keeps of the rotation grid (see [`crate::tracker::sparse`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MatchingConfig {
    /// Match and keep every bin: the dense reference that the sparse step approximates.
    pub dense: bool,
    /// Lattice cells, the best by posterior outside the active bins, whose fine bins are
    /// matched at each step.
    pub refine_cells: usize,
    /// The whole grid is matched once every this many steps, one slice per step.
    pub slice_steps: usize,
    /// A bin stays active while some column's density there is above this many times the
    /// column's floor (or the prior floor): the rest of a plateau goes to the floor.
    pub keep_above_floor: f32,
    /// Then the lowest-density active bins go back to the floor while their mass over it adds
    /// up to at most this much in every histogram.
    #[serde(default = "default_tail_mass")]
    pub tail_mass: f32,
    /// Most active bins per track (the highest peak densities are kept).
    pub max_active_bins: usize,
    /// Also find, at every step, the bin of the whole grid where the heaviest particle's
    /// fused likelihood peaks, and count whether the matched set held it (a diagnostic of the
    /// coarse-to-fine matching: it costs a dense matching of one code per view).
    #[serde(default)]
    pub audit: bool,
}

fn default_tail_mass() -> f32 {
    1e-3
}

impl MatchingConfig {
    /// The pruning rule of these settings over a prior floor of `floor_rel`.
    pub fn prune_rule(&self, floor_rel: f64) -> crate::tracker::sparse::PruneRule {
        crate::tracker::sparse::PruneRule {
            floor_rel: floor_rel as f32,
            margin: self.keep_above_floor,
            tail_mass: self.tail_mass,
            max_active: self.max_active_bins,
        }
    }
}

impl Default for MatchingConfig {
    fn default() -> Self {
        Self {
            dense: false,
            refine_cells: 48,
            slice_steps: 30,
            keep_above_floor: 2.0,
            tail_mass: default_tail_mass(),
            max_active_bins: 16_000,
            audit: false,
        }
    }
}

fn default_view_weight_tempering() -> f64 {
    1.0
}

/// The exponent of a step's weight update with evidence from `views` views (see
/// [`TrackerConfig::view_weight_tempering`]).
pub fn weight_exponent(views: usize, tempering: f64) -> f64 {
    (views.max(1) as f64).powf(-tempering.max(0.0))
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            particles_per_external_camera: 30,
            particles_from_robot_camera: 50,
            only_reference_camera: false,
            observation: ObservationConfig::default(),
            estimate: EstimateConfig::default(),
            lost_similarity: 0.62,
            lost_after_steps: 5,
            brownian_sigma_m: 0.005,
            odometry_noise: OdometryNoise::default(),
            blur_radius_bins: 2,
            blur_sigma_bins: 1.0,
            near_blur: None,
            prior_floor_rel: 1e-3,
            min_component_weight: 0.02,
            init_uv_jitter_rel: 0.1,
            init_depth_sigma_m: 0.03,
            association_margin_rel: 0.3,
            max_tracks_per_object: 1,
            view_weight_tempering: default_view_weight_tempering(),
            matching: MatchingConfig::default(),
            spread: SpreadConfig::default(),
            recovery: RecoveryConfig::default(),
            verification: VerificationConfig::default(),
            registration: RegistrationConfig::default(),
            turn_share: default_turn_share(),
            turn_max_distance_rel: default_turn_max_distance_rel(),
            twins: default_twins(),
            support: None,
            seed: 1,
        }
    }
}

impl TrackerConfig {
    /// The paper's single-view baseline: the reference (robot) camera alone, 110 particles.
    pub fn single_view() -> Self {
        Self {
            particles_from_robot_camera: 110,
            particles_per_external_camera: 110,
            only_reference_camera: true,
            ..Self::default()
        }
    }

    /// `base` with what this tracker's matching needs of a codebook: the box-centred table
    /// where it matches crops against it (`observation.box_codes`).
    pub fn codebook_config(
        &self,
        base: &crate::tracker::codebook::CodebookConfig,
    ) -> crate::tracker::codebook::CodebookConfig {
        crate::tracker::codebook::CodebookConfig {
            box_table: base.box_table || self.observation.box_codes,
            ..base.clone()
        }
    }
}

/// Directions the mean silhouette of a model is averaged over: few enough to measure once per
/// model, enough that the mean stands for every direction.
const SILHOUETTE_DIRECTIONS: usize = 64;

struct Model {
    name: String,
    mesh: Mesh,
    codebook: Arc<Codebook>,
    tables: Arc<GridTables>,
    lattice: Arc<Lattice>,
    /// The near-symmetric turns (object frame) that keep a share of the mass
    /// ([`TrackerConfig::turn_share`]); empty when that is off.
    turns: Vec<nalgebra::Matrix3<f64>>,
    /// Every bin's partner under each turn on this model's grid (`sparse::turn_partners`).
    turn_partners: Vec<u32>,
    /// The off-centre turns twins jump by ([`TwinConfig`]); empty when twins are off.
    twin_turns: Vec<crate::symmetry::CentredTurn>,
    /// Every bin's partner under each twin turn.
    twin_partners: Vec<u32>,
    /// The support prior ([`TrackerConfig::support`]); `None` when off or for a flat mesh.
    support: Option<crate::tracker::support::SupportPrior>,
    /// The mean area of the object's silhouette (m², [`observation::mean_silhouette_area_m2`]);
    /// 0 unless [`observation::ObservationConfig::full_area_px`] reads it.
    silhouette_m2: f64,
    /// Whether the mesh's origin lies near the centre of its bounding box, so that a
    /// detector's box centre is where the codebook's crops are centred
    /// ([`observation::ObservationConfig::box_crops_below_px`] reads it).
    box_centred: bool,
}

/// State of one track.
struct TrackState {
    model: usize,
    positions: Vec<Vector3<f64>>,
    sources: Vec<usize>,
    weights: Vec<f64>,
    rot: RotationState,
    /// Previous rotation estimate, in the histograms' frame.
    rotation: Option<UnitQuaternion<f64>>,
    estimate: Option<Estimate>,
    /// The frame of the histograms (the reference camera when the track started). Keeping
    /// the histograms there avoids re-binning the prior at every robot motion (repeated
    /// nearest-bin re-binning by rotations below half a bin would never move it at all);
    /// every view, the reference camera included, is pulled through its own map instead.
    reference_from_hist: Pose,
    /// Per camera, the rotation of its last bin map, and the whole grid's map once that
    /// rotation held still for two steps (static cameras, a slowly moving mean): reused while
    /// the rotation moves by less than [`MAP_REUSE_RAD`].
    map_cache: Vec<CachedMap>,
    /// Position of the rotating slice of the grid matched at the next step.
    slice_cursor: usize,
    /// The cameras' disagreement with the track (see [`RecoveryConfig`]).
    disagreement: Disagreement,
    /// Per camera, the direction (histogram frame) from which the track was last verified
    /// against its depth (`VerificationConfig::min_view_change_deg`).
    verified_from: Vec<(String, Vector3<f64>)>,
    /// This step's depth registration (`None`: not registered).
    registered: Option<Registered>,
    /// Per camera its newest registration of the track, kept for the steps without one
    /// (`RegistrationConfig::carry_max_age_s`).
    carried_fits: Vec<CarriedFit>,
    /// The rotation's covariance modulo the object's turns at the last estimate
    /// ([`crate::tracker::estimate::RotationSummary::surface_covariance`]): what the
    /// registration counts of the rotation's error.
    surface_rotation_cov: Option<nalgebra::Matrix3<f64>>,
}

/// One camera's registration of a track, kept across steps: the fitted position and its
/// information in the reference frame as it is now (moved with the odometry and widened by
/// the odometry's noise and the drift allowance since it was fitted).
#[derive(Debug, Clone)]
struct CarriedFit {
    camera: String,
    stamp_ns: i64,
    target: Vector3<f64>,
    information: nalgebra::Matrix3<f64>,
}

impl CarriedFit {
    /// The fit after adding a noise of covariance `q` to its position: `(H^-1 + Q)^-1`,
    /// written `H (I + Q H)^-1` so that directions the fit leaves free stay free.
    fn widen(&mut self, q: &nalgebra::Matrix3<f64>) {
        let h = self.information;
        if let Some(inv) = (nalgebra::Matrix3::identity() + q * h).try_inverse() {
            let w = h * inv;
            self.information = (w + w.transpose()) * 0.5;
        }
    }
}

/// A step's depth registration of a track (see `Tracker::register_translation`).
struct Registered {
    /// Information on the position (reference frame, 1/m^2), which also narrows the floor.
    information: nalgebra::Matrix3<f64>,
    /// `sum H_v t_v` over the views' fitted positions.
    target: Vector3<f64>,
    /// The particles' positions updated by it (reported, not kept).
    positions: Vec<Vector3<f64>>,
}

/// One camera's entry of a track's bin-map cache: the camera's name, the rotation of its last
/// bin map, and the whole grid's map when cached.
type CachedMap = (String, UnitQuaternion<f64>, Option<Arc<Vec<u32>>>);

/// A cached bin map is reused while its rotation differs by less than this (a bin is 5 degrees).
const MAP_REUSE_RAD: f64 = 0.002;

impl TrackState {
    fn n(&self) -> usize {
        self.positions.len()
    }
    /// The particles as the filter keeps them.
    fn set<'a>(&'a self, tables: &'a GridTables, spread: SpreadConfig) -> ParticleSet<'a> {
        ParticleSet {
            positions_m: &self.positions,
            sources: &self.sources,
            weights: &self.weights,
            rot: &self.rot,
            tables,
            reference_from_hist: self.reference_from_hist,
            spread,
            floor_information: None,
        }
    }

    /// The particles as the track reports them: with this step's depth registration, its
    /// positions and its narrower floor (see `Tracker::register_translation`).
    fn reported_set<'a>(&'a self, tables: &'a GridTables, spread: SpreadConfig) -> ParticleSet<'a> {
        // a component added since (a detection between steps) drops the registration
        match &self.registered {
            Some(r) if r.positions.len() == self.positions.len() => ParticleSet {
                positions_m: &r.positions,
                floor_information: Some(r.information),
                ..self.set(tables, spread)
            },
            _ => self.set(tables, spread),
        }
    }
}

/// All tracked objects of one scene.
pub struct Tracker {
    config: TrackerConfig,
    cameras: BTreeMap<String, CameraMount>,
    camera_names: Vec<String>,
    reference: String,
    models: Vec<Model>,
    tables: Vec<(Arc<GridTables>, Arc<Lattice>)>,
    tracks: Vec<Track>,
    states: Vec<TrackState>,
    next_id: u64,
    rng: rand_chacha::ChaCha8Rng,
    world_from_reference: Pose,
    last_odometry: Option<RobotOdometry>,
    /// The normal of the surface objects rest on (world frame, unit), for the support prior.
    support_normal_world: Option<Vector3<f64>>,
    /// Reusable similarity buffers, one per view of a step.
    sims: Vec<Vec<f32>>,
    blur_work: BlurWork,
    stamp_ns: i64,
}

impl Tracker {
    pub fn new(config: TrackerConfig, cameras: BTreeMap<String, CameraMount>, reference_camera: String) -> Self {
        let camera_names: Vec<String> = cameras.keys().cloned().collect();
        let world_from_reference = match cameras.get(&reference_camera) {
            Some(CameraMount::Stationary { world_from_camera }) => *world_from_camera,
            _ => Pose::identity(),
        };
        let seed = config.seed;
        Self {
            config,
            cameras,
            camera_names,
            reference: reference_camera,
            models: Vec::new(),
            tables: Vec::new(),
            tracks: Vec::new(),
            states: Vec::new(),
            next_id: 1,
            rng: rand_chacha::ChaCha8Rng::seed_from_u64(seed),
            world_from_reference,
            last_odometry: None,
            support_normal_world: None,
            sims: Vec::new(),
            blur_work: BlurWork::default(),
            stamp_ns: 0,
        }
    }

    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// Registers an object model (detections name it by `name`).
    pub fn add_object_model(&mut self, name: &str, mesh: Mesh, codebook: Arc<Codebook>) {
        if self.config.observation.box_codes && codebook.box_table.is_none() {
            tracing::warn!(
                "{name}: observation.box_codes is on but its codebook has no box-centred table \
                 (built without codebook.box_table); its crops are matched as with box_codes off"
            );
        }
        let grid = codebook.grid;
        let (tables, lattice) = match self.tables.iter().find(|t| t.0.grid == grid) {
            Some(t) => t.clone(),
            None => {
                let t = Arc::new(GridTables::new(grid));
                let l = Arc::new(Lattice::new(&t));
                self.tables.push((t.clone(), l.clone()));
                (t, l)
            }
        };
        // the turns depend on the mesh alone (searched once per mesh for the process), their
        // partner table on the grid too
        let turns = self.turns_of(&mesh, &codebook);
        let turn_partners = crate::tracker::sparse::turn_partners(&tables, &turns);
        let twin_turns = self.twin_turns_of(&mesh, &turns);
        let twin_matrices: Vec<nalgebra::Matrix3<f64>> = twin_turns
            .iter()
            .map(|t| t.rotation.to_rotation_matrix().into_inner())
            .collect();
        let twin_partners = crate::tracker::sparse::turn_partners(&tables, &twin_matrices);
        let support = self.config.support.and_then(|cfg| {
            crate::tracker::support::RestingFaces::of_mesh(&mesh, cfg.box_faces)
                .map(|faces| crate::tracker::support::SupportPrior::new(&faces, &cfg))
        });
        let silhouette_m2 = if self.config.observation.full_area_px > 0.0 {
            crate::tracker::observation::mean_silhouette_area_m2(&mesh, SILHOUETTE_DIRECTIONS)
        } else {
            0.0
        };
        let box_centred = crate::tracker::observation::origin_near_box_centre(&mesh, codebook.box_m());
        if let Some(mi) = self.models.iter().position(|m| m.name == name) {
            // a better codebook for a known model: its tracks move to the new grid through
            // their compact snapshots (see `snapshot`), keeping particles and marginals
            let carried = if self.models[mi].codebook.grid != grid {
                self.snapshots_of_model(mi)
            } else {
                Vec::new()
            };
            let m = &mut self.models[mi];
            m.turn_partners = turn_partners;
            m.turns = turns;
            m.twin_turns = twin_turns;
            m.twin_partners = twin_partners;
            m.support = support;
            m.silhouette_m2 = silhouette_m2;
            m.box_centred = box_centred;
            m.mesh = mesh;
            m.codebook = codebook;
            m.tables = tables;
            m.lattice = lattice;
            self.carry_tracks_to_new_grid(carried);
            return;
        }
        self.models.push(Model {
            name: name.to_string(),
            mesh,
            codebook,
            tables,
            lattice,
            turns,
            turn_partners,
            twin_turns,
            twin_partners,
            support,
            silhouette_m2,
            box_centred,
        });
    }

    /// The mesh's off-centre confusable turns (none when twins are off), less those within
    /// [`TWIN_MIXED_TURN_RAD`] of a turn that turn mixing moves mass to (`mixed`).
    fn twin_turns_of(&self, mesh: &Mesh, mixed: &[nalgebra::Matrix3<f64>]) -> Vec<crate::symmetry::CentredTurn> {
        let Some(tw) = self.config.twins.filter(|t| t.share > 0.0) else {
            return Vec::new();
        };
        let mixed: Vec<UnitQuaternion<f64>> = mixed.iter().map(UnitQuaternion::from_matrix).collect();
        let max_rel = tw.max_trimmed_rel.max(tw.near_max_trimmed_rel);
        crate::symmetry::confusable_turns_cached(mesh, max_rel * mesh.diameter_m(), tw.min_shift_m)
            .into_iter()
            .filter(|t| mixed.iter().all(|q| q.angle_to(&t.rotation) > TWIN_MIXED_TURN_RAD))
            .collect()
    }

    /// The mesh's near-symmetric turns as rotation matrices (none when turn mixing is off).
    fn turns_of(&self, mesh: &Mesh, codebook: &Codebook) -> Vec<nalgebra::Matrix3<f64>> {
        if self.config.turn_share <= 0.0 {
            return Vec::new();
        }
        let max_m = self.config.turn_max_distance_rel * codebook.box_m();
        crate::symmetry::near_symmetric_turns_cached(mesh, max_m)
            .iter()
            .map(|q| q.to_rotation_matrix().into_inner())
            .collect()
    }

    pub fn tracks(&self) -> &[Track] {
        &self.tracks
    }

    pub fn reference_camera(&self) -> &str {
        &self.reference
    }

    /// Whether the track's pose in the reference frame is seen: the reference camera's latest
    /// frame gave evidence of it (steps without a frame of the reference camera, whose
    /// cameras publish at their own rates, keep the answer), or the reference camera is
    /// stationary (its frame does not drift). `false` while a robot's camera looks away: the
    /// pose then rests on odometry and the other cameras seen through the robot's
    /// localisation. `None`: no such track.
    pub fn reference_sees(&self, track_id: u64) -> Option<bool> {
        let t = self.tracks.iter().find(|t| t.id == track_id)?;
        let stationary = matches!(self.cameras.get(&self.reference), Some(CameraMount::Stationary { .. }));
        Some(stationary || t.reference_seen)
    }

    pub fn world_from_reference(&self) -> Pose {
        self.world_from_reference
    }

    /// The normal (world frame) of the surface the objects rest on, the table top of the
    /// scene's support plane: the support prior ([`TrackerConfig::support`]) needs it and is
    /// not applied without it. A zero or non-finite normal counts as none.
    pub fn set_support_normal(&mut self, normal_world: Option<Vector3<f64>>) {
        self.support_normal_world = normal_world
            .filter(|n| n.iter().all(|v| v.is_finite()))
            .and_then(|n| n.try_normalize(1e-12));
    }

    /// The support surface's down direction (minus its normal) in the reference frame: known
    /// when the reference camera is stationary or its odometry has come.
    fn down_in_reference(&self) -> Option<Vector3<f64>> {
        let down_world = -self.support_normal_world?;
        match (self.cameras.get(&self.reference)?, &self.last_odometry) {
            (CameraMount::Stationary { .. }, _) | (CameraMount::Robot { .. }, Some(_)) => {
                Some(self.world_from_reference.rotation.inverse() * down_world)
            }
            (CameraMount::Robot { .. }, None) => None,
        }
    }

    pub fn model_mesh(&self, name: &str) -> Option<&Mesh> {
        self.models.iter().find(|m| m.name == name).map(|m| &m.mesh)
    }

    fn index_of(&self, track_id: u64) -> Option<usize> {
        self.tracks.iter().position(|t| t.id == track_id)
    }

    pub fn estimate(&self, track_id: u64) -> Option<Estimate> {
        let i = self.index_of(track_id)?;
        self.states[i].estimate.clone()
    }

    pub fn sample_poses(&self, track_id: u64, n: usize, rng: &mut impl Rng) -> Option<PoseSamples> {
        let i = self.index_of(track_id)?;
        let s = &self.states[i];
        if s.n() == 0 {
            return None;
        }
        Some(
            s.reported_set(&self.models[s.model].tables, self.config.spread)
                .sample_poses(n, rng),
        )
    }

    pub fn orientation_loglik(
        &self,
        track_id: u64,
        reference_from_object_rotation: &UnitQuaternion<f64>,
    ) -> Option<f64> {
        let i = self.index_of(track_id)?;
        let s = &self.states[i];
        if s.n() == 0 {
            return None;
        }
        Some(
            s.reported_set(&self.models[s.model].tables, self.config.spread)
                .orientation_loglik(reference_from_object_rotation),
        )
    }

    /// Read-only: the rotation marginal's density at each of `rotations`, relative to uniform
    /// and averaged over `orbit` (see `ParticleSet::rotation_densities`).
    pub fn rotation_densities(
        &self,
        track_id: u64,
        rotations: &[UnitQuaternion<f64>],
        orbit: &[UnitQuaternion<f64>],
    ) -> Option<Vec<f64>> {
        let i = self.index_of(track_id)?;
        let s = &self.states[i];
        if s.n() == 0 {
            return None;
        }
        Some(
            s.reported_set(&self.models[s.model].tables, self.config.spread)
                .rotation_densities(rotations, orbit),
        )
    }

    /// The entropy (nats) of a uniform rotation histogram on the grid track `track_id` is
    /// tracked on: what `Estimate::rotation_entropy` is compared with.
    pub fn uniform_rotation_entropy(&self, track_id: u64) -> Option<f64> {
        let i = self.index_of(track_id)?;
        Some(self.models[self.states[i].model].tables.grid.uniform_entropy())
    }

    pub fn particles(&self, track_id: u64) -> Option<Vec<ParticleView>> {
        let i = self.index_of(track_id)?;
        let s = &self.states[i];
        Some(
            (0..s.n())
                .map(|p| ParticleView {
                    position_in_reference_m: [s.positions[p].x, s.positions[p].y, s.positions[p].z],
                    camera: self.camera_names[s.sources[p]].clone(),
                    weight: s.weights[p],
                })
                .collect(),
        )
    }

    /// `view_from_reference` of a camera at the current step.
    fn view_from_reference(&self, camera: &str, odometry: Option<&RobotOdometry>) -> Option<Pose> {
        if camera == self.reference {
            return Some(Pose::identity());
        }
        match self.cameras.get(camera)? {
            CameraMount::Stationary { world_from_camera } => {
                Some(world_from_camera.inverse() * self.world_from_reference)
            }
            CameraMount::Robot { base_from_camera } => {
                let base_from_reference = match (odometry, self.cameras.get(&self.reference)) {
                    (Some(o), _) => o.base_from_camera,
                    (None, Some(CameraMount::Robot { base_from_camera })) => *base_from_camera,
                    _ => return None,
                };
                Some(base_from_camera.inverse() * base_from_reference)
            }
        }
    }

    /// One filter step with the frames of this time (any subset of the cameras) and the robot's
    /// odometry (when the reference camera is on the robot).
    pub fn step(
        &mut self,
        frames: &[CameraFrame],
        odometry: Option<&RobotOdometry>,
    ) -> Result<StepReport, TrackerError> {
        let t_start = Instant::now();
        let mut report = StepReport::default();
        for f in frames {
            if !self.cameras.contains_key(&f.camera) {
                return Err(TrackerError::UnknownCamera(f.camera.clone()));
            }
            let (w, h) = (f.intrinsics.width, f.intrinsics.height);
            if f.depth.width != w
                || f.depth.height != h
                || f.color.as_ref().is_some_and(|c| c.width != w || c.height != h)
            {
                return Err(TrackerError::ImageSize {
                    camera: f.camera.clone(),
                    got_w: f.depth.width,
                    got_h: f.depth.height,
                    want_w: w,
                    want_h: h,
                });
            }
        }
        let frames: Vec<&CameraFrame> = frames
            .iter()
            .filter(|f| !self.config.only_reference_camera || f.camera == self.reference)
            .collect();
        let stamp = frames
            .iter()
            .map(|f| f.stamp_ns)
            .max()
            .or(odometry.map(|o| o.stamp_ns))
            .unwrap_or(self.stamp_ns);
        let previous_stamp_ns = self.stamp_ns;
        self.stamp_ns = stamp;
        report.stamp_ns = stamp;

        // 1. prediction
        let t0 = Instant::now();
        let robot_reference = matches!(self.cameras.get(&self.reference), Some(CameraMount::Robot { .. }));
        if let (Some(o), true) = (odometry, robot_reference) {
            if let Some(prev) = self.last_odometry {
                self.apply_odometry(&prev, o);
            }
            self.world_from_reference = o.world_from_odom * o.odom_from_base * o.base_from_camera;
            self.last_odometry = Some(*o);
        }
        // kept registrations widen by the drift the object may have had since (not by the
        // particles' Brownian steps, which keep hypotheses apart more than they model motion)
        let dt_s = (stamp - previous_stamp_ns).max(0) as f64 * 1e-9;
        let drift_cov = nalgebra::Matrix3::identity() * (self.config.registration.carry_drift_m_per_s * dt_s).powi(2);
        for s in &mut self.states {
            brownian(&mut s.positions, self.config.brownian_sigma_m, &mut self.rng);
            for f in &mut s.carried_fits {
                f.widen(&drift_cov);
            }
        }
        report.timings.motion_s += t0.elapsed().as_secs_f64();
        // poses of this step's views
        let views: Vec<(&CameraFrame, Pose, usize)> = frames
            .iter()
            .filter_map(|f| {
                let ci = self.camera_names.iter().position(|c| c == &f.camera)?;
                Some((*f, self.view_from_reference(&f.camera, odometry)?, ci))
            })
            .collect();
        let t0 = Instant::now();
        let kernel = gaussian_kernel(self.config.blur_radius_bins, self.config.blur_sigma_bins);
        let matching = self.config.matching;
        let rule = matching.prune_rule(self.config.prior_floor_rel);
        for (s, track) in self.states.iter_mut().zip(&self.tracks) {
            if s.n() > 0 {
                let tables = &self.models[s.model].tables;
                let near_kernel = self.config.near_blur.map(|nb| {
                    let mean = s.set(tables, self.config.spread).mean_position();
                    let sigma = nb.sigma_at(mean.norm(), track.best_similarity, self.config.blur_sigma_bins);
                    gaussian_kernel(self.config.blur_radius_bins, sigma)
                });
                let kernel = near_kernel.as_deref().unwrap_or(&kernel);
                crate::tracker::sparse::blur(&mut s.rot, tables, kernel, &mut self.blur_work);
                let m = &self.models[s.model];
                crate::tracker::sparse::mix_turns(
                    &mut s.rot,
                    tables,
                    &m.turn_partners,
                    m.turns.len(),
                    self.config.turn_share as f32,
                );
                if let Some(tw) = self.config.twins {
                    let near = tw.near_min_object_px > 0.0 && {
                        let mean = s.set(tables, self.config.spread).mean_position();
                        nearest_view_px(&views, &mean, &m.codebook) >= tw.near_min_object_px
                    };
                    report.twinned += make_twins(s, m, tables, &tw, near, &mut self.rng);
                }
                // the halo's bins that stay near the floor go back to it: only the rest is
                // matched at this step
                if !matching.dense {
                    s.rot.prune(tables, &rule);
                }
            }
        }
        report.timings.blur_s += t0.elapsed().as_secs_f64();

        // 2. detections
        for (frame, view_from_ref, ci) in &views {
            for det in &frame.detections {
                self.handle_detection(frame, det, view_from_ref, *ci, &mut report);
            }
        }

        // recovery: tracks that the cameras' detections place elsewhere
        if self.config.recovery.steps > 0 {
            for ti in 0..self.states.len() {
                self.check_disagreement(ti, &views, &mut report);
            }
        }

        // 3. update, 4. estimates and resampling
        self.update_tracks(&views, &mut report);
        // whether the reference camera sees each track, from the steps that carry its frame
        if views.iter().any(|(f, _, _)| f.camera == self.reference) {
            let stamp = self.stamp_ns;
            for t in &mut self.tracks {
                t.reference_seen = t.stamp_ns == stamp && t.seen_by.contains(&self.reference);
            }
        }
        report.timings.total_s = t_start.elapsed().as_secs_f64();
        Ok(report)
    }

    fn apply_odometry(&mut self, prev: &RobotOdometry, cur: &RobotOdometry) {
        let prev_from_cur_exact =
            prev.base_from_camera.inverse() * prev.odom_from_base.inverse() * cur.odom_from_base * cur.base_from_camera;
        for i in 0..self.states.len() {
            if self.states[i].n() == 0 {
                continue;
            }
            let s = &mut self.states[i];
            move_with_odometry(
                &mut s.positions,
                &prev.odom_from_base,
                &cur.odom_from_base,
                &prev.base_from_camera,
                &cur.base_from_camera,
                &self.config.odometry_noise,
                &mut self.rng,
            );
            s.reference_from_hist = prev_from_cur_exact.inverse() * s.reference_from_hist;
            // kept registrations move exactly as the world does in the camera, and widen by
            // the odometry's noise at their position
            let cur_from_prev = prev_from_cur_exact.inverse();
            let r = cur_from_prev.rotation.to_rotation_matrix();
            for f in &mut s.carried_fits {
                let q = crate::tracker::motion::odometry_covariance_at(
                    &f.target,
                    &prev.odom_from_base,
                    &cur.odom_from_base,
                    &prev.base_from_camera,
                    &cur.base_from_camera,
                    &self.config.odometry_noise,
                );
                f.target = cur_from_prev.transform_point(&nalgebra::Point3::from(f.target)).coords;
                f.information = r.matrix() * f.information * r.matrix().transpose();
                f.widen(&q);
            }
        }
    }

    fn handle_detection(
        &mut self,
        frame: &CameraFrame,
        det: &Detection,
        view_from_ref: &Pose,
        ci: usize,
        report: &mut StepReport,
    ) {
        let Some(mi) = self.models.iter().position(|m| m.name == det.object) else {
            return;
        };
        let [_, _, bw, bh] = det.bbox_xywh_px;
        if !(bw > 1.0 && bh > 1.0) {
            return;
        }
        let associated = (0..self.states.len()).find(|&i| {
            self.states[i].model == mi
                && self.tracks[i].status != TrackStatus::Lost
                && self.detection_holds(i, frame, det, view_from_ref)
        });
        match associated {
            Some(i) => {
                // a camera that has no component in the track yet gains one at its first
                // detection of it (Eq. 2: one component per camera), however old the track is:
                // cameras are not synchronised, so in the service a second camera's first
                // detection usually arrives a step after the first camera has already made
                // the track `Tracking`; the robot camera, too, often first sees an object the
                // external cameras have long been tracking
                let has_camera = self.states[i].sources.contains(&ci);
                if !has_camera {
                    let parts = self.init_particles(mi, frame, det, view_from_ref, ci);
                    self.add_particles(i, parts, ci);
                }
            }
            None => {
                let lost = (0..self.states.len())
                    .find(|&i| self.states[i].model == mi && self.tracks[i].status == TrackStatus::Lost);
                let cap = self.config.max_tracks_per_object;
                let at_cap = || {
                    (0..self.states.len())
                        .filter(|&i| self.states[i].model == mi && self.tracks[i].status != TrackStatus::Lost)
                        .count()
                        >= cap
                };
                if lost.is_none() && cap > 0 && at_cap() {
                    return;
                }
                let parts = self.init_particles(mi, frame, det, view_from_ref, ci);
                let i = match lost {
                    Some(i) => {
                        report.tracks_reinitialised.push(self.tracks[i].id);
                        self.states[i].positions.clear();
                        self.states[i].sources.clear();
                        self.states[i].weights.clear();
                        self.states[i].rot.clear();
                        self.states[i].rotation = None;
                        self.states[i].reference_from_hist = Pose::identity();
                        self.states[i].map_cache.clear();
                        self.states[i].disagreement = Disagreement::default();
                        self.states[i].verified_from.clear();
                        self.states[i].carried_fits.clear();
                        self.tracks[i].status = TrackStatus::Initialising;
                        self.tracks[i].weak_steps = 0;
                        self.tracks[i].reinitialised = Some(Reinitialisation {
                            stamp_ns: self.stamp_ns,
                            reason: ReinitReason::Redetected {
                                camera: frame.camera.clone(),
                            },
                        });
                        i
                    }
                    None => {
                        let id = self.next_id;
                        self.next_id += 1;
                        self.tracks.push(Track {
                            id,
                            object: det.object.clone(),
                            status: TrackStatus::Initialising,
                            stamp_ns: self.stamp_ns,
                            best_similarity: None,
                            weak_steps: 0,
                            seen_by: Vec::new(),
                            reference_seen: true,
                            reinitialised: None,
                        });
                        self.states.push(TrackState {
                            model: mi,
                            positions: Vec::new(),
                            sources: Vec::new(),
                            weights: Vec::new(),
                            rot: RotationState::default(),
                            rotation: None,
                            estimate: None,
                            reference_from_hist: Pose::identity(),
                            map_cache: Vec::new(),
                            slice_cursor: 0,
                            disagreement: Disagreement::default(),
                            verified_from: Vec::new(),
                            registered: None,
                            carried_fits: Vec::new(),
                            surface_rotation_cov: None,
                        });
                        report.tracks_created.push(id);
                        self.states.len() - 1
                    }
                };
                self.add_particles(i, parts, ci);
            }
        }
    }

    /// Particles (reference frame) from one detection: pixels around the box centre, depth
    /// from the detection ([`detection_centre`]).
    fn init_particles(
        &mut self,
        mi: usize,
        frame: &CameraFrame,
        det: &Detection,
        view_from_ref: &Pose,
        ci: usize,
    ) -> Vec<Vector3<f64>> {
        let robot = matches!(
            self.cameras.get(&self.camera_names[ci]),
            Some(CameraMount::Robot { .. })
        );
        let n = if robot || self.camera_names[ci] == self.reference {
            self.config.particles_from_robot_camera
        } else {
            self.config.particles_per_external_camera
        };
        let diameter = self.models[mi].codebook.diameter_m;
        let [_, _, bw, bh] = det.bbox_xywh_px;
        let ([cu, cv], z0) = detection_centre(frame, det, diameter);
        let k = &frame.intrinsics;
        let zs = Normal::new(0.0, self.config.init_depth_sigma_m + 0.1 * diameter).ok();
        let ref_from_view = view_from_ref.inverse();
        (0..n)
            .map(|_| {
                let u = cu + (self.rng.random::<f64>() - 0.5) * 2.0 * self.config.init_uv_jitter_rel * bw;
                let v = cv + (self.rng.random::<f64>() - 0.5) * 2.0 * self.config.init_uv_jitter_rel * bh;
                let z = (z0 + zs.map(|d| d.sample(&mut self.rng)).unwrap_or(0.0)).max(0.1);
                (ref_from_view * k.unproject([u, v], z)).coords
            })
            .collect()
    }

    /// Appends particles of camera `ci`; the new component starts with the mean weight of the
    /// existing particles and from the track's rotation belief (the particle-weighted mixture;
    /// uniform for a new track): a camera joining a track adds translation hypotheses, it does
    /// not make the track forget what it knows of the rotation.
    fn add_particles(&mut self, i: usize, parts: Vec<Vector3<f64>>, ci: usize) {
        let s = &mut self.states[i];
        let old_n = s.n();
        let new_n = old_n + parts.len();
        if old_n == 0 || s.rot.n_cols() == 0 {
            s.rot = RotationState::uniform(new_n);
        } else {
            let cf = s.rot.column_factors(&s.weights);
            let nc = s.rot.n_cols();
            let cf32: Vec<f32> = cf.iter().map(|v| *v as f32).collect();
            let belief: Vec<f32> = s
                .rot
                .values
                .chunks(nc)
                .map(|row| row.iter().zip(&cf32).map(|(v, w)| v * w).sum())
                .collect();
            let floor: f64 = cf.iter().zip(&s.rot.floors).map(|(w, f)| w * *f as f64).sum();
            s.rot.append_column(&belief, floor as f32, parts.len());
        }
        let w_new = if old_n > 0 {
            1.0 / new_n as f64
        } else {
            1.0 / parts.len() as f64
        };
        for w in &mut s.weights {
            *w *= old_n as f64 / new_n as f64;
        }
        s.weights.extend(std::iter::repeat_n(w_new, parts.len()));
        s.sources.extend(std::iter::repeat_n(ci, parts.len()));
        s.positions.extend(parts);
        normalise(&mut s.weights);
    }
}

/// The pixel of a detection's centre and the depth of the object's centre behind it: the
/// lower quartile of the depth readings in the box's central half plus a quarter of the
/// object's diameter (the visible surface is in front of the centre), or the depth at which
/// the object's diameter fills the box when no reading is there. Readings inside the box of
/// another detection that stands nearer are left out: an object half hidden behind another
/// has its occluder's depth in its box, and the lower quartile would place it there (the
/// whole box is read when the occluder covers the central half).
pub(super) fn detection_centre(frame: &CameraFrame, det: &Detection, diameter: f64) -> ([f64; 2], f64) {
    let [bx, by, bw, bh] = det.bbox_xywh_px;
    let [cu, cv] = det.centre_px();
    let k = &frame.intrinsics;
    let whole = PixelRect::new(k, bx, by, bx + bw - 1.0, by + bh - 1.0);
    let central = PixelRect::new(k, bx + bw * 0.25, by + bh * 0.25, bx + bw * 0.75, by + bh * 0.75);
    let nearer: Vec<PixelRect> = frame
        .detections
        .iter()
        .filter(|o| o.bbox_xywh_px != det.bbox_xywh_px)
        .map(|o| {
            let [x, y, w, h] = o.bbox_xywh_px;
            PixelRect::new(k, x, y, x + w - 1.0, y + h - 1.0)
        })
        .filter(|o| o.overlaps(&whole) && stands_nearer(frame, o, &whole))
        .collect();
    let mut depths = depth_readings(frame, &central, &nearer, 1);
    if depths.len() < MIN_DEPTH_READINGS && !nearer.is_empty() {
        depths = depth_readings(frame, &whole, &nearer, 1);
        if depths.len() < MIN_DEPTH_READINGS {
            depths = depth_readings(frame, &central, &[], 1);
        }
    }
    // the lower quartile: a thin or curved object leaves the box's centre to the table behind
    // it, whose readings would place the object there
    let z0 = match lower_quartile(&mut depths) {
        Some(q) => q + 0.25 * diameter,
        None => k.fx() * diameter * 0.8 / bw.max(bh),
    };
    ([cu, cv], z0)
}

/// Fewest depth readings a detection's depth is read from before a larger region is tried.
const MIN_DEPTH_READINGS: usize = 8;

/// Pixels read from a box when telling which of two overlapping detections stands nearer (a
/// quartile of this many readings is within a few centimetres at 3 m).
const OCCLUSION_SAMPLE_PX: f64 = 2000.0;

/// An inclusive rectangle of pixels, clipped to the image.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PixelRect {
    x0: u32,
    x1: u32,
    y0: u32,
    y1: u32,
}

impl PixelRect {
    /// The pixels from column `floor(x0)` to `floor(x1)` and row `floor(y0)` to `floor(y1)`,
    /// clipped to the image.
    fn new(k: &Intrinsics, x0: f64, y0: f64, x1: f64, y1: f64) -> Self {
        Self {
            x0: x0.max(0.0) as u32,
            x1: (x1.max(0.0) as u32).min(k.width.saturating_sub(1)),
            y0: y0.max(0.0) as u32,
            y1: (y1.max(0.0) as u32).min(k.height.saturating_sub(1)),
        }
    }

    fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..=self.x1).contains(&x) && (self.y0..=self.y1).contains(&y)
    }

    fn overlaps(&self, o: &Self) -> bool {
        self.x0 <= o.x1 && o.x0 <= self.x1 && self.y0 <= o.y1 && o.y0 <= self.y1
    }

    fn area(&self) -> f64 {
        f64::from(self.x1.saturating_sub(self.x0) + 1) * f64::from(self.y1.saturating_sub(self.y0) + 1)
    }
}

/// The valid depth readings of `rect` outside every rectangle of `without`, every `stride`-th
/// pixel in each direction.
fn depth_readings(frame: &CameraFrame, rect: &PixelRect, without: &[PixelRect], stride: u32) -> Vec<f32> {
    let mut out = Vec::new();
    for y in (rect.y0..=rect.y1).step_by(stride.max(1) as usize) {
        for x in (rect.x0..=rect.x1).step_by(stride.max(1) as usize) {
            if without.iter().any(|w| w.contains(x, y)) {
                continue;
            }
            let d = frame.depth.get(x, y);
            if d > 0.0 && d.is_finite() {
                out.push(d);
            }
        }
    }
    out
}

fn lower_quartile(depths: &mut [f32]) -> Option<f64> {
    if depths.is_empty() {
        return None;
    }
    let q = depths.len() / 4;
    depths.select_nth_unstable_by(q, |a, b| a.total_cmp(b));
    Some(f64::from(depths[q]))
}

/// Whether the detection of box `other` stands in front of the one of box `own`: the lower
/// quartile of its readings is nearer than that of `own`'s readings outside it by more than
/// the two quartiles' noise (the sensor's noise grows with the distance).
fn stands_nearer(frame: &CameraFrame, other: &PixelRect, own: &PixelRect) -> bool {
    let stride = |r: &PixelRect| (r.area() / OCCLUSION_SAMPLE_PX).sqrt().ceil().max(1.0) as u32;
    let Some(z_other) = lower_quartile(&mut depth_readings(frame, other, &[], stride(other))) else {
        return false;
    };
    let mut own_readings = depth_readings(frame, own, std::slice::from_ref(other), stride(own));
    if own_readings.len() < MIN_DEPTH_READINGS {
        return false;
    }
    let Some(z_own) = lower_quartile(&mut own_readings) else {
        return false;
    };
    z_other < z_own - (0.02 + 0.02 * z_own)
}

fn normalise(w: &mut [f64]) {
    let s: f64 = w.iter().sum();
    if s > 0.0 && s.is_finite() {
        for v in w.iter_mut() {
            *v /= s;
        }
    } else {
        let u = 1.0 / w.len().max(1) as f64;
        w.fill(u);
    }
}

/// Floors each component's total weight at `min_weight` (then renormalises).
fn floor_components(s: &mut TrackState, min_weight: f64) {
    let mut cams: Vec<usize> = s.sources.clone();
    cams.sort_unstable();
    cams.dedup();
    if cams.len() < 2 {
        return;
    }
    for c in cams {
        let wc: f64 = (0..s.n()).filter(|&i| s.sources[i] == c).map(|i| s.weights[i]).sum();
        if wc < min_weight {
            let m = (0..s.n()).filter(|&i| s.sources[i] == c).count() as f64;
            for i in 0..s.n() {
                if s.sources[i] == c {
                    s.weights[i] = if wc > 0.0 {
                        s.weights[i] * min_weight / wc
                    } else {
                        min_weight / m
                    };
                }
            }
        }
    }
    normalise(&mut s.weights);
}

/// The object's size in pixels ([`crate::tracker::observation::object_size_px`]) at `mean`
/// (reference frame) in the nearest of `views` whose image holds it; 0 when none does.
fn nearest_view_px(views: &[(&CameraFrame, Pose, usize)], mean: &Vector3<f64>, codebook: &Codebook) -> f64 {
    views
        .iter()
        .filter_map(|(frame, view_from_ref, _)| {
            let p = view_from_ref * nalgebra::Point3::from(*mean);
            let k = &frame.intrinsics;
            let inside = k.project(&p).is_some_and(|uv| k.contains(uv));
            inside.then(|| crate::tracker::observation::object_size_px(codebook, k, p.z))
        })
        .fold(0.0, f64::max)
}

/// Moves `share` of a track's particles (at least one) per off-centre turn of its model to
/// their twin pose ([`TwinConfig`]): the histogram turned, the position shifted by the turn's
/// offset at the particle's top bin. A track whose rotation is not known well enough has no
/// pose to turn. Returns how many particles moved.
fn make_twins(
    s: &mut TrackState,
    m: &Model,
    tables: &GridTables,
    tw: &TwinConfig,
    near: bool,
    rng: &mut impl rand::Rng,
) -> usize {
    let nt = m.twin_turns.len();
    let n = s.n();
    if nt == 0 || n < 2 || s.rot.active.is_empty() || tw.share <= 0.0 {
        return 0;
    }
    let uniform = (tables.grid.len() as f64).ln();
    if s.estimate
        .as_ref()
        .is_none_or(|e| e.rotation_entropy > tw.max_entropy_rel * uniform)
    {
        return 0;
    }
    let k = ((tw.share * n as f64).round() as usize).clamp(1, n / 2);
    let far_limit_m = tw.max_trimmed_rel * m.codebook.diameter_m;
    let mut moved = 0;
    for (j, turn) in m.twin_turns.iter().enumerate() {
        if !near && turn.trimmed_distance_m > far_limit_m {
            continue;
        }
        // the turned column holds the parent's mass at `R * turn^-1` (it reads bin `b` at
        // `b * turn`): the twin is the pose turned by the inverse
        let inverse = crate::symmetry::CentredTurn {
            rotation: turn.rotation.inverse(),
            ..*turn
        };
        let chosen = rand::seq::index::sample(rng, n, k).into_vec();
        let mut parents: Vec<u32> = chosen.iter().map(|&p| s.rot.column_of[p]).collect();
        parents.sort_unstable();
        parents.dedup();
        // each parent column's top bin, before the turned columns join
        let tops: Vec<usize> = parents
            .iter()
            .map(|&c| s.rot.top_bin(c as usize).unwrap_or(0))
            .collect();
        let turned =
            crate::tracker::sparse::append_turned_columns(&mut s.rot, tables, &m.twin_partners, nt, j, &parents);
        for &p in &chosen {
            let i = parents.binary_search(&s.rot.column_of[p]).expect("a parent");
            let t_h = s
                .reference_from_hist
                .inverse_transform_point(&nalgebra::Point3::from(s.positions[p]))
                .coords;
            let r_ref = s.reference_from_hist.rotation
                * crate::geometry::ray_rotation(&t_h)
                * UnitQuaternion::from_matrix(&tables.matrix(tops[i]));
            s.positions[p] += inverse.origin_shift(&r_ref);
            s.rot.column_of[p] = turned[i];
        }
        moved += chosen.len();
    }
    moved
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kept_fit_widens_where_it_is_fixed_and_stays_free_elsewhere() {
        // fixed to 1 mm along x and 2 mm along y, free along z
        let mut f = CarriedFit {
            camera: "a".into(),
            stamp_ns: 0,
            target: Vector3::zeros(),
            information: nalgebra::Matrix3::from_diagonal(&Vector3::new(1e6, 2.5e5, 0.0)),
        };
        f.widen(&(nalgebra::Matrix3::identity() * 1e-6));
        let var = |h: f64| 1.0 / h;
        assert!((var(f.information[(0, 0)]) - 2e-6).abs() < 1e-12, "{}", f.information);
        assert!((var(f.information[(1, 1)]) - 5e-6).abs() < 1e-12, "{}", f.information);
        assert_eq!(f.information[(2, 2)], 0.0);
    }

    #[test]
    fn tracker_can_move_between_threads() {
        fn assert_send_sync<T: Send + Sync>() {}
        assert_send_sync::<Tracker>();
        assert_send_sync::<Codebook>();
    }

    /// A 640 x 480 frame of a wall at `wall_m` with rectangles `[x0, y0, x1, y1)` at their
    /// depths, and the given detections.
    fn depth_scene(wall_m: f32, rects: &[([u32; 4], f32)], detections: Vec<Detection>) -> CameraFrame {
        let (w, h) = (640u32, 480u32);
        let mut data = vec![wall_m; (w * h) as usize];
        for ([x0, y0, x1, y1], z) in rects {
            for y in *y0..*y1 {
                for x in *x0..*x1 {
                    data[(y * w + x) as usize] = *z;
                }
            }
        }
        CameraFrame {
            camera: "cam".into(),
            stamp_ns: 0,
            intrinsics: Intrinsics::new(w, h, [615.0, 0.0, 319.5, 0.0, 615.0, 239.5, 0.0, 0.0, 1.0]).unwrap(),
            depth: crate::camera::DepthImage::new(w, h, data).unwrap(),
            color: None,
            detections,
        }
    }

    fn detection(object: &str, [x0, y0, x1, y1]: [u32; 4]) -> Detection {
        Detection {
            object: object.into(),
            bbox_xywh_px: [f64::from(x0), f64::from(y0), f64::from(x1 - x0), f64::from(y1 - y0)],
            score: 1.0,
        }
    }

    #[test]
    fn a_detection_half_hidden_behind_a_nearer_one_takes_its_own_depth() {
        // the drill's visible box (300..340) is half covered by a box 25 cm nearer (300..322)
        let drill = detection("drill", [300, 230, 340, 250]);
        let sugar = detection("sugar", [300, 210, 322, 260]);
        let rects = [([322, 230, 340, 250], 2.85), ([300, 210, 322, 260], 2.60)];
        let diameter = 0.2;
        let alone = depth_scene(4.0, &rects, vec![drill.clone()]);
        let (_, z_alone) = detection_centre(&alone, &drill, diameter);
        assert!(
            (z_alone - 2.65).abs() < 1e-3,
            "without the occluder's box: its depth, {z_alone}"
        );
        let both = depth_scene(4.0, &rects, vec![sugar.clone(), drill.clone()]);
        let (_, z) = detection_centre(&both, &drill, diameter);
        assert!((z - 2.90).abs() < 1e-3, "with it: the drill's own readings, {z}");
        // the nearer object is not moved by the farther one whose box overlaps its own
        let (_, z_sugar) = detection_centre(&both, &sugar, diameter);
        let (_, z_sugar_alone) = detection_centre(&depth_scene(4.0, &rects, vec![sugar.clone()]), &sugar, diameter);
        assert_eq!(z_sugar, z_sugar_alone);
        assert!((z_sugar - 2.65).abs() < 1e-3, "{z_sugar}");
    }

    #[test]
    fn an_occluder_over_the_whole_box_centre_leaves_the_rest_of_the_box() {
        // the occluder's box covers the drill box's central half entirely: the drill's readings
        // are read from the rest of its box
        let drill = detection("drill", [300, 230, 360, 250]);
        let can = detection("can", [310, 200, 350, 270]);
        let rects = [([300, 230, 360, 250], 1.50), ([310, 200, 350, 270], 1.20)];
        let frame = depth_scene(3.0, &rects, vec![can, drill.clone()]);
        let (_, z) = detection_centre(&frame, &drill, 0.2);
        assert!((z - 1.55).abs() < 1e-3, "{z}");
    }

    #[test]
    fn component_floor_keeps_every_camera_alive() {
        let mut s = TrackState {
            model: 0,
            positions: vec![Vector3::zeros(); 4],
            sources: vec![0, 0, 1, 1],
            weights: vec![0.5, 0.5, 1e-9, 1e-9],
            rot: RotationState::default(),
            rotation: None,
            estimate: None,
            reference_from_hist: Pose::identity(),
            map_cache: vec![],
            slice_cursor: 0,
            disagreement: Disagreement::default(),
            verified_from: Vec::new(),
            registered: None,
            carried_fits: Vec::new(),
            surface_rotation_cov: None,
        };
        floor_components(&mut s, 0.05);
        let w1: f64 = s.weights[2] + s.weights[3];
        assert!((w1 - 0.05 / 1.05).abs() < 1e-9, "{w1}");
        assert!((s.weights.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn the_near_blur_goes_from_its_sigma_to_the_far_one() {
        let nb = NearBlur {
            sigma_bins: 0.5,
            full_m: 1.0,
            until_m: 1.4,
            from_similarity: 0.85,
            full_similarity: 0.9,
        };
        let near = |d: f64| nb.sigma_at(d, Some(0.95), 1.0);
        assert_eq!(near(0.4), 0.5);
        assert_eq!(near(1.0), 0.5);
        assert!((near(1.2) - 0.75).abs() < 1e-12);
        assert_eq!(near(1.4), 1.0);
        assert_eq!(near(3.0), 1.0);
        // a poor match keeps the far blur, near or not; half way, half the change
        assert_eq!(nb.sigma_at(0.5, Some(0.75), 1.0), 1.0);
        assert_eq!(nb.sigma_at(0.5, None, 1.0), 1.0);
        assert!((nb.sigma_at(0.5, Some(0.875), 1.0) - 0.75).abs() < 1e-12);
        // steps when both ends are one
        let step = NearBlur {
            until_m: 1.0,
            full_similarity: 0.85,
            ..nb
        };
        assert_eq!(step.sigma_at(1.0, Some(0.85), 1.0), 0.5);
        assert_eq!(step.sigma_at(1.01, Some(0.85), 1.0), 1.0);
        assert_eq!(step.sigma_at(1.0, Some(0.849), 1.0), 1.0);
    }
}
