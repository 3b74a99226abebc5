//! Triangle meshes in metres: loading (PLY binary/ASCII, OBJ, STL), validation, measures,
//! surface sampling, and procedural built-in objects so the service runs without any file.

use nalgebra::{Point3, Vector3};
use rand::Rng;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::Path;

/// Most triangles a mesh may have (uploads and files).
pub const MAX_TRIANGLES: usize = 200_000;
/// Largest extent a mesh may have, metres (catches meshes in millimetres).
pub const MAX_EXTENT_M: f64 = 2.0;
/// Largest mesh file we read, bytes.
pub const MAX_MESH_BYTES: usize = 64 * 1024 * 1024;

#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("cannot read mesh file {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("unknown mesh format (expected PLY, OBJ or STL): {0}")]
    UnknownFormat(String),
    #[error("malformed {format} mesh: {reason}")]
    Parse { format: &'static str, reason: String },
    #[error("mesh has no triangles")]
    Empty,
    #[error("mesh has {0} triangles; the limit is {MAX_TRIANGLES}")]
    TooManyTriangles(usize),
    #[error("mesh file is {0} bytes; the limit is {MAX_MESH_BYTES}")]
    TooLarge(usize),
    #[error("mesh has a non-finite vertex coordinate")]
    NonFinite,
    #[error("triangle {triangle} refers to vertex {index}, but the mesh has {n_vertices} vertices")]
    BadIndex {
        triangle: usize,
        index: u32,
        n_vertices: usize,
    },
    #[error("mesh extent {extent_m:.3} m exceeds {MAX_EXTENT_M} m: is it in millimetres? Meshes must be in metres")]
    TooBig { extent_m: f64 },
    #[error("mesh is degenerate: all triangles have zero area")]
    Degenerate,
}

/// Mesh file formats we read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum MeshFormat {
    Ply,
    Obj,
    Stl,
}

impl MeshFormat {
    /// From a file name's extension.
    pub fn from_path(path: &Path) -> Option<Self> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "ply" => Some(Self::Ply),
            "obj" => Some(Self::Obj),
            "stl" => Some(Self::Stl),
            _ => None,
        }
    }
    /// Guess from the content (PLY magic, binary STL size, `solid`, OBJ `v ` lines).
    pub fn sniff(bytes: &[u8]) -> Option<Self> {
        if bytes.starts_with(b"ply") {
            return Some(Self::Ply);
        }
        if bytes.len() >= 84 {
            let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
            if 84 + n * 50 == bytes.len() {
                return Some(Self::Stl);
            }
        }
        if bytes.starts_with(b"solid") {
            return Some(Self::Stl);
        }
        let head = String::from_utf8_lossy(&bytes[..bytes.len().min(4096)]);
        if head.lines().any(|l| l.starts_with("v ") || l.starts_with("f ")) {
            return Some(Self::Obj);
        }
        None
    }
}

/// A triangle mesh in metres, in the object's frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    pub vertices_m: Vec<[f32; 3]>,
    /// Per-vertex colour (RGB); grey when the file has none.
    pub colors: Vec<[u8; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// Axis-aligned bounds, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    pub min_m: Vector3<f64>,
    pub max_m: Vector3<f64>,
}

impl Bounds {
    pub fn extents_m(&self) -> Vector3<f64> {
        self.max_m - self.min_m
    }
    pub fn center_m(&self) -> Vector3<f64> {
        (self.max_m + self.min_m) * 0.5
    }
}

impl Mesh {
    /// Builds and validates a mesh.
    pub fn new(
        vertices_m: Vec<[f32; 3]>,
        colors: Option<Vec<[u8; 3]>>,
        triangles: Vec<[u32; 3]>,
    ) -> Result<Self, MeshError> {
        let colors = match colors {
            Some(c) if c.len() == vertices_m.len() => c,
            _ => vec![[160, 160, 160]; vertices_m.len()],
        };
        let m = Self {
            vertices_m,
            colors,
            triangles,
        };
        m.validate()?;
        Ok(m)
    }

