//! PNG plots of trial results (plotters, bitmap backend): ||f_ext|| over time for each
//! trial, one panel per arm of the comparison (like the paper's Fig. 2), and box plots of
//! the metric M per arm. Text uses DejaVu Sans, loaded at run time from
//! [`FONT_PATH`] (Debian package `fonts-dejavu-core`).

use std::path::Path;
use std::sync::OnceLock;

use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::stats::quantile_sorted;
use crate::trials::pivot::{PivotResult, PivotSample};
use crate::trials::run::TrialResult;

/// Where the plot font is read from.
pub const FONT_PATH: &str = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";
const FAMILY: &str = "sans-serif";

/// Errors of plotting.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The font is missing or unreadable.
    #[error("plot font {FONT_PATH}: {0} (install the Debian package fonts-dejavu-core: scripts/install-deps)")]
    Font(String),
    /// Drawing or encoding failed.
    #[error("plot {path}: {why}")]
    Draw {
        /// Output file.
        path: String,
        /// Cause.
        why: String,
    },
    /// Nothing to plot.
    #[error("plot: {0}")]
    Empty(&'static str),
}

fn ensure_font() -> Result<(), PlotError> {
    static FONT: OnceLock<Result<(), String>> = OnceLock::new();
    FONT.get_or_init(|| {
        let bytes = std::fs::read(FONT_PATH).map_err(|e| e.to_string())?;
        let leaked: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font(FAMILY, FontStyle::Normal, leaked)
            .map_err(|_| "not a valid TrueType font".to_string())
    })
    .clone()
    .map_err(PlotError::Font)
}

fn draw_err(path: &Path) -> impl Fn(String) -> PlotError + '_ {
    move |why| PlotError::Draw {
        path: path.display().to_string(),
        why,
    }
}

