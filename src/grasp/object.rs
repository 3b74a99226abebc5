//! The object as solid shapes for parry3d, built once per mesh and cached by content hash.
//!
//! A triangle mesh only has a surface: a finger lying wholly inside it is no collision. The
//! object is therefore a convex hull (about 1 ms to build, the fastest to query) or, for a
//! clearly concave object (a mug, a drill), a convex decomposition (VHACD, a compound of
//! convex parts, about 0.5 s). [`GraspObject::new`] picks by the mesh's concavity: the share of
//! the hull's volume that the mesh does not fill.

use super::{GraspError, convert};
use crate::mesh::Mesh;
use nalgebra::{Matrix3, Point3, SymmetricEigen, Vector3};
use parry3d::shape::SharedShape;
use parry3d::transformation::vhacd::VHACDParameters;
use rand::SeedableRng;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

/// Concavity (1 - mesh volume / hull volume) above which [`GraspObject::new`] decomposes.
pub const DECOMPOSE_ABOVE_CONCAVITY: f64 = 0.25;

/// How the solid was built.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SolidKind {
    ConvexHull,
    ConvexDecomposition,
}

#[derive(Debug)]
struct Inner {
    content_hash: String,
    kind: SolidKind,
    shape: SharedShape,
    hull_vertices_m: Vec<Point3<f64>>,
    principal_axes: Matrix3<f64>,
    concavity: f64,
    n_parts: usize,
}

/// An object's solid shape (cheap to clone; shared through the cache).
#[derive(Debug, Clone)]
pub struct GraspObject(Arc<Inner>);

type Cache = Mutex<HashMap<(String, SolidKind), Arc<Inner>>>;

fn cache() -> &'static Cache {
    static CACHE: OnceLock<Cache> = OnceLock::new();
    CACHE.get_or_init(|| Mutex::new(HashMap::new()))
}

impl GraspObject {
    /// Convex hull, or a convex decomposition when the mesh is clearly concave. Cached.
    pub fn new(mesh: &Mesh) -> Result<Self, GraspError> {
        let hull = Self::with_kind(mesh, SolidKind::ConvexHull)?;
        if hull.concavity() > DECOMPOSE_ABOVE_CONCAVITY {
            Self::with_kind(mesh, SolidKind::ConvexDecomposition)
        } else {
            Ok(hull)
        }
    }

    /// A solid of the given kind. Cached per (mesh content hash, kind).
    pub fn with_kind(mesh: &Mesh, kind: SolidKind) -> Result<Self, GraspError> {
        mesh.validate()
            .map_err(|e| GraspError::InvalidMesh(e.to_string()))?;
        let key = (mesh.content_hash(), kind);
        if let Some(inner) = cache().lock().unwrap_or_else(|e| e.into_inner()).get(&key) {
            return Ok(Self(inner.clone()));
        }
        let inner = Arc::new(build(mesh, key.0.clone(), kind)?);
        cache()
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(key, inner.clone());
        Ok(Self(inner))
    }

    /// The parry shape in the object frame.
    pub fn shape(&self) -> &SharedShape {
        &self.0.shape
    }
    pub fn kind(&self) -> SolidKind {
        self.0.kind
    }
    pub fn content_hash(&self) -> &str {
        &self.0.content_hash
    }
    /// Vertices of the convex hull, object frame.
    pub fn hull_vertices_m(&self) -> &[Point3<f64>] {
        &self.0.hull_vertices_m
    }
    /// Principal axes of the surface (columns, object frame), largest spread first.
    pub fn principal_axes(&self) -> &Matrix3<f64> {
        &self.0.principal_axes
    }
    /// 1 - mesh volume / hull volume (0 for a convex closed mesh).
    pub fn concavity(&self) -> f64 {
        self.0.concavity
    }
    /// Number of convex parts (1 for a hull).
    pub fn n_parts(&self) -> usize {
        self.0.n_parts
    }
    /// Least and greatest projection of the hull on a direction (object frame).
    pub fn extent_along(&self, dir: &Vector3<f64>) -> (f64, f64) {
        self.0
            .hull_vertices_m
            .iter()
            .map(|p| p.coords.dot(dir))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| (lo.min(x), hi.max(x)))
    }
}

