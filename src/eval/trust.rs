//! Where the truth lies in the tracked distribution: the highest-density test.
//!
//! For a density `f` and a mass `q`, the highest-density region `R_q = {x : f(x) >= c_q}` is
//! the smallest region holding mass `q`. The truth is in `R_q` when the mass at densities
//! strictly above `f(truth)` is below `q`. Both that mass and the region's volume are
//! estimated from samples `x_i ~ f`: the mass above is the share of samples with
//! `f(x_i) > f(truth)`, and `volume(R_q) = E_f[1{x in R_q} / f(x)]`, i.e. the mean of
//! `1 / f(x_i)` over the `q N` densest samples.
//!
//! Ties (a piecewise-constant histogram, a uniform distribution) are broken at random: the
//! truth is in `R_q` with probability `clamp((q - above) / tied, 0, 1)`, so a uniform
//! distribution scores exactly `q` on coverage, and its region's volume (`q` of the space)
//! shows that it knows nothing.
//!
//! - rotation: densities relative to the uniform distribution on SO(3) (each particle reads
//!   its own bin, mass over the bin's share of SO(3)), averaged over the object's exact
//!   symmetries (`ParticleSet::rotation_densities`); volumes as a fraction of SO(3)
//!   (times [`SO3_VOLUME_SR_RAD`] for steradian-radians);
//! - translation: the mixture of one Gaussian per camera component ([`GaussianMixture`]);
//!   volumes in m^3.

use crate::tracker::Component;
use nalgebra::{Matrix3, Vector3};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Volume of SO(3) in the Euler measure `sin(elevation) d elevation d azimuth d in-plane`
/// (steradian-radians): 2 x 2 pi x 2 pi = 8 pi^2.
pub const SO3_VOLUME_SR_RAD: f64 = 8.0 * std::f64::consts::PI * std::f64::consts::PI;

/// Floor added to each component's covariance diagonal (m^2): a component whose particles
/// collapsed onto one point still has a density (0.1 mm standard deviation).
pub const COVARIANCE_FLOOR_M2: f64 = 1e-8;

/// Relative difference under which two densities count as equal (a tie): the histograms are
/// f32, so equal masses read back equal only to about 1e-7.
const TIE_RELATIVE: f64 = 1e-5;

/// The truth's rank among samples of the distribution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HpdRank {
    /// Share of the mass at densities strictly above the truth's.
    pub above: f64,
    /// Share of the mass at the truth's density.
    pub tied: f64,
}

impl HpdRank {
    /// From the truth's density and the densities of samples of the distribution; `None`
    /// without samples or with a non-finite truth density.
    pub fn from_samples(truth_density: f64, sample_densities: &[f64]) -> Option<Self> {
        if sample_densities.is_empty() || !truth_density.is_finite() {
            return None;
        }
        let tol = TIE_RELATIVE * truth_density.abs();
        let (mut above, mut tied) = (0usize, 0usize);
        for &d in sample_densities {
            if (d - truth_density).abs() <= tol {
                tied += 1;
            } else if d > truth_density {
                above += 1;
            }
        }
        let n = sample_densities.len() as f64;
        Some(Self {
            above: above as f64 / n,
            tied: tied as f64 / n,
        })
    }

    /// Probability that the truth lies in the highest-density region of mass `q` (ties broken
    /// at random).
    pub fn truth_in(&self, q: f64) -> f64 {
        if self.tied > 0.0 {
            ((q - self.above) / self.tied).clamp(0.0, 1.0)
        } else if self.above < q {
            1.0
        } else {
            0.0
        }
    }
}

/// Volume of the highest-density region of mass `q` from densities of samples of the
/// distribution (in the units the densities are per); `None` without positive densities.
pub fn hpd_volume(q: f64, sample_densities: &[f64]) -> Option<f64> {
    let mut d: Vec<f64> = sample_densities
        .iter()
        .copied()
        .filter(|v| *v > 0.0 && v.is_finite())
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(|a, b| b.total_cmp(a));
    let n = sample_densities.len() as f64;
    let take = (q.clamp(0.0, 1.0) * n).min(d.len() as f64);
    let whole = take.floor() as usize;
    let mut v: f64 = d[..whole].iter().map(|f| 1.0 / f).sum();
    if whole < d.len() {
        v += (take - whole as f64) / d[whole];
    }
    Some(v / n)
}

