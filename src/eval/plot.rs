//! Per-sequence plots of the four metrics of the paper's Fig. 5 over time, drawn with
//! `plotters` as SVG and PNG: translation error, orientation error, translation standard
//! deviation and the log-likelihood of the true orientation, one line per tracked object
//! (dashed: a second run, e.g. the single-view baseline beside the multi-view tracker). And the
//! grasp decision's reliability diagram as a PNG ([`reliability_png`]).
//!
//! The PNG text is drawn with an ASCII cut of DejaVu Sans built into the binary
//! (`assets/fonts`), so the plots need no system fonts.

use super::EvalError;
use super::report::{FrameErrors, ObjectTrace, ReliabilityBin};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

/// One line of the plot.
#[derive(Debug, Clone)]
pub struct Series {
    pub label: String,
    pub dashed: bool,
    /// (time in seconds, the four values; `None` where there was no estimate).
    pub points: Vec<(f64, [Option<f64>; 4])>,
}

/// The panels, in order.
pub const PANELS: [&str; 4] = [
    "translation error (m)",
    "orientation error (deg, L1)",
    "translation std (m)",
    "log-likelihood of true orientation",
];

fn values(e: &FrameErrors) -> [Option<f64>; 4] {
    [
        Some(e.translation_error_m),
        Some(e.orientation_error_deg),
        Some(e.translation_std_m),
        e.gt_orientation_loglik,
    ]
}

impl Series {
    /// A series from a trace; time is measured from `t0_ns`.
    pub fn from_trace(trace: &ObjectTrace, label: &str, dashed: bool, t0_ns: i64) -> Self {
        Self {
            label: label.to_string(),
            dashed,
            points: trace
                .frames
                .iter()
                .map(|f| {
                    let t = (f.stamp_ns - t0_ns) as f64 * 1e-9;
                    (t, f.errors.as_ref().map_or([None; 4], values))
                })
                .collect(),
        }
    }
}

const FONT: &str = "sans-serif";

/// Registers the built-in font once per process (plotters keeps one global font table).
fn register_fonts() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let regular: &'static [u8] = include_bytes!("../../assets/fonts/DejaVuSans-ASCII.ttf");
        let bold: &'static [u8] = include_bytes!("../../assets/fonts/DejaVuSans-Bold-ASCII.ttf");
        // Both are valid TrueType files (a unit test draws text with them).
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, regular);
        let _ = plotters::style::register_font(FONT, FontStyle::Bold, bold);
    });
}

fn draw_error<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> EvalError {
    EvalError::Io(format!("drawing a plot: {e}"))
}

fn io_error(path: &std::path::Path, e: impl std::fmt::Display) -> EvalError {
    EvalError::Io(format!("{}: {e}", path.display()))
}

