//! A calibrated `p_success`: a monotone map from the raw sampled success rate to the share of
//! such answers that succeeded on the true pose, fitted on generated sequences, stored with the
//! hash of the settings it was fitted for, and refused for any other settings; the per-track
//! smoother whose smoothed raw rate the map reads; and the rule that turns the calibrated
//! probability into `grasp` (chosen by `pregrasp calibrate`, `crate::eval::refit`).

use super::GraspError;
use super::decision::{DEFAULT_THRESHOLD, wilson_interval};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::sync::Arc;

/// Hash (SHA-256, hex) of a canonical serialisation of `settings`: JSON with the keys of every
/// object sorted, no whitespace and floats to 12 significant digits, so that the same settings
/// give the same hash whatever the order their fields were written in and after a round trip
/// through a JSON file.
pub fn settings_hash(settings: &serde_json::Value) -> String {
    fn canonical(v: &serde_json::Value, out: &mut String) {
        match v {
            serde_json::Value::Object(m) => {
                let mut keys: Vec<&String> = m.keys().collect();
                keys.sort();
                out.push('{');
                for (i, k) in keys.into_iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    out.push_str(&serde_json::Value::String(k.clone()).to_string());
                    out.push(':');
                    canonical(&m[k], out);
                }
                out.push('}');
            }
            serde_json::Value::Array(a) => {
                out.push('[');
                for (i, x) in a.iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    canonical(x, out);
                }
                out.push(']');
            }
            // floats to 12 significant digits: serde_json's parser may read a float written
            // by itself one unit in the last place off, and f32 settings widened to f64 carry
            // digits no setting means
            serde_json::Value::Number(n) if n.is_f64() => {
                out.push_str(&format!("{:.11e}", n.as_f64().unwrap_or(f64::NAN)));
            }
            other => out.push_str(&other.to_string()),
        }
    }
    let mut s = String::new();
    canonical(settings, &mut s);
    let digest = Sha256::digest(s.as_bytes());
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// Version of the map's JSON layout.
pub const MAP_VERSION: u32 = 1;

/// The map shipped with the binary (`pregrasp calibrate --fit` writes it).
pub const SHIPPED_MAP_JSON: &str = include_str!("calibration_map.json");

/// A pooled block of the isotonic fit smaller than this is merged into its neighbour (the
/// default of `pregrasp calibrate --min-block-count`): a rate over a handful of frames says
/// little, a step of the map over it would move answers on its own, and its wide interval
/// would decide a bound-based rule wherever the raw rate's interval touches it.
pub const MIN_BLOCK_COUNT: usize = 20;

/// The smallest block of maps written before the size was stored with them.
fn legacy_min_block_count() -> usize {
    MIN_BLOCK_COUNT
}

/// One block of the isotonic fit: the decisions whose raw rate lies in `raw_lo..=raw_hi`, of
/// which `successes` succeeded on the true pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IsotonicBlock {
    pub raw_lo: f64,
    pub raw_hi: f64,
    /// Mean raw rate of the block: where the map passes through the block's rate.
    pub raw_mean: f64,
    pub count: usize,
    pub successes: usize,
}

impl IsotonicBlock {
    /// The block's observed success rate.
    pub fn rate(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.successes as f64 / self.count as f64
        }
    }

    /// 95 % Wilson interval of the block's rate: how well the fit knows the map here.
    pub fn interval(&self) -> [f64; 2] {
        wilson_interval(self.rate(), self.count as f64)
    }
}

/// The quantity a grasp rule compares with its threshold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum RuleQuantity {
    /// The calibrated probability itself.
    Calibrated,
    /// The lower end of the calibrated probability's 95 % interval.
    CalibratedLower,
    /// The lower end of the raw rate's 95 % Wilson interval on the effective sample size (the
    /// rule before calibration; used when no valid map is loaded).
    #[default]
    RawLower,
    /// The calibrated probability of the lower end of the raw rate's 95 % interval: the map's
    /// estimate, cautious for the few samples an answer drew but not widened by the map's own
    /// fit, whose width shrinks with the data it was fitted on (so a threshold on
    /// [`RuleQuantity::CalibratedLower`] chosen with maps fitted on part of the data does not
    /// carry over to the map fitted on all of it).
    CalibratedAtRawLower,
    /// The raw sampled rate itself (smoothed as the served answer is). The map is monotone, so
    /// a threshold on the raw rate is one on the calibrated probability, placed anywhere rather
    /// than only at the steps between the map's blocks, and it does not move with the map:
    /// judged on out-of-fold answers, it grasps on the same answers as on the map fitted on all.
    Raw,
}

/// When an answer is `grasp`: `quantity >= threshold` in `run_length` successive answers about
/// the track (1: this answer alone; longer runs need the per-track [`AnswerSmoother`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GraspRule {
    pub quantity: RuleQuantity,
    pub threshold: f64,
    pub run_length: u32,
}

impl Default for GraspRule {
    /// The rule without a map: the raw rate's Wilson lower bound must reach 0.9.
    fn default() -> Self {
        Self {
            quantity: RuleQuantity::RawLower,
            threshold: DEFAULT_THRESHOLD,
            run_length: 1,
        }
    }
}

impl GraspRule {
    /// The value of the rule's quantity for an answer calibrated to `(p, ci95)` from the raw
    /// rate and interval `(p_raw, ci95_raw)`; `p_at_raw_lower` gives the calibrated probability
    /// of `ci95_raw[0]` (read only by [`RuleQuantity::CalibratedAtRawLower`]).
    pub fn quantity_value(
        &self,
        (p, ci95): (f64, [f64; 2]),
        (p_raw, ci95_raw): (f64, [f64; 2]),
        p_at_raw_lower: impl FnOnce() -> f64,
    ) -> f64 {
        match self.quantity {
            RuleQuantity::Calibrated => p,
            RuleQuantity::CalibratedLower => ci95[0],
            RuleQuantity::RawLower => ci95_raw[0],
            RuleQuantity::CalibratedAtRawLower => p_at_raw_lower(),
            RuleQuantity::Raw => p_raw,
        }
    }

    /// Whether one answer's quantity reaches the threshold (see [`GraspRule::quantity_value`];
    /// the run is counted by the caller).
    pub fn admits(
        &self,
        calibrated: (f64, [f64; 2]),
        raw: (f64, [f64; 2]),
        p_at_raw_lower: impl FnOnce() -> f64,
    ) -> bool {
        self.quantity_value(calibrated, raw, p_at_raw_lower) >= self.threshold
    }
}

