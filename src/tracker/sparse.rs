//! The sparse rotation state of a track and the kernels of its coarse-to-fine step.
//!
//! A track's particles share one list of *active* bins (frame H); each histogram column holds
//! values there and a *floor* elsewhere (value `floor * volume(b)` at every inactive bin `b`),
//! so an empty belief costs nothing and a converged one costs its support. Particles point to
//! columns: after resampling, the copies of one ancestor share its column until the next update
//! gives each its own.
//!
//! The step matches every crop against the matched set only: the 15-degree lattice (every
//! third bin per angle; no new codebook), the active bins, a rotating slice of the whole grid,
//! and the fine bins around the best lattice cells. The likelihood mass of the bins left out
//! is estimated from their lattice cell and kept as the new floor, so no mass is lost.

use crate::geometry::RotationGrid;
use crate::tracker::bins::{GridTables, fast_exp, flat_of_matrix, gemm_nt, with_wide_simd};
use crate::tracker::observation::ViewEvidence;
use nalgebra::{Matrix3, UnitQuaternion};
use rayon::prelude::*;

/// Lattice factor of the coarse pass: every third bin in each angle.
pub const COARSE_FACTOR: usize = 3;

/// Histograms of one track's particles on the active bins (see the module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RotationState {
    /// Active bins, ascending (flat index in frame H).
    pub active: Vec<u32>,
    /// `values[a * n_cols + c]`: column `c` at active bin `active[a]`.
    pub values: Vec<f32>,
    /// Per column, the value of an inactive bin divided by its volume.
    pub floors: Vec<f32>,
    /// Per particle, its column.
    pub column_of: Vec<u32>,
}

impl RotationState {
    /// Every particle on the uniform distribution (one shared column, nothing active).
    pub fn uniform(n_particles: usize) -> Self {
        Self {
            active: Vec::new(),
            values: Vec::new(),
            floors: vec![1.0],
            column_of: vec![0; n_particles],
        }
    }

    /// Every particle on one dense histogram `column` (normalised here): bins above the
    /// column's lowest density are active, the rest are its floor.
    pub fn from_column(tables: &GridTables, column: &[f32], n_particles: usize) -> Self {
        let total: f64 = column.iter().map(|v| *v as f64).sum();
        if total <= 0.0 || column.len() != tables.grid.len() {
            return Self::uniform(n_particles);
        }
        let inv = 1.0 / total;
        let floor = (0..column.len())
            .map(|b| column[b] as f64 * inv / tables.volume(b))
            .fold(f64::INFINITY, f64::min)
            .max(0.0);
        let mut active = Vec::new();
        let mut values = Vec::new();
        for (b, v) in column.iter().enumerate() {
            let v = *v as f64 * inv;
            if v > floor * tables.volume(b) * (1.0 + 1e-4) {
                active.push(b as u32);
                values.push(v as f32);
            }
        }
        Self {
            active,
            values,
            floors: vec![floor as f32],
            column_of: vec![0; n_particles],
        }
    }

    pub fn n_cols(&self) -> usize {
        self.floors.len()
    }

    pub fn n_particles(&self) -> usize {
        self.column_of.len()
    }

    pub fn clear(&mut self) {
        self.active.clear();
        self.values.clear();
        self.floors.clear();
        self.column_of.clear();
    }

    /// Slot of bin `b` in `active` (binary search).
    #[inline]
    pub fn slot(&self, b: usize) -> Option<usize> {
        self.active.binary_search(&(b as u32)).ok()
    }

    /// Column `c` at bin `b`.
    #[inline]
    pub fn value(&self, tables: &GridTables, b: usize, c: usize) -> f32 {
        match self.slot(b) {
            Some(a) => self.values[a * self.n_cols() + c],
            None => self.floors[c] * tables.volume(b) as f32,
        }
    }

    /// Column `c`'s active bin of the largest value (`None` with no active bin).
    pub fn top_bin(&self, c: usize) -> Option<usize> {
        let nc = self.n_cols();
        (0..self.active.len())
            .max_by(|&a, &b| self.values[a * nc + c].total_cmp(&self.values[b * nc + c]))
            .map(|a| self.active[a] as usize)
    }

    /// Volume of the inactive bins.
    pub fn inactive_volume(&self, tables: &GridTables) -> f64 {
        (1.0 - self.active.iter().map(|b| tables.volume(*b as usize)).sum::<f64>()).max(0.0)
    }

    /// Each column's total mass.
    pub fn column_masses(&self, tables: &GridTables) -> Vec<f64> {
        let nc = self.n_cols();
        let v_in = self.inactive_volume(tables);
        let mut m: Vec<f64> = self.floors.iter().map(|f| *f as f64 * v_in).collect();
        for row in self.values.chunks(nc.max(1)) {
            for (a, v) in m.iter_mut().zip(row) {
                *a += *v as f64;
            }
        }
        m
    }

    /// Scales every column to mass 1.
    pub fn renormalise(&mut self, tables: &GridTables) {
        let nc = self.n_cols();
        if nc == 0 {
            return;
        }
        let inv: Vec<f32> = self
            .column_masses(tables)
            .iter()
            .map(|m| if *m > 0.0 { (1.0 / m) as f32 } else { 0.0 })
            .collect();
        for row in self.values.chunks_mut(nc) {
            for (v, k) in row.iter_mut().zip(&inv) {
                *v *= k;
            }
        }
        for (f, k) in self.floors.iter_mut().zip(&inv) {
            *f *= k;
        }
    }

    /// Per column, the sum of the factors of the particles on it.
    pub fn column_factors(&self, particle_factors: &[f64]) -> Vec<f64> {
        let mut cf = vec![0.0; self.n_cols()];
        for (c, f) in self.column_of.iter().zip(particle_factors) {
            cf[*c as usize] += f;
        }
        cf
    }

