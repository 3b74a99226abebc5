//! The multi-view Rao-Blackwellized particle filter (the seed paper, section IV).
//!
//! Files:
//! - [`bins`]: the rotation grid's tables: Euler angles and the bin of a rotation, volume
//!   weights, one *bin map* per view and step (pull re-binning).
//! - [`kernels`]: the hot loops over histograms: the matching GEMM, the wrap-around separable
//!   blur, a vectorisable `exp`, pull gathers, run-time SIMD dispatch.
//! - [`crop`]: the crop features: sampling a crop, support-plane suppression, depth denoising
//!   and inpainting, chromaticity.
//! - [`encoder`]: the default encoder (PCA + ridge-regression denoising) behind the
//!   [`encoder::Encoder`] trait.
//! - [`codebook`]: templates rendered at every viewpoint, in-plane bins by 2-D rotation,
//!   encoded and cached on disk.
//! - [`observation`]: crops around projected particles, matching (chunked GEMM), likelihoods;
//!   [`observation::fuse`], the fused measurement update of the dense histograms.
//! - [`motion`]: Brownian object motion and the odometry motion model of the robot camera.
//! - [`estimate`]: mean pose, components, rotation modes, covariance, samples.
//! - [`support`]: the prior of an object resting on a table on a stable face of its hull.
//! - [`filter`]: the [`Tracker`] itself.
//!
//! # Where the state lives
//! Particle *positions* live in the reference frame (the robot camera, or the stationary
//! reference camera of a rig without one), as in the paper: the grasp decision consumes the
//! distribution there, and the odometry noise enters the motion model (Eq. 3) per particle.
//! The rotation *histograms* of a track live in the frame `H` of the reference camera at the
//! moment the track started (`reference_from_hist` is updated with the exact odometry):
//! re-binning the prior into the moving reference frame at every step through a nearest-bin
//! pull map never moves it at all when the per-step rotation is below half a bin (2.5 degrees
//! on the full grid), so the estimate would fall behind by the accumulated rotation (the
//! measurement: `docs/decisions.md`). Every view, the reference camera included, is pulled
//! into `H` through one bin map per view and step; the cost is one more map (about 191,808
//! rotation products) per step for the robot camera.
//!
//! Histograms are allocentric with respect to each particle's ray (in `H`); the bin maps use
//! the rays of the object's mean position (particles of one object differ by about a degree).
//!
//! # Robustness
//! - Each view's log-likelihood is floored (`ObservationConfig::loglik_floor`): a view that
//!   disagrees with the others can lower a bin by a bounded factor only, so two agreeing views
//!   outvote a third, and the distribution is never wiped out (see the conflicting-view test).
//! - A view is gated off when its best similarity is below `gate_similarity` (it does not see
//!   the object); an object no camera sees keeps its prior, which grows with the motion noise.
//! - Resampling is stratified by source camera and component weights are floored, so the
//!   mixture of Eq. 2 keeps one component per camera.
//! - The particle weights' update (Eq. 7) is tempered by the number of views
//!   (`TrackerConfig::view_weight_tempering`): the rotation histograms multiply every view,
//!   but the weights that choose translation particles are as peaked as one view's: a plain
//!   product of the views leaves almost no effective particles, and the estimate flips
//!   between the modes of whichever particle wins.

pub mod bins;
pub mod codebook;
pub mod crop;
pub mod encoder;
pub mod estimate;
pub mod filter;
pub mod kernels;
pub mod motion;
pub mod observation;
pub mod register;
pub mod sparse;
pub mod support;
pub mod verify;

use crate::geometry::Pose;
use serde::{Deserialize, Serialize};

/// The CPU rasteriser lives in [`crate::render::raster`]; this path stays for callers.
pub use crate::render::raster;
/// The sensor types live in [`crate::sensor`] (below the tracker); these paths stay for callers.
pub use crate::sensor::{CameraFrame, CameraMount, Detection, RobotOdometry};

