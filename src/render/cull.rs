//! Which faces of a mesh can never be seen, so the rasteriser may skip them.

use super::MAX_FLAWED_EDGE_FRACTION;
use crate::mesh::Mesh;
use std::collections::HashMap;

/// The faces that can be culled without changing any render: back faces (`Face::Back`) of a
/// closed mesh whose triangles are all counter-clockwise seen from outside, front faces of one
/// that is all clockwise; `None` (no culling) for open, non-manifold or inconsistently oriented
/// meshes. Vertices are welded by exact position first (scans duplicate vertices along seams).
/// Decimated scans often have a few flaws (YCB's mug: 14 hole edges of 13,468; the drill: 2
/// non-manifold ones): up to [`MAX_FLAWED_EDGE_FRACTION`] of flawed edges still count as closed,
/// so that only through those tiny holes could a render differ (background or a far front face
/// instead of an inner wall). YCB's master chef can (about 3 % flawed) is rendered unculled.
pub fn invisible_faces(mesh: &Mesh) -> Option<wgpu::Face> {
    let mut weld: HashMap<[u32; 3], u32> = HashMap::with_capacity(mesh.vertices_m.len());
    let ids: Vec<u32> = mesh
        .vertices_m
        .iter()
        .map(|v| {
            let key = v.map(|c| (c + 0.0).to_bits()); // + 0.0 maps -0.0 to 0.0
            let next = weld.len() as u32;
            *weld.entry(key).or_insert(next)
        })
        .collect();
    // Every directed edge exactly once, and its reverse exactly once.
    let mut edges: HashMap<(u32, u32), u32> = HashMap::with_capacity(mesh.triangles.len() * 3);
    let mut volume6 = 0.0f64;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| ids[i as usize]);
        if a == b || b == c || a == c {
            // Degenerate after welding (e.g. at the poles of a sphere): covers no pixel.
            continue;
        }
        for e in [(a, b), (b, c), (c, a)] {
            *edges.entry(e).or_insert(0) += 1;
        }
        let [p, q, r] = t.map(|i| mesh.vertices_m[i as usize].map(f64::from));
        volume6 += p[0] * (q[1] * r[2] - q[2] * r[1]) - p[1] * (q[0] * r[2] - q[2] * r[0])
            + p[2] * (q[0] * r[1] - q[1] * r[0]);
    }
    // Edges in the same direction twice (non-manifold, or neighbours wound oppositely) or
    // without their reverse (holes).
    let flawed = edges
        .iter()
        .filter(|&(&(a, b), &n)| n != 1 || !edges.contains_key(&(b, a)))
        .count();
    if flawed as f64 > MAX_FLAWED_EDGE_FRACTION * edges.len() as f64 || volume6 == 0.0 {
        return None;
    }
    Some(if volume6 > 0.0 {
        wgpu::Face::Back
    } else {
        wgpu::Face::Front
    })
}