    /// The dense mixture `sum_p f_p h_p` over every bin of the grid.
    pub fn mixture_dense(&self, tables: &GridTables, particle_factors: &[f64]) -> Vec<f64> {
        let cf = self.column_factors(particle_factors);
        let nc = self.n_cols();
        let floor: f64 = cf.iter().zip(&self.floors).map(|(w, f)| w * *f as f64).sum();
        let mut m: Vec<f64> = (0..tables.grid.len())
            .into_par_iter()
            .with_min_len(4096)
            .map(|b| floor * tables.volume(b))
            .collect();
        let cf32: Vec<f32> = cf.iter().map(|v| *v as f32).collect();
        // the active bins' values over all threads (each the same sum as alone), then placed
        let on_active: Vec<f64> = self
            .active
            .par_iter()
            .enumerate()
            .with_min_len(256)
            .map(|(a, _)| {
                let row = &self.values[a * nc..(a + 1) * nc];
                row.iter().zip(&cf32).map(|(v, w)| v * w).sum::<f32>() as f64
            })
            .collect();
        for (b, v) in self.active.iter().zip(on_active) {
            m[*b as usize] = v;
        }
        m
    }

    /// Appends one column shared by `count` new particles.
    pub fn append_column(&mut self, on_active: &[f32], floor: f32, count: usize) {
        let nc = self.n_cols();
        let mut values = Vec::with_capacity(self.active.len() * (nc + 1));
        for (a, v) in on_active.iter().enumerate().take(self.active.len()) {
            values.extend_from_slice(&self.values[a * nc..(a + 1) * nc]);
            values.push(*v);
        }
        self.values = values;
        self.floors.push(floor);
        self.column_of.extend(std::iter::repeat_n(nc as u32, count));
    }

    /// After resampling: particle `j` takes particle `ancestors[j]`'s histogram; only the
    /// distinct ancestors' columns are kept.
    pub fn resample(&mut self, ancestors: &[usize]) {
        let nc = self.n_cols();
        let mut new_of_old = vec![u32::MAX; nc];
        let mut kept: Vec<usize> = Vec::new();
        let column_of: Vec<u32> = ancestors
            .iter()
            .map(|&p| {
                let c = self.column_of[p] as usize;
                if new_of_old[c] == u32::MAX {
                    new_of_old[c] = kept.len() as u32;
                    kept.push(c);
                }
                new_of_old[c]
            })
            .collect();
        let k = kept.len();
        if k != nc || kept.iter().enumerate().any(|(i, c)| i != *c) {
            let mut values = par_zeroed(self.active.len() * k);
            values
                .par_chunks_mut(k.max(1) * 256)
                .zip(self.values.par_chunks(nc.max(1) * 256))
                .for_each(|(dst, src)| {
                    for (d, s) in dst.chunks_mut(k).zip(src.chunks(nc)) {
                        for (x, c) in d.iter_mut().zip(&kept) {
                            *x = s[*c];
                        }
                    }
                });
            self.values = values;
            self.floors = kept.iter().map(|c| self.floors[*c]).collect();
        }
        self.column_of = column_of;
    }

    /// Sends bins back to the floor (see [`PruneRule`]); sorts the bins and renormalises each
    /// column.
    pub fn prune(&mut self, tables: &GridTables, rule: &PruneRule) {
        let PruneRule {
            floor_rel,
            margin,
            tail_mass,
            max_active,
        } = *rule;
        let nc = self.n_cols();
        if nc == 0 {
            self.active.clear();
            self.values.clear();
            return;
        }
        let lvl: Vec<f32> = self.floors.iter().map(|f| f.max(floor_rel)).collect();
        let mut keep: Vec<(u32, f32, usize)> = self
            .active
            .par_iter()
            .enumerate()
            .with_min_len(1024)
            .filter_map(|(a, b)| {
                let vol = tables.volume(*b as usize) as f32;
                let row = &self.values[a * nc..(a + 1) * nc];
                let peak = row.iter().zip(&lvl).map(|(v, l)| v / (l * vol)).fold(0f32, f32::max);
                (peak > margin).then_some((*b, peak, a))
            })
            .collect();
        if tail_mass > 0.0 && !keep.is_empty() {
            // the lowest-density bins whose excess over the floor adds up to at most
            // `tail_mass` in every column go too
            keep.par_sort_unstable_by(|x, y| x.1.total_cmp(&y.1));
            let mut acc = vec![0f32; nc];
            let mut cut = 0;
            for (b, _, a) in &keep {
                let vol = tables.volume(*b as usize) as f32;
                let row = &self.values[a * nc..(a + 1) * nc];
                let over = row
                    .iter()
                    .zip(&lvl)
                    .zip(&acc)
                    .any(|((v, l), m)| m + (v - l * vol).max(0.0) > tail_mass);
                if over {
                    break;
                }
                for ((m, v), l) in acc.iter_mut().zip(row).zip(&lvl) {
                    *m += (v - l * vol).max(0.0);
                }
                cut += 1;
            }
            keep.drain(..cut);
        }
        if keep.len() > max_active {
            keep.select_nth_unstable_by(max_active - 1, |x, y| y.1.total_cmp(&x.1));
            keep.truncate(max_active);
        }
        keep.sort_unstable_by_key(|k| k.0);
        let mut values = par_zeroed(keep.len() * nc);
        values.par_chunks_mut(nc).zip(&keep).for_each(|(dst, k)| {
            dst.copy_from_slice(&self.values[k.2 * nc..(k.2 + 1) * nc]);
        });
        self.active = keep.iter().map(|k| k.0).collect();
        self.values = values;
        self.renormalise(tables);
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.active.len() * 4 + self.values.len() * 4 + self.floors.len() * 4 + self.column_of.len() * 4
    }
}

/// Which bins [`RotationState::prune`] sends back to the floor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PruneRule {
    /// The prior's floor (relative to a bin's volume): no column goes below it at an update.
    pub floor_rel: f32,
    /// A bin stays while some column holds more than this many times `max(its floor,
    /// floor_rel)` times the bin's volume.
    pub margin: f32,
    /// Then the lowest-density bins go while their excess over the floor adds up to at most
    /// this much mass in every column.
    pub tail_mass: f32,
    /// At most this many bins stay (the highest peak densities).
    pub max_active: usize,
}