pub use codebook::{Codebook, CodebookConfig, ColorFeatures};
pub use encoder::{Encoder, LinearDenoisingEncoder};
pub use filter::{
    NearBlur, RecoveryConfig, RegistrationConfig, SpreadConfig, TrackPrior, TrackSnapshot, Tracker, TrackerConfig,
    TrackerSnapshot, TwinConfig, VerificationConfig,
};

/// Errors of the tracker module.
#[derive(Debug, thiserror::Error)]
pub enum TrackerError {
    #[error("render failed: {0}")]
    Render(String),
    #[error("codebook cache i/o: {0}")]
    Io(#[from] std::io::Error),
    #[error("codebook cache file {path} is invalid: {why}")]
    BadCache { path: String, why: String },
    #[error("bad configuration: {0}")]
    Config(String),
    #[error("unknown camera {0:?} (not in the rig given to Tracker::new)")]
    UnknownCamera(String),
    #[error("numerical failure: {0}")]
    Numerical(String),
    #[error("image of camera {camera} is {got_w}x{got_h}, intrinsics say {want_w}x{want_h}")]
    ImageSize {
        camera: String,
        got_w: u32,
        got_h: u32,
        want_w: u32,
        want_h: u32,
    },
}

/// Status of a track.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TrackStatus {
    Initialising,
    Tracking,
    Lost,
}

fn yes() -> bool {
    true
}

/// One tracked object instance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Track {
    pub id: u64,
    /// Model name.
    pub object: String,
    pub status: TrackStatus,
    /// Stamp of the last step that updated the track.
    pub stamp_ns: i64,
    /// Best absolute cosine similarity of the last step over all views (None when unseen).
    pub best_similarity: Option<f64>,
    /// Steps in a row whose evidence was below the lost threshold.
    pub weak_steps: u32,
    /// Cameras that gave evidence in the last step.
    pub seen_by: Vec<String>,
    /// The reference camera's latest frame gave evidence of the track (a step without a frame
    /// of the reference camera keeps it): see [`Tracker::reference_sees`].
    #[serde(default = "yes")]
    pub reference_seen: bool,
    /// When and why the track last started again (None: never).
    #[serde(default)]
    pub reinitialised: Option<Reinitialisation>,
}

/// When and why a track started again.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reinitialisation {
    /// Stamp of the step that started it again.
    pub stamp_ns: i64,
    pub reason: ReinitReason,
}

/// Why a track started again.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ReinitReason {
    /// The track was lost and this camera's detection of its object started it again.
    Redetected { camera: String },
    /// These cameras' detections agreed with each other and lay outside the track's 99 %
    /// region for `steps` steps in a row: their particles were spawned again from the
    /// detections, `offset_m` from the track's mean (the rotation belief was kept).
    CamerasDisagreed {
        cameras: Vec<String>,
        offset_m: f64,
        steps: u32,
    },
}

/// One component of the translation mixture (Eq. 2): the particles of one source camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Component {
    pub camera: String,
    pub weight: f64,
    pub mean_m: [f64; 3],
    pub covariance_m2: [[f64; 3]; 3],
}

/// A mode of the rotation distribution (reference frame `reference_from_object` rotation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RotationMode {
    pub rotation_xyzw: [f64; 4],
    pub mass: f64,
}

/// The estimate of one track, in the reference frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub reference_from_object: Pose,
    /// RMS distance of the particles from their weighted mean.
    pub translation_std_m: f64,
    pub components: Vec<Component>,
    pub rotation_modes: Vec<RotationMode>,
    /// Shannon entropy (nats) of the particle-weighted mixture histogram over bins.
    pub rotation_entropy: f64,
    /// Order: translation x, y, z (m), rotation vector x, y, z (rad) about the mean.
    pub covariance_6x6: [[f64; 6]; 6],
    pub status: TrackStatus,
    pub stamp_ns: i64,
}

/// One particle as seen from outside.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParticleView {
    pub position_in_reference_m: [f64; 3],
    pub camera: String,
    pub weight: f64,
}

