//! Reading the render targets back: row padding removed, the reversed z-buffer turned into
//! metric depth, views cut out of an atlas.

use super::batch::Target;
use super::{ClipRange, RenderError};

/// Whole render targets read back into memory (row padding removed).
pub(super) struct Readback {
    pub(super) width: u32,
    pub(super) depth_m: Vec<f32>,
    pub(super) color: Vec<[u8; 3]>,
    pub(super) instance: Vec<u16>,
}

impl Readback {
    pub(super) fn depth_tile(&self, x0: u32, y0: u32, w: u32, h: u32) -> Vec<f32> {
        tile(&self.depth_m, self.width, x0, y0, w, h)
    }
    pub(super) fn color_tile(&self, x0: u32, y0: u32, w: u32, h: u32) -> Vec<[u8; 3]> {
        tile(&self.color, self.width, x0, y0, w, h)
    }
}

pub(super) fn tile<T: Copy>(data: &[T], width: u32, x0: u32, y0: u32, w: u32, h: u32) -> Vec<T> {
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in y0..y0 + h {
        let start = (y * width + x0) as usize;
        out.extend_from_slice(&data[start..start + w as usize]);
    }
    out
}

/// Turns reversed z-buffer values (`d = near (far - z) / ((far - near) z)`, see mesh.wgsl;
/// 0 = cleared, nothing drawn) into metric z-depth. In f32 the z-buffer resolves about 1e-7 of
/// the depth (0.1 micrometre at 1 m).
pub(super) fn zbuffer_to_metric(values: &mut [f32], clip: ClipRange) {
    let (near, far) = (clip.near_m as f64, clip.far_m as f64);
    for v in values.iter_mut() {
        if *v > 0.0 {
            *v = (near * far / (*v as f64 * (far - near) + near)) as f32;
        }
    }
}

/// [`read_rows`] for `f32` targets: whole rows at once where the mapping is aligned (it is: rows
/// start at multiples of 256 bytes), value by value otherwise.
pub(super) fn read_f32_rows(t: &Target, width: u32, height: u32) -> Result<Vec<f32>, RenderError> {
    let mut out = Vec::with_capacity((width * height) as usize);
    {
        let mapped = t
            .readback
            .get_mapped_range(..)
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        for y in 0..height as usize {
            let row = &mapped[y * t.padded_bytes_per_row as usize..][..width as usize * 4];
            match bytemuck::try_cast_slice::<u8, f32>(row) {
                Ok(values) if cfg!(target_endian = "little") => out.extend_from_slice(values),
                _ => out.extend(
                    row.chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                ),
            }
        }
    }
    t.readback.unmap();
    Ok(out)
}

/// Reads a mapped readback buffer row by row (dropping the row padding), then unmaps it.
pub(super) fn read_rows<T>(
    t: &Target,
    width: u32,
    height: u32,
    convert: impl Fn(&[u8]) -> T,
) -> Result<Vec<T>, RenderError> {
    let mut out = Vec::with_capacity((width * height) as usize);
    {
        let mapped = t
            .readback
            .get_mapped_range(..)
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        let bpp = t.bytes_per_pixel as usize;
        for y in 0..height as usize {
            let row = &mapped[y * t.padded_bytes_per_row as usize..][..width as usize * bpp];
            out.extend(row.chunks_exact(bpp).map(&convert));
        }
    }
    t.readback.unmap();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_are_cut_from_the_atlas() {
        let data: Vec<u32> = (0..12).collect(); // 4 x 3
        assert_eq!(tile(&data, 4, 1, 1, 2, 2), vec![5, 6, 9, 10]);
    }
}
