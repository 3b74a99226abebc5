//! Per-sequence plots of the four metrics of the paper's Fig. 5 over time, as hand-written SVG:
//! translation error, orientation error, translation standard deviation and the
//! log-likelihood of the true orientation, one line per tracked object (dashed: a second
//! run, e.g. the single-view baseline beside the multi-view tracker). And the grasp
//! decision's reliability diagram as a PNG ([`reliability_png`]).

use super::report::{FrameErrors, ObjectTrace};
use std::fmt::Write as _;

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

/// Side of the reliability diagram (pixels) and its margin.
const RELIABILITY_SIZE_PX: u32 = 480;
const RELIABILITY_MARGIN_PX: u32 = 40;

/// Draws the reliability diagram: x the predicted `p_success` (0 to 1 left to right), y the
/// share that succeeded on the true pose (0 to 1 bottom to top), grid lines every 0.1, the
/// diagonal of perfect calibration in grey; per non-empty decile a blue bar up to the
/// observed share centred at the mean prediction, a red line from it to the diagonal (the
/// gap the ECE weighs) and a black dot whose area grows with the decile's count.
pub fn reliability_image(bins: &[super::report::ReliabilityBin]) -> image::RgbImage {
    use image::Rgb;
    let (size, m) = (RELIABILITY_SIZE_PX, RELIABILITY_MARGIN_PX);
    let span = (size - 2 * m) as f64;
    let mut c = Canvas(image::RgbImage::from_pixel(size, size, Rgb([255, 255, 255])));
    let px = |v: f64| m as f64 + v.clamp(0.0, 1.0) * span;
    let py = |v: f64| (size - m) as f64 - v.clamp(0.0, 1.0) * span;
    for k in 0..=10 {
        let v = k as f64 / 10.0;
        let colour = if k == 0 || k == 10 {
            Rgb([0, 0, 0])
        } else {
            Rgb([225, 225, 225])
        };
        c.line((px(v), py(0.0)), (px(v), py(1.0)), colour);
        c.line((px(0.0), py(v)), (px(1.0), py(v)), colour);
    }
    c.line((px(0.0), py(0.0)), (px(1.0), py(1.0)), Rgb([150, 150, 150]));
    let total: usize = bins.iter().map(|b| b.count).sum::<usize>().max(1);
    for b in bins {
        let half = 0.04;
        let (x0, x1) = (px(b.predicted - half), px(b.predicted + half));
        let mut y = py(b.observed);
        while y <= py(0.0) {
            c.line((x0, y), (x1, y), Rgb([120, 160, 220]));
            y += 1.0;
        }
        c.line(
            (px(b.predicted), py(b.observed)),
            (px(b.predicted), py(b.predicted)),
            Rgb([210, 30, 30]),
        );
        let r = 3.0 + 12.0 * (b.count as f64 / total as f64).sqrt();
        let (cx, cy) = (px(b.predicted), py(b.observed));
        let ri = r.ceil() as i64;
        for dy in -ri..=ri {
            for dx in -ri..=ri {
                if ((dx * dx + dy * dy) as f64) <= r * r {
                    c.put(cx + dx as f64, cy + dy as f64, Rgb([0, 0, 0]));
                }
            }
        }
    }
    c.0
}

/// An image drawn on with clipped pixels and lines.
struct Canvas(image::RgbImage);

impl Canvas {
    fn put(&mut self, x: f64, y: f64, colour: image::Rgb<u8>) {
        let (x, y) = (x.round(), y.round());
        if x >= 0.0 && y >= 0.0 && (x as u32) < self.0.width() && (y as u32) < self.0.height() {
            self.0.put_pixel(x as u32, y as u32, colour);
        }
    }

    fn line(&mut self, a: (f64, f64), b: (f64, f64), colour: image::Rgb<u8>) {
        let steps = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).max(1);
        for k in 0..=steps {
            let t = k as f64 / steps as f64;
            self.put(a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t, colour);
        }
    }
}

/// Writes [`reliability_image`] as a PNG.
pub fn reliability_png(bins: &[super::report::ReliabilityBin], path: &std::path::Path) -> Result<(), super::EvalError> {
    reliability_image(bins)
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| super::EvalError::Io(format!("{}: {e}", path.display())))
}

const COLORS: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
];

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

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

