//! The rotation grid's tables ([`crate::geometry::RotationGrid`]): Euler angles and the flat
//! bin of a rotation matrix, every bin's rotation and volume, and the *bin maps* that pull a
//! histogram from one frame into another.
//!
//! Histograms are stored *bin-major, particle-minor*: value of particle `p` at flat bin `b` is
//! `h[b * n_particles + p]`. This is the layout the matching GEMM produces (`Q^T C`, column-major
//! `n_particles x n_bins`), it makes the pull re-binning a gather of contiguous particle rows,
//! and it lets the blur vectorise across particles. The kernels over that layout are in
//! [`crate::tracker::kernels`], the fused measurement update in
//! [`crate::tracker::observation::fuse`].

use crate::geometry::RotationGrid;
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use std::f64::consts::PI;

/// The hot kernels moved to [`crate::tracker::kernels`]; these paths stay for callers.
pub use crate::tracker::kernels::{
    add_pulled, blur, blur_reference, fast_exp, gaussian_kernel, gemm_nt, match_best, pull, with_wide_simd,
};

/// Euler angles (elevation, azimuth, in-plane) of a `camera_from_object` rotation matrix, the
/// inverse of [`crate::geometry::euler_to_rotation`] computed directly from the matrix:
/// the third row is `-d` (the viewing direction in the object frame), and the in-plane angle
/// is the angle of `R * x_c(a)` in the camera's x-y plane.
#[inline]
pub fn euler_of_matrix(m: &Matrix3<f64>) -> (f64, f64, f64) {
    let d = Vector3::new(-m[(2, 0)], -m[(2, 1)], -m[(2, 2)]);
    let e = d.z.clamp(-1.0, 1.0).acos();
    let a = if d.x.abs() < 1e-12 && d.y.abs() < 1e-12 {
        0.0
    } else {
        d.y.atan2(d.x).rem_euclid(2.0 * PI)
    };
    let (sa, ca) = a.sin_cos();
    // R * x_c with x_c = (-sin a, cos a, 0)
    let rx = -m[(0, 0)] * sa + m[(0, 1)] * ca;
    let ry = -m[(1, 0)] * sa + m[(1, 1)] * ca;
    let t = ry.atan2(rx).rem_euclid(2.0 * PI);
    (e, a, t)
}

/// Flat bin index of a `camera_from_object` rotation matrix (nearest centre per angle).
///
/// Bin maps call this for every matched bin of every moving view at every step, where the
/// library's `acos` and `atan2` cost more than the rest of the map: angles within a hair of a
/// bin edge take that exact path, every other one a series accurate to 1e-10 rad, which
/// rounds to the same bin (equal to [`flat_of_matrix_exact`] for every input).
#[inline]
pub fn flat_of_matrix(grid: &RotationGrid, m: &Matrix3<f64>) -> usize {
    fast_flat_of_matrix(grid, m).unwrap_or_else(|| flat_of_matrix_exact(grid, m))
}

/// How close (in bins) an angle from the series may come to a rounding edge before the exact
/// functions decide (the series' error is below 1e-8 bins on a 1-degree grid).
const EDGE_MARGIN_BINS: f64 = 1e-6;

/// `atan(u)` for `|u| <= tan(pi / 8)` by its Taylor series to `u^23` (error below 1.2e-11).
#[inline(always)]
fn atan_small(u: f64) -> f64 {
    let u2 = u * u;
    let mut p = -1.0 / 23.0;
    for k in (0..11).rev() {
        let c = 1.0 / (2 * k + 1) as f64;
        p = if k % 2 == 0 { c } else { -c } + u2 * p;
    }
    u * p
}

/// `atan2(y, x)` within 1.2e-11 rad, `None` where signs of zero would matter.
#[inline(always)]
fn atan2_series(y: f64, x: f64) -> Option<f64> {
    let (ax, ay) = (x.abs(), y.abs());
    let (num, den) = if ay > ax { (ax, ay) } else { (ay, ax) };
    if den == 0.0 || !den.is_finite() {
        return None;
    }
    let r = num / den;
    const TAN_PI_8: f64 = 0.414_213_562_373_095_03;
    let mut a = if r > TAN_PI_8 {
        std::f64::consts::FRAC_PI_4 + atan_small((r - 1.0) / (r + 1.0))
    } else {
        atan_small(r)
    };
    if ay > ax {
        a = std::f64::consts::FRAC_PI_2 - a;
    }
    if x < 0.0 {
        a = PI - a;
    }
    Some(if y < 0.0 { -a } else { a })
}

