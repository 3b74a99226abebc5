//! `pregrasp eval`: the command line of the evaluation.

use super::report::Mode;
use super::run::{DecideConfig, EvalConfig, run_all, tracker_config};
use crate::grasp::{Calibration, Gripper};
use crate::tracker::{CodebookConfig, ColorFeatures, TrackerConfig};
use std::path::PathBuf;

/// Options of `pregrasp eval`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// A sequence, or a folder of sequences (`shared/design/multiview-bop.md`).
    #[arg(long)]
    pub data: PathBuf,
    /// `multi`: every camera; `single`: the reference (robot) camera alone, 110 particles.
    #[arg(long, value_enum, default_value = "multi")]
    pub mode: Mode,
    /// Folder of meshes `<object name>.ply` used instead of the paths in rig.json.
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// Output folder: results.json, table.md, frames.json, plots/.
    #[arg(long)]
    pub out: PathBuf,
    /// Codebook cache folder (default: <out>/cache).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Rotation grid step in degrees (5 = the paper's 37 x 72 x 72 grid).
    #[arg(long, default_value_t = 5)]
    pub grid_step_deg: u32,
    /// Decide grasp or observe at every step and report its calibration.
    #[arg(long)]
    pub decide: bool,
    /// Gripper JSON for --decide (default: the built-in parallel-jaw gripper).
    #[arg(long)]
    pub gripper: Option<PathBuf>,
    /// Pose samples per decision.
    #[arg(long, default_value_t = 1000)]
    pub samples: usize,
    /// Threshold of the grasp rule (default: the calibration map's; 0.9 on the raw rate's
    /// Wilson lower bound without a map).
    #[arg(long)]
    pub threshold: Option<f64>,
    /// Calibration map for --decide (default: the one shipped in the binary); a map fitted
    /// for other settings is refused and the raw rate scored instead.
    #[arg(long)]
    pub calibration_map: Option<PathBuf>,
    /// With --decide: decide a second time on an independent draw of samples at every frame
    /// (`p_raw_repeat` in decisions.json: what sampling alone moves).
    #[arg(long)]
    pub repeat_draw: bool,
    /// Evaluate at most this many steps per sequence.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Feed every n-th time step only (the same approach at a lower frame rate).
    #[arg(long, default_value_t = 1)]
    pub frame_stride: usize,
    /// Seed of the stand-in detections.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Track only each sequence's target object (the Table I rows), not every object.
    #[arg(long)]
    pub only_target: bool,
    /// An earlier run's output folder whose traces the plots show dashed (e.g. single-view).
    #[arg(long)]
    pub compare: Option<PathBuf>,
    /// The small codebook `serve` starts tracking with (`CodebookConfig::coarse()`, its default
    /// with the 10-degree grid) instead of the full one.
    #[arg(long)]
    pub coarse_codebook: bool,
    /// Codebooks from the meshes' depth alone (no colour): for meshes whose colours do not
    /// match the cameras' (a scan under other light, an untextured CAD model).
    #[arg(long)]
    pub depth_only: bool,
    /// Colour codes from the renders' RGB (shading included) instead of their chromaticity:
    /// only right when the scenes are lit like the templates (`pregrasp generate --headlight`).
    #[arg(long)]
    pub rgb: bool,
    /// Seed of the codebooks' training crops (how much a result owes to the encoder's random
    /// training set).
    #[arg(long, default_value_t = CodebookConfig::default().seed)]
    pub codebook_seed: u64,
    /// Components of the code given to colour (0: one code of depth and colour together).
    /// (default: the codebook's, 16 for the full one)
    #[arg(long)]
    pub color_code_dim: Option<usize>,
    /// Weight of the colour cosine in the similarity (0..1; the depth's is one minus it).
    /// (default: the codebook's)
    #[arg(long)]
    pub color_code_weight: Option<f32>,
    /// Samples per frame for the truth's place in the distribution (highest-density regions,
    /// `eval::trust`); 0 skips those measures.
    #[arg(long, default_value_t = super::run::DEFAULT_TRUST_SAMPLES)]
    pub trust_samples: usize,
    /// A JSON file of tracker settings that override the defaults, only the fields given, e.g.
    /// `{"observation": {"sigma": 0.08}, "blur_sigma_bins": 1.0}`.
    #[arg(long)]
    pub tracker_config: Option<PathBuf>,
}