/// Draws into an RGB image of `size` with plotters' bitmap backend.
fn bitmap<F, T>(size: (u32, u32), draw: F) -> Result<(image::RgbImage, T), EvalError>
where
    F: FnOnce(DrawingArea<BitMapBackend<'_>, Shift>) -> Result<T, EvalError>,
{
    register_fonts();
    let mut buf = vec![255u8; size.0 as usize * size.1 as usize * 3];
    let out = {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        let out = draw(root.clone())?;
        root.present().map_err(draw_error)?;
        out
    };
    let img = image::RgbImage::from_raw(size.0, size.1, buf)
        .ok_or_else(|| EvalError::Io("plot buffer has the wrong size".into()))?;
    Ok((img, out))
}

// ------------------------------------------------------------------------------------------
// Reliability diagram

/// Side of the reliability diagram (pixels).
const RELIABILITY_SIZE_PX: u32 = 480;
const GRID: RGBColor = RGBColor(225, 225, 225);
const DIAGONAL: RGBColor = RGBColor(150, 150, 150);
const BAR: RGBColor = RGBColor(120, 160, 220);
const GAP: RGBColor = RGBColor(210, 30, 30);

/// Draws the reliability diagram: x the predicted `p_success` (0 to 1 left to right), y the
/// share that succeeded on the true pose (0 to 1 bottom to top), grid lines every 0.1, the
/// diagonal of perfect calibration in grey; per non-empty decile a blue bar up to the
/// observed share centred at the mean prediction, a red line from it to the diagonal (the
/// gap the ECE weighs) and a black dot whose area grows with the decile's count.
pub fn reliability_image(bins: &[ReliabilityBin]) -> Result<image::RgbImage, EvalError> {
    Ok(draw_reliability(bins)?.0)
}

/// Maps (predicted, observed) to a pixel of the reliability diagram.
type PixelOf = Box<dyn Fn(f64, f64) -> (i32, i32)>;

fn draw_reliability(bins: &[ReliabilityBin]) -> Result<(image::RgbImage, PixelOf), EvalError> {
    let size = (RELIABILITY_SIZE_PX, RELIABILITY_SIZE_PX);
    bitmap(size, |root| {
        root.fill(&WHITE).map_err(draw_error)?;
        let mut chart = ChartBuilder::on(&root)
            .caption("reliability of p_success", (FONT, 16, FontStyle::Bold))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(44)
            .build_cartesian_2d(0.0..1.0, 0.0..1.0)
            .map_err(draw_error)?;
        chart
            .configure_mesh()
            .x_labels(11)
            .y_labels(11)
            .disable_x_mesh()
            .disable_y_mesh()
            .x_desc("predicted p_success")
            .y_desc("observed success rate")
            .x_label_formatter(&|v| format!("{v:.1}"))
            .y_label_formatter(&|v| format!("{v:.1}"))
            .label_style((FONT, 12))
            .draw()
            .map_err(draw_error)?;
        let grid = (1..10).map(|k| k as f64 / 10.0);
        chart
            .draw_series(grid.clone().map(|v| PathElement::new(vec![(v, 0.0), (v, 1.0)], GRID)))
            .map_err(draw_error)?;
        chart
            .draw_series(grid.map(|v| PathElement::new(vec![(0.0, v), (1.0, v)], GRID)))
            .map_err(draw_error)?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![(0.0, 0.0), (1.0, 1.0)],
                DIAGONAL,
            )))
            .map_err(draw_error)?;
        let total = bins.iter().map(|b| b.count).sum::<usize>().max(1) as f64;
        let clamp = |v: f64| v.clamp(0.0, 1.0);
        chart
            .draw_series(bins.iter().map(|b| {
                let (x0, x1) = (clamp(b.predicted - 0.04), clamp(b.predicted + 0.04));
                Rectangle::new([(x0, 0.0), (x1, clamp(b.observed))], BAR.filled())
            }))
            .map_err(draw_error)?;
        chart
            .draw_series(bins.iter().map(|b| {
                let x = clamp(b.predicted);
                PathElement::new(vec![(x, clamp(b.observed)), (x, x)], GAP)
            }))
            .map_err(draw_error)?;
        chart
            .draw_series(bins.iter().map(|b| {
                let r = 3.0 + 12.0 * (b.count as f64 / total).sqrt();
                Circle::new(
                    (clamp(b.predicted), clamp(b.observed)),
                    r.round() as i32,
                    BLACK.filled(),
                )
            }))
            .map_err(draw_error)?;
        let coord = chart.as_coord_spec().clone();
        let pixel_of: PixelOf = Box::new(move |x, y| coord.translate(&(x, y)));
        Ok(pixel_of)
    })
}

/// Writes [`reliability_image`] as a PNG.
pub fn reliability_png(bins: &[ReliabilityBin], path: &std::path::Path) -> Result<(), EvalError> {
    reliability_image(bins)?
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| io_error(path, e))
}

// ------------------------------------------------------------------------------------------
// The sequence plot