/// The nearest bin index of `angle / step`, `None` within [`EDGE_MARGIN_BINS`] of an edge.
#[inline(always)]
fn round_clear_of_edge(x: f64) -> Option<f64> {
    let r = x.round();
    ((x - r).abs() < 0.5 - EDGE_MARGIN_BINS).then_some(r)
}

/// [`flat_of_matrix`] from the series; `None` where an angle lies near a bin edge.
#[inline]
fn fast_flat_of_matrix(grid: &RotationGrid, m: &Matrix3<f64>) -> Option<usize> {
    let s = grid.step_rad();
    let (ne, na, ni) = (grid.n_elevation(), grid.n_azimuth(), grid.n_inplane());
    let d = Vector3::new(-m[(2, 0)], -m[(2, 1)], -m[(2, 2)]);
    let z = d.z.clamp(-1.0, 1.0);
    let e = atan2_series(((1.0 - z) * (1.0 + z)).sqrt(), z)?;
    let (a, sa, ca) = if d.x.abs() < 1e-12 && d.y.abs() < 1e-12 {
        (0.0, 0.0, 1.0)
    } else {
        let h = d.x.hypot(d.y);
        let a = atan2_series(d.y, d.x)?;
        (if a < 0.0 { a + 2.0 * PI } else { a }, d.y / h, d.x / h)
    };
    let rx = -m[(0, 0)] * sa + m[(0, 1)] * ca;
    let ry = -m[(1, 0)] * sa + m[(1, 1)] * ca;
    let t = atan2_series(ry, rx)?;
    let t = if t < 0.0 { t + 2.0 * PI } else { t };
    let ei = (round_clear_of_edge(e / s)? as isize).clamp(0, ne as isize - 1) as usize;
    let ai = (round_clear_of_edge(a / s)? as isize).rem_euclid(na as isize) as usize;
    let ti = (round_clear_of_edge(t / s)? as isize).rem_euclid(ni as isize) as usize;
    Some((ei * na + ai) * ni + ti)
}

/// [`flat_of_matrix`] through the library's `acos` and `atan2`.
pub fn flat_of_matrix_exact(grid: &RotationGrid, m: &Matrix3<f64>) -> usize {
    let (e, a, t) = euler_of_matrix(m);
    let s = grid.step_rad();
    let ne = grid.n_elevation();
    let na = grid.n_azimuth();
    let ni = grid.n_inplane();
    let ei = ((e / s).round() as isize).clamp(0, ne as isize - 1) as usize;
    let ai = ((a / s).round() as isize).rem_euclid(na as isize) as usize;
    let ti = ((t / s).round() as isize).rem_euclid(ni as isize) as usize;
    (ei * na + ai) * ni + ti
}

/// Per-grid tables computed once: the rotation matrix of every bin centre and the SO(3)
/// volume of every bin.
#[derive(Debug, Clone)]
pub struct GridTables {
    pub grid: RotationGrid,
    /// Row-major 3x3 matrix per bin (f32 to halve the memory: 7 MB for the full grid).
    pub rotations: Vec<[f32; 9]>,
    /// Relative volume of one bin of each elevation row (sums to 1 over all bins).
    pub elevation_volume: Vec<f64>,
}

impl GridTables {
    pub fn new(grid: RotationGrid) -> Self {
        let rotations: Vec<[f32; 9]> = (0..grid.len())
            .into_par_iter()
            .map(|b| {
                let r = grid.rotation(grid.unflat(b)).to_rotation_matrix();
                let m = r.matrix();
                let mut out = [0f32; 9];
                for row in 0..3 {
                    for col in 0..3 {
                        out[row * 3 + col] = m[(row, col)] as f32;
                    }
                }
                out
            })
            .collect();
        Self {
            grid,
            rotations,
            elevation_volume: grid.elevation_volume_weights(),
        }
    }

    /// Volume of flat bin `b`.
    #[inline]
    pub fn volume(&self, b: usize) -> f64 {
        self.elevation_volume[b / (self.grid.n_azimuth() * self.grid.n_inplane())]
    }

    pub fn matrix(&self, b: usize) -> Matrix3<f64> {
        let r = &self.rotations[b];
        Matrix3::new(
            r[0] as f64,
            r[1] as f64,
            r[2] as f64,
            r[3] as f64,
            r[4] as f64,
            r[5] as f64,
            r[6] as f64,
            r[7] as f64,
            r[8] as f64,
        )
    }