/// The fitted map with what it was fitted for and on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationMap {
    pub version: u32,
    /// [`settings_hash`] of `settings`.
    pub settings_hash: String,
    /// The settings the map was fitted for (tracker, codebook, grid, gripper, samples).
    pub settings: serde_json::Value,
    /// When the fit ran (UTC, RFC 3339).
    pub fitted_at: String,
    /// What it was fitted on (the data sets and their seeds).
    pub fitted_on: Vec<String>,
    pub n_decisions: usize,
    pub n_successes: usize,
    pub n_approaches: usize,
    /// Pose samples each fitted decision drew. An answer that drew fewer gets the raw rate
    /// ([`Calibration::for_samples`]): its rate is noisier, so at the top of the map, where the
    /// rule sits, more of its high rates are luck than the map's were. `None` (maps from
    /// before it was recorded): any count.
    #[serde(default)]
    pub n_samples: Option<usize>,
    /// Isotonic blocks, lowest raw rate first; rates non-decreasing.
    pub blocks: Vec<IsotonicBlock>,
    /// The rule chosen on the fitting data by its failures (`pregrasp calibrate`).
    pub rule: GraspRule,
    /// Time constant (s) of the [`AnswerSmoother`] whose smoothed raw rate the map was fitted
    /// on (0: each answer alone); the service smooths with the same.
    #[serde(default)]
    pub smoothing_time_constant_s: f64,
    /// The smallest block the fit kept (smaller ones were merged into a neighbour).
    #[serde(default = "legacy_min_block_count")]
    pub min_block_count: usize,
    /// Separate fits by the track's translation spread (empty: `blocks` for every answer).
    /// The same raw rate means more when the distribution is tight: its few failing samples
    /// are then the grasp's own margins, not a track that may be centimetres off.
    #[serde(default)]
    pub spread_strata: Vec<SpreadStratum>,
}

/// The isotonic fit of the answers whose track's translation spread lay below
/// `max_translation_std_m` (and at or above the previous stratum's; `None`: no upper end).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpreadStratum {
    pub max_translation_std_m: Option<f64>,
    pub n_decisions: usize,
    pub n_successes: usize,
    /// Isotonic blocks, lowest raw rate first; rates non-decreasing.
    pub blocks: Vec<IsotonicBlock>,
}

/// The map's value at `raw` over `blocks`: linear between the blocks' (mean raw rate, rate)
/// points, flat beyond the first and last.
fn apply_blocks(b: &[IsotonicBlock], raw: f64) -> f64 {
    let raw = if raw.is_finite() { raw.clamp(0.0, 1.0) } else { 0.0 };
    let i = b.partition_point(|k| k.raw_mean <= raw);
    if i == 0 {
        return b[0].rate();
    }
    if i == b.len() {
        return b[b.len() - 1].rate();
    }
    let (l, r) = (&b[i - 1], &b[i]);
    let t = (raw - l.raw_mean) / (r.raw_mean - l.raw_mean);
    l.rate() + t * (r.rate() - l.rate())
}

/// Blocks ordered by raw rate with non-decreasing rates.
fn check_blocks(blocks: &[IsotonicBlock], what: &str) -> Result<(), GraspError> {
    if blocks.is_empty() {
        return Err(GraspError::Calibration(format!("{what} has no blocks")));
    }
    for w in blocks.windows(2) {
        if w[1].raw_mean <= w[0].raw_mean || w[1].rate() < w[0].rate() {
            return Err(GraspError::Calibration(format!(
                "{what}: blocks are not ordered with non-decreasing rates"
            )));
        }
    }
    Ok(())
}

impl CalibrationMap {
    /// Parses a map and checks its shape (blocks ordered, rates non-decreasing).
    pub fn from_json(text: &str) -> Result<Self, GraspError> {
        let m: CalibrationMap =
            serde_json::from_str(text).map_err(|e| GraspError::Calibration(format!("map JSON: {e}")))?;
        if m.version != MAP_VERSION {
            return Err(GraspError::Calibration(format!(
                "map version {} (this build reads {MAP_VERSION})",
                m.version
            )));
        }
        check_blocks(&m.blocks, "map")?;
        for (i, st) in m.spread_strata.iter().enumerate() {
            check_blocks(&st.blocks, &format!("spread stratum {i}"))?;
            let last = i + 1 == m.spread_strata.len();
            let ordered = match (st.max_translation_std_m, m.spread_strata.get(i + 1)) {
                (Some(max), Some(next)) => max.is_finite() && next.max_translation_std_m.is_none_or(|n| n > max),
                (None, _) => last,
                (Some(max), None) => max.is_finite(),
            };
            if !ordered {
                return Err(GraspError::Calibration(
                    "spread strata must have increasing upper ends, only the last one open".into(),
                ));
            }
        }
        if !(m.smoothing_time_constant_s.is_finite() && m.smoothing_time_constant_s >= 0.0) {
            return Err(GraspError::Calibration(format!(
                "invalid smoothing time constant {}",
                m.smoothing_time_constant_s
            )));
        }
        if !(m.rule.threshold > 0.0 && m.rule.threshold <= 1.0) || m.rule.run_length == 0 {
            return Err(GraspError::Calibration(format!("invalid rule {:?}", m.rule)));
        }
        Ok(m)
    }

    /// The map when it was fitted for `running_hash`; an error naming both hashes otherwise.
    pub fn check(self, running_hash: &str) -> Result<Self, GraspError> {
        if self.settings_hash != running_hash {
            return Err(GraspError::StaleCalibration {
                map: self.settings_hash,
                running: running_hash.to_string(),
            });
        }
        Ok(self)
    }

    /// The blocks that answer for a track of translation spread `translation_std_m`: its
    /// stratum's, or the pooled fit's without strata or without a (finite) spread.
    pub fn blocks_for(&self, translation_std_m: Option<f64>) -> &[IsotonicBlock] {
        Self::stratum_of(&self.spread_strata, translation_std_m)
            .map_or(&self.blocks[..], |i| &self.spread_strata[i].blocks[..])
    }

    /// The stratum among `strata` (ordered by upper end) that a track of translation spread
    /// `translation_std_m` belongs to: the first whose upper end lies above it; `None` without
    /// a finite spread or beyond the last closed stratum.
    pub fn stratum_of(strata: &[SpreadStratum], translation_std_m: Option<f64>) -> Option<usize> {
        let s = translation_std_m.filter(|s| s.is_finite())?;
        strata
            .iter()
            .position(|st| st.max_translation_std_m.is_none_or(|m| s < m))
    }

    /// The upper ends of the closed spread strata (what `calibrate --spread-edges-m` took).
    pub fn spread_edges_m(&self) -> Vec<f64> {
        self.spread_strata
            .iter()
            .filter_map(|s| s.max_translation_std_m)
            .collect()
    }

