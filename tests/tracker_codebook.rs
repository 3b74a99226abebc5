//! Codebook cache: a second load comes from the cache; a corrupt, truncated or stale file is
//! detected and rebuilt, never trusted; a different key gets its own file.

#![allow(clippy::unwrap_used)] // test helpers: a failure is a test failure

use pregrasp::geometry::RotationGrid;
use pregrasp::tracker::Codebook;
use pregrasp::tracker::codebook::{CodebookConfig, CpuViews};

fn tiny_config() -> CodebookConfig {
    CodebookConfig {
        feature_px: 8,
        render_px: 16,
        code_dim: 16,
        color_code_dim: 4,
        n_train: 400,
        ..CodebookConfig::default()
    }
}

fn only_file(dir: &std::path::Path) -> std::path::PathBuf {
    let files: Vec<_> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(files.len(), 1, "{files:?}");
    files[0].clone()
}

#[test]
fn cache_hits_and_invalidation() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let grid = RotationGrid::new(30).unwrap();
    let cfg = tiny_config();
    let src = CpuViews(&mesh);
    let a = Codebook::load_or_build_with(&src, &mesh, grid, &cfg, Some(dir.path())).unwrap();
    assert!(!a.from_cache);
    let b = Codebook::load_or_build_with(&src, &mesh, grid, &cfg, Some(dir.path())).unwrap();
    assert!(b.from_cache);
    assert_eq!(a.codes, b.codes);
    assert_eq!(a.encoder.ridge_t, b.encoder.ridge_t);
    assert_eq!(a.encoder.blocks.len(), 2, "depth and colour codes of their own");
    assert_eq!(a.encoder.blocks, b.encoder.blocks);
    let path = only_file(dir.path());

    // flip one byte in the payload: checksum mismatch -> rebuilt (and rewritten)
    let mut bytes = std::fs::read(&path).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x5a;
    std::fs::write(&path, &bytes).unwrap();
    let c = Codebook::load_or_build_with(&src, &mesh, grid, &cfg, Some(dir.path())).unwrap();
    assert!(!c.from_cache, "a corrupt file must not be trusted");
    assert_eq!(c.codes, a.codes, "the rebuild is deterministic");
    assert!(
        Codebook::load_or_build_with(&src, &mesh, grid, &cfg, Some(dir.path()))
            .unwrap()
            .from_cache
    );

    // truncated file
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 3]).unwrap();
    assert!(
        !Codebook::load_or_build_with(&src, &mesh, grid, &cfg, Some(dir.path()))
            .unwrap()
            .from_cache
    );

    // a valid file of another key renamed onto this key's name: stale header -> rebuilt
    let other_cfg = CodebookConfig {
        color_weight: 0.3,
        ..cfg.clone()
    };
    let other_dir = tempfile::tempdir().unwrap();
    Codebook::load_or_build_with(&src, &mesh, grid, &other_cfg, Some(other_dir.path())).unwrap();
    std::fs::copy(only_file(other_dir.path()), &path).unwrap();
    assert!(
        !Codebook::load_or_build_with(&src, &mesh, grid, &cfg, Some(dir.path()))
            .unwrap()
            .from_cache
    );

    // another mesh gets its own file
    let mug = pregrasp::mesh::builtin("mug").unwrap();
    let m = Codebook::load_or_build_with(&CpuViews(&mug), &mug, grid, &cfg, Some(dir.path())).unwrap();
    assert!(!m.from_cache);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
}