/// The default tracker configuration with the fields of `overrides` (a JSON object, nested
/// objects merged field by field) put over it. Unknown fields and wrong types are errors.
pub fn tracker_config_with(overrides: &serde_json::Value) -> anyhow::Result<TrackerConfig> {
    // `full` lists the settings an override may name (the defaults', and those off by default
    // at the values they take when named; `twins: null` switches twins off)
    fn merge(
        base: &mut serde_json::Value,
        full: &serde_json::Value,
        over: &serde_json::Value,
        path: &str,
    ) -> anyhow::Result<()> {
        match (base, over) {
            (serde_json::Value::Object(b), serde_json::Value::Object(o)) => {
                for (k, v) in o {
                    let here = format!("{path}{k}");
                    let full_k = full
                        .get(k)
                        .ok_or_else(|| anyhow::anyhow!("tracker config: unknown field `{here}`"))?;
                    let slot = b.entry(k.clone()).or_insert_with(|| full_k.clone());
                    merge(slot, full_k, v, &format!("{here}."))?;
                }
                Ok(())
            }
            (b, o) => {
                *b = o.clone();
                Ok(())
            }
        }
    }
    if !overrides.is_object() {
        anyhow::bail!("tracker config: expected a JSON object");
    }
    let mut base = serde_json::to_value(TrackerConfig::default())?;
    let mut full = base.clone();
    full["support"] = serde_json::to_value(crate::tracker::support::SupportConfig::default())?;
    // off by default and then left out of the settings (their hash stays that of the map)
    full["observation"]["full_area_px"] = serde_json::json!(0.0);
    full["observation"]["near_box_rotation"] = serde_json::json!(false);
    full["twins"]["near_max_trimmed_rel"] = serde_json::json!(0.0);
    full["twins"]["near_min_object_px"] = serde_json::json!(0.0);
    full["verification"]["register_modes"] = serde_json::json!(false);
    merge(&mut base, &full, overrides, "")?;
    serde_json::from_value(base).map_err(|e| anyhow::anyhow!("tracker config: {e}"))
}