/// The truth's place in one distribution: in the 50 % and 90 % highest-density regions
/// (probabilities, ties broken at random) and the 90 % region's volume.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RegionScore {
    pub truth_in_50: f64,
    pub truth_in_90: f64,
    /// In the density's units (a fraction of SO(3) for rotations, m^3 for positions).
    pub volume_90: f64,
}

impl RegionScore {
    pub fn from_samples(truth_density: f64, sample_densities: &[f64]) -> Option<Self> {
        let rank = HpdRank::from_samples(truth_density, sample_densities)?;
        Some(Self {
            truth_in_50: rank.truth_in(0.5),
            truth_in_90: rank.truth_in(0.9),
            volume_90: hpd_volume(0.9, sample_densities)?,
        })
    }
}

/// One Gaussian per camera component of the translation (the tracker's Eq. 2 mixture).
#[derive(Debug, Clone)]
pub struct GaussianMixture {
    components: Vec<Gaussian>,
}

/// One weighted component.
#[derive(Debug, Clone)]
struct Gaussian {
    /// Normalised over the mixture.
    weight: f64,
    mean_m: Vector3<f64>,
    /// Lower Cholesky factor of the covariance.
    chol_l: Matrix3<f64>,
    inverse: Matrix3<f64>,
    /// ln of the density's normaliser.
    log_norm: f64,
}

impl GaussianMixture {
    /// From the tracker's components (each covariance floored by [`COVARIANCE_FLOOR_M2`]);
    /// `None` when no component has weight.
    pub fn from_components(components: &[Component]) -> Option<Self> {
        let total: f64 = components
            .iter()
            .map(|c| c.weight)
            .filter(|w| w.is_finite() && *w > 0.0)
            .sum();
        if total <= 0.0 {
            return None;
        }
        let mut out = Vec::new();
        for c in components.iter().filter(|c| c.weight.is_finite() && c.weight > 0.0) {
            let cov = Matrix3::from_fn(|r, k| c.covariance_m2[r][k]) + Matrix3::identity() * COVARIANCE_FLOOR_M2;
            let cov = 0.5 * (cov + cov.transpose());
            let chol = cov.cholesky()?;
            let l = chol.l();
            let inv = chol.inverse();
            let log_det = 2.0 * (0..3).map(|i| l[(i, i)].ln()).sum::<f64>();
            let log_norm = -0.5 * (3.0 * (2.0 * std::f64::consts::PI).ln() + log_det);
            out.push(Gaussian {
                weight: c.weight / total,
                mean_m: Vector3::from(c.mean_m),
                chol_l: l,
                inverse: inv,
                log_norm,
            });
        }
        Some(Self { components: out })
    }

    /// Density (per m^3) at `x`.
    pub fn density(&self, x: &Vector3<f64>) -> f64 {
        self.components
            .iter()
            .map(|g| {
                let d = x - g.mean_m;
                g.weight * (g.log_norm - 0.5 * d.dot(&(g.inverse * d))).exp()
            })
            .sum()
    }

    /// `n` draws: a component by weight, then its Gaussian.
    pub fn sample(&self, n: usize, rng: &mut impl Rng) -> Vec<Vector3<f64>> {
        (0..n)
            .map(|_| {
                let u: f64 = rng.random();
                let mut acc = 0.0;
                let mut pick = self.components.len() - 1;
                for (k, c) in self.components.iter().enumerate() {
                    acc += c.weight;
                    if u < acc {
                        pick = k;
                        break;
                    }
                }
                let g = &self.components[pick];
                let z = Vector3::from_fn(|_, _| StandardNormal.sample(rng));
                g.mean_m + g.chol_l * z
            })
            .collect()
    }