    /// The calibrated probability of a raw rate (for a track of that translation spread):
    /// linear between the blocks' (mean raw rate, rate) points, flat beyond the first and
    /// last; non-decreasing in `raw`, and continuous, so that a small change of the raw rate
    /// never jumps a whole step of the fit.
    pub fn apply(&self, raw: f64, translation_std_m: Option<f64>) -> f64 {
        apply_blocks(self.blocks_for(translation_std_m), raw)
    }

    /// The calibrated probability's 95 % interval from the raw rate's: the raw interval's ends
    /// through the map (sampling), widened to the Wilson intervals of every block the raw
    /// interval touches (how well the fit knows the map there).
    pub fn interval(&self, ci95_raw: [f64; 2], translation_std_m: Option<f64>) -> [f64; 2] {
        let [lo, hi] = ci95_raw;
        let blocks = self.blocks_for(translation_std_m);
        let mut out = [apply_blocks(blocks, lo), apply_blocks(blocks, hi)];
        // blocks whose range (extended to the neighbours' means, where the map interpolates)
        // meets [lo, hi]
        let n = blocks.len();
        for (i, b) in blocks.iter().enumerate() {
            let from = if i == 0 { 0.0 } else { blocks[i - 1].raw_mean };
            let to = if i + 1 == n { 1.0 } else { blocks[i + 1].raw_mean };
            if to < lo || from > hi {
                continue;
            }
            let [wl, wu] = b.interval();
            out[0] = out[0].min(wl);
            out[1] = out[1].max(wu);
        }
        out
    }
}

/// Pool-adjacent-violators on (raw rate, success) pairs: the non-decreasing step function of
/// the raw rate closest to the outcomes in squared error; equal raw rates share a block, and
/// blocks under `min_block_count` are merged into a neighbour (merging neighbours of a
/// non-decreasing sequence keeps it non-decreasing).
pub fn fit_isotonic(points: &[(f64, bool)], min_block_count: usize) -> Vec<IsotonicBlock> {
    let mut pts: Vec<(f64, bool)> = points
        .iter()
        .filter(|(x, _)| x.is_finite())
        .map(|&(x, y)| (x.clamp(0.0, 1.0), y))
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    #[derive(Clone, Copy)]
    struct B {
        lo: f64,
        hi: f64,
        sum_x: f64,
        n: usize,
        k: usize,
    }
    let merge = |a: B, b: B| B {
        lo: a.lo.min(b.lo),
        hi: a.hi.max(b.hi),
        sum_x: a.sum_x + b.sum_x,
        n: a.n + b.n,
        k: a.k + b.k,
    };
    let rate = |b: &B| b.k as f64 / b.n as f64;
    let mut stack: Vec<B> = Vec::new();
    for (x, y) in pts {
        let mut cur = B {
            lo: x,
            hi: x,
            sum_x: x,
            n: 1,
            k: y as usize,
        };
        // ties first: an equal raw rate joins the block on top
        if let Some(top) = stack.last()
            && top.hi == x
        {
            cur = merge(stack.pop().unwrap_or(cur), cur);
        }
        while let Some(top) = stack.last() {
            // a violator: the block below has a higher rate (k/n > k'/n' without division)
            if top.k * cur.n > cur.k * top.n {
                cur = merge(*top, cur);
                stack.pop();
            } else {
                break;
            }
        }
        stack.push(cur);
    }
    // small blocks join the neighbour whose rate is closer (the last one its left neighbour)
    while stack.len() >= 2 {
        let Some(i) = stack.iter().position(|b| b.n < min_block_count) else {
            break;
        };
        let left_closer = |i: usize| {
            i + 1 == stack.len()
                || (rate(&stack[i]) - rate(&stack[i - 1])).abs() <= (rate(&stack[i + 1]) - rate(&stack[i])).abs()
        };
        let j = if i == 0 {
            1
        } else if left_closer(i) {
            i - 1
        } else {
            i + 1
        };
        let (a, b) = (i.min(j), i.max(j));
        stack[a] = merge(stack[a], stack[b]);
        stack.remove(b);
    }
    stack
        .into_iter()
        .map(|b| IsotonicBlock {
            raw_lo: b.lo,
            raw_hi: b.hi,
            raw_mean: b.sum_x / b.n as f64,
            count: b.n,
            successes: b.k,
        })
        .collect()
}

/// Whether an answer's `p_success` went through a map, and if not, why: a map for other
/// settings is named as such (it must be refitted), never silently applied.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum CalibrationStatus {
    /// `p_success` and `ci95` come from a map fitted for the running settings.
    Calibrated {
        /// The settings hash the map was fitted for (= the running one).
        settings_hash: String,
    },
    /// The map was fitted for other settings and is refused: `p_success` is the raw rate and
    /// the rule the one without a map.
    Stale {
        map_settings_hash: String,
        running_settings_hash: String,
        message: String,
    },
    /// No usable map (none given, or it could not be read): the raw rate and the rule without
    /// a map.
    Absent { message: String },
}

impl Default for CalibrationStatus {
    fn default() -> Self {
        Self::Absent {
            message: "no calibration map; p_success is the raw rate".into(),
        }
    }
}

impl CalibrationStatus {
    /// `p_success` went through a map.
    pub fn is_calibrated(&self) -> bool {
        matches!(self, Self::Calibrated { .. })
    }
    /// Why there is no map, for the caller to show (`None` when calibrated).
    pub fn warning(&self) -> Option<&str> {
        match self {
            Self::Calibrated { .. } => None,
            Self::Stale { message, .. } | Self::Absent { message } => Some(message),
        }
    }
    /// The settings hash of the map found (used or refused).
    pub fn map_settings_hash(&self) -> Option<&str> {
        match self {
            Self::Calibrated { settings_hash } => Some(settings_hash),
            Self::Stale { map_settings_hash, .. } => Some(map_settings_hash),
            Self::Absent { .. } => None,
        }
    }
}

/// What `decide` calibrates with: a map checked against the running settings, a map refused
/// because it was fitted for other settings, or no map.
#[derive(Debug, Clone)]
pub enum Calibration {
    Fitted(Arc<CalibrationMap>),
    /// The map's settings hash differs from the running one: answers carry the raw rate.
    Stale {
        map_settings_hash: String,
        running_settings_hash: String,
    },
    Raw {
        reason: String,
    },
}

impl Calibration {
    /// No map: answers carry the raw rate and the pre-calibration rule.
    pub fn raw(reason: &str) -> Self {
        Self::Raw {
            reason: reason.to_string(),
        }
    }

