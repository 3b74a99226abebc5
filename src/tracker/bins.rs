//! Fast operations on the rotation grid ([`crate::geometry::RotationGrid`]).
//!
//! Histograms are stored *bin-major, particle-minor*: value of particle `p` at flat bin `b` is
//! `h[b * n_particles + p]`. This is the layout the matching GEMM produces (`Q^T C`, column-major
//! `n_particles x n_bins`), it makes the pull re-binning a gather of contiguous particle rows,
//! and it lets the blur vectorise across particles.

use crate::geometry::RotationGrid;
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use std::f64::consts::PI;

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
#[inline]
pub fn flat_of_matrix(grid: &RotationGrid, m: &Matrix3<f64>) -> usize {
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

/// A normalised 1-D Gaussian kernel of `2 * radius + 1` taps.
pub fn gaussian_kernel(radius: usize, sigma_bins: f64) -> Vec<f32> {
    let mut k: Vec<f64> = (0..=2 * radius)
        .map(|i| {
            let x = i as f64 - radius as f64;
            (-0.5 * x * x / (sigma_bins * sigma_bins).max(1e-12)).exp()
        })
        .collect();
    let s: f64 = k.iter().sum();
    for v in &mut k {
        *v /= s;
    }
    k.into_iter().map(|v| v as f32).collect()
}

/// Separable Gaussian blur of `n_p` histograms (bin-major layout) with `kernel`: azimuth and
/// in-plane wrap around (they are angles), elevation is truncated at the poles with the kernel
/// renormalised. `scratch` is resized as needed and reused between calls.
pub fn blur(grid: &RotationGrid, h: &mut [f32], n_p: usize, kernel: &[f32], scratch: &mut Vec<f32>) {
    let ne = grid.n_elevation();
    let na = grid.n_azimuth();
    let ni = grid.n_inplane();
    assert_eq!(h.len(), ne * na * ni * n_p, "histogram size");
    let r = (kernel.len() / 2) as isize;
    let slab = na * ni * n_p;
    // in-plane and azimuth passes, one elevation slab at a time (wrap-around)
    h.par_chunks_mut(slab).for_each(|slab_h| {
        let mut tmp = slab_h.to_vec();
        // in-plane: rows of ni * n_p
        for a in 0..na {
            let row = &mut slab_h[a * ni * n_p..(a + 1) * ni * n_p];
            let src = &tmp[a * ni * n_p..(a + 1) * ni * n_p];
            for i in 0..ni {
                let dst = &mut row[i * n_p..(i + 1) * n_p];
                dst.fill(0.0);
                for (k, &w) in kernel.iter().enumerate() {
                    let j = (i as isize + k as isize - r).rem_euclid(ni as isize) as usize;
                    let s = &src[j * n_p..(j + 1) * n_p];
                    for (d, v) in dst.iter_mut().zip(s) {
                        *d += w * v;
                    }
                }
            }
        }
        tmp.copy_from_slice(slab_h);
        // azimuth: stride ni * n_p
        let row_len = ni * n_p;
        for a in 0..na {
            let dst = &mut slab_h[a * row_len..(a + 1) * row_len];
            dst.fill(0.0);
            for (k, &w) in kernel.iter().enumerate() {
                let j = (a as isize + k as isize - r).rem_euclid(na as isize) as usize;
                let s = &tmp[j * row_len..(j + 1) * row_len];
                for (d, v) in dst.iter_mut().zip(s) {
                    *d += w * v;
                }
            }
        }
    });
    // elevation pass (truncated, renormalised)
    scratch.resize(h.len(), 0.0);
    scratch.copy_from_slice(h);
    let src: &[f32] = scratch;
    // mass-preserving: each source row spreads its mass over the rows that exist
    let row_sum = |j: isize| -> f32 {
        kernel
            .iter()
            .enumerate()
            .filter(|(k, _)| {
                let e = j - (*k as isize - r);
                e >= 0 && e < ne as isize
            })
            .map(|(_, w)| *w)
            .sum()
    };
    h.par_chunks_mut(slab).enumerate().for_each(|(e, dst)| {
        dst.fill(0.0);
        for (k, &w) in kernel.iter().enumerate() {
            let j = e as isize + k as isize - r;
            if j < 0 || j >= ne as isize {
                continue;
            }
            let w = w / row_sum(j);
            let s = &src[j as usize * slab..(j as usize + 1) * slab];
            for (d, v) in dst.iter_mut().zip(s) {
                *d += w * v;
            }
        }
    });
}

/// Gathers `src` (bin-major, `n_p` per bin) through a pull map and adds it into `dst`:
/// `dst[b][p] += src[map[b]][p]`.
pub fn add_pulled(dst: &mut [f32], src: &[f32], map: &[u32], n_p: usize) {
    dst.par_chunks_mut(n_p * 1024).enumerate().for_each(|(c, chunk)| {
        let b0 = c * 1024;
        for (k, row) in chunk.chunks_mut(n_p).enumerate() {
            let s = map[b0 + k] as usize * n_p;
            for (d, v) in row.iter_mut().zip(&src[s..s + n_p]) {
                *d += v;
            }
        }
    });
}

/// `dst[b][p] = src[map[b]][p]` (re-binning a prior).
pub fn pull(dst: &mut [f32], src: &[f32], map: &[u32], n_p: usize) {
    dst.par_chunks_mut(n_p * 1024).enumerate().for_each(|(c, chunk)| {
        let b0 = c * 1024;
        for (k, row) in chunk.chunks_mut(n_p).enumerate() {
            let s = map[b0 + k] as usize * n_p;
            row.copy_from_slice(&src[s..s + n_p]);
        }
    });
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

    #[test]
    fn blur_preserves_mass_and_wraps() {
        let grid = RotationGrid::new(30).unwrap();
        let n_p = 3;
        let mut h = vec![0f32; grid.len() * n_p];
        let b = grid.flat(crate::geometry::BinIndex {
            elevation: 3,
            azimuth: 0,
            inplane: 0,
        });
        h[b * n_p + 1] = 1.0;
        let k = gaussian_kernel(2, 1.0);
        let mut scratch = Vec::new();
        blur(&grid, &mut h, n_p, &k, &mut scratch);
        let mass: f32 = (0..grid.len()).map(|b| h[b * n_p + 1]).sum();
        assert!((mass - 1.0).abs() < 1e-5);
        let other: f32 = (0..grid.len()).map(|b| h[b * n_p]).sum();
        assert_eq!(other, 0.0);
        // the wrapped neighbour (azimuth n-1, in-plane n-1) received mass
        let w = grid.flat(crate::geometry::BinIndex {
            elevation: 3,
            azimuth: grid.n_azimuth() - 1,
            inplane: grid.n_inplane() - 1,
        });
        assert!(h[w * n_p + 1] > 0.01);
        let c = h[b * n_p + 1];
        assert!((h[w * n_p + 1] - h[grid.flat(crate::geometry::BinIndex { elevation: 3, azimuth: 1, inplane: 1 }) * n_p + 1]).abs() < 1e-6);
        assert!(c > h[w * n_p + 1]);
    }
}