    /// Empty, non-finite, bad indices, too many triangles, too large (millimetres?), degenerate.
    pub fn validate(&self) -> Result<(), MeshError> {
        if self.triangles.is_empty() || self.vertices_m.is_empty() {
            return Err(MeshError::Empty);
        }
        if self.triangles.len() > MAX_TRIANGLES {
            return Err(MeshError::TooManyTriangles(self.triangles.len()));
        }
        if self.vertices_m.iter().flatten().any(|v| !v.is_finite()) {
            return Err(MeshError::NonFinite);
        }
        let n = self.vertices_m.len();
        for (t, tri) in self.triangles.iter().enumerate() {
            for &i in tri {
                if i as usize >= n {
                    return Err(MeshError::BadIndex {
                        triangle: t,
                        index: i,
                        n_vertices: n,
                    });
                }
            }
        }
        let ext = self.bounds().extents_m().max();
        if ext > MAX_EXTENT_M {
            return Err(MeshError::TooBig { extent_m: ext });
        }
        if self.surface_area_m2() <= 1e-12 {
            return Err(MeshError::Degenerate);
        }
        Ok(())
    }

    /// Reads a mesh file; the format comes from the extension, else from the content.
    pub fn load(path: &Path) -> Result<Self, MeshError> {
        let bytes = std::fs::read(path).map_err(|source| MeshError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let format = MeshFormat::from_path(path)
            .or_else(|| MeshFormat::sniff(&bytes))
            .ok_or_else(|| MeshError::UnknownFormat(path.display().to_string()))?;
        Self::from_bytes(&bytes, format)
    }

    /// Parses a mesh held in memory.
    pub fn from_bytes(bytes: &[u8], format: MeshFormat) -> Result<Self, MeshError> {
        if bytes.len() > MAX_MESH_BYTES {
            return Err(MeshError::TooLarge(bytes.len()));
        }
        let (v, c, t) = match format {
            MeshFormat::Ply => ply::parse(bytes)?,
            MeshFormat::Obj => obj::parse(bytes)?,
            MeshFormat::Stl => stl::parse(bytes)?,
        };
        Self::new(v, c, t)
    }

    /// The mesh as parry3d's triangle mesh (for distances to its surface); `None` when parry3d
    /// rejects it.
    pub fn to_parry(&self) -> Option<parry3d::shape::TriMesh> {
        parry3d::shape::TriMesh::new(self.parry_vertices(), self.triangles.clone()).ok()
    }

    /// The convex hull of the vertices (parry3d's); `None` for a flat or degenerate mesh.
    pub fn convex_hull(&self) -> Option<parry3d::shape::ConvexPolyhedron> {
        parry3d::shape::ConvexPolyhedron::from_convex_hull(&self.parry_vertices())
    }

    fn parry_vertices(&self) -> Vec<parry3d::math::Vector> {
        self.vertices_m
            .iter()
            .map(|v| parry3d::math::Vector::new(v[0], v[1], v[2]))
            .collect()
    }

    pub fn vertex(&self, i: u32) -> Point3<f64> {
        let v = self.vertices_m[i as usize];
        Point3::new(v[0] as f64, v[1] as f64, v[2] as f64)
    }

    pub fn bounds(&self) -> Bounds {
        let mut min = Vector3::repeat(f64::INFINITY);
        let mut max = Vector3::repeat(f64::NEG_INFINITY);
        for v in &self.vertices_m {
            for k in 0..3 {
                min[k] = min[k].min(v[k] as f64);
                max[k] = max[k].max(v[k] as f64);
            }
        }
        Bounds { min_m: min, max_m: max }
    }

    /// Largest distance between two vertices (exact for small meshes, on the convex hull's
    /// candidates otherwise: vertices extreme along 26 directions, then all pairs of those plus
    /// a sample).
    pub fn diameter_m(&self) -> f64 {
        let pts: Vec<Point3<f64>> = (0..self.vertices_m.len() as u32).map(|i| self.vertex(i)).collect();
        let cand: Vec<Point3<f64>> = if pts.len() <= 3000 {
            pts
        } else {
            let mut c = Vec::new();
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        if dx == 0 && dy == 0 && dz == 0 {
                            continue;
                        }
                        let d = Vector3::new(dx as f64, dy as f64, dz as f64);
                        if let Some(p) = pts.iter().max_by(|a, b| a.coords.dot(&d).total_cmp(&b.coords.dot(&d))) {
                            c.push(*p);
                        }
                    }
                }
            }
            c.extend(pts.iter().step_by(pts.len() / 2000 + 1).copied());
            c
        };
        let mut best: f64 = 0.0;
        for i in 0..cand.len() {
            for j in i + 1..cand.len() {
                best = best.max((cand[i] - cand[j]).norm_squared());
            }
        }
        best.sqrt()
    }

    fn triangle_area(&self, t: &[u32; 3]) -> f64 {
        let (a, b, c) = (self.vertex(t[0]), self.vertex(t[1]), self.vertex(t[2]));
        (b - a).cross(&(c - a)).norm() * 0.5
    }

    pub fn surface_area_m2(&self) -> f64 {
        self.triangles.iter().map(|t| self.triangle_area(t)).sum()
    }

    /// Points uniformly distributed over the surface (area-weighted).
    pub fn sample_surface(&self, n: usize, rng: &mut impl Rng) -> Vec<Point3<f64>> {
        let mut cdf = Vec::with_capacity(self.triangles.len());
        let mut acc = 0.0;
        for t in &self.triangles {
            acc += self.triangle_area(t);
            cdf.push(acc);
        }
        (0..n)
            .map(|_| {
                let x = rng.random::<f64>() * acc;
                let k = cdf.partition_point(|&c| c < x).min(self.triangles.len() - 1);
                let t = self.triangles[k];
                let (a, b, c) = (self.vertex(t[0]), self.vertex(t[1]), self.vertex(t[2]));
                let (mut r1, mut r2) = (rng.random::<f64>(), rng.random::<f64>());
                if r1 + r2 > 1.0 {
                    r1 = 1.0 - r1;
                    r2 = 1.0 - r2;
                }
                a + (b - a) * r1 + (c - a) * r2
            })
            .collect()
    }

    /// Unnormalised face normal of each triangle (outward for counter-clockwise winding).
    pub fn face_normals(&self) -> Vec<Vector3<f64>> {
        self.triangles
            .iter()
            .map(|t| {
                let (a, b, c) = (self.vertex(t[0]), self.vertex(t[1]), self.vertex(t[2]));
                (b - a).cross(&(c - a))
            })
            .collect()
    }

    /// SHA-256 of the geometry and colours: the key of every cache derived from the mesh.
    pub fn content_hash(&self) -> String {
        let mut h = Sha256::new();
        for v in &self.vertices_m {
            for x in v {
                h.update(x.to_le_bytes());
            }
        }
        for c in &self.colors {
            h.update(c);
        }
        for t in &self.triangles {
            for i in t {
                h.update(i.to_le_bytes());
            }
        }
        h.finalize().iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Binary little-endian PLY with `x y z` floats, `red green blue` uchars, triangle faces
    /// (the layout of the YCB meshes in `shared/ycb`).
    pub fn to_ply_bytes(&self) -> Vec<u8> {
        let mut out = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
            self.vertices_m.len(),
            self.triangles.len()
        )
        .into_bytes();
        for (v, c) in self.vertices_m.iter().zip(&self.colors) {
            for x in v {
                out.extend_from_slice(&x.to_le_bytes());
            }
            out.extend_from_slice(c);
        }
        for t in &self.triangles {
            out.push(3);
            for i in t {
                out.extend_from_slice(&(*i as i32).to_le_bytes());
            }
        }
        out
    }
}

