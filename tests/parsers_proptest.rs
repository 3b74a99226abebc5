//! Property tests of what parses client bytes: the frame meta, the depth/colour decode path and
//! the mesh parsers. Whatever the bytes, the answer is a value or an error, never a panic, and
//! an accepted image always has the camera's size. Few cases each, so they stay fast in CI.

use pregrasp::api::frames::{DepthEncoding, FrameMeta, decode_color, decode_depth};
use pregrasp::api::types::IntrinsicsDto;
use pregrasp::mesh::{Mesh, MeshFormat};
use proptest::prelude::*;

const W: u32 = 16;
const H: u32 = 12;

fn intrinsics() -> IntrinsicsDto {
    IntrinsicsDto {
        width: W,
        height: H,
        k: [20.0, 0.0, 8.0, 0.0, 20.0, 6.0, 0.0, 0.0, 1.0],
    }
}

fn png16(w: u32, h: u32, seed: u16) -> Vec<u8> {
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
        image::Luma([seed.wrapping_add((x * 31 + y * 7) as u16)])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("png");
    out.into_inner()
}

fn rgb_png(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, 7]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("png");
    out.into_inner()
}

/// `bytes` with a few bytes overwritten (positions and values from the strategy).
fn mutate(mut bytes: Vec<u8>, edits: &[(usize, u8)]) -> Vec<u8> {
    let n = bytes.len();
    for (i, v) in edits {
        bytes[i % n] = *v;
    }
    bytes
}

fn cube_ply_ascii() -> Vec<u8> {
    pregrasp::mesh::builtin("box").expect("box").to_ply_bytes()
}

fn obj_text() -> Vec<u8> {
    b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n".to_vec()
}

fn stl_binary() -> Vec<u8> {
    let tris: [[[f32; 3]; 3]; 2] = [
        [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]],
        [[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]],
    ];
    let mut out = vec![0u8; 80];
    out.extend_from_slice(&(tris.len() as u32).to_le_bytes());
    for t in tris {
        out.extend_from_slice(&[0u8; 12]);
        for v in t {
            for c in v {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        out.extend_from_slice(&[0u8; 2]);
    }
    out
}

fn check_mesh(result: Result<Mesh, pregrasp::mesh::MeshError>) {
    if let Ok(m) = result {
        // an accepted mesh indexes only its own vertices
        let n = m.vertices_m.len() as u32;
        assert!(m.triangles.iter().flatten().all(|i| *i < n));
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn frame_meta_parses_or_errs(bytes in proptest::collection::vec(any::<u8>(), 0..256)) {
        let _ = serde_json::from_slice::<FrameMeta>(&bytes);
    }

    #[test]
    fn frame_meta_with_any_numbers_parses_or_errs(
        stamp in any::<i64>(), scale in any::<f64>(), x in any::<f64>(), score in any::<f64>(),
        extra in any::<bool>(),
    ) {
        let mut meta = serde_json::json!({
            "stamp_ns": stamp,
            "depth_scale": scale,
            "detections": [{"object": "o", "bbox_xywh_px": [x, 1.0, 2.0, 3.0], "score": score}],
        });
        if extra {
            meta["unknown"] = serde_json::json!(1);
        }
        let parsed = serde_json::from_slice::<FrameMeta>(meta.to_string().as_bytes());
        // serde_json writes non-finite numbers as null, which is not a number
        if extra || !scale.is_finite() || !x.is_finite() || !score.is_finite() {
            prop_assert!(parsed.is_err());
        } else {
            prop_assert_eq!(parsed.expect("meta").stamp_ns, stamp);
        }
    }

    #[test]
    fn depth_png_decode_never_panics_and_keeps_the_camera_size(
        w in 1u32..40, h in 1u32..40, seed in any::<u16>(),
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..6),
        scale in prop_oneof![Just(1.0), Just(0.1), any::<f64>()],
    ) {
        let bytes = mutate(png16(w, h, seed), &edits);
        if let Ok(d) = decode_depth(&bytes, DepthEncoding::Png16, Some(scale), &intrinsics()) {
            prop_assert_eq!((d.width, d.height), (W, H));
            prop_assert!(d.data_m.iter().all(|v| v.is_finite() && *v >= 0.0));
        }
    }

    #[test]
    fn raw_depth_decode_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..(W * H * 4 + 8) as usize)) {
        if let Ok(d) = decode_depth(&bytes, DepthEncoding::F32le, None, &intrinsics()) {
            prop_assert_eq!(d.data_m.len(), (W * H) as usize);
            prop_assert!(d.data_m.iter().all(|v| v.is_finite() && *v >= 0.0));
        }
    }

    #[test]
    fn colour_decode_never_panics_and_keeps_the_camera_size(
        w in 1u32..40, h in 1u32..40,
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..6),
    ) {
        let bytes = mutate(rgb_png(w, h), &edits);
        if let Ok(c) = decode_color(&bytes, &intrinsics()) {
            prop_assert_eq!((c.width, c.height), (W, H));
        }
    }

    #[test]
    fn mesh_parsers_never_panic_on_any_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        for format in [MeshFormat::Ply, MeshFormat::Obj, MeshFormat::Stl] {
            check_mesh(Mesh::from_bytes(&bytes, format));
        }
    }

    #[test]
    fn mesh_parsers_never_panic_on_damaged_files(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8),
        cut in any::<usize>(),
    ) {
        for (bytes, format) in [
            (cube_ply_ascii(), MeshFormat::Ply),
            (obj_text(), MeshFormat::Obj),
            (stl_binary(), MeshFormat::Stl),
        ] {
            let damaged = mutate(bytes.clone(), &edits);
            check_mesh(Mesh::from_bytes(&damaged, format));
            let truncated = &bytes[..cut % (bytes.len() + 1)];
            check_mesh(Mesh::from_bytes(truncated, format));
        }
    }
}
