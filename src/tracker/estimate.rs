//! Estimates from a particle set (paper section IV.D, PoseRBPF's rotation estimate).
//!
//! - Translation: weighted mean of the per-camera components (a component's weight is the sum
//!   of its particles' weights).
//! - Rotation: the particle-weighted mixture histogram; its top-K bins (egocentric through the
//!   ray of the mean position) are clustered into modes. The estimate is the eigenvector
//!   average of the top bins weighted by mass x a Gaussian of their angle to the previous
//!   estimate (bins beyond `max_angle_rad` dropped). It *jumps to the global mode* when there
//!   is no previous estimate, when no top bin lies near it, or when the best mode holds more
//!   than `jump_ratio` times the mass found near the previous estimate (PoseRBPF's
//!   `check_rot_expectation`); without the jump a wrong first guess would stick for ever.

use crate::geometry::{Pose, PoseSamples, RotationGrid, euler_to_rotation, ray_rotation};
use crate::tracker::bins::GridTables;
use crate::tracker::sparse::RotationState;
use crate::tracker::{Component, RotationMode};
use nalgebra::{Matrix3, Matrix4, Point3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use serde::{Deserialize, Serialize};

/// Parameters of the rotation estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EstimateConfig {
    pub top_k_bins: usize,
    pub sigma_rad: f64,
    pub max_angle_rad: f64,
    pub jump_ratio: f64,
    pub mode_merge_rad: f64,
    pub max_modes: usize,
}

impl Default for EstimateConfig {
    fn default() -> Self {
        Self {
            top_k_bins: 200,
            sigma_rad: 0.1,
            max_angle_rad: 0.5,
            jump_ratio: 2.0,
            mode_merge_rad: 0.3,
            max_modes: 8,
        }
    }
}

/// Regularised resampling of the translation particles (Musso et al.'s regularised particle
/// filter with Liu and West's shrinkage): after resampling, each component's particles are
/// pulled towards its mean by `a = sqrt(1 - h^2)` and jittered by `N(0, h^2 S)` with `S` the
/// component's covariance, which keeps its mean and covariance while copies of one ancestor
/// become distinct hypotheses. Then a component narrower than `floor_m + floor_per_m * range`
/// (isotropic) is jittered up to it: the crops cannot place an object more finely than the
/// depth noise and the codebook's crop alignment allow, and a collapsed cloud reports a
/// spread far below its error. The default (4 mm + 0.6 % of the range) covers the real clip's
/// 0.5-1.3 cm errors; a quarter of it fitted the generated sequences but missed the real
/// mug in most frames (`docs/decisions.md`, "The spread floor kept").
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SpreadConfig {
    /// Kernel bandwidth `h` relative to the component's spread (0: plain resampling).
    pub bandwidth: f64,
    /// Smallest per-axis standard deviation of a component, metres, plus `floor_per_m` times
    /// the component's distance from the reference camera.
    pub floor_m: f64,
    pub floor_per_m: f64,
}

impl SpreadConfig {
    /// No regularisation and no floor: the particles as they are.
    pub const NONE: Self = Self {
        bandwidth: 0.0,
        floor_m: 0.0,
        floor_per_m: 0.0,
    };

    /// The isotropic standard deviation to add to a component of covariance `cov` whose mean
    /// is `mean` (reference frame) to bring it up to the floor.
    pub fn extra_std_m(&self, mean: &Vector3<f64>, cov: &Matrix3<f64>) -> f64 {
        let floor = self.floor_m + self.floor_per_m * mean.norm();
        (floor * floor - cov.trace() / 3.0).max(0.0).sqrt()
    }
}

/// What a component's floor adds to its spread: an isotropic standard deviation (the plain
/// floor), or a covariance (the floor combined with the depth registration's information:
/// tight along what the depth fixes, the floor elsewhere) with its square root.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FloorExtra {
    Isotropic(f64),
    Matrix { cov: Matrix3<f64>, sqrt: Matrix3<f64> },
}

impl FloorExtra {
    /// The covariance it adds.
    pub fn cov(&self) -> Matrix3<f64> {
        match self {
            Self::Isotropic(s) => Matrix3::identity() * (s * s),
            Self::Matrix { cov, .. } => *cov,
        }
    }

    /// A draw of it from three standard normal numbers `z`.
    pub fn draw(&self, z: &Vector3<f64>) -> Vector3<f64> {
        match self {
            Self::Isotropic(s) => z * *s,
            Self::Matrix { sqrt, .. } => sqrt * z,
        }
    }

    pub fn is_zero(&self) -> bool {
        match self {
            Self::Isotropic(s) => *s <= 0.0,
            Self::Matrix { cov, .. } => cov.trace() <= 0.0,
        }
    }
}