    /// The map in `text` when it parses and was fitted for `running_hash`; otherwise the raw
    /// rate, with a warning logged and carried in every answer.
    pub fn load(text: &str, running_hash: &str) -> Self {
        match CalibrationMap::from_json(text) {
            Ok(m) => Self::checked(Arc::new(m), running_hash),
            Err(e) => {
                tracing::warn!(error = %e, "grasp calibration map unreadable: answers carry the raw rate");
                Self::Raw {
                    reason: format!("calibration map refused ({e}); p_success is the raw rate"),
                }
            }
        }
    }

    /// `map` when it was fitted for `running_hash`, else [`Calibration::Stale`] (logged).
    pub fn checked(map: Arc<CalibrationMap>, running_hash: &str) -> Self {
        if map.settings_hash == running_hash {
            return Self::Fitted(map);
        }
        tracing::warn!(
            map = %map.settings_hash,
            running = %running_hash,
            "grasp calibration map fitted for other settings: answers carry the raw rate"
        );
        Self::Stale {
            map_settings_hash: map.settings_hash.clone(),
            running_settings_hash: running_hash.to_string(),
        }
    }

    /// The map shipped with the binary, checked against `running_hash`.
    pub fn shipped(running_hash: &str) -> Self {
        Self::load(SHIPPED_MAP_JSON, running_hash)
    }

    pub fn map(&self) -> Option<&CalibrationMap> {
        match self {
            Self::Fitted(m) => Some(m),
            Self::Stale { .. } | Self::Raw { .. } => None,
        }
    }

    /// The calibration for an answer of `n_samples` pose samples: the raw rate, with the
    /// reason, when the map was fitted on answers that drew more (see
    /// [`CalibrationMap::n_samples`]); else unchanged.
    pub fn for_samples(&self, n_samples: usize) -> Self {
        if let Self::Fitted(m) = self
            && let Some(fitted) = m.n_samples
            && n_samples < fitted
        {
            return Self::Raw {
                reason: format!(
                    "the calibration map was fitted on answers of {fitted} pose samples and this one \
                     drew {n_samples}: p_success is the raw rate and the rule the one without a map \
                     (ask for n_samples >= {fitted} for a calibrated answer)"
                ),
            };
        }
        self.clone()
    }

    /// The time constant answers are smoothed with (the map's; 0 without a map).
    pub fn smoothing_time_constant_s(&self) -> f64 {
        self.map().map_or(0.0, |m| m.smoothing_time_constant_s)
    }

    /// A smoother for one track with the map's time constant.
    pub fn smoother(&self) -> AnswerSmoother {
        AnswerSmoother::new(self.smoothing_time_constant_s())
    }

    /// The map's rule, or without one the pre-calibration rule.
    pub fn rule(&self) -> GraspRule {
        self.map().map_or_else(GraspRule::default, |m| m.rule)
    }

    /// The calibrated probability of a raw rate (the rate itself without a map).
    pub fn at(&self, raw: f64, translation_std_m: Option<f64>) -> f64 {
        self.map().map_or(raw, |m| m.apply(raw, translation_std_m))
    }

    /// The value of `rule`'s quantity for an answer calibrated to `(p, ci95)` from the raw
    /// rate and interval `(p_raw, ci95_raw)` of a track of translation spread
    /// `translation_std_m`.
    pub fn rule_value(
        &self,
        rule: &GraspRule,
        calibrated: (f64, [f64; 2]),
        (p_raw, ci95_raw): (f64, [f64; 2]),
        translation_std_m: Option<f64>,
    ) -> f64 {
        rule.quantity_value(calibrated, (p_raw, ci95_raw), || {
            self.at(ci95_raw[0], translation_std_m)
        })
    }

    /// (p_success, ci95, status) of a raw rate and its interval, for a track of translation
    /// spread `translation_std_m` (`None`: the pooled fit).
    pub fn calibrate(
        &self,
        raw: f64,
        ci95_raw: [f64; 2],
        translation_std_m: Option<f64>,
    ) -> (f64, [f64; 2], CalibrationStatus) {
        match self {
            Self::Fitted(m) => (
                m.apply(raw, translation_std_m),
                m.interval(ci95_raw, translation_std_m),
                CalibrationStatus::Calibrated {
                    settings_hash: m.settings_hash.clone(),
                },
            ),
            Self::Stale {
                map_settings_hash,
                running_settings_hash,
            } => (
                raw,
                ci95_raw,
                CalibrationStatus::Stale {
                    map_settings_hash: map_settings_hash.clone(),
                    running_settings_hash: running_settings_hash.clone(),
                    message: GraspError::StaleCalibration {
                        map: map_settings_hash.clone(),
                        running: running_settings_hash.clone(),
                    }
                    .to_string()
                        + "; p_success is the raw rate and the rule the one without a map",
                },
            ),
            Self::Raw { reason } => (
                raw,
                ci95_raw,
                CalibrationStatus::Absent {
                    message: reason.clone(),
                },
            ),
        }
    }
}

/// Successive answers about one track, smoothed: the raw rate and its interval are averaged
/// exponentially over time (weight `1 - exp(-dt / time_constant)` for an answer `dt` after
/// the last), then put through the map; a run of answers that clear the rule is counted.
/// Why: the tracker's distribution itself moves from step to step (resampling of ~110
/// particles), so the raw rate of one step jumps even when nothing in the scene changed; an
/// average over the last `time_constant` seconds is what the filter's recent steps agree on.
/// The service holds one per track and question; a map is fitted on the raw rate smoothed the
/// same way. Answers at the stamp of the last one replace it (planners polling faster than
/// the tracker steps do not shorten the time constant).
#[derive(Debug, Clone, PartialEq)]
pub struct AnswerSmoother {
    time_constant_s: f64,
    /// The state before the latest stamp: (stamp, smoothed raw rate, its interval, run).
    before: Option<Smoothed>,
    latest: Option<Smoothed>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Smoothed {
    stamp_ns: i64,
    p_raw: f64,
    ci95_raw: [f64; 2],
    translation_std_m: Option<f64>,
    run: u32,
}

/// How a [`super::Decision`] was smoothed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SmoothingStatus {
    pub time_constant_s: f64,
    /// Successive answers (this one included) that cleared the rule's threshold.
    pub run: u32,
    /// The smoothed raw rate the map was applied to.
    pub p_success_raw_smoothed: f64,
    /// This answer's own calibrated probability, before smoothing.
    pub p_success_unsmoothed: f64,
    /// The smoothed translation spread that chose the map's stratum (`None`: its pooled fit).
    #[serde(default)]
    pub translation_std_m_smoothed: Option<f64>,
}