const COLORS: [RGBColor; 8] = [
    RGBColor(0x1f, 0x77, 0xb4),
    RGBColor(0xd6, 0x27, 0x28),
    RGBColor(0x2c, 0xa0, 0x2c),
    RGBColor(0xff, 0x7f, 0x0e),
    RGBColor(0x94, 0x67, 0xbd),
    RGBColor(0x8c, 0x56, 0x4b),
    RGBColor(0xe3, 0x77, 0xc2),
    RGBColor(0x17, 0xbe, 0xcf),
];

/// Size of the sequence plot (pixels): four stacked panels and the legend on the right.
const SEQUENCE_SIZE_PX: (u32, u32) = (900, 880);
const LEGEND_W_PX: u32 = 250;
const TITLE_H_PX: u32 = 36;

/// A "nice" upper or lower axis limit.
fn nice_range(lo: f64, hi: f64) -> (f64, f64) {
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    if (hi - lo).abs() < 1e-12 {
        return (lo - 0.5 * lo.abs().max(1e-3), hi + 0.5 * hi.abs().max(1e-3));
    }
    let pad = 0.05 * (hi - lo);
    (lo - pad, hi + pad)
}

/// The time axis shared by the panels.
fn time_range(series: &[Series]) -> (f64, f64) {
    let (t_min, t_max) = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.0))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), t| (a.min(t), b.max(t)));
    if t_min.is_finite() && t_max > t_min {
        (t_min, t_max)
    } else {
        (0.0, 1.0)
    }
}

/// Panel `k`'s value axis; errors and deviations are never negative, so those start at 0.
fn value_range(series: &[Series], k: usize) -> (f64, f64) {
    let (lo, hi) = series
        .iter()
        .flat_map(|s| s.points.iter().filter_map(|p| p.1[k]))
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let signed = k == 3;
    let (l, h) = nice_range(if signed { lo } else { lo.min(0.0) }, hi);
    (if signed { l } else { l.max(0.0) }, h)
}

/// A series' stretches with an estimate in panel `k` (the line breaks where there is none).
fn runs(series: &Series, k: usize) -> Vec<Vec<(f64, f64)>> {
    let mut runs: Vec<Vec<(f64, f64)>> = vec![Vec::new()];
    for (t, v) in &series.points {
        match v[k].filter(|v| v.is_finite()) {
            Some(v) => runs.last_mut().map_or((), |r| r.push((*t, v))),
            None => {
                if runs.last().is_some_and(|r| !r.is_empty()) {
                    runs.push(Vec::new());
                }
            }
        }
    }
    runs.retain(|r| !r.is_empty());
    runs
}

fn tick(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 {
        "0".into()
    } else if a < 0.1 {
        format!("{v:.3}")
    } else if a < 10.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.0}")
    }
}

