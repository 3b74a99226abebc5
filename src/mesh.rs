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
            MeshFormat::Ply => parse_ply(bytes)?,
            MeshFormat::Obj => parse_obj(bytes)?,
            MeshFormat::Stl => parse_stl(bytes)?,
        };
        Self::new(v, c, t)
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
// Parsers

type Parsed = (Vec<[f32; 3]>, Option<Vec<[u8; 3]>>, Vec<[u32; 3]>);

fn perr(format: &'static str, reason: impl Into<String>) -> MeshError {
    MeshError::Parse {
        format,
        reason: reason.into(),
    }
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum PlyType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl PlyType {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
    fn read(self, b: &[u8], big: bool) -> f64 {
        macro_rules! rd {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                (if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => rd!(i16, 2),
            Self::U16 => rd!(u16, 2),
            Self::I32 => rd!(i32, 4),
            Self::U32 => rd!(u32, 4),
            Self::F32 => rd!(f32, 4),
            Self::F64 => rd!(f64, 8),
        }
    }
}

#[derive(Debug)]
enum PlyProp {
    Scalar(String, PlyType),
    List(String, PlyType, PlyType),
}

struct PlyElement {
    name: String,
    count: usize,
    props: Vec<PlyProp>,
}

fn parse_ply(bytes: &[u8]) -> Result<Parsed, MeshError> {
    const F: &str = "PLY";
    let header_end = bytes
        .windows(10)
        .position(|w| w == b"end_header")
        .ok_or_else(|| perr(F, "no end_header line"))?;
    let mut body_start = header_end + 10;
    while body_start < bytes.len() && (bytes[body_start] == b'\r' || bytes[body_start] == b' ') {
        body_start += 1;
    }
    if body_start < bytes.len() && bytes[body_start] == b'\n' {
        body_start += 1;
    }
    let header = std::str::from_utf8(&bytes[..header_end]).map_err(|_| perr(F, "header is not text"))?;
    let mut format = None;
    let mut elements: Vec<PlyElement> = Vec::new();
    for line in header.lines() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.first().copied() {
            Some("format") => format = w.get(1).map(|s| s.to_string()),
            Some("element") => {
                let name = w.get(1).ok_or_else(|| perr(F, "element without a name"))?.to_string();
                let count: usize = w
                    .get(2)
                    .and_then(|s| s.parse().ok())
                    .ok_or_else(|| perr(F, "element count"))?;
                if count > 10 * MAX_TRIANGLES {
                    return Err(MeshError::TooManyTriangles(count));
                }
                elements.push(PlyElement {
                    name,
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let el = elements.last_mut().ok_or_else(|| perr(F, "property before element"))?;
                if w.get(1) == Some(&"list") {
                    let ct = w
                        .get(2)
                        .and_then(|s| PlyType::parse(s))
                        .ok_or_else(|| perr(F, "list count type"))?;
                    let it = w
                        .get(3)
                        .and_then(|s| PlyType::parse(s))
                        .ok_or_else(|| perr(F, "list item type"))?;
                    el.props
                        .push(PlyProp::List(w.get(4).unwrap_or(&"").to_string(), ct, it));
                } else {
                    let t = w
                        .get(1)
                        .and_then(|s| PlyType::parse(s))
                        .ok_or_else(|| perr(F, format!("property type in '{line}'")))?;
                    el.props.push(PlyProp::Scalar(w.get(2).unwrap_or(&"").to_string(), t));
                }
            }
            _ => {}
        }
    }
    let format = format.ok_or_else(|| perr(F, "no format line"))?;
    let body = &bytes[body_start..];
    let mut verts = Vec::new();
    let mut cols = Vec::new();
    let mut has_color = false;
    let mut tris = Vec::new();

    // One record reader for both encodings: yields property values element by element.
    enum Src<'a> {
        Ascii(std::str::SplitAsciiWhitespace<'a>),
        Bin { data: &'a [u8], pos: usize, big: bool },
    }
    impl Src<'_> {
        fn next(&mut self, t: PlyType) -> Result<f64, MeshError> {
            match self {
                Src::Ascii(it) => it
                    .next()
                    .and_then(|s| s.parse::<f64>().ok())
                    .ok_or_else(|| perr("PLY", "truncated or non-numeric ASCII body")),
                Src::Bin { data, pos, big } => {
                    let n = t.size();
                    if *pos + n > data.len() {
                        return Err(perr("PLY", "truncated binary body"));
                    }
                    let v = t.read(&data[*pos..*pos + n], *big);
                    *pos += n;
                    Ok(v)
                }
            }
        }
    }
    let mut src = match format.as_str() {
        "ascii" => Src::Ascii(
            std::str::from_utf8(body)
                .map_err(|_| perr(F, "ASCII body is not text"))?
                .split_ascii_whitespace(),
        ),
        "binary_little_endian" => Src::Bin {
            data: body,
            pos: 0,
            big: false,
        },
        "binary_big_endian" => Src::Bin {
            data: body,
            pos: 0,
            big: true,
        },
        other => return Err(perr(F, format!("unsupported format {other}"))),
    };
    for el in &elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        if is_vertex {
            has_color = el
                .props
                .iter()
                .any(|p| matches!(p, PlyProp::Scalar(n, _) if n == "red"));
            verts.reserve(el.count);
        }
        for _ in 0..el.count {
            let mut xyz = [0f32; 3];
            let mut rgb = [160u8; 3];
            for p in &el.props {
                match p {
                    PlyProp::Scalar(name, t) => {
                        let v = src.next(*t)?;
                        if is_vertex {
                            match name.as_str() {
                                "x" => xyz[0] = v as f32,
                                "y" => xyz[1] = v as f32,
                                "z" => xyz[2] = v as f32,
                                "red" | "r" => rgb[0] = v.clamp(0.0, 255.0) as u8,
                                "green" | "g" => rgb[1] = v.clamp(0.0, 255.0) as u8,
                                "blue" | "b" => rgb[2] = v.clamp(0.0, 255.0) as u8,
                                _ => {}
                            }
                        }
                    }
                    PlyProp::List(name, ct, it) => {
                        let n = src.next(*ct)?;
                        if !(0.0..=1024.0).contains(&n) {
                            return Err(perr(F, format!("list of {n} items")));
                        }
                        let mut idx = Vec::with_capacity(n as usize);
                        for _ in 0..n as usize {
                            idx.push(src.next(*it)?);
                        }
                        if is_face && (name == "vertex_indices" || name == "vertex_index") {
                            if idx.iter().any(|&i| i < 0.0) {
                                return Err(perr(F, "negative vertex index"));
                            }
                            for k in 1..idx.len().saturating_sub(1) {
                                tris.push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
                                if tris.len() > MAX_TRIANGLES {
                                    return Err(MeshError::TooManyTriangles(tris.len()));
                                }
                            }
                        }
                    }
                }
            }
            if is_vertex {
                verts.push(xyz);
                cols.push(rgb);
            }
        }
    }
    Ok((verts, has_color.then_some(cols), tris))
}

fn parse_obj(bytes: &[u8]) -> Result<Parsed, MeshError> {
    const F: &str = "OBJ";
    let text = std::str::from_utf8(bytes).map_err(|_| perr(F, "not UTF-8 text"))?;
    let mut verts = Vec::new();
    let mut cols = Vec::new();
    let mut any_color = false;
    let mut tris = Vec::new();
    for (ln, line) in text.lines().enumerate() {
        let mut w = line.split_whitespace();
        match w.next() {
            Some("v") => {
                let nums: Vec<f64> = w
                    .map(|s| s.parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| perr(F, format!("line {}: bad vertex", ln + 1)))?;
                if nums.len() < 3 {
                    return Err(perr(F, format!("line {}: vertex needs 3 coordinates", ln + 1)));
                }
                verts.push([nums[0] as f32, nums[1] as f32, nums[2] as f32]);
                if nums.len() >= 6 {
                    any_color = true;
                    let s = if nums[3..6].iter().any(|&c| c > 1.0) {
                        1.0
                    } else {
                        255.0
                    };
                    cols.push([
                        (nums[3] * s).clamp(0.0, 255.0) as u8,
                        (nums[4] * s).clamp(0.0, 255.0) as u8,
                        (nums[5] * s).clamp(0.0, 255.0) as u8,
                    ]);
                } else {
                    cols.push([160, 160, 160]);
                }
            }
            Some("f") => {
                let mut idx = Vec::new();
                for tok in w {
                    let first = tok.split('/').next().unwrap_or("");
                    let i: i64 = first
                        .parse()
                        .map_err(|_| perr(F, format!("line {}: bad face index '{tok}'", ln + 1)))?;
                    let i = if i < 0 { verts.len() as i64 + i } else { i - 1 };
                    if i < 0 {
                        return Err(perr(F, format!("line {}: face index out of range", ln + 1)));
                    }
                    idx.push(i as u32);
                }
                for k in 1..idx.len().saturating_sub(1) {
                    tris.push([idx[0], idx[k], idx[k + 1]]);
                }
                if tris.len() > MAX_TRIANGLES {
                    return Err(MeshError::TooManyTriangles(tris.len()));
                }
            }
            _ => {}
        }
    }
    Ok((verts, any_color.then_some(cols), tris))
}

fn parse_stl(bytes: &[u8]) -> Result<Parsed, MeshError> {
    const F: &str = "STL";
    let binary = bytes.len() >= 84 && {
        let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
        84 + n.saturating_mul(50) == bytes.len()
    };
    let mut verts = Vec::new();
    let mut tris = Vec::new();
    if binary {
        let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
        if n > MAX_TRIANGLES {
            return Err(MeshError::TooManyTriangles(n));
        }
        for t in 0..n {
            let rec = &bytes[84 + t * 50..84 + t * 50 + 50];
            for k in 0..3 {
                let off = 12 + k * 12;
                let f = |o: usize| f32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]]);
                verts.push([f(off), f(off + 4), f(off + 8)]);
            }
            let b = (t * 3) as u32;
            tris.push([b, b + 1, b + 2]);
        }
    } else {
        let text = std::str::from_utf8(bytes).map_err(|_| perr(F, "neither binary STL nor text"))?;
        if !text.trim_start().starts_with("solid") {
            return Err(perr(F, "ASCII STL must start with 'solid'"));
        }
        for line in text.lines() {
            let mut w = line.split_whitespace();
            if w.next() == Some("vertex") {
                let nums: Vec<f32> = w
                    .map(|s| s.parse::<f32>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| perr(F, "bad vertex"))?;
                if nums.len() != 3 {
                    return Err(perr(F, "vertex needs 3 coordinates"));
                }
                verts.push([nums[0], nums[1], nums[2]]);
            }
        }
        if verts.len() % 3 != 0 {
            return Err(perr(F, "vertex count is not a multiple of 3"));
        }
        for t in 0..verts.len() / 3 {
            let b = (t * 3) as u32;
            tris.push([b, b + 1, b + 2]);
        }
        if tris.len() > MAX_TRIANGLES {
            return Err(MeshError::TooManyTriangles(tris.len()));
        }
    }
    Ok((weld(&verts, &mut tris), None, tris))
}

