//! Headless check of the demo's tracks against its ground truth, over HTTP only:
//!
//! ```text
//! cargo run --release -- serve --demo --addr 127.0.0.1:8080 &
//! cargo run --release --example demo_check -- [SERVER=http://127.0.0.1:8080] [LOOPS=5] [SETTLE_S=5]
//! ```
//!
//! Polls `GET /api/v1/tracks` four times a second for `LOOPS` demo loops. A track *fails* a
//! poll when, later than `SETTLE_S` into its loop, it is more than 10 cm from the truth and the
//! truth lies outside its reported 3-sigma translation region (3 x `translation_std_m`): a
//! confident error, the one a planner cannot see coming. Prints every failure, then one line
//! per loop and object (worst error, worst error / std, orientation error modulo symmetry as
//! the service reports it, and whether the object's track ever answered `grasp`). Exits 1 on
//! any failure. The tracker never sees the truth; only the service's `truth` field is read.

use pregrasp::service::demo::{DEMO_DRIVE_S, DEMO_PAUSE_S};
use serde_json::Value;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// Translation error (m) beyond which a confident error counts.
const MAX_ERROR_M: f64 = 0.10;
/// The reported region: this many standard deviations.
const SIGMAS: f64 = 3.0;

#[derive(Default)]
struct LoopObject {
    polls: usize,
    failures: usize,
    worst_error_m: f64,
    worst_ratio: f64,
    worst_orientation_deg: f64,
    grasp_answers: usize,
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let server = args.first().cloned().unwrap_or_else(|| "http://127.0.0.1:8080".into());
    let loops: u64 = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(5);
    let settle_s: f64 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(5.0);
    let loop_s = DEMO_DRIVE_S + DEMO_PAUSE_S;
    let rt = tokio::runtime::Runtime::new()?;
    let client = reqwest::Client::builder().timeout(Duration::from_secs(5)).build()?;
    let url = format!("{}/api/v1/tracks", server.trim_end_matches('/'));
    // (loop index, object) -> summary
    let mut summary: BTreeMap<(u64, String), LoopObject> = BTreeMap::new();
    let mut first_loop: Option<u64> = None;
    let deadline = Instant::now() + Duration::from_secs_f64(loop_s * (loops as f64 + 1.0) + 120.0);
    let mut failures = 0usize;
    while Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(250));
        let tracks: Vec<Value> = match rt.block_on(async { client.get(&url).send().await?.json().await }) {
            Ok(t) => t,
            Err(e) => {
                eprintln!("poll failed: {e}");
                continue;
            }
        };
        let mut done = false;
        for t in &tracks {
            let (Some(stamp_ns), Some(truth)) = (t["stamp_ns"].as_i64(), t.get("truth").filter(|v| !v.is_null()))
            else {
                continue;
            };
            let stamp_s = stamp_ns as f64 * 1e-9;
            let loop_index = (stamp_s / loop_s).floor() as u64;
            // the first loop seen may have started before the check: judge only whole loops
            let first = *first_loop.get_or_insert(loop_index + 1);
            if loop_index < first {
                continue;
            }
            if loop_index >= first + loops {
                done = true;
                continue;
            }
            let t_loop = stamp_s - loop_index as f64 * loop_s;
            let object = t["object_id"].as_str().unwrap_or("?").to_string();
            let error_m = truth["translation_error_m"].as_f64().unwrap_or(f64::NAN);
            let orientation_deg = truth["orientation_error_deg"].as_f64().unwrap_or(f64::NAN);
            let std_m = t["translation_std_m"].as_f64().unwrap_or(0.0);
            let s = summary.entry((loop_index - first, object.clone())).or_default();
            if t["decision"]["decision"].as_str() == Some("grasp") {
                s.grasp_answers += 1;
            }
            if t_loop < settle_s {
                continue;
            }
            s.polls += 1;
            s.worst_error_m = s.worst_error_m.max(error_m);
            s.worst_ratio = s.worst_ratio.max(error_m / std_m.max(1e-9));
            s.worst_orientation_deg = s.worst_orientation_deg.max(orientation_deg);
            if error_m > MAX_ERROR_M && error_m > SIGMAS * std_m {
                s.failures += 1;
                failures += 1;
                println!(
                    "FAIL loop {} t {t_loop:.1} s track {} {object}: {error_m:.3} m off, std {std_m:.3} m",
                    loop_index - first,
                    t["id"]
                );
            }
        }
        if done {
            break;
        }
    }
    println!("loop object polls failures worst_error_m worst_error/std worst_orientation_deg grasp_answers");
    for ((l, object), s) in &summary {
        println!(
            "{l} {object} {} {} {:.3} {:.1} {:.1} {}",
            s.polls, s.failures, s.worst_error_m, s.worst_ratio, s.worst_orientation_deg, s.grasp_answers
        );
    }
    let judged = summary.keys().map(|(l, _)| *l).max().map_or(0, |l| l + 1);
    println!("{judged} loops judged, {failures} confident errors (> {MAX_ERROR_M} m and > {SIGMAS} sigma)");
    if judged < loops {
        anyhow::bail!("only {judged} of {loops} loops were seen");
    }
    if failures > 0 {
        std::process::exit(1);
    }
    Ok(())
}