fn draw_sequence<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    series: &[Series],
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let (title_area, body) = root.split_vertically(TITLE_H_PX);
    title_area.draw_text(
        title,
        &(FONT, 17, FontStyle::Bold).into_text_style(&title_area),
        (70, 12),
    )?;
    let (panels_area, legend) = body.split_horizontally(SEQUENCE_SIZE_PX.0 - LEGEND_W_PX);
    let (t_min, t_max) = time_range(series);
    for (k, (area, name)) in panels_area.split_evenly((4, 1)).iter().zip(PANELS).enumerate() {
        let (lo, hi) = value_range(series, k);
        let mut chart = ChartBuilder::on(area)
            .caption(name, (FONT, 14, FontStyle::Bold))
            .margin_right(12)
            .margin_bottom(8)
            .x_label_area_size(22)
            .y_label_area_size(62)
            .build_cartesian_2d(t_min..t_max, lo..hi)?;
        chart
            .configure_mesh()
            .x_labels(6)
            .y_labels(5)
            .disable_x_mesh()
            .bold_line_style(RGBColor(221, 221, 221))
            .light_line_style(TRANSPARENT)
            .x_label_formatter(&|t| format!("{t:.1} s"))
            .y_label_formatter(&|v| tick(*v))
            .label_style((FONT, 12))
            .draw()?;
        for (j, s) in series.iter().enumerate() {
            let style = COLORS[j % COLORS.len()].stroke_width(2);
            for run in runs(s, k) {
                if s.dashed {
                    chart.draw_series(DashedLineSeries::new(run, 6, 3, style))?;
                } else {
                    chart.draw_series(LineSeries::new(run, style))?;
                }
            }
        }
    }
    for (j, s) in series.iter().enumerate() {
        let y = 14 + 18 * j as i32;
        let style = COLORS[j % COLORS.len()].stroke_width(2);
        let line = vec![(8, y), (32, y)];
        if s.dashed {
            legend.draw(&DashedPathElement::new(line, 6, 3, style))?;
        } else {
            legend.draw(&PathElement::new(line, style))?;
        }
        let text = (FONT, 12)
            .into_text_style(&legend)
            .pos(plotters::style::text_anchor::Pos::new(
                plotters::style::text_anchor::HPos::Left,
                plotters::style::text_anchor::VPos::Center,
            ));
        legend.draw_text(&s.label, &text, (38, y))?;
    }
    Ok(())
}

/// The SVG document: four stacked panels sharing the time axis.
pub fn sequence_svg(title: &str, series: &[Series]) -> Result<String, EvalError> {
    register_fonts();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SEQUENCE_SIZE_PX).into_drawing_area();
        draw_sequence(&root, title, series).map_err(draw_error)?;
        root.present().map_err(draw_error)?;
    }
    Ok(svg)
}

/// The same plot as [`sequence_svg`], as an image.
pub fn sequence_image(title: &str, series: &[Series]) -> Result<image::RgbImage, EvalError> {
    Ok(bitmap(SEQUENCE_SIZE_PX, |root| {
        draw_sequence(&root, title, series).map_err(draw_error)
    })?
    .0)
}

