//! The crate's layering, read from its source: which top-level modules each module names
//! (`crate::x` paths and `use crate::{x, ...}` groups), and which HTTP crates it uses.
//!
//! - Only `api` uses axum, utoipa, tower or hyper (the binary calls `api`); `service`, the
//!   runtime below it, uses none of them.
//! - The modules form layers: each names only modules of lower layers, so there is no cycle,
//!   and sensors, data sets and the generator never depend on the filter.
//! - Inside `api` and `service`, the files name each other without a cycle either.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Layers, lowest first; a module may name modules of lower layers only.
const LAYERS: &[&[&str]] = &[
    // the unit tests' helpers (compiled for tests only)
    &["testing"],
    &["geometry", "camera", "mesh"],
    &["render", "sensor", "symmetry", "grasp"],
    &["dataset"],
    &["generate", "tracker"],
    &["eval"],
    // the runtime: registry, ingest, the worker, codebook builds, decisions, storage, demo
    &["service"],
    // HTTP over the service; tools talk to a server over the network only
    &["api", "tools"],
];

/// Crates that belong to the HTTP layer.
const HTTP_CRATES: &[&str] = &[
    "axum",
    "utoipa",
    "utoipa_axum",
    "utoipa_swagger_ui",
    "tower",
    "tower_http",
    "hyper",
];

fn rust_files(path: &Path) -> Vec<PathBuf> {
    if path.is_file() {
        return vec![path.to_path_buf()];
    }
    let mut out = Vec::new();
    let mut stack = vec![path.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("readable source folder") {
            let p = entry.expect("folder entry").path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|e| e == "rs") {
                out.push(p);
            }
        }
    }
    out
}