// ---------------------------------------------------------------------------------------------
// Parsers (one file per format) and the built-in shapes

mod builtin;
mod obj;
mod ply;
mod stl;

pub use builtin::{BUILTIN_OBJECTS, builtin, builtin_box, builtin_cylinder, builtin_mug};

/// What a parser gives: vertices, optional vertex colours, triangles.
type Parsed = (Vec<[f32; 3]>, Option<Vec<[u8; 3]>>, Vec<[u32; 3]>);

fn perr(format: &'static str, reason: impl Into<String>) -> MeshError {
    MeshError::Parse {
        format,
        reason: reason.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn builtins_are_valid_and_sized_in_metres() {
        for name in BUILTIN_OBJECTS {
            let m = builtin(name).unwrap();
            m.validate().unwrap();
            let d = m.diameter_m();
            assert!(d > 0.05 && d < 0.4, "{name}: diameter {d}");
        }
        let b = builtin("box").unwrap();
        let e = b.bounds().extents_m();
        assert!((e.x - 0.16).abs() < 1e-6 && (e.z - 0.21).abs() < 1e-6);
        // box is closed with outward normals: signed volume is positive
        let vol: f64 = b
            .triangles
            .iter()
            .map(|t| {
                b.vertex(t[0])
                    .coords
                    .dot(&b.vertex(t[1]).coords.cross(&b.vertex(t[2]).coords))
                    / 6.0
            })
            .sum();
        assert!((vol - 0.16 * 0.06 * 0.21).abs() < 1e-6, "volume {vol}");
    }

    #[test]
    fn ply_round_trip_binary_and_ascii() {
        let m = builtin("can").unwrap();
        let bytes = m.to_ply_bytes();
        let back = Mesh::from_bytes(&bytes, MeshFormat::Ply).unwrap();
        assert_eq!(back, m);
        let ascii = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n0.1 0 0\n0.1 0.1 0\n0 0.1 0\n4 0 1 2 3\n";
        let q = Mesh::from_bytes(ascii.as_bytes(), MeshFormat::Ply).unwrap();
        assert_eq!(q.triangles.len(), 2);
    }

    #[test]
    fn obj_and_stl_parse() {
        let obj = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1/1 2/2 3/3\n";
        let m = Mesh::from_bytes(obj.as_bytes(), MeshFormat::Obj).unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
        let stl = "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0.1 0 0\nvertex 0 0.1 0\nendloop\nendfacet\nendsolid t\n";
        let s = Mesh::from_bytes(stl.as_bytes(), MeshFormat::Stl).unwrap();
        assert_eq!(s.vertices_m.len(), 3);
        let mut bin = vec![0u8; 80];
        bin.extend_from_slice(&1u32.to_le_bytes());
        bin.extend_from_slice(&[0u8; 12]);
        for v in [[0f32, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]] {
            for x in v {
                bin.extend_from_slice(&x.to_le_bytes());
            }
        }
        bin.extend_from_slice(&[0u8; 2]);
        assert_eq!(MeshFormat::sniff(&bin), Some(MeshFormat::Stl));
        assert_eq!(Mesh::from_bytes(&bin, MeshFormat::Stl).unwrap().triangles.len(), 1);
    }

    #[test]
    fn truncated_ascii_stl_is_refused() {
        let facet = "facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0.1 0 0\nvertex 0 0.1 0\nendloop\nendfacet\n";
        let whole = format!("solid t\n{facet}{facet}endsolid t\n");
        assert!(Mesh::from_bytes(whole.as_bytes(), MeshFormat::Stl).is_ok());
        // Cut after the first whole facet: three vertices, so only the missing end shows it.
        let cut = format!("solid t\n{facet}");
        assert!(matches!(
            Mesh::from_bytes(cut.as_bytes(), MeshFormat::Stl),
            Err(MeshError::Parse { format: "STL", .. })
        ));
    }

    #[test]
    fn broken_meshes_are_rejected_with_reasons() {
        assert!(matches!(
            Mesh::from_bytes(b"ply\nformat ascii 1.0\nend_header\n", MeshFormat::Ply),
            Err(MeshError::Empty)
        ));
        assert!(matches!(
            Mesh::from_bytes(b"garbage", MeshFormat::Ply),
            Err(MeshError::Parse { .. })
        ));
        assert!(matches!(
            Mesh::from_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", MeshFormat::Obj),
            Err(MeshError::BadIndex { .. })
        ));
        assert!(matches!(
            Mesh::from_bytes(b"v 0 0 0\nv 100 0 0\nv 0 100 0\nf 1 2 3\n", MeshFormat::Obj),
            Err(MeshError::TooBig { .. })
        ));
        assert!(matches!(
            Mesh::from_bytes(b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", MeshFormat::Obj),
            Err(MeshError::NonFinite)
        ));
        assert!(matches!(
            Mesh::from_bytes(b"v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n", MeshFormat::Obj),
            Err(MeshError::Degenerate)
        ));
        let truncated = &builtin("box").unwrap().to_ply_bytes()[..300];
        assert!(matches!(
            Mesh::from_bytes(truncated, MeshFormat::Ply),
            Err(MeshError::Parse { .. })
        ));
    }

    #[test]
    fn surface_samples_lie_on_the_box() {
        let m = builtin("box").unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let half = [0.08, 0.03, 0.105];
        for p in m.sample_surface(500, &mut rng) {
            let on_face = (0..3).any(|k| (p[k].abs() - half[k]).abs() < 1e-6);
            assert!(on_face, "{p:?}");
        }
    }

    #[test]
    fn loads_every_shared_ycb_mesh() {
        let dir = crate::testing::shared_dir().join("ycb");
        if !dir.exists() {
            eprintln!("skipping: ../shared/ycb not present");
            return;
        }
        let info: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("models_info.json")).unwrap()).unwrap();
        for (_, o) in info.as_object().unwrap() {
            let m = Mesh::load(&dir.join(o["file"].as_str().unwrap())).unwrap();
            assert_eq!(m.triangles.len() as u64, o["n_triangles"].as_u64().unwrap());
            let d = m.diameter_m();
            assert!((d - o["diameter"].as_f64().unwrap()).abs() < 1e-3, "{} {d}", o["name"]);
        }
    }
}