/// A smoothed answer: the raw rate averaged over recent answers, through the map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SmoothedAnswer {
    /// The smoothed raw rate.
    pub p_success_raw: f64,
    pub ci95_raw: [f64; 2],
    /// The smoothed translation spread the map read (`None`: its pooled fit).
    pub translation_std_m: Option<f64>,
    /// The rule's quantity in this answer.
    pub rule_value: f64,
    /// The calibrated probability of the smoothed raw rate (the raw rate without a map).
    pub p_success: f64,
    pub ci95: [f64; 2],
    /// Successive answers (this one included) that cleared the rule's threshold.
    pub run: u32,
    /// The rule's quantity reached its threshold in the last `run_length` answers.
    pub grasp: bool,
}

impl AnswerSmoother {
    /// `time_constant_s` 0 (or negative) keeps the latest answer alone.
    pub fn new(time_constant_s: f64) -> Self {
        Self {
            time_constant_s: if time_constant_s.is_finite() {
                time_constant_s.max(0.0)
            } else {
                0.0
            },
            before: None,
            latest: None,
        }
    }

    pub fn time_constant_s(&self) -> f64 {
        self.time_constant_s
    }

    /// Forgets the past (a restarted track or clock).
    pub fn reset(&mut self) {
        self.before = None;
        self.latest = None;
    }

    /// Smooths a decision in place: `p_success`, `ci95` and `decision` become the smoothed,
    /// calibrated ones by the decision's rule (the raw rate and its interval stay this
    /// answer's own); `smoothing` says how. `stamp_ns` is the tracker step's stamp.
    pub fn apply(&mut self, stamp_ns: i64, decision: &mut super::Decision, calibration: &Calibration) {
        let a = self.update_seen(
            stamp_ns,
            (decision.p_success_raw, decision.ci95_raw),
            decision.translation_std_m,
            calibration,
            &decision.rule,
            decision.reference_sees,
        );
        decision.smoothing = Some(SmoothingStatus {
            time_constant_s: self.time_constant_s,
            run: a.run,
            p_success_raw_smoothed: a.p_success_raw,
            p_success_unsmoothed: decision.p_success,
            translation_std_m_smoothed: a.translation_std_m,
        });
        decision.p_success = a.p_success;
        decision.ci95 = a.ci95;
        decision.rule_value = a.rule_value;
        decision.decision = if a.grasp {
            super::Verdict::Grasp
        } else {
            super::Verdict::Observe
        };
    }

    /// Adds one raw answer (rate and interval) taken at `stamp_ns` (the tracker step's stamp)
    /// on a track of translation spread `translation_std_m` and returns the smoothed one (the
    /// spread smoothed alike). An answer older than the last (a restarted clock) starts over.
    pub fn update(
        &mut self,
        stamp_ns: i64,
        raw: (f64, [f64; 2]),
        translation_std_m: Option<f64>,
        calibration: &Calibration,
        rule: &GraspRule,
    ) -> SmoothedAnswer {
        self.update_seen(stamp_ns, raw, translation_std_m, calibration, rule, true)
    }