/// Per-stage timings and what happened in one step.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StepReport {
    pub stamp_ns: i64,
    pub tracks_created: Vec<u64>,
    pub tracks_reinitialised: Vec<u64>,
    pub tracks_lost: Vec<u64>,
    pub timings: StageTimings,
    /// Bins matched in this step, summed over tracks and views' shared set.
    #[serde(default)]
    pub matched_bins: usize,
    /// Active bins after this step, summed over tracks.
    #[serde(default)]
    pub active_bins: usize,
    /// Tracks audited in this step (`MatchingConfig::audit`), and those whose heaviest
    /// particle's likelihood peaked outside the matched set.
    #[serde(default)]
    pub audited: usize,
    #[serde(default)]
    pub audit_outside: usize,
    /// Tracks whose competing rotation modes were checked against the images in this step.
    #[serde(default)]
    pub verified: usize,
    /// Tracks whose particles were weighed by their depth registration in this step.
    #[serde(default)]
    pub registered: usize,
    /// Particles moved to a twin pose in this step (`TwinConfig`), summed over tracks.
    #[serde(default)]
    pub twinned: usize,
}

/// Seconds spent per stage in one step (summed over objects).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTimings {
    pub motion_s: f64,
    pub crops_s: f64,
    pub encoding_s: f64,
    pub matching_s: f64,
    pub likelihoods_s: f64,
    pub fusion_s: f64,
    pub blur_s: f64,
    pub resampling_s: f64,
    pub estimates_s: f64,
    /// Rendering and scoring competing rotation modes ([`verify`]).
    #[serde(default)]
    pub verification_s: f64,
    /// Registering the translation to near views' depth ([`register`]).
    #[serde(default)]
    pub registration_s: f64,
    pub total_s: f64,
}

impl StepReport {
    /// Adds another report of the same step (one track's update) to this one.
    pub fn absorb(&mut self, other: StepReport) {
        let StepReport {
            stamp_ns: _,
            tracks_created,
            tracks_reinitialised,
            tracks_lost,
            timings,
            matched_bins,
            active_bins,
            audited,
            audit_outside,
            verified,
            registered,
            twinned,
        } = other;
        self.tracks_created.extend(tracks_created);
        self.tracks_reinitialised.extend(tracks_reinitialised);
        self.tracks_lost.extend(tracks_lost);
        self.timings.accumulate(&timings);
        self.matched_bins += matched_bins;
        self.active_bins += active_bins;
        self.audited += audited;
        self.audit_outside += audit_outside;
        self.verified += verified;
        self.registered += registered;
        self.twinned += twinned;
    }
}

impl StageTimings {
    /// The stages by name (the total last), for tables and metrics.
    pub fn stages(&self) -> [(&'static str, f64); 12] {
        [
            ("motion", self.motion_s),
            ("crops", self.crops_s),
            ("encoding", self.encoding_s),
            ("matching", self.matching_s),
            ("likelihoods", self.likelihoods_s),
            ("fusion", self.fusion_s),
            ("blur", self.blur_s),
            ("resampling", self.resampling_s),
            ("estimates", self.estimates_s),
            ("verification", self.verification_s),
            ("registration", self.registration_s),
            ("total", self.total_s),
        ]
    }

    /// Adds another step's timings to these (a running sum).
    pub fn accumulate(&mut self, other: &StageTimings) {
        self.motion_s += other.motion_s;
        self.crops_s += other.crops_s;
        self.encoding_s += other.encoding_s;
        self.matching_s += other.matching_s;
        self.likelihoods_s += other.likelihoods_s;
        self.fusion_s += other.fusion_s;
        self.blur_s += other.blur_s;
        self.resampling_s += other.resampling_s;
        self.estimates_s += other.estimates_s;
        self.verification_s += other.verification_s;
        self.registration_s += other.registration_s;
        self.total_s += other.total_s;
    }
}