impl SpreadConfig {
    /// The floor's addition to a component of covariance `cov` at `mean`; with the depth
    /// registration's `information` (reference frame, 1/m^2) the floor is the covariance of
    /// the isotropic floor's Gaussian combined with it, and the addition is the positive part
    /// of that less `cov`.
    pub fn extra(&self, mean: &Vector3<f64>, cov: &Matrix3<f64>, information: Option<&Matrix3<f64>>) -> FloorExtra {
        let Some(h) = information else {
            return FloorExtra::Isotropic(self.extra_std_m(mean, cov));
        };
        let floor = self.floor_m + self.floor_per_m * mean.norm();
        if floor <= 0.0 {
            return FloorExtra::Isotropic(0.0);
        }
        let Some(c) = (h + Matrix3::identity() / (floor * floor)).try_inverse() else {
            return FloorExtra::Isotropic(self.extra_std_m(mean, cov));
        };
        let eig = (c - cov).symmetric_eigen();
        let (mut add, mut sqrt) = (Matrix3::zeros(), Matrix3::zeros());
        for j in 0..3 {
            let lam = eig.eigenvalues[j].max(0.0);
            let v = eig.eigenvectors.column(j);
            add += v * v.transpose() * lam;
            sqrt += v * v.transpose() * lam.sqrt();
        }
        FloorExtra::Matrix { cov: add, sqrt }
    }
}

impl Default for SpreadConfig {
    fn default() -> Self {
        Self {
            bandwidth: 0.3,
            floor_m: 0.004,
            floor_per_m: 0.006,
        }
    }
}

/// Bins per chunk of the sampler's prefix sums.
const SAMPLE_CHUNK_BINS: usize = 1024;

/// A read-only view of one object's particles.
pub struct ParticleSet<'a> {
    pub positions_m: &'a [Vector3<f64>],
    pub sources: &'a [usize],
    /// Normalised particle weights.
    pub weights: &'a [f64],
    /// The particles' rotation histograms (each sums to 1).
    pub rot: &'a RotationState,
    pub tables: &'a GridTables,
    /// The histograms' frame `H` (the reference camera when the track started): positions are
    /// in the current reference frame, bins are allocentric in `H`.
    pub reference_from_hist: Pose,
    /// The floor on each component's spread (see [`SpreadConfig`]): the reported components,
    /// covariance and samples include it.
    pub spread: SpreadConfig,
    /// The depth registration's information on the position in this step (reference frame,
    /// 1/m^2), which narrows the floor along what it fixes ([`SpreadConfig::extra`]).
    pub floor_information: Option<Matrix3<f64>>,
}