/// [`tracker_config_with`] the overrides of a JSON file (`--tracker-config` of `eval` and
/// `demo-loops`); errors name the file.
pub fn tracker_config_from_file(path: &std::path::Path) -> anyhow::Result<TrackerConfig> {
    let text = std::fs::read_to_string(path).map_err(|e| anyhow::anyhow!("tracker config {}: {e}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| anyhow::anyhow!("tracker config {}: {e}", path.display()))?;
    tracker_config_with(&v)
}

/// The defaults, or [`tracker_config_from_file`] of the file the environment variable `var`
/// names: how a test or a bench is run with other tracker settings.
pub fn tracker_config_from_env(var: &str) -> anyhow::Result<TrackerConfig> {
    match std::env::var_os(var) {
        Some(path) => tracker_config_from_file(std::path::Path::new(&path)),
        None => Ok(TrackerConfig::default()),
    }
}

impl Args {
    /// The run's configuration.
    pub fn config(&self) -> anyhow::Result<EvalConfig> {
        let decide = if self.decide {
            let gripper = match &self.gripper {
                Some(p) => Gripper::from_file(p)?,
                None => Gripper::default_parallel_jaw(),
            };
            let mut d = DecideConfig::new(gripper);
            d.n_samples = self.samples;
            d.repeat_draw = self.repeat_draw;
            Some(d)
        } else {
            None
        };
        let mut cfg = self.config_without_calibration(decide)?;
        let settings_hash = cfg.decide.as_ref().map(|d| {
            super::calibration::calibration_settings_hash(
                &tracker_config(&cfg.tracker, cfg.mode),
                &cfg.codebook,
                cfg.grid_step_deg,
                &d.gripper,
            )
        });
        if let (Some(d), Some(hash)) = (cfg.decide.as_mut(), settings_hash) {
            d.calibration = match &self.calibration_map {
                Some(p) => {
                    let text = std::fs::read_to_string(p)
                        .map_err(|e| anyhow::anyhow!("calibration map {}: {e}", p.display()))?;
                    Calibration::load(&text, &hash)
                }
                None => Calibration::shipped(&hash),
            }
            .for_samples(d.n_samples);
            d.threshold = self.threshold.unwrap_or(d.calibration.rule().threshold);
        }
        Ok(cfg)
    }

    fn config_without_calibration(&self, decide: Option<DecideConfig>) -> anyhow::Result<EvalConfig> {
        Ok(EvalConfig {
            mode: self.mode,
            models_dir: self.models.clone(),
            cache_dir: Some(self.cache.clone().unwrap_or_else(|| self.out.join("cache"))),
            grid_step_deg: self.grid_step_deg,
            codebook: {
                let base = if self.coarse_codebook {
                    CodebookConfig::coarse()
                } else {
                    CodebookConfig::default()
                };
                CodebookConfig {
                    use_color: !self.depth_only,
                    color_features: if self.rgb {
                        ColorFeatures::Rgb
                    } else {
                        ColorFeatures::Chromaticity
                    },
                    seed: self.codebook_seed,
                    color_code_dim: self.color_code_dim.unwrap_or(base.color_code_dim),
                    color_code_weight: self.color_code_weight.unwrap_or(base.color_code_weight),
                    ..base
                }
            },
            tracker: match &self.tracker_config {
                Some(p) => tracker_config_from_file(p)?,
                None => TrackerConfig::default(),
            },
            detection_seed: self.seed,
            max_frames: self.max_frames,
            frame_stride: self.frame_stride,
            decide,
            only_target: self.only_target,
            trust_samples: self.trust_samples,
        })
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let cfg = args.config()?;
    let results = run_all(&args.data, &args.out, &cfg, args.compare.as_deref())?;
    let m = &results.mean;
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.4}"));
    println!(
        "{} sequences, mode {}: mean translation error {} m, orientation error {} deg, std {} m, loglik {}, ADD-S AUC {}, coverage {}",
        results.sequences.len(),
        results.mode.as_str(),
        f(m.translation_error_m),
        f(m.orientation_error_deg),
        f(m.translation_std_m),
        f(m.gt_orientation_loglik),
        f(m.add_s_auc),
        f(m.coverage)
    );
    if let Some(d) = &results.decision {
        println!(
            "decision: grasp rate {:.3}, false grasp rate {}, ECE {:.4} over {} frames",
            d.grasp_rate,
            f(d.false_grasp_rate),
            d.ece,
            d.frames
        );
    }
    if let Some(dc) = &cfg.decide {
        match dc.calibration.map() {
            Some(m) => println!(
                "calibrated: map for settings {} (smoothing {} s, rule {:?} >= {} in {} answers)",
                m.settings_hash, m.smoothing_time_constant_s, m.rule.quantity, dc.threshold, m.rule.run_length
            ),
            None => println!("not calibrated: raw rate, Wilson lower bound >= {}", dc.threshold),
        }
    }
    println!("wrote {}", args.out.join("results.json").display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tracker_overrides_change_only_the_fields_given() {
        let c = tracker_config_with(&serde_json::json!({"observation": {"sigma": 0.08}, "blur_sigma_bins": 1.5}))
            .expect("valid overrides");
        let d = TrackerConfig::default();
        assert_eq!(c.observation.sigma, 0.08);
        assert_eq!(c.blur_sigma_bins, 1.5);
        assert_eq!(c.observation.loglik_floor, d.observation.loglik_floor);
        assert_eq!(c.particles_from_robot_camera, d.particles_from_robot_camera);
        let unknown = tracker_config_with(&serde_json::json!({"observation": {"sigmaa": 0.08}}));
        assert!(unknown.unwrap_err().to_string().contains("observation.sigmaa"));
        assert!(tracker_config_with(&serde_json::json!({"blur_sigma_bins": "wide"})).is_err());
        assert!(tracker_config_with(&serde_json::json!([1, 2])).is_err());
        // every field of the defaults can be overridden, the verification's included
        let v = tracker_config_with(&serde_json::json!({"verification": {"min_mode_mass": 0.1, "min_view_change_deg": 10.0, "occlusion_truncation": 0.5}}))
            .expect("verification overrides");
        assert_eq!(v.verification.min_view_change_deg, 10.0);
        assert_eq!(v.verification.occlusion_truncation, 0.5);
        // an optional setting the defaults leave out starts from its own defaults
        let t = tracker_config_with(&serde_json::json!({"twins": {"share": 0.1}})).expect("twins overrides");
        let tw = t.twins.expect("twins on");
        assert_eq!(tw.share, 0.1);
        assert_eq!(tw.min_shift_m, crate::tracker::TwinConfig::default().min_shift_m);
        assert_eq!(d.twins, Some(crate::tracker::TwinConfig::default()));
        let off = tracker_config_with(&serde_json::json!({"twins": null})).expect("twins off");
        assert!(off.twins.is_none());
        let back: TrackerConfig = serde_json::from_value(serde_json::to_value(&off).unwrap()).unwrap();
        assert!(back.twins.is_none(), "twins switched off stay off through JSON");
        let mut without = serde_json::to_value(&d).unwrap();
        without.as_object_mut().unwrap().remove("twins");
        let missing: TrackerConfig = serde_json::from_value(without).unwrap();
        assert_eq!(
            missing.twins, d.twins,
            "settings that do not name twins keep the default"
        );
        let unknown = tracker_config_with(&serde_json::json!({"twins": {"sharee": 0.1}}));
        assert!(unknown.unwrap_err().to_string().contains("twins.sharee"));
    }

    #[test]
    fn the_far_box_crops_on_by_default_can_be_switched_off() {
        let d = TrackerConfig::default();
        assert_eq!(d.observation.box_crops_below_px, 60.0);
        let off = tracker_config_with(&serde_json::json!({"observation": {"box_crops_below_px": 0.0}})).expect("off");
        assert_eq!(off.observation.box_crops_below_px, 0.0);
        assert_eq!(off.observation.sigma, d.observation.sigma);
        // switched off, it stays off through the serialised settings (the map's hash reads them)
        let back: TrackerConfig = serde_json::from_value(serde_json::to_value(&off).unwrap()).unwrap();
        assert_eq!(back.observation, off.observation);
        let mut without = serde_json::to_value(&d).unwrap();
        without["observation"]
            .as_object_mut()
            .unwrap()
            .remove("box_crops_below_px");
        let missing: TrackerConfig = serde_json::from_value(without).unwrap();
        assert_eq!(
            missing.observation, d.observation,
            "settings that do not name it keep the default"
        );
    }

    #[test]
    fn the_silhouette_area_off_by_default_can_be_named() {
        let a = tracker_config_with(&serde_json::json!({"observation": {"full_area_px": 1000.0}})).expect("area");
        assert_eq!(a.observation.full_area_px, 1000.0);
        let off = serde_json::to_value(TrackerConfig::default()).unwrap();
        assert!(
            off["observation"].get("full_area_px").is_none(),
            "full_area_px off stays out of the settings"
        );
        assert_eq!(serde_json::to_value(a).unwrap()["observation"]["full_area_px"], 1000.0);
    }

    #[test]
    fn the_box_centred_codes_on_by_default_can_be_switched_off() {
        assert!(TrackerConfig::default().observation.box_codes);
        let on = serde_json::to_value(TrackerConfig::default()).unwrap();
        assert_eq!(
            on["observation"]["box_codes"], true,
            "part of the settings (and the map's hash)"
        );
        let a = tracker_config_with(&serde_json::json!({"observation": {"box_codes": false}})).expect("box codes off");
        assert!(!a.observation.box_codes);
        let back: TrackerConfig = serde_json::from_value(serde_json::to_value(&a).unwrap()).unwrap();
        assert_eq!(back.observation, a.observation);
        // a settings file written before the field existed reads as the default
        let mut old = on.clone();
        old["observation"].as_object_mut().unwrap().remove("box_codes");
        let read: TrackerConfig = serde_json::from_value(old).unwrap();
        assert!(read.observation.box_codes);
    }

    #[test]
    fn the_near_twins_off_by_default_can_be_named() {
        let a = tracker_config_with(
            &serde_json::json!({"twins": {"near_max_trimmed_rel": 0.021, "near_min_object_px": 90.0}}),
        )
        .expect("near twins");
        let tw = a.twins.expect("twins stay on");
        assert_eq!((tw.near_max_trimmed_rel, tw.near_min_object_px), (0.021, 90.0));
        assert_eq!(tw.share, crate::tracker::TwinConfig::default().share);
        let off = serde_json::to_value(TrackerConfig::default()).unwrap();
        assert!(
            off["twins"].get("near_max_trimmed_rel").is_none() && off["twins"].get("near_min_object_px").is_none(),
            "off, they stay out of the settings"
        );
    }

    #[test]
    fn the_registered_verification_off_by_default_can_be_named() {
        let a = tracker_config_with(&serde_json::json!({
            "verification": {"min_mode_mass": 0.1, "register_modes": true, "max_side_px": 128}
        }))
        .expect("registered verification");
        assert!(a.verification.register_modes);
        assert_eq!((a.verification.min_mode_mass, a.verification.max_side_px), (0.1, 128));
        let off = serde_json::to_value(TrackerConfig::default()).unwrap();
        assert!(
            off["verification"].get("register_modes").is_none(),
            "off, it stays out of the settings"
        );
    }
}