/// The coarse lattice of a grid and each fine bin's cell.
#[derive(Debug, Clone)]
pub struct Lattice {
    /// Flat bins of the lattice points, ascending.
    pub points: Vec<u32>,
    /// Per fine bin, the index (into `points`) of its nearest lattice point.
    pub cell_of: Vec<u32>,
    /// Per cell, the volume of its fine bins.
    pub cell_volume: Vec<f64>,
    /// Per cell, its fine bins.
    pub cell_bins: Vec<Vec<u32>>,
}

impl Lattice {
    /// Every `COARSE_FACTOR`-th bin per angle where the grid's angle counts allow it (else every bin).
    pub fn new(tables: &GridTables) -> Self {
        let g: RotationGrid = tables.grid;
        let (ne, na, ni) = (g.n_elevation(), g.n_azimuth(), g.n_inplane());
        let f = if na % COARSE_FACTOR == 0 && ni % COARSE_FACTOR == 0 && ne > COARSE_FACTOR {
            COARSE_FACTOR
        } else {
            1
        };
        let rows_e: Vec<usize> = (0..ne).filter(|e| e % f == 0 || *e == ne - 1).collect();
        let (ca, ci) = (na / f, ni / f);
        let mut points = Vec::with_capacity(rows_e.len() * ca * ci);
        for &e in &rows_e {
            for a in 0..ca {
                for i in 0..ci {
                    points.push(((e * na + a * f) * ni + i * f) as u32);
                }
            }
        }
        let nearest_row = |e: usize| -> usize {
            let mut best = 0;
            for (k, r) in rows_e.iter().enumerate() {
                if r.abs_diff(e) < rows_e[best].abs_diff(e) {
                    best = k;
                }
            }
            best
        };
        let wrap = |x: usize, n: usize| -> usize { ((x + f / 2) / f) % (n / f) };
        let mut cell_of = vec![0u32; g.len()];
        let mut cell_volume = vec![0.0; points.len()];
        let mut cell_bins = vec![Vec::new(); points.len()];
        for (b, c) in cell_of.iter_mut().enumerate() {
            let i = b % ni;
            let a = (b / ni) % na;
            let e = b / (ni * na);
            let cell = (nearest_row(e) * ca + wrap(a, na)) * ci + wrap(i, ni);
            *c = cell as u32;
            cell_volume[cell] += tables.volume(b);
            cell_bins[cell].push(b as u32);
        }
        Self {
            points,
            cell_of,
            cell_volume,
            cell_bins,
        }
    }
}

/// The map of `q` restricted to `bins`: `out[i] = bin(q * R_bins[i])` (see
/// [`GridTables::pull_map`]).
pub fn map_bins(tables: &GridTables, q: &UnitQuaternion<f64>, bins: &[u32]) -> Vec<u32> {
    let qm = q.to_rotation_matrix().into_inner();
    let grid = tables.grid;
    bins.par_iter()
        .with_min_len(2048)
        .map(|b| flat_of_matrix(&grid, &(qm * tables.matrix(*b as usize))) as u32)
        .collect()
}

/// A zeroed buffer of `len` values, the zeros written by all threads: the step's buffers run to
/// tens of megabytes, and one thread's `memset` of them held the other threads idle.
pub fn par_zeroed(len: usize) -> Vec<f32> {
    let mut v = Vec::with_capacity(len);
    v.par_extend(rayon::iter::repeat_n(0f32, len));
    v
}

/// Rows of a gathered matching task.
const GATHER_ROWS: usize = 256;