/// The SVG document: four stacked panels sharing the time axis.
pub fn sequence_svg(title: &str, series: &[Series]) -> String {
    let (w, panel_h, left, right, top, gap) = (820.0, 170.0, 70.0, 180.0, 40.0, 40.0);
    let plot_w = w - left - right;
    let h = top + 4.0 * (panel_h + gap);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="11">"#
    );
    let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        s,
        r#"<text x="{left}" y="20" font-size="14" font-weight="bold">{}</text>"#,
        escape(title)
    );
    let (t_min, t_max) = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.0))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), t| (a.min(t), b.max(t)));
    let (t_min, t_max) = if t_min.is_finite() && t_max > t_min {
        (t_min, t_max)
    } else {
        (0.0, 1.0)
    };
    for (k, name) in PANELS.iter().enumerate() {
        let y0 = top + k as f64 * (panel_h + gap);
        let (lo, hi) = series
            .iter()
            .flat_map(|s| s.points.iter().filter_map(|p| p.1[k]))
            .filter(|v| v.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
        let (lo, hi) = if lo.is_finite() {
            let (l, h) = nice_range(lo.min(if k == 3 { lo } else { 0.0 }), hi);
            // Errors and deviations are never negative: start those axes at 0.
            (if k == 3 { l } else { l.max(0.0) }, h)
        } else {
            (0.0, 1.0)
        };
        let x_of = |t: f64| left + (t - t_min) / (t_max - t_min) * plot_w;
        let y_of = |v: f64| y0 + panel_h - (v - lo) / (hi - lo) * panel_h;
        let _ = writeln!(
            s,
            r##"<rect x="{left}" y="{y0}" width="{plot_w}" height="{panel_h}" fill="none" stroke="#444"/>"##
        );
        let _ = writeln!(
            s,
            r#"<text x="{left}" y="{}" font-weight="bold">{}</text>"#,
            y0 - 6.0,
            escape(name)
        );
        for i in 0..=4 {
            let v = lo + (hi - lo) * i as f64 / 4.0;
            let y = y_of(v);
            let _ = writeln!(
                s,
                r##"<line x1="{left}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#ddd"/><text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"##,
                left + plot_w,
                left - 4.0,
                y + 4.0,
                tick(v)
            );
        }
        for i in 0..=5 {
            let t = t_min + (t_max - t_min) * i as f64 / 5.0;
            let _ = writeln!(
                s,
                r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">{:.1} s</text>"#,
                x_of(t),
                y0 + panel_h + 14.0,
                t
            );
        }
        for (j, ser) in series.iter().enumerate() {
            let color = COLORS[j % COLORS.len()];
            let dash = if ser.dashed { r#" stroke-dasharray="6 3""# } else { "" };
            // Break the line where there is no estimate.
            let mut runs: Vec<Vec<(f64, f64)>> = vec![Vec::new()];
            for (t, v) in &ser.points {
                match v[k].filter(|v| v.is_finite()) {
                    Some(v) => runs.last_mut().map_or((), |r| r.push((x_of(*t), y_of(v)))),
                    None => {
                        if runs.last().is_some_and(|r| !r.is_empty()) {
                            runs.push(Vec::new());
                        }
                    }
                }
            }
            for run in runs.iter().filter(|r| !r.is_empty()) {
                let pts: Vec<String> = run.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
                let _ = writeln!(
                    s,
                    r#"<polyline fill="none" stroke="{color}" stroke-width="1.5"{dash} points="{}"/>"#,
                    pts.join(" ")
                );
            }
            if k == 0 {
                let ly = top + 10.0 + j as f64 * 16.0;
                let lx = left + plot_w + 12.0;
                let _ = writeln!(
                    s,
                    r#"<line x1="{lx}" y1="{ly}" x2="{}" y2="{ly}" stroke="{color}" stroke-width="2"{dash}/><text x="{}" y="{}">{}</text>"#,
                    lx + 20.0,
                    lx + 24.0,
                    ly + 4.0,
                    escape(&ser.label)
                );
            }
        }
    }
    s.push_str("</svg>\n");
    s
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::report::{FrameMetrics, ReliabilityBin};

    #[test]
    fn reliability_diagram_draws_bars_gaps_and_dots() {
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
        let img = reliability_image(&bins);
        let (m, span) = (
            RELIABILITY_MARGIN_PX as f64,
            (RELIABILITY_SIZE_PX - 2 * RELIABILITY_MARGIN_PX) as f64,
        );
        let at = |x: f64, y: f64| {
            *img.get_pixel(
                (m + x * span).round() as u32,
                (RELIABILITY_SIZE_PX as f64 - m - y * span).round() as u32,
            )
        };
        // The over-confident decile: a red gap between its observed 0.5 and the diagonal.
        assert_eq!(at(0.95, 0.7).0, [210, 30, 30]);
        // Its bar is blue below the dot, and the dot is black.
        assert_eq!(at(0.93, 0.2).0, [120, 160, 220]);
        assert_eq!(at(0.95, 0.5).0, [0, 0, 0]);
        // Nothing drawn above a calibrated decile's dot, up to the grid.
        assert_eq!(at(0.27, 0.65).0, [255, 255, 255]);
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("r.png");
        reliability_png(&bins, &p).expect("png");
        let back = image::open(&p).expect("read png").to_rgb8();
        assert_eq!(back.dimensions(), (RELIABILITY_SIZE_PX, RELIABILITY_SIZE_PX));
    }

    #[test]
    fn svg_has_four_panels_a_line_per_series_and_gaps() {
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
        let a = Series::from_trace(&trace, "025_mug multi", false, 0);
        let b = Series::from_trace(&trace, "025_mug <single>", true, 0);
        let svg = sequence_svg("seq & co", &[a, b]);
        assert!(svg.starts_with("<svg"));
        assert!(svg.trim_end().ends_with("</svg>"));
        for p in PANELS {
            assert!(svg.contains(&escape(p)));
        }
        // Two series x four panels x two runs (frame 4 has no estimate).
        assert_eq!(svg.matches("<polyline").count(), 16);
        assert_eq!(svg.matches("stroke-dasharray").count(), 9);
        assert!(svg.contains("&lt;single&gt;") && svg.contains("seq &amp; co"));
        assert!(!svg.contains("NaN") && !svg.contains("inf"));
    }

    #[test]
    fn empty_plot_is_still_valid() {
        let svg = sequence_svg("nothing", &[]);
        assert!(svg.contains("</svg>") && !svg.contains("NaN"));
    }
}
