//! `pregrasp generate`: options and entry point.

use super::{GenerateConfig, load_models, write_sequences};
use crate::render::Renderer;
use std::path::PathBuf;

/// Options of `pregrasp generate`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Output folder (must not exist or be empty); sequences go to OUT/000000, OUT/000001, ...
    #[arg(long)]
    pub out: PathBuf,
    /// Number of sequences.
    #[arg(long, default_value_t = 1)]
    pub sequences: u32,
    /// Frames per sequence (time steps; every camera captures each).
    #[arg(long, default_value_t = 100)]
    pub frames: u32,
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Relative depth noise sigma: N(0, (sigma d)^2) per pixel.
    #[arg(long, default_value_t = 0.05)]
    pub depth_noise: f64,
    /// Objects (comma-separated names: PLY stems of --models, or box,can,mug built in). Given:
    /// all of them are placed; omitted: a random subset of all models per sequence.
    #[arg(long, value_delimiter = ',')]
    pub objects: Vec<String>,
    /// Folder of meshes in metres (PLY/OBJ/STL, e.g. shared/ycb); default: the built-in objects.
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// Capture-time offset between the cameras (ext1 +1x, ext2 +2x), milliseconds.
    #[arg(long, default_value_t = 0.0)]
    pub stagger_ms: f64,
    /// Target objects, cycled over the sequences (default: a random placed object).
    #[arg(long, value_delimiter = ',')]
    pub targets: Vec<String>,
    /// Time between frames, milliseconds.
    #[arg(long, default_value_t = 100.0)]
    pub frame_period_ms: f64,
    /// Probability that the robot camera looks away from the target for a stretch of frames.
    #[arg(long, default_value_t = 0.5)]
    pub look_away_probability: f64,
    /// Probability that a box on the table hides the target from the robot camera for a
    /// stretch of the approach.
    #[arg(long, default_value_t = 0.0)]
    pub occluder_probability: f64,
    /// Light every camera's view from the camera itself (how the codebook's templates are
    /// lit) instead of from a light above the table drawn per sequence.
    #[arg(long)]
    pub headlight: bool,
}

impl Args {
    /// The generator settings these options describe (loads the meshes).
    pub fn config(&self) -> Result<GenerateConfig, super::GenerateError> {
        let models = load_models(self.models.as_deref(), &self.objects)?;
        let mut c = GenerateConfig::new(models);
        c.place_all = !self.objects.is_empty();
        c.frames = self.frames;
        c.width = self.width;
        c.height = self.height;
        c.depth_noise_relative_sigma = self.depth_noise;
        c.stagger_ms = self.stagger_ms;
        c.frame_period_ms = self.frame_period_ms;
        c.look_away_probability = self.look_away_probability;
        c.occluder_probability = self.occluder_probability;
        c.headlight = self.headlight;
        for t in &self.targets {
            if !c.models.iter().any(|m| &m.name == t) {
                return Err(super::GenerateError::UnknownObject {
                    name: t.clone(),
                    available: c.models.iter().map(|m| m.name.clone()).collect(),
                });
            }
        }
        c.validate()?;
        Ok(c)
    }
}

/// Runs `pregrasp generate`: checks every option before rendering anything, then writes the
/// sequences atomically.
pub fn run(args: Args) -> anyhow::Result<()> {
    let config = args.config()?;
    let renderer = Renderer::new()?;
    tracing::info!(adapter = %renderer.adapter_name(), software = renderer.is_software(), "renderer");
    let start = std::time::Instant::now();
    let dirs = write_sequences(&renderer, &config, args.sequences, args.seed, &args.targets, &args.out)?;
    tracing::info!(
        sequences = dirs.len(),
        frames = args.frames,
        seconds = start.elapsed().as_secs_f64(),
        out = %args.out.display(),
        "done"
    );
    Ok(())
}