std::thread_local! {
    /// Per-thread buffer of the gathered codebook rows.
    static GATHER: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Cosine similarities of `n` unit codes (row-major `n x kd`) with the codebook rows
/// `rows[i]` (rows of `book`), into `out` (`out[i * n + p]`, resized),
/// over all threads; returns each particle's best similarity and the codebook row where it is
/// reached (`u32::MAX` when none is).
pub fn match_rows(
    codes: &[f32],
    book: &crate::tracker::codebook::Codes,
    n: usize,
    kd: usize,
    rows: &[u32],
    out: &mut Vec<f32>,
) -> (Vec<f32>, Vec<u32>) {
    out.resize(rows.len() * n, 0.0);
    let none = || (vec![f32::NEG_INFINITY; n], vec![u32::MAX; n]);
    if n == 0 || rows.is_empty() {
        return none();
    }
    out.par_chunks_mut(GATHER_ROWS * n)
        .zip(rows.par_chunks(GATHER_ROWS))
        .map(|(chunk, rs)| {
            GATHER.with_borrow_mut(|g| {
                g.resize(rs.len() * kd, 0.0);
                book.rows_into(rs, g);
                gemm_nt(chunk, codes, g, n, rs.len(), kd);
            });
            let mut m = vec![f32::NEG_INFINITY; n];
            let mut a = vec![u32::MAX; n];
            for (row, r) in chunk.chunks(n).zip(rs) {
                for ((mi, ai), v) in m.iter_mut().zip(a.iter_mut()).zip(row) {
                    if *v > *mi || (*v == *mi && *r < *ai) {
                        *mi = *v;
                        *ai = *r;
                    }
                }
            }
            (m, a)
        })
        .reduce(none, |(mut m0, mut a0), (m1, a1)| {
            for p in 0..n {
                if m1[p] > m0[p] || (m1[p] == m0[p] && a1[p] < a0[p]) {
                    m0[p] = m1[p];
                    a0[p] = a1[p];
                }
            }
            (m0, a0)
        })
}

/// The fused log-likelihood of row `i` of every view (the views' `sim` are in the matched set's
/// order), into `f`.
#[inline(always)]
pub fn fused_row(views: &[&ViewEvidence], i: usize, n: usize, f: &mut [f32]) {
    for (v, ev) in views.iter().enumerate() {
        ev.loglik_row(&ev.sim[i * n..(i + 1) * n], f, v == 0);
    }
}

/// Per particle, the prior of row `i` (bin `bins[i]`): its column's value, floored at
/// `floor_rel * volume`.
#[inline(always)]
fn prior_row(state: &RotationState, tables: &GridTables, bin: u32, slot: u32, floor_rel: f32, out: &mut [f32]) {
    let vol = tables.volume(bin as usize) as f32;
    let floor = floor_rel * vol;
    let nc = state.n_cols();
    if slot == u32::MAX {
        for (o, c) in out.iter_mut().zip(&state.column_of) {
            *o = (state.floors[*c as usize] * vol).max(floor);
        }
    } else {
        let row = &state.values[slot as usize * nc..(slot as usize + 1) * nc];
        for (o, c) in out.iter_mut().zip(&state.column_of) {
            *o = row[*c as usize].max(floor);
        }
    }
}

/// The measurement update on the matched set (Eq. 6 and the marginal of Eq. 7): for row `i`
/// (bin `bins[i]`, prior slot `slots[i]` in `state.active` or `u32::MAX`) and particle `p`,
/// `post = max(prior, floor_rel * volume) * support[i] * exp(f - fmax[p])` with `f` the views'
/// fused log-likelihood and `support` the support prior's factors (`None`: 1). Returns the
/// posteriors (`post[i * n + p]`) and their sums per particle.
#[allow(clippy::too_many_arguments)]
pub fn fused_update(
    bins: &[u32],
    slots: &[u32],
    views: &[&ViewEvidence],
    state: &RotationState,
    tables: &GridTables,
    floor_rel: f32,
    fmax: &[f32],
    support: Option<&[f32]>,
) -> (Vec<f32>, Vec<f64>) {
    let n = fmax.len();
    let mut post = par_zeroed(bins.len() * n);
    if n == 0 || bins.is_empty() {
        return (post, vec![0.0; n]);
    }
    const CHUNK: usize = 512;
    let chunk_sums = post
        .par_chunks_mut(CHUNK * n)
        .enumerate()
        .map(|(c, out)| {
            with_wide_simd(
                #[inline(always)]
                || {
                    let mut acc = vec![0f32; n];
                    let mut f = vec![0f32; n];
                    let mut prior = vec![0f32; n];
                    for (r, orow) in out.chunks_mut(n).enumerate() {
                        let i = c * CHUNK + r;
                        fused_row(views, i, n, &mut f);
                        prior_row(state, tables, bins[i], slots[i], floor_rel, &mut prior);
                        if let Some(k) = support.map(|s| s[i]) {
                            prior.iter_mut().for_each(|h| *h *= k);
                        }
                        for ((((o, h), f), m), a) in orow.iter_mut().zip(&prior).zip(&f).zip(fmax).zip(acc.iter_mut()) {
                            let v = h * fast_exp(f - m);
                            *o = v;
                            *a += v;
                        }
                    }
                    acc.into_iter().map(f64::from).collect::<Vec<f64>>()
                },
            )
        })
        .collect::<Vec<Vec<f64>>>();
    // the chunks' sums in chunk order: the same sums however the threads shared the chunks
    let mut sums = vec![0f64; n];
    for c in chunk_sums {
        for (x, y) in sums.iter_mut().zip(c) {
            *x += y;
        }
    }
    (post, sums)
}

/// Per particle, the largest fused log-likelihood over the matched rows.
pub fn fused_max(views: &[&ViewEvidence], rows: usize, n: usize) -> Vec<f32> {
    (0..rows)
        .into_par_iter()
        .with_min_len(512)
        .fold(
            || (vec![f32::NEG_INFINITY; n], vec![0f32; n]),
            |(mut m, mut f), i| {
                fused_row(views, i, n, &mut f);
                for (a, v) in m.iter_mut().zip(&f) {
                    *a = a.max(*v);
                }
                (m, f)
            },
        )
        .map(|(m, _)| m)
        .reduce(
            || vec![f32::NEG_INFINITY; n],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x = x.max(y);
                }
                a
            },
        )
}

/// Work space of [`blur`]: per-bin stamps and slots, reused between calls.
#[derive(Debug, Default)]
pub struct BlurWork {
    stamp: Vec<u32>,
    out_stamp: Vec<u32>,
    slot: Vec<u32>,
    generation: u32,
}

impl BlurWork {
    fn next(&mut self, nb: usize) -> u32 {
        if self.stamp.len() != nb {
            self.stamp = vec![0; nb];
            self.out_stamp = vec![0; nb];
            self.slot = vec![0; nb];
            self.generation = 0;
        }
        self.generation = self.generation.wrapping_add(1);
        if self.generation == 0 {
            self.stamp.fill(0);
            self.out_stamp.fill(0);
            self.generation = 1;
        }
        self.generation
    }
}

/// The axis of a blur pass.
#[derive(Clone, Copy)]
enum Axis {
    InPlane,
    Azimuth,
    Elevation,
}

/// Every bin's partner under each turn (`turn_partners[b * turns.len() + j]`: bin `b`'s
/// rotation times turn `j`, binned), for [`mix_turns`]: built once per grid and object (a
/// fraction of a second), it spares each step the binning of every active bin's turns.
pub fn turn_partners(tables: &GridTables, turns: &[Matrix3<f64>]) -> Vec<u32> {
    if turns.is_empty() {
        return Vec::new();
    }
    let grid = tables.grid;
    (0..grid.len() as u32)
        .into_par_iter()
        .with_min_len(1024)
        .flat_map_iter(|b| {
            let m = tables.matrix(b as usize);
            turns.iter().map(move |t| flat_of_matrix(&grid, &(m * t)) as u32)
        })
        .collect()
}