impl ParticleSet<'_> {
    pub fn n(&self) -> usize {
        self.positions_m.len()
    }

    pub fn mean_position(&self) -> Vector3<f64> {
        let mut m = Vector3::zeros();
        for (p, w) in self.positions_m.iter().zip(self.weights) {
            m += p * *w;
        }
        m
    }

    /// Mixture histogram `sum_p w_p h_p` (f64).
    pub fn mixture(&self) -> Vec<f64> {
        self.mixture_with(self.weights)
    }

    /// Mixture histogram with other per-particle factors, over every bin of the grid.
    pub fn mixture_with(&self, factors: &[f64]) -> Vec<f64> {
        self.rot.mixture_dense(self.tables, factors)
    }

    /// Particle `p`'s histogram at bin `b`.
    #[inline]
    fn value(&self, b: usize, p: usize) -> f64 {
        self.rot.value(self.tables, b, self.rot.column_of[p] as usize) as f64
    }

    /// Per-camera components (camera index, weight, mean, covariance).
    pub fn components(&self, camera_names: &[String]) -> Vec<Component> {
        let mut out = Vec::new();
        for (ci, name) in camera_names.iter().enumerate() {
            if !self.sources.contains(&ci) {
                continue;
            }
            let w: f64 = (0..self.n())
                .filter(|&i| self.sources[i] == ci)
                .map(|i| self.weights[i])
                .sum();
            let (mean, cov) = component_moments(self.positions_m, self.weights, self.sources, ci);
            let cov = cov + self.spread.extra(&mean, &cov, self.floor_information.as_ref()).cov();
            let mut c = [[0.0; 3]; 3];
            for (r, row) in c.iter_mut().enumerate() {
                for (k, v) in row.iter_mut().enumerate() {
                    *v = cov[(r, k)];
                }
            }
            out.push(Component {
                camera: name.clone(),
                weight: w,
                mean_m: [mean.x, mean.y, mean.z],
                covariance_m2: c,
            });
        }
        out
    }

    /// Translation covariance of all particles (each component's floor included, see
    /// [`SpreadConfig`]) and the RMS distance from the mean.
    pub fn translation_covariance(&self) -> (Matrix3<f64>, f64) {
        let m = self.mean_position();
        let mut cov = Matrix3::zeros();
        for (p, w) in self.positions_m.iter().zip(self.weights) {
            let d = p - m;
            cov += d * d.transpose() * *w;
        }
        for (c, _, extra) in self.component_floors() {
            let wc: f64 = (0..self.n())
                .filter(|&i| self.sources[i] == c)
                .map(|i| self.weights[i])
                .sum();
            cov += match extra {
                FloorExtra::Isotropic(e) => Matrix3::identity() * (wc * e * e),
                FloorExtra::Matrix { cov, .. } => cov * wc,
            };
        }
        (cov, cov.trace().max(0.0).sqrt())
    }

    /// Per source camera: its index, its weighted mean and the standard deviation its floor
    /// adds (see [`SpreadConfig`]).
    fn component_floors(&self) -> Vec<(usize, Vector3<f64>, FloorExtra)> {
        let mut cams = self.sources.to_vec();
        cams.sort_unstable();
        cams.dedup();
        cams.into_iter()
            .map(|c| {
                let (mean, cov) = component_moments(self.positions_m, self.weights, self.sources, c);
                (c, mean, self.spread.extra(&mean, &cov, self.floor_information.as_ref()))
            })
            .collect()
    }

    /// Natural log of the mixture mass of the bin holding `reference_from_object` (each
    /// particle reads its own allocentric bin).
    pub fn orientation_loglik(&self, reference_from_object: &UnitQuaternion<f64>) -> f64 {
        let n = self.n();
        let grid = self.tables.grid;
        let r_h = self.reference_from_hist.rotation.inverse() * reference_from_object;
        let mut mass = 0.0;
        for p in 0..n {
            let t_h = self
                .reference_from_hist
                .inverse_transform_point(&Point3::from(self.positions_m[p]))
                .coords;
            let allo = ray_rotation(&t_h).inverse() * r_h;
            let b = grid.flat_of(&allo);
            mass += self.weights[p] * self.value(b, p);
        }
        mass.max(1e-300).ln()
    }

    /// Density of the rotation marginal at each of `rotations` (`reference_from_object`),
    /// relative to the uniform distribution on SO(3): `sum_p w_p h_p(b_p) / v(b_p)`, where
    /// each particle reads its own allocentric bin `b_p` (as [`Self::orientation_loglik`])
    /// and `v` is the bin's share of SO(3). Averaged over `orbit` (object-frame rotations
    /// that look the same: `R * s` for each `s`); an empty orbit means the identity alone.
    /// Read-only: the evaluation's highest-density test (`eval::trust`).
    pub fn rotation_densities(&self, rotations: &[UnitQuaternion<f64>], orbit: &[UnitQuaternion<f64>]) -> Vec<f64> {
        use rayon::prelude::*;
        let grid = self.tables.grid;
        let per_elevation = grid.n_azimuth() * grid.n_inplane();
        let wsum: f64 = self.weights.iter().sum();
        let hist_from_reference = self.reference_from_hist.rotation.inverse();
        // Per particle: allocentric-in-H from reference, `ray(t_h)^-1 * H_from_reference`.
        let allo_from_reference: Vec<UnitQuaternion<f64>> = self
            .positions_m
            .iter()
            .map(|p| {
                let t_h = self
                    .reference_from_hist
                    .inverse_transform_point(&Point3::from(*p))
                    .coords;
                ray_rotation(&t_h).inverse() * hist_from_reference
            })
            .collect();
        let identity = [UnitQuaternion::identity()];
        let orbit = if orbit.is_empty() { &identity[..] } else { orbit };
        rotations
            .par_iter()
            .with_min_len(16)
            .map(|r| {
                let mut total = 0.0;
                for s in orbit {
                    let rs = r * s;
                    for (p, (w, allo)) in self.weights.iter().zip(&allo_from_reference).enumerate() {
                        if *w <= 0.0 {
                            continue;
                        }
                        let b = grid.flat_of(&(allo * rs));
                        let volume = self.tables.elevation_volume[b / per_elevation];
                        total += w * self.value(b, p) / volume;
                    }
                }
                if wsum > 0.0 {
                    total / (wsum * orbit.len() as f64)
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// `n` poses: a particle by weight, a bin from its histogram (an inactive bin by volume),
    /// a rotation uniform inside the bin (elevation clamped to [0, pi]), egocentric through the
    /// particle's ray.
    pub fn sample_poses(&self, count: usize, rng: &mut impl Rng) -> PoseSamples {
        let n = self.n();
        let grid = self.tables.grid;
        let rot = self.rot;
        let nc = rot.n_cols();
        let wsum: f64 = self.weights.iter().sum();
        // per column: prefix sums over chunks of active bins, the active and the floor mass
        let na = rot.active.len();
        let chunks = na.div_ceil(SAMPLE_CHUNK_BINS);
        let mut chunk_sums = vec![0f64; chunks * nc];
        for (a, row) in rot.values.chunks(nc.max(1)).enumerate() {
            let k = a / SAMPLE_CHUNK_BINS;
            for (c, v) in row.iter().enumerate() {
                chunk_sums[k * nc + c] += v.max(0.0) as f64;
            }
        }
        let active_mass: Vec<f64> = (0..nc)
            .map(|c| (0..chunks).map(|k| chunk_sums[k * nc + c]).sum())
            .collect();
        let v_in = rot.inactive_volume(self.tables);
        let floor_mass: Vec<f64> = rot.floors.iter().map(|f| f.max(0.0) as f64 * v_in).collect();
        let mut weight_cdf = Vec::with_capacity(n);
        let mut acc = 0.0;
        for w in self.weights {
            acc += *w;
            weight_cdf.push(acc);
        }
        // elevation rows by volume, for draws from the floor
        let per_row = (grid.n_azimuth() * grid.n_inplane()) as f64;
        let mut row_cdf = Vec::with_capacity(grid.n_elevation());
        let mut racc = 0.0;
        for v in &self.tables.elevation_volume {
            racc += v * per_row;
            row_cdf.push(racc);
        }
        let floors = self.component_floors();
        let mut poses = Vec::with_capacity(count);
        let s = grid.step_rad();
        for _ in 0..count {
            let u = rng.random::<f64>() * wsum;
            let p = weight_cdf.partition_point(|c| *c <= u).min(n - 1);
            let c = rot.column_of[p] as usize;
            let total = active_mass[c] + floor_mass[c];
            let mut target = rng.random::<f64>() * total;
            let b = if target < active_mass[c] && na > 0 {
                let mut found = rot.active[na - 1] as usize;
                'chunks: for k in 0..chunks {
                    let cs = chunk_sums[k * nc + c];
                    if target >= cs && k + 1 < chunks {
                        target -= cs;
                        continue;
                    }
                    let a0 = k * SAMPLE_CHUNK_BINS;
                    let a1 = (a0 + SAMPLE_CHUNK_BINS).min(na);
                    for a in a0..a1 {
                        let h = rot.values[a * nc + c].max(0.0) as f64;
                        if target < h {
                            found = rot.active[a] as usize;
                            break 'chunks;
                        }
                        target -= h;
                    }
                    // rounding left a sliver: the chunk's last bin with mass
                    found = (a0..a1)
                        .rev()
                        .find(|a| rot.values[a * nc + c] > 0.0)
                        .map_or(rot.active[a1 - 1] as usize, |a| rot.active[a] as usize);
                    break;
                }
                found
            } else {
                // the floor: a bin by volume, outside the active ones
                let mut b = 0;
                for _ in 0..64 {
                    let r = rng.random::<f64>() * racc;
                    let e = row_cdf.partition_point(|x| *x <= r).min(grid.n_elevation() - 1);
                    let a = rng.random_range(0..grid.n_azimuth());
                    let t = rng.random_range(0..grid.n_inplane());
                    b = (e * grid.n_azimuth() + a) * grid.n_inplane() + t;
                    if rot.slot(b).is_none() {
                        break;
                    }
                }
                b
            };
            let (e, a, t) = grid.angles_rad(grid.unflat(b));
            let e = (e + (rng.random::<f64>() - 0.5) * s).clamp(0.0, std::f64::consts::PI);
            let a = a + (rng.random::<f64>() - 0.5) * s;
            let t = t + (rng.random::<f64>() - 0.5) * s;
            let jitter = floors
                .iter()
                .find(|f| f.0 == self.sources[p])
                .map_or(FloorExtra::Isotropic(0.0), |f| f.2);
            let pos = self.positions_m[p]
                + if jitter.is_zero() {
                    Vector3::zeros()
                } else {
                    jitter.draw(&Vector3::from_fn(|_, _| {
                        rng.sample::<f64, _>(rand_distr::StandardNormal)
                    }))
                };
            let t_h = self
                .reference_from_hist
                .inverse_transform_point(&Point3::from(pos))
                .coords;
            let rot_q = self.reference_from_hist.rotation * ray_rotation(&t_h) * euler_to_rotation(e, a, t);
            poses.push(Pose::from_parts(Translation3::from(pos), rot_q));
        }
        let ess = 1.0 / self.weights.iter().map(|w| (w / wsum).powi(2)).sum::<f64>();
        PoseSamples {
            poses,
            effective_sample_size: ess.min(count as f64),
        }
    }
}

/// Weighted mean and covariance of the particles of camera `c`.
pub fn component_moments(
    positions: &[Vector3<f64>],
    weights: &[f64],
    sources: &[usize],
    c: usize,
) -> (Vector3<f64>, nalgebra::Matrix3<f64>) {
    let idx: Vec<usize> = (0..positions.len()).filter(|&i| sources[i] == c).collect();
    let w: f64 = idx.iter().map(|&i| weights[i]).sum();
    let wi = |i: usize| {
        if w > 0.0 {
            weights[i] / w
        } else {
            1.0 / idx.len() as f64
        }
    };
    let mean: Vector3<f64> = idx.iter().map(|&i| positions[i] * wi(i)).sum();
    let cov = idx
        .iter()
        .map(|&i| {
            let d = positions[i] - mean;
            d * d.transpose() * wi(i)
        })
        .fold(nalgebra::Matrix3::zeros(), |a, b| a + b);
    (mean, cov)
}

/// Weighted average of quaternions (largest eigenvector of `sum w q q^T`).
pub fn average_quaternions(qs: &[(UnitQuaternion<f64>, f64)]) -> Option<UnitQuaternion<f64>> {
    let mut m = Matrix4::zeros();
    let mut total = 0.0;
    for (q, w) in qs {
        let v = q.as_vector();
        m += v * v.transpose() * *w;
        total += w;
    }
    if total <= 0.0 {
        return None;
    }
    let eig = m.symmetric_eigen();
    let (i, _) = eig.eigenvalues.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?;
    let v = eig.eigenvectors.column(i);
    Some(UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        v[3], v[0], v[1], v[2],
    )))
}