    /// The pull map of a rotation `q`: `map[b] = bin(q * R_b)`. Reference bin `b` reads the
    /// other histogram at `map[b]`. For fusion, `q = R_ray_v^-1 * v_from_reference * R_ray_ref`;
    /// for the prior after the reference camera moved, `q = R_ray_old^-1 * old_from_new *
    /// R_ray_new`.
    pub fn pull_map(&self, q: &UnitQuaternion<f64>) -> Vec<u32> {
        let qm = q.to_rotation_matrix().into_inner();
        let grid = self.grid;
        (0..self.rotations.len())
            .into_par_iter()
            .with_min_len(4096)
            .map(|b| flat_of_matrix(&grid, &(qm * self.matrix(b))) as u32)
            .collect()
    }
}
#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{euler_to_rotation, rotation_to_euler};
    use rand::{Rng, SeedableRng};

    fn random_rotation(rng: &mut impl Rng) -> UnitQuaternion<f64> {
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
        ))
    }

    #[test]
    fn binning_by_series_is_the_exact_binning() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
        for step in [5, 10, 15] {
            let grid = RotationGrid::new(step).unwrap();
            let s = grid.step_rad();
            let mut near_edge = 0;
            for i in 0..200_000 {
                // random rotations, and rotations with an angle on or next to a bin edge
                let m = if i % 4 == 0 {
                    let k = |r: &mut rand_chacha::ChaCha8Rng, n: usize| (r.random_range(0..n) as f64 + 0.5) * s;
                    let wobble = [0.0, 1e-12, -1e-12, 1e-9, -1e-9][i % 5];
                    let (e, a, t) = (
                        k(&mut rng, grid.n_elevation() - 1) + wobble,
                        k(&mut rng, grid.n_azimuth()),
                        k(&mut rng, grid.n_inplane()) - wobble,
                    );
                    *euler_to_rotation(e, a, t).to_rotation_matrix().matrix()
                } else {
                    *random_rotation(&mut rng).to_rotation_matrix().matrix()
                };
                near_edge += usize::from(fast_flat_of_matrix(&grid, &m).is_none());
                assert_eq!(flat_of_matrix(&grid, &m), flat_of_matrix_exact(&grid, &m), "{m}");
            }
            // the exact path decides the angles on the edges, and few others
            assert!((10_000..60_000).contains(&near_edge), "{near_edge}");
        }
        // the poles and the axes (zero components)
        let grid = RotationGrid::new(5).unwrap();
        for q in [
            UnitQuaternion::identity(),
            UnitQuaternion::from_euler_angles(PI, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, PI / 2.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, -PI / 2.0),
            UnitQuaternion::from_euler_angles(PI / 2.0, PI / 2.0, PI),
        ] {
            let m = *q.to_rotation_matrix().matrix();
            assert_eq!(flat_of_matrix(&grid, &m), flat_of_matrix_exact(&grid, &m), "{m}");
        }
        for u in [-0.4142, -0.41, -1e-3, 0.0, 0.2, 0.4142] {
            assert!((atan_small(u) - f64::atan(u)).abs() < 1.2e-11);
        }
    }

    #[test]
    fn fast_euler_matches_geometry() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for _ in 0..500 {
            let r = random_rotation(&mut rng);
            let (e, a, t) = euler_of_matrix(r.to_rotation_matrix().matrix());
            let back = euler_to_rotation(e, a, t);
            assert!(back.angle_to(&r) < 1e-9);
            let (e2, a2, t2) = rotation_to_euler(&r);
            assert!((e - e2).abs() < 1e-9 && (a - a2).abs() < 1e-9);
            let dt = (t - t2).abs();
            assert!(dt < 1e-9 || (dt - 2.0 * PI).abs() < 1e-9);
        }
        let grid = RotationGrid::new(10).unwrap();
        for _ in 0..200 {
            let r = random_rotation(&mut rng);
            let m = r.to_rotation_matrix().into_inner();
            let a = grid.rotation(grid.unflat(flat_of_matrix(&grid, &m)));
            let b = grid.rotation(grid.bin_of(&r));
            assert!(a.angle_to(&b) < 1e-6);
        }
    }

    #[test]
    fn identity_map_is_identity_up_to_pole_aliases_and_rotation_map_moves_bins() {
        let grid = RotationGrid::new(15).unwrap();
        let t = GridTables::new(grid);
        let map = t.pull_map(&UnitQuaternion::identity());
        for (b, &m) in map.iter().enumerate() {
            let ra = grid.rotation(grid.unflat(b));
            let rb = grid.rotation(grid.unflat(m as usize));
            assert!(ra.angle_to(&rb) < 1e-5, "bin {b}");
        }
        // a rotation by one in-plane step about the optical axis shifts in-plane by one
        let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), grid.step_rad());
        let map = t.pull_map(&q);
        let b = grid.flat(crate::geometry::BinIndex {
            elevation: 5,
            azimuth: 3,
            inplane: 7,
        });
        let m = grid.unflat(map[b] as usize);
        assert_eq!((m.elevation, m.azimuth, m.inplane), (5, 3, 8));
    }
}