/// Appends, for each column of `parents`, a column holding it turned by turn `j` of
/// `partners_of` (`nt` turns a bin; [`turn_partners`]): the new column's value at bin `b` is
/// the parent's at `b`'s partner (a half turn is its own inverse). The partners of the active
/// bins join the active set; the new columns are normalised. Returns the new columns, in the
/// order of `parents`.
pub fn append_turned_columns(
    state: &mut RotationState,
    tables: &GridTables,
    partners_of: &[u32],
    nt: usize,
    j: usize,
    parents: &[u32],
) -> Vec<u32> {
    let nc = state.n_cols();
    if parents.is_empty() || nt == 0 || j >= nt {
        return Vec::new();
    }
    let partner = |b: u32| partners_of[b as usize * nt + j];
    let mut all: Vec<u32> = state
        .active
        .iter()
        .copied()
        .chain(state.active.iter().map(|&b| partner(b)))
        .collect();
    all.sort_unstable();
    all.dedup();
    let k = parents.len();
    let width = nc + k;
    let mut vals = vec![0f32; all.len() * width];
    let old = &*state;
    vals.par_chunks_mut(width)
        .with_min_len(64)
        .enumerate()
        .for_each(|(r, row)| {
            let b = all[r];
            match old.slot(b as usize) {
                Some(a) => row[..nc].copy_from_slice(&old.values[a * nc..(a + 1) * nc]),
                None => {
                    let vol = tables.volume(b as usize) as f32;
                    for (v, f) in row[..nc].iter_mut().zip(&old.floors) {
                        *v = f * vol;
                    }
                }
            }
            let src = partner(b) as usize;
            for (i, c) in parents.iter().enumerate() {
                row[nc + i] = old.value(tables, src, *c as usize);
            }
        });
    let floors: Vec<f32> = parents.iter().map(|c| state.floors[*c as usize]).collect();
    state.active = all;
    state.values = vals;
    state.floors.extend(floors);
    // the new columns to mass 1 (the gathered values need not sum to the parent's)
    let w = state.n_cols();
    let inv: Vec<f32> = state.column_masses(tables)[nc..]
        .iter()
        .map(|m| if *m > 0.0 { (1.0 / m) as f32 } else { 1.0 })
        .collect();
    for row in state.values.chunks_mut(w) {
        for (v, k) in row[nc..].iter_mut().zip(&inv) {
            *v *= k;
        }
    }
    for (f, k) in state.floors[nc..].iter_mut().zip(&inv) {
        *f *= k;
    }
    (nc as u32..w as u32).collect()
}

/// Moves `share` of each column's mass above its floor at every active bin onto the bins of
/// that bin's `nt` turns (object frame: bin `b`'s rotation times the turn, read from
/// `partners_of`, [`turn_partners`]), in equal parts; the partner bins join the active set.
/// Mass is kept, so nothing is renormalised.
///
/// Gathered per destination bin, in parallel: each bin adds what its sources give it in the
/// order the sources come (ascending, a source's own mass before its turns' shares), so the
/// sums are those of scattering source by source, to the bit (`mix_turns_scatter` in the
/// tests), at a fraction of its time (no allocation per bin, every core).
pub fn mix_turns(state: &mut RotationState, tables: &GridTables, partners_of: &[u32], nt: usize, share: f32) {
    let nc = state.n_cols();
    if nc == 0 || state.active.is_empty() || nt == 0 || share <= 0.0 {
        return;
    }
    debug_assert_eq!(
        partners_of.len(),
        tables.grid.len() * nt,
        "a partner table of this grid"
    );
    let partners: Vec<u32> = state
        .active
        .iter()
        .flat_map(|b| partners_of[*b as usize * nt..(*b as usize + 1) * nt].iter().copied())
        .collect();
    let mut all: Vec<u32> = state.active.iter().chain(&partners).copied().collect();
    all.sort_unstable();
    all.dedup();
    let at = |b: &u32| all.binary_search(b).expect("in the union") as u32;
    let own: Vec<u32> = state.active.par_iter().with_min_len(256).map(at).collect();
    let to: Vec<u32> = partners.par_iter().with_min_len(256).map(at).collect();
    // every destination's sources as (source, 0 for its own mass or 1 + turn), grouped by
    // destination (counting sort), each group in source order
    let mut start = vec![0usize; all.len() + 1];
    for k in own.iter().chain(&to) {
        start[*k as usize + 1] += 1;
    }
    for k in 0..all.len() {
        start[k + 1] += start[k];
    }
    let mut fill = start.clone();
    let mut sources = vec![(0u32, 0u32); own.len() * (nt + 1)];
    for (a, k) in own.iter().enumerate() {
        for (j, k) in std::iter::once(k).chain(&to[a * nt..(a + 1) * nt]).enumerate() {
            sources[fill[*k as usize]] = (a as u32, j as u32);
            fill[*k as usize] += 1;
        }
    }
    let each = share / nt as f32;
    let (active, values, floors) = (&state.active, &state.values, &state.floors);
    let mut vals = vec![0f32; all.len() * nc];
    vals.par_chunks_mut(nc)
        .with_min_len(64)
        .enumerate()
        .for_each(|(k, row)| {
            let vol = tables.volume(all[k] as usize) as f32;
            for (v, f) in row.iter_mut().zip(floors) {
                *v = f * vol;
            }
            for &(a, j) in &sources[start[k]..start[k + 1]] {
                let a = a as usize;
                let vol = tables.volume(active[a] as usize) as f32;
                let old = &values[a * nc..(a + 1) * nc];
                for c in 0..nc {
                    let excess = (old[c] - floors[c] * vol).max(0.0);
                    row[c] += if j == 0 {
                        old[c] - floors[c] * vol - share * excess
                    } else {
                        each * excess
                    };
                }
            }
        });
    state.active = all;
    state.values = vals;
}

/// The wrap-around Gaussian blur of every column (azimuth and in-plane wrap; elevation is
/// truncated at the poles, each source row keeping its mass), as the dense blur, applied to
/// each column's excess over its floor: the floor is (nearly) unchanged by a blur, so only
/// the active bins and a halo of `kernel.len() / 2` bins per axis are touched.
pub fn blur(state: &mut RotationState, tables: &GridTables, kernel: &[f32], work: &mut BlurWork) {
    let nc = state.n_cols();
    if nc == 0 || state.active.is_empty() || kernel.len() <= 1 {
        return;
    }
    let grid = tables.grid;
    // excess over the floor
    let mut bins = std::mem::take(&mut state.active);
    let mut vals = std::mem::take(&mut state.values);
    vals.par_chunks_mut(nc).zip(&bins).for_each(|(row, b)| {
        let vol = tables.volume(*b as usize) as f32;
        for (v, f) in row.iter_mut().zip(&state.floors) {
            *v -= f * vol;
        }
    });
    for axis in [Axis::InPlane, Axis::Azimuth, Axis::Elevation] {
        (bins, vals) = blur_pass(&grid, &bins, &vals, nc, kernel, axis, work);
    }
    vals.par_chunks_mut(nc).zip(&bins).for_each(|(row, b)| {
        let vol = tables.volume(*b as usize) as f32;
        for (v, f) in row.iter_mut().zip(&state.floors) {
            *v += f * vol;
        }
    });
    state.active = bins;
    state.values = vals;
}