    /// [`Self::update`] for an answer whose reference camera did (`reference_sees`) or did not
    /// see the object: one that did not is `observe` and starts the rule's run over, while
    /// its rate still enters the smoothed one.
    pub fn update_seen(
        &mut self,
        stamp_ns: i64,
        (p_raw, ci95_raw): (f64, [f64; 2]),
        translation_std_m: Option<f64>,
        calibration: &Calibration,
        rule: &GraspRule,
        reference_sees: bool,
    ) -> SmoothedAnswer {
        match self.latest {
            Some(l) if stamp_ns == l.stamp_ns => {}
            Some(l) if stamp_ns > l.stamp_ns => self.before = Some(l),
            _ => self.before = None,
        }
        let spread_now = translation_std_m.filter(|s| s.is_finite());
        let (p, ci, spread, run_before) = match self.before {
            Some(b) if self.time_constant_s > 0.0 => {
                let dt_s = (stamp_ns - b.stamp_ns) as f64 * 1e-9;
                let w = 1.0 - (-dt_s / self.time_constant_s).exp();
                (
                    b.p_raw + w * (p_raw - b.p_raw),
                    [
                        b.ci95_raw[0] + w * (ci95_raw[0] - b.ci95_raw[0]),
                        b.ci95_raw[1] + w * (ci95_raw[1] - b.ci95_raw[1]),
                    ],
                    match (b.translation_std_m, spread_now) {
                        (Some(a), Some(n)) => Some(a + w * (n - a)),
                        (_, n) => n,
                    },
                    b.run,
                )
            }
            Some(b) => (p_raw, ci95_raw, spread_now, b.run),
            None => (p_raw, ci95_raw, spread_now, 0),
        };
        let (pc, cic, _) = calibration.calibrate(p, ci, spread);
        let value = calibration.rule_value(rule, (pc, cic), (p, ci), spread);
        let run = if value >= rule.threshold && reference_sees {
            run_before + 1
        } else {
            0
        };
        self.latest = Some(Smoothed {
            stamp_ns,
            p_raw: p,
            ci95_raw: ci,
            translation_std_m: spread,
            run,
        });
        SmoothedAnswer {
            p_success_raw: p,
            ci95_raw: ci,
            translation_std_m: spread,
            rule_value: value,
            p_success: pc,
            ci95: cic,
            run,
            grasp: run >= rule.run_length.max(1),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map_of(blocks: Vec<IsotonicBlock>, rule: GraspRule, tau_s: f64) -> CalibrationMap {
        CalibrationMap {
            version: MAP_VERSION,
            settings_hash: "h".into(),
            settings: serde_json::json!({}),
            fitted_at: "2026-12-02T00:00:00Z".into(),
            fitted_on: vec!["test".into()],
            n_decisions: blocks.iter().map(|b| b.count).sum(),
            n_successes: blocks.iter().map(|b| b.successes).sum(),
            n_approaches: 1,
            n_samples: None,
            blocks,
            rule,
            smoothing_time_constant_s: tau_s,
            min_block_count: 20,
            spread_strata: Vec::new(),
        }
    }

    fn block(lo: f64, hi: f64, count: usize, successes: usize) -> IsotonicBlock {
        IsotonicBlock {
            raw_lo: lo,
            raw_hi: hi,
            raw_mean: 0.5 * (lo + hi),
            count,
            successes,
        }
    }

    fn calibrated_rule(t: f64, run: u32) -> GraspRule {
        GraspRule {
            quantity: RuleQuantity::Calibrated,
            threshold: t,
            run_length: run,
        }
    }

    #[test]
    fn settings_hash_ignores_key_order_and_sees_every_value() {
        let a = serde_json::json!({"tracker": {"sigma": 0.1, "n": 50}, "grid": 10});
        let b: serde_json::Value =
            serde_json::from_str(r#"{"grid": 10, "tracker": {"n": 50, "sigma": 0.1}}"#).expect("json");
        assert_eq!(settings_hash(&a), settings_hash(&b));
        let c = serde_json::json!({"tracker": {"sigma": 0.1, "n": 51}, "grid": 10});
        assert_ne!(settings_hash(&a), settings_hash(&c));
        assert_eq!(settings_hash(&a).len(), 64);
        // an f32 setting widened to f64, and the same read back from text one unit off
        let wide = serde_json::json!({"sigma": f64::from(0.015f32)});
        let read = serde_json::json!({"sigma": 0.014999999664723871});
        assert_eq!(settings_hash(&wide), settings_hash(&read));
        assert_ne!(
            settings_hash(&wide),
            settings_hash(&serde_json::json!({"sigma": 0.016}))
        );
    }

    #[test]
    fn pool_adjacent_violators_by_hand() {
        // x: 0.1 0.2 0.3 0.4, y: 1 0 0 1 (20 copies each so no block is merged for its size):
        // 0.1 (rate 1) violates 0.2 and 0.3 (rate 0): pooled to 20/60; 0.4 stays at 1.
        let mut pts = Vec::new();
        for _ in 0..20 {
            pts.extend([(0.1, true), (0.2, false), (0.3, false), (0.4, true)]);
        }
        let b = fit_isotonic(&pts, MIN_BLOCK_COUNT);
        assert_eq!(b.len(), 2, "{b:?}");
        assert_eq!((b[0].count, b[0].successes), (60, 20));
        assert!((b[0].raw_mean - 0.2).abs() < 1e-12 && b[0].raw_lo == 0.1 && b[0].raw_hi == 0.3);
        assert_eq!((b[1].count, b[1].successes), (20, 20));
        // rates never decrease, whatever the data
        let noisy: Vec<(f64, bool)> = (0..1000)
            .map(|i| {
                let x = (i * 7919 % 1000) as f64 / 1000.0;
                (x, (i * 104_729 % 997) as f64 / 997.0 < x)
            })
            .collect();
        let b = fit_isotonic(&noisy, MIN_BLOCK_COUNT);
        assert!(
            b.windows(2)
                .all(|w| w[1].rate() >= w[0].rate() && w[1].raw_lo > w[0].raw_hi)
        );
        assert!(b.iter().all(|k| k.count >= MIN_BLOCK_COUNT));
        assert_eq!(b.iter().map(|k| k.count).sum::<usize>(), 1000);
    }

    #[test]
    fn a_track_reads_the_stratum_of_its_spread() {
        let block = |mean: f64, count: usize, successes: usize| IsotonicBlock {
            raw_lo: mean - 0.05,
            raw_hi: mean + 0.05,
            raw_mean: mean,
            count,
            successes,
        };
        let rule = GraspRule {
            quantity: RuleQuantity::CalibratedAtRawLower,
            threshold: 0.95,
            run_length: 1,
        };
        let mut m = map_of(vec![block(0.2, 100, 20), block(0.9, 100, 90)], rule, 0.0);
        m.spread_strata = vec![
            SpreadStratum {
                max_translation_std_m: Some(0.005),
                n_decisions: 200,
                n_successes: 119,
                blocks: vec![block(0.2, 100, 20), block(0.9, 100, 99)],
            },
            SpreadStratum {
                max_translation_std_m: None,
                n_decisions: 200,
                n_successes: 100,
                blocks: vec![block(0.2, 100, 20), block(0.9, 100, 80)],
            },
        ];
        assert!((m.apply(0.9, Some(0.003)) - 0.99).abs() < 1e-12);
        assert!((m.apply(0.9, Some(0.005)) - 0.80).abs() < 1e-12);
        assert!((m.apply(0.9, Some(0.03)) - 0.80).abs() < 1e-12);
        // no spread (or none that means anything): the pooled fit
        assert!((m.apply(0.9, None) - 0.90).abs() < 1e-12);
        assert!((m.apply(0.9, Some(f64::NAN)) - 0.90).abs() < 1e-12);
        let text = serde_json::to_string(&m).expect("json");
        let back = CalibrationMap::from_json(&text).expect("valid");
        assert!((back.apply(0.9, Some(0.003)) - 0.99).abs() < 1e-12);
        // strata out of order, or an open one before the last, are refused
        let mut bad = m.clone();
        bad.spread_strata.swap(0, 1);
        let text = serde_json::to_string(&bad).expect("json");
        assert!(CalibrationMap::from_json(&text).is_err());
        let mut bad = m.clone();
        bad.spread_strata[1].max_translation_std_m = Some(0.004);
        let text = serde_json::to_string(&bad).expect("json");
        assert!(CalibrationMap::from_json(&text).is_err());

        // the rule on the raw rate's lower end reads that end through the track's stratum
        let cal = Calibration::Fitted(Arc::new(m));
        let ci_raw = [0.9, 0.95];
        let tight = cal.at(ci_raw[0], Some(0.003));
        let loose = cal.at(ci_raw[0], Some(0.02));
        assert!(rule.admits((0.0, [0.0, 1.0]), (0.92, ci_raw), || tight));
        assert!(!rule.admits((1.0, [1.0, 1.0]), (0.92, ci_raw), || loose));
        assert_eq!(
            cal.rule_value(&rule, (0.0, [0.0, 1.0]), (0.92, ci_raw), Some(0.003)),
            tight
        );
        // and the smoother carries the spread along with the rate: 2 mm, then 2 cm one time
        // constant later
        let mut s = AnswerSmoother::new(1.0);
        let a = s.update(0, (0.9, ci_raw), Some(0.002), &cal, &rule);
        assert!(a.grasp && a.translation_std_m == Some(0.002));
        let b = s.update(1_000_000_000, (0.9, ci_raw), Some(0.02), &cal, &rule);
        let expected = 0.002 + (1.0 - (-1.0f64).exp()) * 0.018;
        assert!((b.translation_std_m.expect("spread") - expected).abs() < 1e-12);
        assert!(!b.grasp, "{b:?}");
    }

    #[test]
    fn small_blocks_join_a_neighbour() {
        // 5 points at 0.9 (all succeed) after 100 at 0.5 (half succeed): too few for a block
        let mut pts: Vec<(f64, bool)> = (0..100).map(|i| (0.5, i % 2 == 0)).collect();
        pts.extend((0..5).map(|_| (0.9, true)));
        let b = fit_isotonic(&pts, MIN_BLOCK_COUNT);
        assert_eq!(b.len(), 1);
        assert_eq!((b[0].count, b[0].successes), (105, 55));
    }

    #[test]
    fn the_map_is_monotone_continuous_and_passes_through_the_blocks() {
        let m = map_of(
            vec![
                block(0.0, 0.4, 100, 10),
                block(0.4, 0.8, 100, 50),
                block(0.8, 1.0, 100, 95),
            ],
            calibrated_rule(0.9, 1),
            0.0,
        );
        assert!((m.apply(0.2, None) - 0.1).abs() < 1e-12);
        assert!((m.apply(0.6, None) - 0.5).abs() < 1e-12);
        assert!((m.apply(0.9, None) - 0.95).abs() < 1e-12);
        // flat beyond the outer means, linear between
        assert_eq!(m.apply(0.0, None), 0.1);
        assert_eq!(m.apply(1.0, None), 0.95);
        assert!((m.apply(0.4, None) - 0.3).abs() < 1e-12);
        let mut last = m.apply(0.0, None);
        for i in 0..=1000 {
            let p = m.apply(i as f64 / 1000.0, None);
            assert!(p >= last && p - last < 0.01, "{i}: {last} -> {p}");
            last = p;
        }
        assert_eq!(m.apply(f64::NAN, None), 0.1);
    }

    #[test]
    fn the_interval_holds_the_sampling_and_the_fit_uncertainty() {
        let m = map_of(
            vec![
                block(0.0, 0.5, 1000, 250),
                block(0.5, 0.9, 30, 24),
                block(0.9, 1.0, 1000, 970),
            ],
            calibrated_rule(0.9, 1),
            0.0,
        );
        // a narrow raw interval inside the well-known top block: about its Wilson interval
        let [lo, hi] = m.interval([0.96, 0.98], None);
        let [wl, wu] = m.blocks[2].interval();
        assert!(lo <= m.apply(0.96, None) && hi >= m.apply(0.98, None));
        assert!((lo - wl.min(m.apply(0.96, None))).abs() < 1e-12 && (hi - wu).abs() < 1e-12);
        // a raw interval reaching into the 30-frame block is wider than that block's rate alone
        let [lo2, _] = m.interval([0.6, 0.98], None);
        assert!(lo2 <= m.blocks[1].interval()[0] && lo2 < 0.7, "{lo2}");
        // always around the calibrated value
        for (a, b) in [(0.1, 0.3), (0.5, 0.99), (0.0, 1.0)] {
            let [l, h] = m.interval([a, b], None);
            let p = m.apply(0.5 * (a + b), None);
            assert!(l <= p && p <= h, "{a} {b}: {l} {p} {h}");
        }
    }

    #[test]
    fn answers_that_drew_fewer_samples_than_the_map_was_fitted_on_stay_raw() {
        let mut m = map_of(vec![block(0.0, 1.0, 100, 50)], calibrated_rule(0.8, 1), 0.5);
        m.n_samples = Some(1000);
        let fitted = Calibration::Fitted(Arc::new(m.clone()));
        for n in [1000, 5000] {
            let c = fitted.for_samples(n);
            assert!(c.map().is_some(), "{n}");
            assert!(c.calibrate(0.9, [0.85, 0.95], None).2.is_calibrated());
        }
        let few = fitted.for_samples(300);
        assert!(few.map().is_none());
        assert_eq!(few.rule(), GraspRule::default());
        let (p, ci, status) = few.calibrate(0.9, [0.85, 0.95], None);
        assert_eq!((p, ci), (0.9, [0.85, 0.95]));
        let w = status.warning().expect("a warning");
        assert!(w.contains("1000") && w.contains("300"), "{w}");
        // maps from before the count was recorded calibrate any count
        m.n_samples = None;
        assert!(Calibration::Fitted(Arc::new(m)).for_samples(10).map().is_some());
        // the count survives the map's JSON
        let shipped = CalibrationMap::from_json(SHIPPED_MAP_JSON).expect("shipped map");
        assert_eq!(shipped.n_samples, Some(crate::grasp::decision::DEFAULT_N_SAMPLES));
    }

    #[test]
    fn a_map_for_other_settings_is_refused_and_answers_fall_back_to_raw() {
        let m = map_of(vec![block(0.0, 1.0, 100, 50)], calibrated_rule(0.8, 1), 0.5);
        let text = serde_json::to_string(&m).expect("json");
        let ok = Calibration::load(&text, "h");
        assert!(ok.map().is_some());
        assert_eq!(ok.rule(), calibrated_rule(0.8, 1));
        assert_eq!(ok.smoothing_time_constant_s(), 0.5);
        let (p, _, status) = ok.calibrate(0.9, [0.85, 0.95], None);
        assert_eq!(p, 0.5);
        assert!(status.is_calibrated() && status.warning().is_none());

        let stale = Calibration::load(&text, "other");
        assert!(stale.map().is_none());
        assert_eq!(stale.rule(), GraspRule::default());
        let (p, ci, status) = stale.calibrate(0.9, [0.85, 0.95], None);
        assert_eq!((p, ci), (0.9, [0.85, 0.95]));
        let w = status.warning().expect("a warning");
        assert!(
            !status.is_calibrated() && w.contains("other") && w.contains("refit"),
            "{w}"
        );
        assert!(matches!(
            &status,
            CalibrationStatus::Stale { map_settings_hash, running_settings_hash, .. }
                if map_settings_hash == "h" && running_settings_hash == "other"
        ));
        assert!(matches!(
            CalibrationMap::from_json(&text).and_then(|m| m.check("other")),
            Err(GraspError::StaleCalibration { .. })
        ));
        // a broken map is refused too
        let broken = Calibration::load("{}", "h");
        assert!(broken.map().is_none());
        assert!(matches!(
            broken.calibrate(0.5, [0.4, 0.6], None).2,
            CalibrationStatus::Absent { .. }
        ));
        let mut bad = m.clone();
        bad.blocks = vec![block(0.0, 0.5, 50, 40), block(0.5, 1.0, 50, 10)];
        assert!(CalibrationMap::from_json(&serde_json::to_string(&bad).expect("json")).is_err());
    }

    #[test]
    fn the_shipped_map_parses() {
        let m = CalibrationMap::from_json(SHIPPED_MAP_JSON).expect("the shipped map");
        assert!(!m.blocks.is_empty());
    }

    /// The raw rates of one unchanged scene as the filter gives them step after step
    /// (issue 20: between 0.62 and 0.95 from one second to the next).
    fn alternating(i: usize) -> f64 {
        if i.is_multiple_of(2) { 0.62 } else { 0.95 }
    }

    #[test]
    fn smoothed_answers_about_an_unchanged_scene_do_not_jump() {
        let raw = Calibration::raw("test");
        let rule = GraspRule::default();
        let jumps = |tau_s: f64| {
            let mut s = AnswerSmoother::new(tau_s);
            let answers: Vec<f64> = (0..50)
                .map(|i| {
                    s.update(i as i64 * 100_000_000, (alternating(i), [0.5, 1.0]), None, &raw, &rule)
                        .p_success
                })
                .collect();
            // after the first second
            answers[10..]
                .windows(2)
                .map(|w| (w[1] - w[0]).abs())
                .fold(0.0, f64::max)
        };
        // each answer alone jumps by the filter's 0.33; a 1 s time constant at 10 Hz moves
        // by at most 1 - exp(-0.1) of it around the mean
        assert!(jumps(0.0) > 0.3);
        let smooth = jumps(1.0);
        assert!(smooth < 0.1 * 0.33 + 1e-9, "{smooth}");
        let mut s = AnswerSmoother::new(1.0);
        let mut last = 0.0;
        for i in 0..100 {
            last = s
                .update(
                    i * 100_000_000,
                    (alternating(i as usize), [0.5, 1.0]),
                    None,
                    &raw,
                    &rule,
                )
                .p_success;
        }
        assert!((last - 0.785).abs() < 0.02, "{last}");
    }

    #[test]
    fn smoothing_follows_a_real_change_within_a_few_time_constants() {
        let raw = Calibration::raw("test");
        let rule = GraspRule::default();
        let mut s = AnswerSmoother::new(0.5);
        for i in 0..10 {
            s.update(i * 100_000_000, (0.2, [0.1, 0.3]), None, &raw, &rule);
        }
        // the grasp becomes safe at 1 s: after 3 time constants the answer is within 5 %
        let mut p = 0.0;
        for i in 10..25 {
            p = s
                .update(i * 100_000_000, (1.0, [0.97, 1.0]), None, &raw, &rule)
                .p_success;
        }
        assert!(p > 0.2 + 0.95 * 0.8 && p < 1.0, "{p}");
    }

    #[test]
    fn answers_at_one_stamp_replace_each_other_and_a_restarted_clock_starts_over() {
        let raw = Calibration::raw("test");
        let rule = GraspRule::default();
        let mut s = AnswerSmoother::new(1.0);
        s.update(0, (0.2, [0.1, 0.3]), None, &raw, &rule);
        let a = s.update(100_000_000, (0.9, [0.8, 0.95]), None, &raw, &rule);
        // a planner asking ten times within the same step gets the same answer
        for _ in 0..10 {
            let b = s.update(100_000_000, (0.9, [0.8, 0.95]), None, &raw, &rule);
            assert_eq!(a, b);
        }
        // a clock that went back: the new answer alone
        let c = s.update(50_000_000, (0.7, [0.6, 0.8]), None, &raw, &rule);
        assert_eq!(c.p_success, 0.7);
    }

    #[test]
    fn a_run_rule_needs_successive_answers_over_the_threshold() {
        let m = map_of(
            vec![block(0.0, 0.5, 100, 10), block(0.5, 1.0, 100, 99)],
            calibrated_rule(0.9, 3),
            0.0,
        );
        let cal = Calibration::Fitted(Arc::new(m));
        let rule = cal.rule();
        let mut s = cal.smoother();
        let raws = [0.95, 0.95, 0.1, 0.95, 0.95, 0.95, 0.95];
        let grasp: Vec<bool> = raws
            .iter()
            .enumerate()
            .map(|(i, &p)| s.update(i as i64 * 100_000_000, (p, [p, p]), None, &cal, &rule).grasp)
            .collect();
        assert_eq!(grasp, [false, false, false, false, false, true, true]);
    }

    /// While the robot's camera looks away the answer is `observe` and the rule's run starts
    /// over; the rate still smooths on, so the run rebuilds from the next seen answer.
    #[test]
    fn an_answer_the_reference_camera_did_not_see_is_observe_and_restarts_the_run() {
        let m = map_of(
            vec![block(0.0, 0.5, 100, 10), block(0.5, 1.0, 100, 99)],
            calibrated_rule(0.9, 2),
            0.0,
        );
        let cal = Calibration::Fitted(Arc::new(m));
        let rule = cal.rule();
        let mut s = cal.smoother();
        let seen = [true, true, true, false, false, true, true];
        let out: Vec<(bool, u32)> = seen
            .iter()
            .enumerate()
            .map(|(i, &sees)| {
                let a = s.update_seen(i as i64 * 100_000_000, (0.95, [0.94, 0.96]), None, &cal, &rule, sees);
                (a.grasp, a.run)
            })
            .collect();
        assert_eq!(
            out,
            [
                (false, 1),
                (true, 2),
                (true, 3),
                (false, 0),
                (false, 0),
                (false, 1),
                (true, 2)
            ]
        );
    }

    #[test]
    fn a_rule_on_the_raw_rate_reads_the_smoothed_rate_between_the_maps_steps() {
        // one block maps every raw rate from 0.5 up to 0.99: a calibrated threshold can only
        // take all of them or none, the raw rate's threshold splits them
        let mut m = map_of(
            vec![block(0.0, 0.5, 100, 10), block(0.5, 1.0, 100, 99)],
            calibrated_rule(0.95, 1),
            0.5,
        );
        m.rule = GraspRule {
            quantity: RuleQuantity::Raw,
            threshold: 0.94,
            run_length: 1,
        };
        let cal = Calibration::Fitted(Arc::new(m));
        let rule = cal.rule();
        let answer = |raws: &[f64]| {
            let mut s = cal.smoother();
            let mut last = None;
            for (i, &p) in raws.iter().enumerate() {
                last = Some(s.update(i as i64 * 100_000_000, (p, [p - 0.02, p]), None, &cal, &rule));
            }
            last.expect("an answer")
        };
        let steady = answer(&[0.95; 20]);
        assert!(steady.grasp && (steady.rule_value - 0.95).abs() < 1e-9, "{steady:?}");
        let below = answer(&[0.93; 20]);
        assert!(!below.grasp && below.p_success > 0.95, "{below:?}");
        // the value is the smoothed raw rate, not this answer's own: one high answer after a
        // low run does not grasp
        let mut raws = vec![0.6; 20];
        raws.push(0.99);
        let jump = answer(&raws);
        assert!(!jump.grasp && jump.rule_value < 0.94 && jump.rule_value == jump.p_success_raw);
    }
}