/// The rotation part of an estimate.
pub struct RotationSummary {
    pub rotation: UnitQuaternion<f64>,
    pub modes: Vec<RotationMode>,
    pub entropy: f64,
    /// Covariance of the rotation vector about `rotation` over the top bins.
    pub covariance: Matrix3<f64>,
    /// The same with each bin taken at its turn (of those given) nearest to `rotation`: the
    /// error of the surface, which a near-symmetric turn leaves where it was.
    pub surface_covariance: Matrix3<f64>,
    /// True when the estimate jumped to the global mode.
    pub jumped: bool,
}

/// The `k` heaviest bins of `mixture`, heaviest first: the `k - 1`-th selection of all bins
/// then a stable sort (ties in the order the selection left them). Where the `k + 1`
/// heaviest values are all distinct (the usual case: the floor's many equal bins lie below
/// them) the answer is unique, and a bounded heap over one pass finds it without the
/// selection over the whole grid.
fn top_bins(mixture: &[f64], k: usize) -> Vec<usize> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    #[derive(PartialEq)]
    struct Key(f64, usize);
    impl Eq for Key {}
    impl PartialOrd for Key {
        fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
            Some(self.cmp(other))
        }
    }
    impl Ord for Key {
        fn cmp(&self, other: &Self) -> std::cmp::Ordering {
            self.0.total_cmp(&other.0)
        }
    }
    let dense = || {
        let mut idx: Vec<usize> = (0..mixture.len()).collect();
        idx.select_nth_unstable_by(k - 1, |a, b| mixture[*b].total_cmp(&mixture[*a]));
        idx.truncate(k);
        idx.sort_by(|a, b| mixture[*b].total_cmp(&mixture[*a]));
        idx
    };
    if mixture.len() <= k + 1 {
        return dense();
    }
    // the k + 1 largest values (a min-heap of them)
    let mut heap: BinaryHeap<Reverse<Key>> = BinaryHeap::with_capacity(k + 2);
    for (b, v) in mixture.iter().enumerate() {
        if heap.len() <= k {
            heap.push(Reverse(Key(*v, b)));
        } else if v.total_cmp(&heap.peek().expect("non-empty").0.0).is_gt() {
            heap.pop();
            heap.push(Reverse(Key(*v, b)));
        }
    }
    let mut top: Vec<(f64, usize)> = heap.into_iter().map(|Reverse(Key(v, b))| (v, b)).collect();
    top.sort_by(|a, b| b.0.total_cmp(&a.0));
    let distinct = top.windows(2).all(|w| w[0].0.total_cmp(&w[1].0).is_gt()) && top.iter().all(|t| t.0.is_finite());
    if !distinct {
        return dense();
    }
    top.truncate(k);
    top.into_iter().map(|(_, b)| b).collect()
}