fn build(mesh: &Mesh, content_hash: String, kind: SolidKind) -> Result<Inner, GraspError> {
    let points: Vec<_> = mesh
        .vertices_m
        .iter()
        .map(|v| parry3d::math::Vector::new(v[0], v[1], v[2]))
        .collect();
    let hull = parry3d::shape::ConvexPolyhedron::from_convex_hull(&points)
        .ok_or_else(|| GraspError::InvalidMesh("the convex hull is degenerate (flat mesh?)".into()))?;
    let hull_vertices_m: Vec<Point3<f64>> = hull
        .points()
        .iter()
        .map(|p| Point3::from(convert::vector_from_parry(*p)))
        .collect();
    let hull_volume = hull_volume_m3(&hull);
    let mesh_volume = mesh_volume_m3(mesh).abs();
    let concavity = if hull_volume > 0.0 {
        (1.0 - mesh_volume / hull_volume).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let (shape, n_parts) = match kind {
        SolidKind::ConvexHull => (SharedShape::new(hull), 1),
        SolidKind::ConvexDecomposition => {
            let params = VHACDParameters {
                resolution: 48,
                concavity: 0.01,
                max_convex_hulls: 24,
                ..VHACDParameters::default()
            };
            let s = SharedShape::convex_decomposition_with_params(&points, &mesh.triangles, &params);
            let n = s.as_compound().map(|c| c.shapes().len()).unwrap_or(1);
            if n == 0 {
                return Err(GraspError::InvalidMesh("convex decomposition found no parts".into()));
            }
            (s, n)
        }
    };
    Ok(Inner {
        content_hash,
        kind,
        shape,
        hull_vertices_m,
        principal_axes: principal_axes(mesh),
        concavity,
        n_parts,
    })
}

/// Signed volume of a closed, outward-wound mesh (an approximation for a nearly closed one).
fn mesh_volume_m3(mesh: &Mesh) -> f64 {
    mesh.triangles
        .iter()
        .map(|t| {
            let (a, b, c) = (mesh.vertex(t[0]), mesh.vertex(t[1]), mesh.vertex(t[2]));
            a.coords.dot(&b.coords.cross(&c.coords)) / 6.0
        })
        .sum()
}

fn hull_volume_m3(hull: &parry3d::shape::ConvexPolyhedron) -> f64 {
    let (vertices, triangles) = hull.to_trimesh();
    triangles
        .iter()
        .map(|t| {
            let p = |i: u32| convert::vector_from_parry(vertices[i as usize]);
            let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
            a.dot(&b.cross(&c)) / 6.0
        })
        .sum::<f64>()
        .abs()
}

/// Principal axes of the surface (area-uniform samples), columns sorted by decreasing spread,
/// right-handed. Deterministic (fixed seed).
fn principal_axes(mesh: &Mesh) -> Matrix3<f64> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let pts = mesh.sample_surface(4000, &mut rng);
    let n = pts.len().max(1) as f64;
    let mean = pts.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let cov = pts.iter().fold(Matrix3::zeros(), |a, p| {
        let d = p.coords - mean;
        a + d * d.transpose()
    }) / n;
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let mut axes = Matrix3::zeros();
    for (k, &i) in order.iter().enumerate() {
        let mut v: Vector3<f64> = eig.eigenvectors.column(i).into();
        // snap near-axis-aligned directions onto the object axes (meshes are usually modelled
        // axis-aligned; a 1-degree PCA wobble would tilt every candidate grasp)
        for j in 0..3 {
            if v[j].abs() > 0.999 {
                v = Vector3::ith(j, v[j].signum());
            }
        }
        axes.set_column(k, &v);
    }
    let z = axes.column(0).cross(&axes.column(1));
    axes.set_column(2, &z.normalize());
    axes
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh;

    #[test]
    fn box_is_a_convex_hull_with_its_extents() {
        let m = mesh::builtin_box([0.16, 0.06, 0.21], [[1, 2, 3], [4, 5, 6]]);
        let o = GraspObject::new(&m).unwrap();
        assert_eq!(o.kind(), SolidKind::ConvexHull);
        assert!(o.concavity() < 0.02, "{}", o.concavity());
        let (lo, hi) = o.extent_along(&Vector3::x());
        assert!((lo + 0.08).abs() < 1e-6 && (hi - 0.08).abs() < 1e-6);
        // largest spread first: z (0.21), then x (0.16), then y
        let a = o.principal_axes();
        assert!(a.column(0).z.abs() > 0.99 && a.column(1).x.abs() > 0.99, "{a}");
        // cached: same Arc
        let again = GraspObject::new(&m).unwrap();
        assert!(Arc::ptr_eq(&o.0, &again.0));
    }

    #[test]
    fn mug_is_concave_and_gets_decomposed() {
        let m = mesh::builtin("mug").unwrap();
        let o = GraspObject::new(&m).unwrap();
        assert!(o.concavity() > DECOMPOSE_ABOVE_CONCAVITY, "{}", o.concavity());
        assert_eq!(o.kind(), SolidKind::ConvexDecomposition);
        assert!(o.n_parts() > 1);
    }
}