/// Merges identical vertices (STL stores every triangle's corners separately).
fn weld(verts: &[[f32; 3]], tris: &mut [[u32; 3]]) -> Vec<[f32; 3]> {
    let mut map = std::collections::HashMap::new();
    let mut out = Vec::new();
    let mut remap = Vec::with_capacity(verts.len());
    for v in verts {
        let key = [v[0].to_bits(), v[1].to_bits(), v[2].to_bits()];
        let id = *map.entry(key).or_insert_with(|| {
            out.push(*v);
            out.len() as u32 - 1
        });
        remap.push(id);
    }
    for t in tris.iter_mut() {
        for i in t.iter_mut() {
            *i = remap[*i as usize];
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Built-in objects

/// Names of the procedural objects built into the binary.
pub const BUILTIN_OBJECTS: [&str; 3] = ["box", "can", "mug"];

/// A procedural object by name (see [`BUILTIN_OBJECTS`]).
pub fn builtin(name: &str) -> Option<Mesh> {
    match name {
        "box" => Some(builtin_box([0.16, 0.06, 0.21], [[200, 40, 30], [240, 200, 40]])),
        "can" => Some(builtin_cylinder(0.051, 0.14, 48, [[40, 70, 160], [200, 200, 210]])),
        "mug" => Some(builtin_mug()),
        _ => None,
    }
}

/// A box centred at the origin with sides `size_m` (x, y, z); the +x half gets the second
/// colour so that the box is not colour-symmetric.
pub fn builtin_box(size_m: [f64; 3], colors: [[u8; 3]; 2]) -> Mesh {
    let mut b = Builder::default();
    b.add_box(Vector3::zeros(), Vector3::from(size_m) * 0.5, colors);
    b.finish()
}

/// A closed cylinder along z, centred at the origin; a stripe of the second colour on +x.
pub fn builtin_cylinder(radius_m: f64, height_m: f64, segments: usize, colors: [[u8; 3]; 2]) -> Mesh {
    let mut b = Builder::default();
    b.add_cylinder(Vector3::zeros(), radius_m, height_m, segments, colors, true);
    b.finish()
}

/// A cup with a handle on +x: an open cylinder (outer wall, inner wall, rim, bottom) plus a
/// box-shaped handle.
pub fn builtin_mug() -> Mesh {
    let mut b = Builder::default();
    let (r, h, wall) = (0.04, 0.09, 0.006);
    b.add_tube(r, r - wall, h, 40, [230, 230, 225]);
    b.add_box(
        Vector3::new(r + 0.014, 0.0, 0.0),
        Vector3::new(0.016, 0.006, 0.028),
        [[180, 40, 40], [180, 40, 40]],
    );
    b.finish()
}

#[derive(Default)]
struct Builder {
    v: Vec<[f32; 3]>,
    c: Vec<[u8; 3]>,
    t: Vec<[u32; 3]>,
}

impl Builder {
    fn push(&mut self, p: Vector3<f64>, c: [u8; 3]) -> u32 {
        self.v.push([p.x as f32, p.y as f32, p.z as f32]);
        self.c.push(c);
        self.v.len() as u32 - 1
    }
    fn quad(&mut self, a: u32, b: u32, c: u32, d: u32) {
        self.t.push([a, b, c]);
        self.t.push([a, c, d]);
    }
    fn add_box(&mut self, center: Vector3<f64>, half: Vector3<f64>, colors: [[u8; 3]; 2]) {
        // six faces, each with its own 4 vertices (flat colour), counter-clockwise from outside
        for axis in 0..3 {
            for sign in [-1.0, 1.0] {
                let n = Vector3::ith(axis, sign);
                let u = Vector3::ith((axis + 1) % 3, 1.0);
                let w = n.cross(&u);
                let col = if (center + n.component_mul(&half)).x > 1e-9 && axis == 0 {
                    colors[1]
                } else {
                    colors[0]
                };
                let corner = |su: f64, sw: f64| {
                    center + n.component_mul(&half) + (u * su).component_mul(&half) + (w * sw).component_mul(&half)
                };
                let a = self.push(corner(-1.0, -1.0), col);
                let b = self.push(corner(1.0, -1.0), col);
                let c = self.push(corner(1.0, 1.0), col);
                let d = self.push(corner(-1.0, 1.0), col);
                self.quad(a, b, c, d);
            }
        }
    }
    fn add_cylinder(&mut self, center: Vector3<f64>, r: f64, h: f64, n: usize, colors: [[u8; 3]; 2], caps: bool) {
        let ring = |k: usize, z: f64| {
            let a = k as f64 / n as f64 * std::f64::consts::TAU;
            center + Vector3::new(r * a.cos(), r * a.sin(), z)
        };
        let col = |k: usize| {
            if (k as f64 / n as f64) < 0.12 || (k as f64 / n as f64) > 0.88 {
                colors[1]
            } else {
                colors[0]
            }
        };
        let mut bottom = Vec::new();
        let mut top = Vec::new();
        for k in 0..n {
            bottom.push(self.push(ring(k, -h / 2.0), col(k)));
            top.push(self.push(ring(k, h / 2.0), col(k)));
        }
        for k in 0..n {
            let k2 = (k + 1) % n;
            self.quad(bottom[k], bottom[k2], top[k2], top[k]);
        }
        if caps {
            let cb = self.push(center - Vector3::new(0.0, 0.0, h / 2.0), colors[0]);
            let ct = self.push(center + Vector3::new(0.0, 0.0, h / 2.0), colors[0]);
            for k in 0..n {
                let k2 = (k + 1) % n;
                self.t.push([cb, bottom[k2], bottom[k]]);
                self.t.push([ct, top[k], top[k2]]);
            }
        }
    }
    fn add_tube(&mut self, r_out: f64, r_in: f64, h: f64, n: usize, color: [u8; 3]) {
        let ring = |k: usize, r: f64, z: f64| {
            let a = k as f64 / n as f64 * std::f64::consts::TAU;
            Vector3::new(r * a.cos(), r * a.sin(), z)
        };
        let (z0, z1, zb) = (-h / 2.0, h / 2.0, -h / 2.0 + 0.008);
        let mut ob = Vec::new();
        let mut ot = Vec::new();
        let mut ib = Vec::new();
        let mut it = Vec::new();
        for k in 0..n {
            ob.push(self.push(ring(k, r_out, z0), color));
            ot.push(self.push(ring(k, r_out, z1), color));
            ib.push(self.push(ring(k, r_in, zb), color));
            it.push(self.push(ring(k, r_in, z1), color));
        }
        let cb = self.push(Vector3::new(0.0, 0.0, z0), color);
        let ci = self.push(Vector3::new(0.0, 0.0, zb), color);
        for k in 0..n {
            let k2 = (k + 1) % n;
            self.quad(ob[k], ob[k2], ot[k2], ot[k]); // outer wall, outward
            self.quad(ib[k2], ib[k], it[k], it[k2]); // inner wall, facing the axis
            self.quad(ot[k], ot[k2], it[k2], it[k]); // rim
            self.t.push([cb, ob[k2], ob[k]]); // bottom, facing down
            self.t.push([ci, ib[k], ib[k2]]); // inside floor, facing up
        }
    }
    fn finish(self) -> Mesh {
        Mesh {
            vertices_m: self.v,
            colors: self.c,
            triangles: self.t,
        }
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
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/ycb");
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