/// Rotation estimate, modes and entropy from a mixture histogram (see the module docs).
pub fn summarise_rotation(
    grid: &RotationGrid,
    mixture: &[f64],
    mean_position: &Vector3<f64>,
    previous: Option<&UnitQuaternion<f64>>,
    config: &EstimateConfig,
    turns: &[Matrix3<f64>],
) -> RotationSummary {
    let total: f64 = mixture.iter().sum::<f64>().max(1e-300);
    // the same terms in the same order; a run of equal values (a row of bins on the floor)
    // reuses its term instead of taking the logarithm again
    let mut last = (f64::NAN, 0.0);
    let entropy = -mixture
        .iter()
        .map(|m| m / total)
        .filter(|p| *p > 0.0)
        .map(|p| {
            if p.to_bits() != last.0.to_bits() {
                last = (p, p * p.ln());
            }
            last.1
        })
        .sum::<f64>();
    let k = config.top_k_bins.min(mixture.len()).max(1);
    let idx = top_bins(mixture, k);
    let ray = ray_rotation(mean_position);
    let top: Vec<(UnitQuaternion<f64>, f64)> = idx
        .iter()
        .map(|&b| (ray * grid.rotation(grid.unflat(b)), mixture[b] / total))
        .collect();
    // modes: greedy clustering by angle, heaviest first
    type Cluster = (UnitQuaternion<f64>, Vec<(UnitQuaternion<f64>, f64)>);
    let mut clusters: Vec<Cluster> = Vec::new();
    for (q, m) in &top {
        if let Some(c) = clusters.iter_mut().find(|c| c.0.angle_to(q) < config.mode_merge_rad) {
            c.1.push((*q, *m));
        } else {
            clusters.push((*q, vec![(*q, *m)]));
        }
    }
    let mut modes: Vec<RotationMode> = clusters
        .iter()
        .map(|(seed, members)| {
            let r = average_quaternions(members).unwrap_or(*seed);
            let q = r.quaternion();
            RotationMode {
                rotation_xyzw: [q.i, q.j, q.k, q.w],
                mass: members.iter().map(|m| m.1).sum(),
            }
        })
        .collect();
    modes.sort_by(|a, b| b.mass.total_cmp(&a.mass));
    modes.truncate(config.max_modes);
    let global = modes
        .first()
        .map(|m| {
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                m.rotation_xyzw[3],
                m.rotation_xyzw[0],
                m.rotation_xyzw[1],
                m.rotation_xyzw[2],
            ))
        })
        .unwrap_or_else(UnitQuaternion::identity);
    let best_mass = modes.first().map(|m| m.mass).unwrap_or(0.0);
    let (rotation, jumped) = match previous {
        None => (global, true),
        Some(prev) => {
            let near: Vec<(UnitQuaternion<f64>, f64)> = top
                .iter()
                .filter_map(|(q, m)| {
                    let a = q.angle_to(prev);
                    (a < config.max_angle_rad)
                        .then(|| (*q, m * (-0.5 * a * a / (config.sigma_rad * config.sigma_rad)).exp()))
                })
                .collect();
            let near_mass: f64 = top
                .iter()
                .filter(|(q, _)| q.angle_to(prev) < config.max_angle_rad)
                .map(|(_, m)| m)
                .sum();
            if near.is_empty() || best_mass > config.jump_ratio * near_mass {
                (global, true)
            } else {
                // include the previous estimate itself lightly, so an average never flips sign
                (average_quaternions(&near).unwrap_or(global), false)
            }
        }
    };
    let turns: Vec<UnitQuaternion<f64>> = turns.iter().map(UnitQuaternion::from_matrix).collect();
    let (mut cov, mut surface_cov) = (Matrix3::zeros(), Matrix3::zeros());
    let mut wsum = 0.0;
    for (q, m) in &top {
        let e = rotation.inverse() * q;
        let d = e.scaled_axis();
        cov += d * d.transpose() * *m;
        let ds = turns
            .iter()
            .map(|t| (e * t).scaled_axis())
            .fold(d, |best, v| if v.norm() < best.norm() { v } else { best });
        surface_cov += ds * ds.transpose() * *m;
        wsum += m;
    }
    if wsum > 0.0 {
        cov /= wsum;
        surface_cov /= wsum;
    }
    RotationSummary {
        rotation,
        modes,
        entropy,
        covariance: cov,
        surface_covariance: surface_cov,
        jumped,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The selection of the heaviest bins over the whole grid, as it was.
    fn top_bins_by_selection(mixture: &[f64], k: usize) -> Vec<usize> {
        let mut idx: Vec<usize> = (0..mixture.len()).collect();
        idx.select_nth_unstable_by(k - 1, |a, b| mixture[*b].total_cmp(&mixture[*a]));
        idx.truncate(k);
        idx.sort_by(|a, b| mixture[*b].total_cmp(&mixture[*a]));
        idx
    }

    #[test]
    fn heaviest_bins_are_those_of_the_selection_over_the_grid() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for (active, k) in [(5000, 200), (150, 200), (201, 200), (0, 200), (3000, 1)] {
            // a floor of a few equal values per row, and active bins above it
            let mut m: Vec<f64> = (0..20_000).map(|b| 1e-6 * (1 + b / 5000) as f64).collect();
            for _ in 0..active {
                let b = rng.random_range(0..m.len());
                m[b] = rng.random::<f64>();
            }
            let got = top_bins(&m, k);
            let want = top_bins_by_selection(&m, k);
            assert_eq!(got.len(), k);
            // the same bins in the same order wherever the order is unique; the values agree
            // everywhere
            let gv: Vec<f64> = got.iter().map(|b| m[*b]).collect();
            let wv: Vec<f64> = want.iter().map(|b| m[*b]).collect();
            assert_eq!(gv, wv, "active {active}, k {k}");
            if active >= 2 * k {
                assert_eq!(got, want, "active {active}, k {k}");
            }
        }
        // ties among the heaviest: the selection's own answer
        let mut m = vec![0.5; 1000];
        m[7] = 0.9;
        assert_eq!(top_bins(&m, 10), top_bins_by_selection(&m, 10));
    }

    #[test]
    fn average_of_close_quaternions_is_between_them() {
        let a = UnitQuaternion::from_euler_angles(0.1, 0.0, 0.0);
        let b = UnitQuaternion::from_euler_angles(0.3, 0.0, 0.0);
        // the sign of a quaternion does not matter
        let b_neg = UnitQuaternion::new_unchecked(-b.into_inner());
        let m = average_quaternions(&[(a, 1.0), (b_neg, 1.0)]).unwrap();
        let (r, _, _) = m.euler_angles();
        assert!((r.abs() - 0.2).abs() < 1e-6, "{r}");
    }

    #[test]
    fn a_near_symmetric_turn_widens_the_rotation_but_not_the_surface() {
        let grid = RotationGrid::new(5).unwrap();
        let mut h = vec![1e-9; grid.len()];
        let a = grid.flat(crate::geometry::BinIndex {
            elevation: 12,
            azimuth: 20,
            inplane: 30,
        });
        let ra = grid.rotation(grid.unflat(a));
        let turn = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let b = grid.flat_of(&(ra * turn));
        h[a] = 0.7;
        h[b] = 0.3;
        let pos = Vector3::new(0.0, 0.0, 1.0);
        let cfg = EstimateConfig::default();
        let plain = summarise_rotation(&grid, &h, &pos, None, &cfg, &[]);
        assert_eq!(
            plain.covariance, plain.surface_covariance,
            "no turns: the same covariance"
        );
        let turned = summarise_rotation(&grid, &h, &pos, None, &cfg, &[turn.to_rotation_matrix().into_inner()]);
        assert_eq!(
            turned.covariance, plain.covariance,
            "the reported covariance keeps the turn"
        );
        // the turn's bin lies within half a bin (2.5 degrees per angle) of the turned rotation
        let (wide, surface) = (plain.covariance.trace(), turned.surface_covariance.trace());
        assert!(wide > 1.5, "the turn's 30 % at pi rad: {wide}");
        assert!(surface < 0.01, "folded onto the estimate: {surface}");
    }

    #[test]
    fn summary_finds_two_modes_and_jumps_only_when_the_other_dominates() {
        let grid = RotationGrid::new(15).unwrap();
        let mut h = vec![1e-6; grid.len()];
        let ba = grid.flat(crate::geometry::BinIndex {
            elevation: 4,
            azimuth: 3,
            inplane: 2,
        });
        let bb = grid.flat(crate::geometry::BinIndex {
            elevation: 8,
            azimuth: 12,
            inplane: 10,
        });
        h[ba] = 0.3;
        h[bb] = 0.6;
        let pos = Vector3::new(0.0, 0.0, 1.0);
        let cfg = EstimateConfig::default();
        let s = summarise_rotation(&grid, &h, &pos, None, &cfg, &[]);
        assert!(s.modes.len() >= 2);
        assert!((s.modes[0].mass / s.modes[1].mass - 2.0).abs() < 0.05, "{:?}", s.modes);
        let rb = grid.rotation(grid.unflat(bb));
        assert!(s.rotation.angle_to(&rb) < 1e-6);
        // previous estimate at mode a: b holds only 2x a's mass -> no jump at ratio 2.5
        let ra = grid.rotation(grid.unflat(ba));
        let cfg2 = EstimateConfig { jump_ratio: 2.5, ..cfg };
        let s2 = summarise_rotation(&grid, &h, &pos, Some(&ra), &cfg2, &[]);
        assert!(!s2.jumped && s2.rotation.angle_to(&ra) < 1e-6);
        let s3 = summarise_rotation(
            &grid,
            &h,
            &pos,
            Some(&ra),
            &EstimateConfig { jump_ratio: 1.5, ..cfg },
            &[],
        );
        assert!(s3.jumped && s3.rotation.angle_to(&rb) < 1e-6);
        assert!(s.entropy > 0.0);
    }

    #[test]
    fn the_registration_narrows_the_floor_only_where_it_fixes_the_position() {
        let spread = SpreadConfig {
            bandwidth: 0.3,
            floor_m: 0.01,
            floor_per_m: 0.0,
        };
        let mean = Vector3::new(0.0, 0.0, 1.0);
        // the depth fixes x to a millimetre and says nothing of y and z
        let info = Matrix3::from_diagonal(&Vector3::new(1e6, 0.0, 0.0));
        let extra = spread.extra(&mean, &Matrix3::zeros(), Some(&info)).cov();
        assert!((extra[(0, 0)].sqrt() - 0.001).abs() < 1e-4, "{extra}");
        assert!((extra[(1, 1)].sqrt() - 0.01).abs() < 1e-9 && (extra[(2, 2)].sqrt() - 0.01).abs() < 1e-9);
        // a cloud already wider than the combined floor gets nothing more
        let wide = Matrix3::identity() * 4e-4;
        assert!(spread.extra(&mean, &wide, Some(&info)).is_zero());
        // without the registration: the plain isotropic floor
        match spread.extra(&mean, &Matrix3::zeros(), None) {
            FloorExtra::Isotropic(s) => assert!((s - 0.01).abs() < 1e-12, "{s}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_collapsed_component_reports_at_least_the_spread_floor() {
        use rand::SeedableRng;
        let grid = RotationGrid::new(15).unwrap();
        let tables = GridTables::new(grid);
        let rot = RotationState::uniform(4);
        // camera 0: four copies of one particle 2 m away; camera 1 would be wide already
        let positions = vec![Vector3::new(0.0, 0.0, 2.0); 4];
        let spread = SpreadConfig {
            bandwidth: 0.3,
            floor_m: 0.004,
            floor_per_m: 0.006,
        };
        let set = ParticleSet {
            positions_m: &positions,
            sources: &[0, 0, 0, 0],
            weights: &[0.25; 4],
            rot: &rot,
            tables: &tables,
            reference_from_hist: Pose::identity(),
            spread,
            floor_information: None,
        };
        let floor = 0.004 + 0.006 * 2.0;
        let c = &set.components(&["cam".to_string()])[0];
        for (k, row) in c.covariance_m2.iter().enumerate() {
            assert!((row[k] - floor * floor).abs() < 1e-12, "{:?}", c.covariance_m2);
        }
        let (cov, std) = set.translation_covariance();
        assert!((cov[(0, 0)] - floor * floor).abs() < 1e-12 && (std - floor * 3f64.sqrt()).abs() < 1e-9);
        // the samples carry the floor too: their spread matches it
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let poses = set.sample_poses(4000, &mut rng).poses;
        let var_x = poses.iter().map(|p| p.translation.x.powi(2)).sum::<f64>() / poses.len() as f64;
        assert!((var_x.sqrt() / floor - 1.0).abs() < 0.05, "{} vs {floor}", var_x.sqrt());
        // a component already wider than the floor is left as it is
        assert_eq!(
            spread.extra_std_m(&Vector3::new(0.0, 0.0, 2.0), &(Matrix3::identity() * 1e-3)),
            0.0
        );
    }

    #[test]
    fn samples_follow_particle_weights_and_histograms() {
        use rand::SeedableRng;
        let grid = RotationGrid::new(15).unwrap();
        let tables = GridTables::new(grid);
        let nb = grid.len();
        let n = 3;
        // particle 0: bins 5 (1/4) and nb-1 (3/4, the last chunk's last bin); particle 1:
        // bin 2000 only; particle 2: weight 0
        let mut hist = vec![0f32; nb * n];
        hist[5 * n] = 0.25;
        hist[(nb - 1) * n] = 0.75;
        hist[2000 * n + 1] = 1.0;
        hist[7 * n + 2] = 1.0;
        let positions = vec![
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.1, 0.0, 1.0),
            Vector3::new(0.0, 0.2, 1.0),
        ];
        // a dense state (every bin active, no floor) and a sparse one with the same histograms
        let dense = RotationState {
            active: (0..nb as u32).collect(),
            values: hist.clone(),
            floors: vec![0.0; n],
            column_of: vec![0, 1, 2],
        };
        let mut sparse = dense.clone();
        sparse.prune(
            &tables,
            &crate::tracker::sparse::PruneRule {
                floor_rel: 1e-6,
                margin: 1.0,
                tail_mass: 0.0,
                max_active: usize::MAX,
            },
        );
        assert_eq!(sparse.active, vec![5, 7, 2000, nb as u32 - 1]);
        for rot in [&dense, &sparse] {
            let set = ParticleSet {
                positions_m: &positions,
                sources: &[0, 0, 0],
                weights: &[0.6, 0.4, 0.0],
                rot,
                tables: &tables,
                reference_from_hist: Pose::identity(),
                spread: SpreadConfig::NONE,
                floor_information: None,
            };
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
            let s = set.sample_poses(4000, &mut rng);
            // each sample lies inside (jittered within) one of its particle's bins
            let mut counts = std::collections::BTreeMap::<(usize, usize), usize>::new();
            for pose in &s.poses {
                let p = positions
                    .iter()
                    .position(|q| (q - pose.translation.vector).norm() < 1e-12)
                    .unwrap();
                let allo = ray_rotation(&pose.translation.vector).inverse() * pose.rotation;
                let (b, angle) = [5, nb - 1, 2000, 7]
                    .into_iter()
                    .map(|b| (b, grid.rotation(grid.unflat(b)).angle_to(&allo)))
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap();
                assert!(angle < 20f64.to_radians(), "sample {angle} rad from its bin");
                *counts.entry((p, b)).or_default() += 1;
            }
            let share = |k: (usize, usize)| *counts.get(&k).unwrap_or(&0) as f64 / 4000.0;
            assert!((share((0, 5)) - 0.15).abs() < 0.03, "{counts:?}");
            assert!((share((0, nb - 1)) - 0.45).abs() < 0.03, "{counts:?}");
            assert!((share((1, 2000)) - 0.4).abs() < 0.03, "{counts:?}");
            assert_eq!(
                counts.keys().filter(|k| k.0 == 2).count(),
                0,
                "weightless particle drawn"
            );
            assert_eq!(counts.values().sum::<usize>(), 4000);
        }
    }
}