/// The true contact force ||f|| over time (the simulator's, the headline metric's force),
/// one panel per arm (`(label, trials)`), one colour per trial.
pub fn force_over_time(path: &Path, arms: &[(&str, &[TrialResult])]) -> Result<(), PlotError> {
    if arms.is_empty() {
        return Err(PlotError::Empty("no arms to plot"));
    }
    ensure_font()?;
    let e = draw_err(path);
    let root = BitMapBackend::new(path, (1000, 420 * arms.len() as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let panels = root.split_evenly((arms.len(), 1));
    let t_max = arms
        .iter()
        .flat_map(|(_, r)| r.iter())
        .map(|r| r.time_s)
        .fold(1.0, f64::max);
    // One force scale for every panel, so the arms compare at a glance.
    let f_max = arms
        .iter()
        .flat_map(|(_, r)| r.iter())
        .flat_map(|r| r.samples.iter().map(|s| s.f_true))
        .filter(|x| x.is_finite())
        .fold(1.0, f64::max)
        * 1.05;
    for ((label, trials), area) in arms.iter().zip(panels.iter()) {
        let mut chart = ChartBuilder::on(area)
            .caption(format!("true contact force over time: {label}"), (FAMILY, 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(55)
            .build_cartesian_2d(0.0..t_max, 0.0..f_max)
            .map_err(|x| e(x.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("time [s]")
            .y_desc("||f|| [N]")
            .label_style((FAMILY, 14))
            .draw()
            .map_err(|x| e(x.to_string()))?;
        for (i, r) in trials.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(
                    r.samples.iter().map(|s| (s.t, s.f_true)),
                    colour.stroke_width(1),
                ))
                .map_err(|x| e(x.to_string()))?;
        }
    }
    root.present().map_err(|x| e(x.to_string()))
}

/// Box plots (median, quartiles, whiskers at 1.5 IQR, outliers as dots) of the values of
/// each group, e.g. M per arm.
pub fn box_plot(path: &Path, title: &str, y_desc: &str, groups: &[(String, Vec<f64>)]) -> Result<(), PlotError> {
    let groups: Vec<(&str, Vec<f64>)> = groups
        .iter()
        .map(|(l, v)| {
            let mut v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
            v.sort_by(f64::total_cmp);
            (l.as_str(), v)
        })
        .collect();
    if groups.iter().all(|(_, v)| v.is_empty()) {
        return Err(PlotError::Empty("no finite values to box-plot"));
    }
    ensure_font()?;
    let e = draw_err(path);
    let y_max = groups
        .iter()
        .flat_map(|(_, v)| v.last())
        .fold(1e-3, |a, &b| f64::max(a, b))
        * 1.1;
    let root = BitMapBackend::new(path, (300 + 200 * groups.len() as u32, 500)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let n = groups.len();
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FAMILY, 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(55)
        .build_cartesian_2d(-0.5..(n as f64 - 0.5), 0.0..y_max)
        .map_err(|x| e(x.to_string()))?;
    let labels: Vec<String> = groups.iter().map(|(l, v)| format!("{l} (n={})", v.len())).collect();
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(n)
        .x_label_formatter(&|x| {
            let i = x.round();
            if (x - i).abs() < 1e-6 && i >= 0.0 {
                labels.get(i as usize).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        })
        .y_desc(y_desc)
        .label_style((FAMILY, 14))
        .draw()
        .map_err(|x| e(x.to_string()))?;
    for (i, (_, v)) in groups.iter().enumerate() {
        if v.is_empty() {
            continue;
        }
        let x = i as f64;
        let q = |p: f64| quantile_sorted(v, p);
        let (q1, med, q3) = (q(0.25), q(0.5), q(0.75));
        let iqr = q3 - q1;
        let lo = v.iter().copied().find(|&y| y >= q1 - 1.5 * iqr).unwrap_or(q1);
        let hi = v.iter().rev().copied().find(|&y| y <= q3 + 1.5 * iqr).unwrap_or(q3);
        let colour = Palette99::pick(i).to_rgba();
        let w = 0.25;
        let lines = [
            vec![(x - w, q1), (x + w, q1), (x + w, q3), (x - w, q3), (x - w, q1)],
            vec![(x - w, med), (x + w, med)],
            vec![(x, q3), (x, hi)],
            vec![(x, q1), (x, lo)],
            vec![(x - w / 2.0, hi), (x + w / 2.0, hi)],
            vec![(x - w / 2.0, lo), (x + w / 2.0, lo)],
        ];
        for l in lines {
            chart
                .draw_series(std::iter::once(PathElement::new(l, colour.stroke_width(2))))
                .map_err(|x| e(x.to_string()))?;
        }
        chart
            .draw_series(
                v.iter()
                    .filter(|&&y| y < lo || y > hi)
                    .map(|&y| Circle::new((x, y), 3, colour.filled())),
            )
            .map_err(|x| e(x.to_string()))?;
    }
    root.present().map_err(|x| e(x.to_string()))
}

/// One panel of [`lines_over_time`]: a title, the y axis, and named lines of (t, y).
#[derive(Debug, Clone, PartialEq)]
pub struct TimePanel {
    /// The panel's caption.
    pub title: String,
    /// The y axis' description (with its unit).
    pub y_desc: &'static str,
    /// Each line's legend and points.
    pub lines: Vec<(String, Vec<(f64, f64)>)>,
    /// Spans of time to shade (e.g. while commanded), s.
    pub shaded: Vec<(f64, f64)>,
}

/// Panels stacked vertically over a common time axis, one colour per line with a legend.
pub fn lines_over_time(path: &Path, panels: &[TimePanel]) -> Result<(), PlotError> {
    let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let points = || {
        panels
            .iter()
            .flat_map(|p| p.lines.iter())
            .flat_map(|(_, v)| v.iter())
            .filter(finite)
    };
    if points().next().is_none() {
        return Err(PlotError::Empty("no finite points to plot"));
    }
    ensure_font()?;
    let e = draw_err(path);
    let (t0, t1) = points().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let root = BitMapBackend::new(path, (1100, 320 * panels.len() as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    for (panel, area) in panels.iter().zip(root.split_evenly((panels.len(), 1)).iter()) {
        let y_max = panel
            .lines
            .iter()
            .flat_map(|(_, v)| v.iter())
            .filter(finite)
            .fold(1e-3, |m, p| f64::max(m, p.1))
            * 1.1;
        let mut chart = ChartBuilder::on(area)
            .caption(&panel.title, (FAMILY, 20))
            .margin(10)
            .x_label_area_size(36)
            .y_label_area_size(55)
            .build_cartesian_2d(t0..t1.max(t0 + 1e-3), 0.0..y_max)
            .map_err(|x| e(x.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("time [s]")
            .y_desc(panel.y_desc)
            .label_style((FAMILY, 14))
            .draw()
            .map_err(|x| e(x.to_string()))?;
        chart
            .draw_series(
                panel
                    .shaded
                    .iter()
                    .map(|&(a, b)| Rectangle::new([(a, 0.0), (b, y_max)], RGBColor(235, 235, 245).filled())),
            )
            .map_err(|x| e(x.to_string()))?;
        for (i, (label, v)) in panel.lines.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(
                    v.iter().filter(finite).copied(),
                    colour.stroke_width(2),
                ))
                .map_err(|x| e(x.to_string()))?
                .label(label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font((FAMILY, 14))
            .position(SeriesLabelPosition::UpperRight)
            .draw()
            .map_err(|x| e(x.to_string()))?;
    }
    root.present().map_err(|x| e(x.to_string()))
}

/// One pivoting run per arm (`(label, run)`) over time: the shaft's distance from the true
/// port and the wall dragged (mm), then the true force across the shaft, its estimate and
/// the true force along it (N); the commanded steps shaded.
pub fn pivot_runs(path: &Path, arms: &[(&str, &PivotResult)]) -> Result<(), PlotError> {
    let mut panels = Vec::new();
    for (label, r) in arms {
        let line =
            |name: &str, f: fn(&PivotSample) -> f64| (name.to_string(), r.trace.iter().map(|s| (s.t, f(s))).collect());
        let mut shaded: Vec<(f64, f64)> = Vec::new();
        for s in r.trace.iter().filter(|s| s.commanded) {
            match shaded.last_mut() {
                Some(span) if s.t - span.1 < 0.05 => span.1 = s.t,
                _ => shaded.push((s.t, s.t)),
            }
        }
        panels.push(TimePanel {
            title: format!("{label}, seed {}: distances (shaded: commanded)", r.seed),
            y_desc: "[mm]",
            lines: vec![
                line("shaft from the true port", |s| s.distance_m * 1e3),
                line("wall dragged", |s| s.wall_m * 1e3),
            ],
            shaded: shaded.clone(),
        });
        panels.push(TimePanel {
            title: format!("{label}, seed {}: forces on the shaft", r.seed),
            y_desc: "[N]",
            lines: vec![
                line("across, true", |s| s.lateral_true_n),
                line("across, the controller's estimate", |s| s.lateral_est_n),
                line("along, true", |s| s.axial_true_n),
            ],
            shaded,
        });
    }
    lines_over_time(path, &panels)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_pngs() {
        if std::fs::metadata(FONT_PATH).is_err() {
            // Without the font the error must say so.
            let err = box_plot(Path::new("/tmp/x.png"), "t", "y", &[("a".into(), vec![1.0])]).unwrap_err();
            assert!(err.to_string().contains("fonts-dejavu-core"));
            return;
        }
        let dir = std::env::temp_dir().join(format!("plot_test_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("box.png");
        box_plot(
            &p,
            "M",
            "M [N]",
            &[("a".into(), vec![1.0, 2.0, 3.0, 10.0]), ("b".into(), vec![0.5, 0.6])],
        )
        .unwrap();
        let png = std::fs::read(&p).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        assert!(box_plot(&p, "M", "M", &[]).is_err());
        assert!(force_over_time(&dir.join("f.png"), &[]).is_err());
        let panel = TimePanel {
            title: "t".into(),
            y_desc: "y",
            lines: vec![("a".into(), vec![(0.0, 1.0), (1.0, 2.0), (2.0, f64::NAN)])],
            shaded: vec![(0.5, 1.0)],
        };
        let lines = dir.join("lines.png");
        lines_over_time(&lines, &[panel.clone(), panel.clone()]).unwrap();
        assert_eq!(&std::fs::read(&lines).unwrap()[1..4], b"PNG");
        let empty = TimePanel {
            lines: vec![("a".into(), vec![(0.0, f64::NAN)])],
            ..panel
        };
        assert!(lines_over_time(&dir.join("none.png"), &[empty]).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