/// The source without `//` comments (doc links name other modules without depending on them).
fn strip_comments(source: &str) -> String {
    source
        .lines()
        .map(|l| match l.find("//") {
            Some(i) => &l[..i],
            None => l,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

fn code_of(path: &Path) -> String {
    strip_comments(&std::fs::read_to_string(path).expect("readable source"))
}

fn ident_at(s: &str) -> &str {
    let end = s
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(s.len());
    &s[..end]
}

/// Top-level modules named by `code` through `crate::`.
fn crate_modules(code: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut rest = code;
    while let Some(i) = rest.find("crate::") {
        let after = &rest[i + "crate::".len()..];
        if let Some(group) = after.strip_prefix('{') {
            // `crate::{a::x, b, c::{y, z}}`: the first identifier of each item at depth 0
            let mut depth = 0;
            let mut start = true;
            for (j, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => start = true,
                    c if start && (c.is_ascii_alphabetic() || c == '_') => {
                        out.insert(ident_at(&group[j..]).to_string());
                        start = false;
                    }
                    _ => {}
                }
            }
        } else {
            let name = ident_at(after);
            if !name.is_empty() {
                out.insert(name.to_string());
            }
        }
        rest = after;
    }
    out
}

/// HTTP crates named by `code` (`axum::...` or `use axum`).
fn http_crates(code: &str) -> BTreeSet<&'static str> {
    HTTP_CRATES
        .iter()
        .copied()
        .filter(|c| {
            code.match_indices(c).any(|(i, _)| {
                let before = code[..i].chars().next_back();
                let after = &code[i + c.len()..];
                let starts_word = !before.is_some_and(|b| b.is_ascii_alphanumeric() || b == '_' || b == ':');
                starts_word && (after.starts_with("::") || after.starts_with(';'))
            })
        })
        .collect()
}

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Every top-level module of the library with the modules and HTTP crates it names.
fn graph() -> BTreeMap<String, (BTreeSet<String>, BTreeSet<&'static str>)> {
    let lib = code_of(&src().join("lib.rs"));
    let modules: Vec<String> = lib
        .lines()
        .filter_map(|l| l.trim().strip_prefix("pub mod "))
        .map(|m| m.trim_end_matches(';').trim().to_string())
        .collect();
    assert!(modules.len() >= 10, "modules of lib.rs: {modules:?}");
    modules
        .iter()
        .map(|m| {
            let dir = src().join(m);
            let path = if dir.is_dir() {
                dir
            } else {
                src().join(format!("{m}.rs"))
            };
            let mut names = BTreeSet::new();
            let mut http = BTreeSet::new();
            for f in rust_files(&path) {
                let code = code_of(&f);
                names.extend(crate_modules(&code).into_iter().filter(|n| n != m));
                http.extend(http_crates(&code));
            }
            (m.clone(), (names, http))
        })
        .collect()
}

#[test]
fn the_parser_sees_paths_groups_and_crates() {
    let code = "use crate::{camera::Intrinsics, geometry::{Pose, look_at}, mesh};\nlet x = crate::tracker::Tracker::new();\nuse axum::Router;\n// crate::api in a comment\n";
    let names = crate_modules(&strip_comments(code));
    assert_eq!(
        names.into_iter().collect::<Vec<_>>(),
        ["camera", "geometry", "mesh", "tracker"]
    );
    assert_eq!(http_crates(code).into_iter().collect::<Vec<_>>(), ["axum"]);
    assert!(http_crates("let tower_height = 3; mytower::x();").is_empty());
}

#[test]
fn only_the_api_speaks_http() {
    let g = graph();
    for (m, (_, http)) in &g {
        if m != "api" {
            assert!(http.is_empty(), "{m} uses {http:?}: only api may");
        }
    }
    assert!(!g["api"].1.is_empty(), "the parser finds api's HTTP crates");
    assert!(g["service"].1.is_empty(), "service uses {:?}", g["service"].1);
}

/// The files of a module folder (`src/<module>/<file>.rs`, `mod.rs` as the module itself) with
/// the sibling files each names (`super::x`, `crate::<module>::x`, `use super::{x, ...}`).
fn file_graph(module: &str) -> BTreeMap<String, BTreeSet<String>> {
    let dir = src().join(module);
    let files: Vec<String> = std::fs::read_dir(&dir)
        .expect("module folder")
        .filter_map(|e| {
            let p = e.expect("entry").path();
            (p.extension().is_some_and(|x| x == "rs") && p.file_stem().is_some_and(|s| s != "mod"))
                .then(|| p.file_stem().expect("stem").to_string_lossy().to_string())
        })
        .collect();
    files
        .iter()
        .map(|f| {
            let code = code_of(&dir.join(format!("{f}.rs")));
            // `super::x` and `crate::module::x` name sibling x; only siblings count
            let mut names = BTreeSet::new();
            let prefixed = code.replace(&format!("crate::{module}::"), "crate::");
            let as_crate = prefixed.replace("super::", "crate::");
            // the test modules' `use super::*` is their own file
            for n in crate_modules(&as_crate) {
                if n != *f && files.contains(&n) {
                    names.insert(n);
                }
            }
            (f.clone(), names)
        })
        .collect()
}

fn assert_acyclic(module: &str, g: &BTreeMap<String, BTreeSet<String>>) {
    // depth-first search for a back edge
    fn visit(
        n: &str,
        g: &BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        path: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        match state.get(n) {
            Some(1) => {
                let i = path.iter().position(|p| p == n).unwrap_or(0);
                let mut cycle = path[i..].to_vec();
                cycle.push(n.to_string());
                return Some(cycle);
            }
            Some(2) => return None,
            _ => {}
        }
        state.insert(n.to_string(), 1);
        path.push(n.to_string());
        for m in g.get(n).into_iter().flatten() {
            if let Some(c) = visit(m, g, state, path) {
                return Some(c);
            }
        }
        path.pop();
        state.insert(n.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for n in g.keys() {
        if let Some(cycle) = visit(n, g, &mut state, &mut Vec::new()) {
            panic!("files of {module} name each other in a cycle: {}", cycle.join(" -> "));
        }
    }
}

#[test]
fn the_files_of_api_and_service_form_no_cycle() {
    for module in ["api", "service"] {
        let g = file_graph(module);
        assert!(g.len() >= 5, "{module}: {g:?}");
        assert_acyclic(module, &g);
    }
    // the checker sees a cycle when there is one
    let mut g = BTreeMap::new();
    g.insert("a".to_string(), BTreeSet::from(["b".to_string()]));
    g.insert("b".to_string(), BTreeSet::from(["a".to_string()]));
    assert!(std::panic::catch_unwind(|| assert_acyclic("test", &g)).is_err());
}

#[test]
fn modules_name_only_lower_layers() {
    let layer_of = |m: &str| LAYERS.iter().position(|l| l.contains(&m));
    let g = graph();
    for (m, (names, _)) in &g {
        let Some(lm) = layer_of(m) else {
            panic!("module {m} is in no layer of tests/layers.rs: place it");
        };
        for n in names {
            let Some(ln) = layer_of(n) else {
                panic!("{m} names {n}, which is in no layer");
            };
            assert!(
                ln < lm,
                "{m} (layer {lm}) names {n} (layer {ln}): a module may name lower layers only"
            );
        }
    }
    // the point of the sensor module: data sets and the generator need no filter
    for m in ["sensor", "dataset", "generate"] {
        assert!(!g[m].0.contains("tracker"), "{m} imports the tracker");
    }
    // service sits above the filter, the decision and the metrics and below api
    assert!(!g["service"].0.contains("api"), "service imports api");
    assert!(g["api"].0.contains("service"), "api calls the service");
}
