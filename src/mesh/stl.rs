//! STL, binary and ASCII; identical corners are welded into shared vertices.

use super::{MAX_TRIANGLES, MeshError, Parsed, perr};

pub(super) fn parse(bytes: &[u8]) -> Result<Parsed, MeshError> {
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
        // A cut-off upload otherwise passes whenever it ends after a whole facet.
        let last = text.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("");
        if !last.trim_start().starts_with("endsolid") {
            return Err(perr(F, "no closing 'endsolid' (truncated?)"));
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