    /// The truth's place: its density against `n` samples' densities.
    pub fn region_score(&self, truth_m: &Vector3<f64>, n: usize, rng: &mut impl Rng) -> Option<RegionScore> {
        let samples = self.sample(n, rng);
        let densities: Vec<f64> = samples.iter().map(|x| self.density(x)).collect();
        RegionScore::from_samples(self.density(truth_m), &densities)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use rand::SeedableRng;

    fn rng() -> rand_chacha::ChaCha8Rng {
        rand_chacha::ChaCha8Rng::seed_from_u64(7)
    }

    #[test]
    fn uniform_density_scores_the_mass_and_a_volume_of_the_mass() {
        let samples = vec![1.0; 1000];
        let r = RegionScore::from_samples(1.0, &samples).expect("samples");
        assert_relative_eq!(r.truth_in_50, 0.5, epsilon = 1e-12);
        assert_relative_eq!(r.truth_in_90, 0.9, epsilon = 1e-12);
        assert_relative_eq!(r.volume_90, 0.9, epsilon = 1e-12);
    }

    #[test]
    fn point_mass_on_the_truth_and_on_a_flip() {
        // A distribution with density 100 on 1 % of the space (one bin, the rest zero). The
        // truth inside that bin ties with every sample: the regions are parts of the bin
        // drawn at random, so it is in R_q with probability q, at the smallest volume.
        let samples = vec![100.0; 500];
        let on = RegionScore::from_samples(100.0, &samples).expect("samples");
        assert_relative_eq!(on.truth_in_50, 0.5, epsilon = 1e-12);
        assert_relative_eq!(on.truth_in_90, 0.9, epsilon = 1e-12);
        assert_relative_eq!(on.volume_90, 0.009, epsilon = 1e-12);
        let off = RegionScore::from_samples(0.0, &samples).expect("samples");
        assert_eq!((off.truth_in_50, off.truth_in_90), (0.0, 0.0));
        assert_relative_eq!(off.volume_90, 0.009, epsilon = 1e-12);
    }

    #[test]
    fn two_modes_rank_the_truth_by_its_mode() {
        // 70 % of the mass at density 70 (volume 0.01), 30 % at density 30 (volume 0.01).
        let mut samples = vec![70.0; 700];
        samples.extend(vec![30.0; 300]);
        let major = RegionScore::from_samples(70.0, &samples).expect("samples");
        // Ties inside the major mode: in R_50 with probability 0.5 / 0.7.
        assert_relative_eq!(major.truth_in_50, 0.5 / 0.7, epsilon = 1e-12);
        assert_eq!(major.truth_in_90, 1.0);
        let minor = RegionScore::from_samples(30.0, &samples).expect("samples");
        assert_eq!(minor.truth_in_50, 0.0);
        assert_relative_eq!(minor.truth_in_90, (0.9 - 0.7) / 0.3, epsilon = 1e-12);
        // R_90: all of the major mode (0.01) and two thirds of the minor (0.01 * 2/3).
        assert_relative_eq!(major.volume_90, 0.01 + 0.01 * 2.0 / 3.0, epsilon = 1e-12);
        assert!(HpdRank::from_samples(1.0, &[]).is_none());
    }

    fn component(mean: [f64; 3], std_m: f64, weight: f64) -> Component {
        let v = std_m * std_m;
        Component {
            camera: "c".into(),
            weight,
            mean_m: mean,
            covariance_m2: [[v, 0.0, 0.0], [0.0, v, 0.0], [0.0, 0.0, v]],
        }
    }

    #[test]
    fn one_gaussian_has_the_chi_square_region() {
        let g = GaussianMixture::from_components(&[component([0.0, 0.0, 1.0], 0.01, 1.0)]).expect("mixture");
        let mut r = rng();
        // At the mean: the densest point, inside every region.
        let at_mean = g
            .region_score(&Vector3::new(0.0, 0.0, 1.0), 4000, &mut r)
            .expect("score");
        assert_eq!((at_mean.truth_in_50, at_mean.truth_in_90), (1.0, 1.0));
        // The 90 % region of a 3-D Gaussian is the ball of radius sqrt(chi2_3(0.9)) = 2.5003
        // standard deviations: volume 4/3 pi (2.5003 sigma)^3.
        let expect = 4.0 / 3.0 * std::f64::consts::PI * (2.5003f64 * 0.01).powi(3);
        assert_relative_eq!(at_mean.volume_90, expect, max_relative = 0.08);
        // 2 sigma is inside R_90 (2.50 sigma) and outside R_50 (1.54 sigma); 3 sigma outside both.
        let two = g
            .region_score(&Vector3::new(0.02, 0.0, 1.0), 4000, &mut r)
            .expect("score");
        assert_eq!((two.truth_in_50, two.truth_in_90), (0.0, 1.0));
        let three = g
            .region_score(&Vector3::new(0.0, 0.03, 1.0), 4000, &mut r)
            .expect("score");
        assert_eq!((three.truth_in_50, three.truth_in_90), (0.0, 0.0));
        // Coverage over draws from the distribution itself is about q.
        let truths = g.sample(2000, &mut r);
        let inside: f64 = truths
            .iter()
            .map(|t| g.region_score(t, 400, &mut r).expect("score").truth_in_90)
            .sum::<f64>()
            / 2000.0;
        assert!((inside - 0.9).abs() < 0.03, "{inside}");
    }

    #[test]
    fn two_components_and_a_collapsed_one() {
        // Two far components, 90 / 10: the heavy one is denser than the light one's peak
        // within r^2 < 2 ln 9 sigma^2, which holds 0.9 x chi2_3(4.39) = 0.70 of the mass: a
        // truth at the light one's mean is in R_90, not in R_50.
        let g = GaussianMixture::from_components(&[
            component([0.0, 0.0, 1.0], 0.01, 0.9),
            component([0.5, 0.0, 1.0], 0.01, 0.1),
        ])
        .expect("mixture");
        let mut r = rng();
        let light = g
            .region_score(&Vector3::new(0.5, 0.0, 1.0), 4000, &mut r)
            .expect("score");
        assert_eq!((light.truth_in_50, light.truth_in_90), (0.0, 1.0));
        // A collapsed component still has a (tiny) region, and the truth 1 cm away is outside.
        let c = GaussianMixture::from_components(&[component([0.0, 0.0, 1.0], 0.0, 1.0)]).expect("floored");
        let s = c
            .region_score(&Vector3::new(0.01, 0.0, 1.0), 1000, &mut r)
            .expect("score");
        assert_eq!(s.truth_in_90, 0.0);
        assert!(s.volume_90 < 1e-10, "{}", s.volume_90);
        assert!(GaussianMixture::from_components(&[component([0.0; 3], 0.01, 0.0)]).is_none());
    }

    /// The rotation test end to end on one particle's hand-made histogram (coarse grid, the
    /// particle on the optical axis, so allocentric = egocentric).
    mod rotation {
        use super::*;
        use crate::geometry::{BinIndex, Pose, RotationGrid};
        use crate::symmetry::Symmetries;
        use crate::tracker::bins::GridTables;
        use crate::tracker::estimate::ParticleSet;
        use nalgebra::UnitQuaternion;
        use std::f64::consts::PI;

        struct Case {
            tables: GridTables,
            rot: crate::tracker::sparse::RotationState,
            positions: Vec<Vector3<f64>>,
        }

        impl Case {
            fn new(fill: impl Fn(&GridTables, usize) -> f32) -> Self {
                let tables = GridTables::new(RotationGrid::new(30).expect("grid"));
                let hist: Vec<f32> = (0..tables.grid.len()).map(|b| fill(&tables, b)).collect();
                let rot = crate::tracker::sparse::RotationState::from_column(&tables, &hist, 1);
                Self {
                    tables,
                    rot,
                    positions: vec![Vector3::new(0.0, 0.0, 1.0)],
                }
            }

            fn set(&self) -> ParticleSet<'_> {
                ParticleSet {
                    positions_m: &self.positions,
                    sources: &[0],
                    weights: &[1.0],
                    rot: &self.rot,
                    tables: &self.tables,
                    reference_from_hist: Pose::identity(),
                    spread: crate::tracker::estimate::SpreadConfig::NONE,
                    floor_information: None,
                }
            }

            /// (truth's log density, region score) modulo `orbit`.
            fn score(&self, truth: &UnitQuaternion<f64>, orbit: &[UnitQuaternion<f64>]) -> (f64, RegionScore) {
                let set = self.set();
                let mut r = rng();
                let samples = set.sample_poses(2000, &mut r);
                let mut rotations = vec![*truth];
                rotations.extend(samples.poses.iter().map(|p| p.rotation));
                let d = set.rotation_densities(&rotations, orbit);
                (
                    d[0].max(1e-300).ln(),
                    RegionScore::from_samples(d[0], &d[1..]).expect("samples"),
                )
            }

            fn volume(&self, b: usize) -> f64 {
                let g = self.tables.grid;
                self.tables.elevation_volume[b / (g.n_azimuth() * g.n_inplane())]
            }
        }

        fn bin(grid: &RotationGrid, e: usize, a: usize, t: usize) -> usize {
            grid.flat(BinIndex {
                elevation: e,
                azimuth: a,
                inplane: t,
            })
        }

        fn truth(case: &Case) -> (usize, UnitQuaternion<f64>) {
            let b = bin(&case.tables.grid, 2, 3, 4);
            (b, case.tables.grid.rotation(case.tables.grid.unflat(b)))
        }

        #[test]
        fn uniform_knows_nothing() {
            let case = Case::new(|t, b| case_volume(t, b) as f32);
            let (_, r) = truth(&case);
            let (log_density, s) = case.score(&r, &[]);
            assert!(log_density.abs() < 1e-5, "uniform's density is 1: {log_density}");
            assert_relative_eq!(s.truth_in_50, 0.5, epsilon = 1e-9);
            assert_relative_eq!(s.truth_in_90, 0.9, epsilon = 1e-9);
            assert_relative_eq!(s.volume_90, 0.9, max_relative = 1e-4);
        }

        fn case_volume(t: &GridTables, b: usize) -> f64 {
            t.elevation_volume[b / (t.grid.n_azimuth() * t.grid.n_inplane())]
        }

        #[test]
        fn point_mass_on_the_truth() {
            let b_truth = bin(&RotationGrid::new(30).expect("grid"), 2, 3, 4);
            let case = Case::new(|_, b| (b == b_truth) as u8 as f32);
            let (_, r) = truth(&case);
            let (log_density, s) = case.score(&r, &[]);
            assert_relative_eq!(log_density, -case.volume(b_truth).ln(), epsilon = 1e-5);
            assert!(log_density > 0.0, "not confidently wrong");
            // Every sample ties with the truth (one flat bin): in R_q with probability q,
            // in the smallest region there is.
            assert_relative_eq!(s.truth_in_90, 0.9, epsilon = 1e-9);
            assert_relative_eq!(s.volume_90, 0.9 * case.volume(b_truth), max_relative = 1e-4);
        }

        #[test]
        fn point_mass_on_a_flip_is_wrong_unless_the_flip_is_an_exact_symmetry() {
            let grid = RotationGrid::new(30).expect("grid");
            let truth_rot = grid.rotation(grid.unflat(bin(&grid, 2, 3, 4)));
            let bx = Symmetries::exact(&crate::mesh::builtin("box").expect("builtin"));
            for (turn, exact) in [
                (UnitQuaternion::from_axis_angle(&Vector3::y_axis(), PI), false),
                (UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI), true),
            ] {
                let b_flip = grid.flat_of(&(truth_rot * turn));
                let case = Case::new(|_, b| (b == b_flip) as u8 as f32);
                // Without symmetries: the truth has no mass, below uniform, outside every region.
                let (log_density, s) = case.score(&truth_rot, &[]);
                assert!(log_density < -100.0, "{log_density}");
                assert_eq!((s.truth_in_50, s.truth_in_90), (0.0, 0.0));
                // Modulo the box's exact symmetries (its turn about x only).
                let (log_density, s) = case.score(&truth_rot, &bx.orbit(12));
                if exact {
                    assert!(log_density > 0.0, "the x turn is no error: {log_density}");
                    assert!(s.truth_in_90 > 0.5, "{s:?}");
                } else {
                    assert!(log_density < -100.0, "the y turn is one: {log_density}");
                    assert_eq!(s.truth_in_90, 0.0);
                }
            }
        }

        #[test]
        fn two_modes() {
            let grid = RotationGrid::new(30).expect("grid");
            let (b_major, b_minor) = (bin(&grid, 2, 3, 4), bin(&grid, 2, 9, 1));
            let case = Case::new(|_, b| {
                if b == b_major {
                    0.7
                } else if b == b_minor {
                    0.3
                } else {
                    0.0
                }
            });
            let v = case.volume(b_major);
            let major = grid.rotation(grid.unflat(b_major));
            let minor = grid.rotation(grid.unflat(b_minor));
            let (_, s) = case.score(&major, &[]);
            // 2000 samples: the mode shares are drawn, so allow their sampling error.
            assert_relative_eq!(s.truth_in_50, 0.5 / 0.7, epsilon = 0.04);
            assert_eq!(s.truth_in_90, 1.0);
            assert_relative_eq!(s.volume_90, v + 0.2 / 0.3 * v, max_relative = 0.06);
            let (log_density, s) = case.score(&minor, &[]);
            assert_relative_eq!(log_density, (0.3 / v).ln(), epsilon = 1e-5);
            assert_eq!(s.truth_in_50, 0.0);
            assert_relative_eq!(s.truth_in_90, 0.2 / 0.3, epsilon = 0.08);
        }
    }
}