/// One axis of [`blur`]: the output bins are the inputs' neighbours along `axis`.
fn blur_pass(
    grid: &RotationGrid,
    bins: &[u32],
    vals: &[f32],
    nc: usize,
    kernel: &[f32],
    axis: Axis,
    work: &mut BlurWork,
) -> (Vec<u32>, Vec<f32>) {
    let (ne, na, ni) = (grid.n_elevation(), grid.n_azimuth(), grid.n_inplane());
    let r = (kernel.len() / 2) as isize;
    // neighbour of bin b at offset d along the axis (None past a pole)
    let step = move |b: usize, d: isize| -> Option<usize> {
        let i = b % ni;
        let a = (b / ni) % na;
        let e = b / (ni * na);
        match axis {
            Axis::InPlane => Some(b - i + (i as isize + d).rem_euclid(ni as isize) as usize),
            Axis::Azimuth => Some((e * na + (a as isize + d).rem_euclid(na as isize) as usize) * ni + i),
            Axis::Elevation => {
                let e2 = e as isize + d;
                (e2 >= 0 && e2 < ne as isize).then(|| (e2 as usize * na + a) * ni + i)
            }
        }
    };
    // elevation: source row j spreads its mass over the rows that exist
    let row_sums = crate::tracker::kernels::elevation_row_sums(kernel, ne);
    let gen_in = work.next(grid.len());
    for (s, b) in bins.iter().enumerate() {
        work.stamp[*b as usize] = gen_in;
        work.slot[*b as usize] = s as u32;
    }
    // outputs: every bin within r of an input, each once
    let mut out_bins: Vec<u32> = Vec::with_capacity(bins.len() * 2);
    for b in bins {
        for d in -r..=r {
            if let Some(o) = step(*b as usize, d)
                && work.out_stamp[o] != gen_in
            {
                work.out_stamp[o] = gen_in;
                out_bins.push(o as u32);
            }
        }
    }
    out_bins.par_sort_unstable();
    let stamp = &work.stamp;
    let slot = &work.slot;
    let mut out = par_zeroed(out_bins.len() * nc);
    out.par_chunks_mut(nc * 64)
        .zip(out_bins.par_chunks(64))
        .for_each(|(chunk, obs)| {
            with_wide_simd(
                #[inline(always)]
                || {
                    for (dst, o) in chunk.chunks_mut(nc).zip(obs) {
                        for (k, w) in kernel.iter().enumerate() {
                            let Some(src) = step(*o as usize, k as isize - r) else {
                                continue;
                            };
                            if stamp[src] != gen_in {
                                continue;
                            }
                            let w = match axis {
                                Axis::Elevation => w / row_sums[src / (ni * na)],
                                _ => *w,
                            };
                            let s = slot[src] as usize;
                            for (d, v) in dst.iter_mut().zip(&vals[s * nc..(s + 1) * nc]) {
                                *d += w * v;
                            }
                        }
                    }
                },
            )
        });
    (out_bins, out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tracker::bins::{blur_reference, gaussian_kernel};
    use rand::{Rng, SeedableRng};

    /// The mixing as it was first written, source by source: the reference the gathered
    /// [`mix_turns`] must equal to the bit.
    fn mix_turns_scatter(state: &mut RotationState, tables: &GridTables, turns: &[Matrix3<f64>], share: f32) {
        let nc = state.n_cols();
        let grid = tables.grid;
        let partners: Vec<u32> = state
            .active
            .iter()
            .flat_map(|b| {
                let m = tables.matrix(*b as usize);
                turns.iter().map(move |t| flat_of_matrix(&grid, &(m * t)) as u32)
            })
            .collect();
        let mut all: Vec<u32> = state.active.iter().chain(&partners).copied().collect();
        all.sort_unstable();
        all.dedup();
        let mut vals = vec![0f32; all.len() * nc];
        for (row, b) in vals.chunks_mut(nc).zip(&all) {
            let vol = tables.volume(*b as usize) as f32;
            for (v, f) in row.iter_mut().zip(&state.floors) {
                *v = f * vol;
            }
        }
        let at = |b: u32| all.binary_search(&b).expect("in the union");
        let each = share / turns.len() as f32;
        let nt = turns.len();
        for (a, b) in state.active.iter().enumerate() {
            let k = at(*b);
            let vol = tables.volume(*b as usize) as f32;
            let old = &state.values[a * nc..(a + 1) * nc];
            let dests: Vec<usize> = partners[a * nt..(a + 1) * nt].iter().map(|p| at(*p)).collect();
            for c in 0..nc {
                let excess = (old[c] - state.floors[c] * vol).max(0.0);
                vals[k * nc + c] += old[c] - state.floors[c] * vol - share * excess;
                for d in &dests {
                    vals[d * nc + c] += each * excess;
                }
            }
        }
        state.active = all;
        state.values = vals;
    }

    #[test]
    fn gathered_mixing_equals_the_scatter_to_the_bit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let grid = RotationGrid::new(10).unwrap();
        let tables = GridTables::new(grid);
        let nc = 5;
        let mut active: Vec<u32> = (0..3000).map(|_| rng.random_range(0..grid.len() as u32)).collect();
        active.sort_unstable();
        active.dedup();
        let floors: Vec<f32> = (0..nc).map(|_| rng.random_range(0.0..0.5f32)).collect();
        let values: Vec<f32> = active
            .iter()
            .flat_map(|b| {
                let vol = tables.volume(*b as usize) as f32;
                // some bins below their floor (no excess), most above
                let f = floors.clone();
                (0..nc).map(move |c| f[c] * vol * 0.9 + (b % 7) as f32 * 0.013 + c as f32 * 1e-3)
            })
            .collect();
        let state = RotationState {
            active,
            values,
            floors,
            column_of: (0..nc as u32).collect(),
        };
        // several turns, two of which can send a bin to the same partner or back onto itself
        let turns: Vec<Matrix3<f64>> = [
            (nalgebra::Vector3::z_axis(), std::f64::consts::PI),
            (nalgebra::Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
            (nalgebra::Vector3::x_axis(), std::f64::consts::PI),
            (nalgebra::Vector3::z_axis(), 1e-4),
        ]
        .iter()
        .map(|(ax, ang)| {
            UnitQuaternion::from_axis_angle(ax, *ang)
                .to_rotation_matrix()
                .into_inner()
        })
        .collect();
        let (mut gathered, mut scattered) = (state.clone(), state);
        mix_turns(
            &mut gathered,
            &tables,
            &turn_partners(&tables, &turns),
            turns.len(),
            0.02,
        );
        mix_turns_scatter(&mut scattered, &tables, &turns, 0.02);
        assert_eq!(gathered.active, scattered.active);
        assert_eq!(gathered.values.len(), scattered.values.len());
        let differing = gathered
            .values
            .iter()
            .zip(&scattered.values)
            .filter(|(g, s)| g.to_bits() != s.to_bits())
            .count();
        assert_eq!(differing, 0, "{differing} values differ");
    }

    #[test]
    fn a_turned_column_holds_its_parent_s_mass_at_the_turned_bins() {
        let grid = RotationGrid::new(15).unwrap();
        let tables = GridTables::new(grid);
        let b = (10 * grid.n_azimuth() + 5) * grid.n_inplane() + 7;
        let (floor, vol) = (0.01f32, tables.volume(b) as f32);
        // two columns: the first peaked at `b`, the second at another bin
        let other = b + 3 * grid.n_inplane();
        let mut active = vec![b as u32, other as u32];
        active.sort_unstable();
        let at0 = active.binary_search(&(b as u32)).unwrap();
        let mut values = vec![0f32; 4];
        for (a, bin) in active.iter().enumerate() {
            let v = tables.volume(*bin as usize) as f32 * floor;
            values[a * 2] = v + if a == at0 { 1.0 } else { 0.0 };
            values[a * 2 + 1] = v + if a == at0 { 0.0 } else { 1.0 };
        }
        let mut state = RotationState {
            active,
            values,
            floors: vec![floor, floor],
            column_of: vec![0, 1, 1],
        };
        state.renormalise(&tables);
        let masses_before = state.column_masses(&tables);
        let turn = UnitQuaternion::from_axis_angle(&nalgebra::Vector3::z_axis(), std::f64::consts::PI);
        let t = turn.to_rotation_matrix().into_inner();
        let partners = turn_partners(&tables, &[t]);
        let new = append_turned_columns(&mut state, &tables, &partners, 1, 0, &[0]);
        assert_eq!(new, vec![2]);
        assert_eq!(state.n_cols(), 3);
        assert_eq!(state.column_of, vec![0, 1, 1], "no particle moves onto it by itself");
        let masses = state.column_masses(&tables);
        for c in 0..2 {
            assert!(
                (masses[c] - masses_before[c]).abs() < 1e-5,
                "column {c} keeps its mass: {masses:?}"
            );
        }
        assert!(
            (masses[2] - 1.0).abs() < 1e-5,
            "the new column is normalised: {masses:?}"
        );
        // the first column's peak sits at the turned bin of the new column, and only there
        let partner = flat_of_matrix(&grid, &(tables.matrix(b) * t));
        assert_ne!(partner, b);
        let peak = (0..grid.len())
            .max_by(|x, y| state.value(&tables, *x, 2).total_cmp(&state.value(&tables, *y, 2)))
            .unwrap();
        assert_eq!(peak, partner);
        // each column's top bin, read at the state's new width
        assert_eq!(state.top_bin(0), Some(b));
        assert_eq!(state.top_bin(1), Some(other));
        assert_eq!(state.top_bin(2), Some(partner));
        assert!(state.value(&tables, partner, 2) > 0.5 + floor * vol);
        // the old columns at the new active bin are their floor
        let vp = tables.volume(partner) as f32;
        let v0 = state.value(&tables, partner, 0);
        assert!((v0 - state.floors[0] * vp).abs() <= 1e-6 * v0.max(1e-12), "{v0}");
    }

    #[test]
    fn mixing_moves_a_share_of_the_excess_to_the_turned_bins() {
        let grid = RotationGrid::new(15).unwrap();
        let tables = GridTables::new(grid);
        let b = (10 * grid.n_azimuth() + 5) * grid.n_inplane() + 7;
        let floor = 0.01f32;
        let vol = tables.volume(b) as f32;
        let mut state = RotationState {
            active: vec![b as u32],
            values: vec![floor * vol + 1.0],
            floors: vec![floor],
            column_of: vec![0, 0],
        };
        let mass = |s: &RotationState| -> f64 {
            let active: f64 = s.values.iter().map(|v| *v as f64).sum();
            let inactive: f64 = (0..grid.len())
                .filter(|i| s.active.binary_search(&(*i as u32)).is_err())
                .map(|i| (s.floors[0] * tables.volume(i) as f32) as f64)
                .sum();
            active + inactive
        };
        let before = mass(&state);
        let turn = UnitQuaternion::from_axis_angle(&nalgebra::Vector3::z_axis(), std::f64::consts::PI);
        let t = turn.to_rotation_matrix().into_inner();
        mix_turns(&mut state, &tables, &turn_partners(&tables, &[t]), 1, 0.2);
        // the turned pose's bin: the bin's rotation (its frame from the object's) times the turn
        let partner = flat_of_matrix(&grid, &(tables.matrix(b) * t)) as u32;
        assert_ne!(partner, b as u32);
        let at = |bin: u32| state.active.binary_search(&bin).expect("active");
        let excess = |bin: u32| state.values[at(bin)] - floor * tables.volume(bin as usize) as f32;
        assert!((excess(b as u32) - 0.8).abs() < 1e-5, "{}", excess(b as u32));
        assert!((excess(partner) - 0.2).abs() < 1e-5, "{}", excess(partner));
        assert!((mass(&state) - before).abs() < 1e-3 * before, "mass is kept");
        // a 180-degree turn of the turned pose is the pose again
        assert_eq!(flat_of_matrix(&grid, &(tables.matrix(partner as usize) * t)), b);
    }

    #[test]
    fn sparse_blur_matches_the_dense_blur_of_the_excess() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let grid = RotationGrid::new(15).unwrap();
        let tables = GridTables::new(grid);
        let nb = grid.len();
        let nc = 3;
        // a few active bins per column over a floor
        let active: Vec<u32> = {
            let mut a: Vec<u32> = (0..40).map(|_| rng.random_range(0..nb as u32)).collect();
            a.sort_unstable();
            a.dedup();
            a
        };
        let floors = vec![0.5f32, 0.0, 0.1];
        let values: Vec<f32> = active
            .iter()
            .flat_map(|b| {
                let vol = tables.volume(*b as usize) as f32;
                floors.iter().map(move |f| f * vol + 0.01).collect::<Vec<_>>()
            })
            .collect();
        let mut state = RotationState {
            active: active.clone(),
            values,
            floors: floors.clone(),
            column_of: vec![0, 1, 2],
        };
        // dense excess, blurred by the reference
        let mut dense = vec![0f32; nb * nc];
        for (a, b) in active.iter().enumerate() {
            for c in 0..nc {
                let vol = tables.volume(*b as usize) as f32;
                dense[*b as usize * nc + c] = state.values[a * nc + c] - floors[c] * vol;
            }
        }
        let k = gaussian_kernel(2, 1.0);
        let mut scratch = Vec::new();
        blur_reference(&grid, &mut dense, nc, &k, &mut scratch);
        let mut work = BlurWork::default();
        blur(&mut state, &tables, &k, &mut work);
        assert!(state.active.windows(2).all(|w| w[0] < w[1]), "sorted");
        for b in 0..nb {
            for c in 0..nc {
                let vol = tables.volume(b) as f32;
                let want = dense[b * nc + c] + floors[c] * vol;
                let got = state.value(&tables, b, c);
                assert!((got - want).abs() < 1e-6, "bin {b} column {c}: {got} vs {want}");
            }
        }
    }

    #[test]
    fn resampling_keeps_distinct_ancestors_once_and_pruning_keeps_mass() {
        let grid = RotationGrid::new(15).unwrap();
        let tables = GridTables::new(grid);
        let nb = grid.len();
        let mut column = vec![0f32; nb];
        for (b, v) in column.iter_mut().enumerate() {
            *v = tables.volume(b) as f32 * if b % 97 == 0 { 50.0 } else { 1e-3 };
        }
        let mut s = RotationState::from_column(&tables, &column, 4);
        assert_eq!(s.active.len(), nb.div_ceil(97));
        let masses = s.column_masses(&tables);
        assert!((masses[0] - 1.0).abs() < 1e-4, "{masses:?}");
        // a second column, then resampling from particles 3, 3, 0, 3
        let other: Vec<f32> = s.values.iter().map(|v| v * 0.5).collect();
        s.append_column(&other, s.floors[0] * 0.5, 2);
        assert_eq!(s.column_of, vec![0, 0, 0, 0, 1, 1]);
        s.resample(&[4, 4, 0, 5]);
        assert_eq!(s.n_cols(), 2);
        assert_eq!(s.column_of, vec![0, 0, 1, 0]);
        assert_eq!(s.values[1], s.values[0] * 2.0);
        // pruning with a high floor drops everything and leaves unit mass
        let rule = PruneRule {
            floor_rel: 1e6,
            margin: 1.0,
            tail_mass: 0.0,
            max_active: usize::MAX,
        };
        s.prune(&tables, &rule);
        assert!(s.active.is_empty());
        for m in s.column_masses(&tables) {
            assert!((m - 1.0).abs() < 1e-4);
        }
    }

    #[test]
    fn lattice_cells_partition_the_grid() {
        let grid = RotationGrid::new(5).unwrap();
        let tables = GridTables::new(grid);
        let l = Lattice::new(&tables);
        assert_eq!(l.points.len(), 13 * 24 * 24);
        let total: f64 = l.cell_volume.iter().sum();
        assert!((total - 1.0).abs() < 1e-9);
        assert_eq!(l.cell_bins.iter().map(|c| c.len()).sum::<usize>(), grid.len());
        for (c, p) in l.points.iter().enumerate() {
            assert_eq!(
                l.cell_of[*p as usize] as usize, c,
                "a lattice point lies in its own cell"
            );
            assert!(l.cell_bins[c].len() <= 27);
        }
    }

    #[test]
    fn gathered_matching_equals_the_plain_product() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let (n, kd, nb) = (7, 16, 900);
        let book32: Vec<f32> = (0..nb * kd).map(|_| rng.random::<f32>() - 0.5).collect();
        let codes: Vec<f32> = (0..n * kd).map(|_| rng.random::<f32>() - 0.5).collect();
        let rows: Vec<u32> = (0..600).map(|_| rng.random_range(0..nb as u32)).collect();
        let book_codes = crate::tracker::codebook::Codes::from_f32(&book32, kd);
        let book = book_codes.to_f32();
        let mut out = Vec::new();
        let (mx, arg) = match_rows(&codes, &book_codes, n, kd, &rows, &mut out);
        for (i, r) in rows.iter().enumerate() {
            for p in 0..n {
                let want: f32 = (0..kd).map(|k| codes[p * kd + k] * book[*r as usize * kd + k]).sum();
                assert!((out[i * n + p] - want).abs() < 1e-4);
            }
        }
        for p in 0..n {
            let best = (0..rows.len())
                .map(|i| out[i * n + p])
                .fold(f32::NEG_INFINITY, f32::max);
            assert_eq!(mx[p], best);
            let i = (0..rows.len()).find(|i| out[i * n + p] == best).unwrap();
            assert_eq!(
                out[rows.iter().position(|r| *r == arg[p]).unwrap() * n + p],
                out[i * n + p]
            );
        }
    }
}
