//! Wavefront OBJ: `v` (with optional vertex colours) and `f` lines; polygons are fanned.

use super::{MAX_TRIANGLES, MeshError, Parsed, perr};

pub(super) fn parse(bytes: &[u8]) -> Result<Parsed, MeshError> {
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