/// The box-centred table is built only when asked for (`box_table`, derived from the tracker's
/// `observation.box_codes`); a book with it and one without are separate cache files, both
/// round-trip, and the flag stays out of the serialised settings.
#[test]
fn the_box_centred_table_is_built_and_cached_only_when_asked_for() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = pregrasp::mesh::builtin("mug").unwrap();
    let grid = RotationGrid::new(30).unwrap();
    let plain = tiny_config();
    let boxed = CodebookConfig {
        box_table: true,
        ..plain.clone()
    };
    assert_eq!(
        serde_json::to_string(&plain).unwrap(),
        serde_json::to_string(&boxed).unwrap(),
        "a derived flag, not a setting"
    );
    let src = CpuViews(&mesh);
    let a = Codebook::load_or_build_with(&src, &mesh, grid, &plain, Some(dir.path())).unwrap();
    assert!(a.box_table.is_none());
    let b = Codebook::load_or_build_with(&src, &mesh, grid, &boxed, Some(dir.path())).unwrap();
    assert!(!b.from_cache, "the plain book's file must not answer for the boxed one");
    let table = b.box_table.as_ref().expect("the box table");
    assert_eq!(table.codes.to_f32().len(), a.codes.to_f32().len());
    assert_eq!(table.median_depth_norm.len(), grid.len());
    assert_ne!(table.codes, a.codes, "the mug's box is off its origin");
    assert_eq!(b.codes, a.codes, "the origin-centred table is the same either way");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    for (cfg, has) in [(&plain, false), (&boxed, true)] {
        let c = Codebook::load_or_build_with(&src, &mesh, grid, cfg, Some(dir.path())).unwrap();
        assert!(c.from_cache);
        assert_eq!(c.box_table.is_some(), has);
        assert_eq!(c.config, *cfg);
    }
    let c = Codebook::load_or_build_with(&src, &mesh, grid, &boxed, Some(dir.path())).unwrap();
    assert_eq!(c.box_table.unwrap().codes, table.codes);
    // without the table, a box-centred lookup falls back to the origin-centred codes
    assert_eq!(*a.table(true), a.codes);
    assert_eq!(*b.table(true), table.codes);
}

#[test]
fn codes_are_unit_and_in_plane_bins_are_image_rotations() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let grid = RotationGrid::new(15).unwrap();
    let cb = Codebook::build(&CpuViews(&mesh), &mesh, grid, &CodebookConfig::coarse()).unwrap();
    for b in (0..grid.len()).step_by(97) {
        let n: f32 = cb.code(b).iter().map(|v| v * v).sum();
        // unit rows, stored as half floats (11 bits of mantissa)
        assert!((n - 1.0).abs() < 2e-3, "bin {b}: {n}");
    }
    // a render made directly at an in-plane angle matches the bin built by rotating the image
    use pregrasp::tracker::observation::{ViewImage, encode_particles, match_codes};
    let k = pregrasp::camera::Intrinsics::from_focal(96, 96, 200.0).unwrap();
    let bin = pregrasp::geometry::BinIndex {
        elevation: 5,
        azimuth: 7,
        inplane: 5,
    };
    let r = grid.rotation(bin);
    let pos = nalgebra::Vector3::new(0.0, 0.0, 0.6);
    let pose = pregrasp::geometry::Pose::from_parts(nalgebra::Translation3::from(pos), r);
    let img = pregrasp::tracker::raster::render(&k, &[(&mesh, pose)], 0.01, [0, 0, 0]);
    let view = ViewImage {
        intrinsics: &k,
        depth: &img.depth,
        color: Some(&img.color),
    };
    let (codes, valid, _, _, _) = encode_particles(&cb, &view, &[pos]);
    assert!(valid[0]);
    let mut sim = Vec::new();
    match_codes(&cb, &codes, 1, &mut sim);
    let best = (0..sim.len()).max_by(|a, b| sim[*a].total_cmp(&sim[*b])).unwrap();
    let err = grid.rotation(grid.unflat(best)).angle_to(&r).to_degrees();
    // the box's flip about its x axis looks the same
    let flip = r * nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::x_axis(), std::f64::consts::PI);
    let err_flip = grid.rotation(grid.unflat(best)).angle_to(&flip).to_degrees();
    assert!(
        err.min(err_flip) < 16.0,
        "best bin {err} deg from the truth (flip {err_flip})"
    );
    // rotating the image by one bin the wrong way would land two bins off
    let wrong = grid.flat(pregrasp::geometry::BinIndex { inplane: 3, ..bin });
    assert!(sim[grid.flat(bin)] > sim[wrong]);
}