/// Writes the sequence plot as `<dir>/<name>.svg` and `<dir>/<name>.png`.
pub fn write_sequence_plots(
    title: &str,
    series: &[Series],
    dir: &std::path::Path,
    name: &str,
) -> Result<(), EvalError> {
    let svg_path = dir.join(format!("{name}.svg"));
    std::fs::write(&svg_path, sequence_svg(title, series)?).map_err(|e| io_error(&svg_path, e))?;
    let png_path = dir.join(format!("{name}.png"));
    sequence_image(title, series)?
        .save_with_format(&png_path, image::ImageFormat::Png)
        .map_err(|e| io_error(&png_path, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::report::FrameMetrics;

    #[test]
    fn reliability_diagram_draws_bars_gaps_dots_and_labels() {
        let bins = [
            ReliabilityBin {
                predicted: 0.25,
                observed: 0.25,
                count: 4,
            },
            ReliabilityBin {
                predicted: 0.95,
                observed: 0.5,
                count: 20,
            },
        ];
        let (img, pixel_of) = draw_reliability(&bins).expect("draw");
        let at = |x: f64, y: f64| {
            let (px, py) = pixel_of(x, y);
            img.get_pixel(px as u32, py as u32).0
        };
        // The over-confident decile: a red gap between its observed 0.5 and the diagonal.
        assert_eq!(at(0.95, 0.7), [210, 30, 30]);
        // Its bar is blue below the dot, and the dot is black.
        assert_eq!(at(0.93, 0.2), [120, 160, 220]);
        assert_eq!(at(0.95, 0.5), [0, 0, 0]);
        // Nothing drawn above a calibrated decile's dot, up to the grid.
        assert_eq!(at(0.27, 0.65), [255, 255, 255]);
        // The axes are labelled: dark text pixels left of and below the plotting area.
        let (left, bottom) = pixel_of(0.0, 0.0);
        let dark_below = (0..img.width())
            .flat_map(|x| (bottom as u32 + 4..img.height()).map(move |y| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y).0.iter().all(|&c| c < 100))
            .count();
        let dark_left = (0..left as u32 - 4)
            .flat_map(|x| (0..img.height()).map(move |y| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y).0.iter().all(|&c| c < 100))
            .count();
        assert!(dark_below > 200 && dark_left > 200, "{dark_below} {dark_left}");
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("r.png");
        reliability_png(&bins, &p).expect("png");
        let back = image::open(&p).expect("read png").to_rgb8();
        assert_eq!(back.dimensions(), (RELIABILITY_SIZE_PX, RELIABILITY_SIZE_PX));
    }

    fn two_series() -> [Series; 2] {
        let errs = |t: f64| FrameErrors {
            translation_error_m: t,
            translation_error_l1_m: t,
            orientation_error_deg: 100.0 * t,
            geodesic_error_deg: 0.0,
            symmetric_error_deg: 0.0,
            translation_std_m: 0.5 * t,
            gt_orientation_loglik: Some(-10.0 + t),
            add_m: t,
            add_s_m: t,
            rotation_entropy: 0.0,
            shape_symmetric_error_deg: None,
            truth_place: None,
            estimate_xyzw: None,
            error_rotvec_object_rad: None,
            error_translation_object_m: None,
        };
        let trace = ObjectTrace {
            sequence: "s".into(),
            object: "025_mug".into(),
            table_row: true,
            frames: (0..10)
                .map(|i| FrameMetrics {
                    frame_id: i,
                    stamp_ns: i as i64 * 100_000_000,
                    errors: (i != 4).then(|| errs(0.01 * i as f64)),
                })
                .collect(),
        };
        [
            Series::from_trace(&trace, "025_mug multi", false, 0),
            Series::from_trace(&trace, "025_mug <single>", true, 0),
        ]
    }

    #[test]
    fn svg_has_four_panels_a_line_per_series_and_gaps() {
        let series = two_series();
        // Frame 4 has no estimate: each series breaks into two runs in every panel.
        assert!((0..4).all(|k| runs(&series[0], k).len() == 2));
        let svg = sequence_svg("seq & co", &series).expect("svg");
        assert!(svg.starts_with("<svg"));
        assert!(svg.trim_end().ends_with("</svg>"));
        for p in PANELS {
            assert!(svg.contains(p), "panel {p}");
        }
        // The solid series: one polyline per run and panel in its colour.
        assert_eq!(svg.matches(r##"stroke="#1F77B4""##).count(), 8 + 1);
        // The dashed one is drawn in many short dashes.
        assert!(svg.matches(r##"stroke="#D62728""##).count() > 8 * 3);
        assert!(svg.contains("&lt;single&gt;") && svg.contains("seq &amp; co"));
        assert!(!svg.contains("NaN") && !svg.contains("inf"));
    }

    #[test]
    fn png_is_drawn_with_text_and_both_series() {
        let img = sequence_image("seq", &two_series()).expect("png");
        assert_eq!(img.dimensions(), SEQUENCE_SIZE_PX);
        let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
        assert!(count([0x1f, 0x77, 0xb4]) > 200 && count([0xd6, 0x27, 0x28]) > 100);
        // Text: anti-aliased grey pixels from the built-in font.
        let grey = img
            .pixels()
            .filter(|p| p.0[0] == p.0[1] && p.0[1] == p.0[2] && (30..200).contains(&p.0[0]))
            .count();
        assert!(grey > 500, "{grey} grey pixels");
    }

    #[test]
    fn empty_plot_is_still_valid() {
        let svg = sequence_svg("nothing", &[]).expect("svg");
        assert!(svg.contains("</svg>") && !svg.contains("NaN"));
        sequence_image("nothing", &[]).expect("png");
    }
}
