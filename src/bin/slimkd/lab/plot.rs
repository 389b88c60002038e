//! SVG charts for the report: a labelled scatter plot (Figure 5, size
//! reduction against frame-rate loss), stacked line panels (Figure 6,
//! leaf-depth histograms) and the trade-off chart of `slimkd sweep` (tree
//! bytes against trace time, one line per family of settings, the Pareto
//! front).
//!
//! Drawn with `plotters` into a `String` through its SVG backend, so no
//! font library is needed: text is written as SVG `<text>` elements and
//! laid out with plotters' estimate of the glyph widths. Non-finite values
//! are left out of every chart.

use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

/// A chart that could not be drawn: the error of its SVG drawing area.
#[derive(Debug, thiserror::Error)]
#[error("cannot draw the chart: {0}")]
pub struct PlotError(#[from] DrawingAreaErrorKind<std::io::Error>);

/// A chart of `f64` against `f64` drawn into an SVG string.
type Chart<'a, 'b> = ChartContext<'a, SVGBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Draws the axes: their descriptions, tick labels with `xd` and `yd`
/// decimals, and no light grid lines.
fn draw_mesh(
    chart: &mut Chart<'_, '_>,
    (x_desc, y_desc): (&str, &str),
    (xd, yd): (usize, usize),
) -> Result<(), PlotError> {
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(&|x| format!("{x:.xd$}"))
        .y_label_formatter(&|y| format!("{y:.yd$}"))
        .light_line_style(WHITE.mix(0.0))
        .draw()?;
    Ok(())
}

/// A whole-figure chart on `root` (filled white): the caption, the plot
/// over `xs` × `ys` with a `y_label`-pixel label area, and its axes
/// ([`draw_mesh`], tick decimals from the ranges).
fn figure_chart<'a, 'b>(
    root: &'a DrawingArea<SVGBackend<'b>, Shift>,
    title: &str,
    y_label: u32,
    (xs, ys): (std::ops::Range<f64>, std::ops::Range<f64>),
    axes: (&str, &str),
) -> Result<Chart<'a, 'b>, PlotError> {
    root.fill(&WHITE)?;
    let decimals = (tick_decimals(&xs), tick_decimals(&ys));
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 18))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(y_label)
        .build_cartesian_2d(xs, ys)?;
    draw_mesh(&mut chart, axes, decimals)?;
    Ok(chart)
}

/// Draws the legend of the chart's series at `position`.
fn draw_legend<'a, 'b: 'a>(
    chart: &mut Chart<'a, 'b>,
    position: SeriesLabelPosition,
) -> Result<(), PlotError> {
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(position)
        .draw()?;
    Ok(())
}

/// One point of a scatter plot with the text written next to it.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelledPoint {
    pub x: f64,
    pub y: f64,
    pub label: String,
    /// A vertical error bar from the first to the second `y`, if any.
    pub y_range: Option<(f64, f64)>,
}

/// A named set of points drawn in one colour.
#[derive(Clone, Debug, PartialEq)]
pub struct ScatterSeries {
    pub name: String,
    pub points: Vec<LabelledPoint>,
}

/// A named polyline.
#[derive(Clone, Debug, PartialEq)]
pub struct LineSeries {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// One chart of a stack of line charts.
#[derive(Clone, Debug, PartialEq)]
pub struct LinePanel {
    pub title: String,
    pub series: Vec<LineSeries>,
}

/// Series colours, distinguishable in print and for colour-blind readers
/// (the Okabe–Ito palette).
const COLOURS: [RGBColor; 7] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(0, 0, 0),
];

fn colour(i: usize) -> RGBColor {
    COLOURS[i % COLOURS.len()]
}

/// The range covering `values` with a margin of `pad` of its width on each
/// side; a degenerate or empty range is widened to a unit interval.
fn padded_range(values: impl Iterator<Item = f64>, pad: f64) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    if hi - lo <= f64::EPSILON * lo.abs().max(1.0) {
        return lo - 0.5..hi + 0.5;
    }
    let m = (hi - lo) * pad;
    lo - m..hi + m
}

/// Decimals for tick labels over a range of this width.
fn tick_decimals(r: &std::ops::Range<f64>) -> usize {
    match r.end - r.start {
        w if w >= 10.0 => 0,
        w if w >= 1.0 => 1,
        _ => 2,
    }
}

/// A scatter plot: each series in its own colour with a legend, each point
/// with its label. Both ranges include zero, and the zero lines are drawn
/// (in Figure 5 the std tree sits at the origin).
pub fn scatter_svg(
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[ScatterSeries],
    size: (u32, u32),
) -> Result<String, PlotError> {
    let finite = |p: &&LabelledPoint| p.x.is_finite() && p.y.is_finite();
    // The range of one coordinate over every series, zero included.
    let range = |coord: fn(&LabelledPoint) -> [f64; 3]| {
        let values = series.iter().flat_map(|s| s.points.iter().filter(finite));
        padded_range(values.flat_map(coord).chain([0.0]), 0.12)
    };
    let (xs, ys) = (
        range(|p| [p.x; 3]),
        range(|p| {
            let (lo, hi) = p.y_range.unwrap_or((p.y, p.y));
            [p.y, lo, hi]
        }),
    );
    let (x0, x1, y0, y1) = (xs.start, xs.end, ys.start, ys.end);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        let mut chart = figure_chart(&root, title, 56, (xs, ys), (x_desc, y_desc))?;
        let zero = BLACK.mix(0.5).stroke_width(1);
        chart.draw_series([
            PathElement::new(vec![(0.0, y0), (0.0, y1)], zero),
            PathElement::new(vec![(x0, 0.0), (x1, 0.0)], zero),
        ])?;
        for (i, s) in series.iter().enumerate() {
            let c = colour(i);
            let bars = s.points.iter().filter(finite).filter_map(|p| {
                let (lo, hi) = p.y_range?;
                (lo.is_finite() && hi.is_finite())
                    .then(|| PathElement::new(vec![(p.x, lo), (p.x, hi)], c.stroke_width(1)))
            });
            chart.draw_series(bars)?;
            chart
                .draw_series(s.points.iter().filter(finite).map(|p| {
                    EmptyElement::at((p.x, p.y))
                        + Circle::new((0, 0), 4, c.filled())
                        + Text::new(p.label.clone(), (6, -12), ("sans-serif", 11).into_font())
                }))?
                .label(s.name.as_str())
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, c.filled()));
        }
        if !series.is_empty() {
            draw_legend(&mut chart, SeriesLabelPosition::UpperLeft)?;
        }
        root.present()?;
    }
    Ok(svg)
}

/// One point of a trade-off chart ([`front_svg`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TradeOffPoint {
    pub x: f64,
    /// A horizontal whisker from the first to the second `x` (the spread
    /// of the repetitions).
    pub x_range: (f64, f64),
    pub y: f64,
    /// Written next to the point.
    pub label: String,
    /// Drawn larger, ringed and with its label in bold (the presets).
    pub highlight: bool,
    /// On the Pareto front: joined by the front's dashed staircase.
    pub on_front: bool,
}

/// A polyline through some of a trade-off chart's points, by index.
#[derive(Clone, Debug, PartialEq)]
pub struct TradeOffLine {
    pub name: String,
    pub points: Vec<usize>,
}

/// A trade-off chart: every point with its whisker and label, one
/// polyline per family in its own colour (with a legend), the highlighted
/// points ringed, and the Pareto front (lower left: smaller and faster) as
/// a dashed grey staircase through the points on it. Neither range is
/// forced to include zero.
pub fn front_svg(
    title: &str,
    x_desc: &str,
    y_desc: &str,
    points: &[TradeOffPoint],
    lines: &[TradeOffLine],
    size: (u32, u32),
) -> Result<String, PlotError> {
    let finite = |p: &&TradeOffPoint| p.x.is_finite() && p.y.is_finite();
    let xs = padded_range(
        points
            .iter()
            .filter(finite)
            .flat_map(|p| [p.x, p.x_range.0, p.x_range.1]),
        0.08,
    );
    let ys = padded_range(points.iter().filter(finite).map(|p| p.y), 0.08);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        let mut chart = figure_chart(&root, title, 64, (xs, ys), (x_desc, y_desc))?;
        // The front: sorted by x, each step across then down.
        let mut front: Vec<&TradeOffPoint> = points
            .iter()
            .filter(finite)
            .filter(|p| p.on_front)
            .collect();
        front.sort_by(|a, b| a.x.total_cmp(&b.x).then(b.y.total_cmp(&a.y)));
        let mut stairs = Vec::new();
        for (i, p) in front.iter().enumerate() {
            if i > 0 {
                stairs.push((p.x, front[i - 1].y));
            }
            stairs.push((p.x, p.y));
        }
        let grey = RGBColor(110, 110, 110);
        chart
            .draw_series([DashedPathElement::new(stairs, 6, 4, grey.stroke_width(2))])?
            .label("Pareto front")
            .legend(move |(x, y)| {
                DashedPathElement::new(vec![(x, y), (x + 20, y)], 6, 4, grey.stroke_width(2))
            });
        for (i, line) in lines.iter().enumerate() {
            let c = colour(i);
            let pts: Vec<(f64, f64)> = line
                .points
                .iter()
                .filter_map(|&k| points.get(k))
                .filter(finite)
                .map(|p| (p.x, p.y))
                .collect();
            chart
                .draw_series(plotters::series::LineSeries::new(pts, c.stroke_width(2)))?
                .label(line.name.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                });
        }
        // Whiskers and points in the colour of the first line through them.
        let colour_of = |k: usize| {
            lines
                .iter()
                .position(|l| l.points.contains(&k))
                .map_or(BLACK, colour)
        };
        for (k, p) in points.iter().enumerate().filter(|(_, p)| finite(p)) {
            let c = colour_of(k);
            let (lo, hi) = p.x_range;
            if lo.is_finite() && hi.is_finite() {
                chart.draw_series([PathElement::new(
                    vec![(lo, p.y), (hi, p.y)],
                    c.stroke_width(1),
                )])?;
            }
            let (radius, font) = if p.highlight {
                (6, ("sans-serif", 14).into_font().style(FontStyle::Bold))
            } else {
                (4, ("sans-serif", 11).into_font())
            };
            chart.draw_series([EmptyElement::at((p.x, p.y))
                + Circle::new((0, 0), radius, c.filled())
                + Text::new(p.label.clone(), (7, -14), font)])?;
            if p.highlight {
                chart.draw_series([Circle::new((p.x, p.y), radius + 3, BLACK.stroke_width(2))])?;
            }
        }
        draw_legend(&mut chart, SeriesLabelPosition::UpperRight)?;
        root.present()?;
    }
    Ok(svg)
}

/// The width of the legend strip right of a line panel.
const LEGEND_WIDTH: u32 = 120;

/// The stroke width and marker radius of line series `i`: the first series
/// widest and drawn first, so that where later ones lie on it, it still
/// shows around them.
fn line_style(i: usize) -> (u32, u32) {
    match i {
        0 => (7, 5),
        1 => (4, 3),
        _ => (1, 2),
    }
}

/// Draws one line panel into `area`: the chart, and its legend in a strip
/// to the right of it (outside the curves).
fn line_panel(
    area: &DrawingArea<SVGBackend<'_>, Shift>,
    panel: &LinePanel,
    x_desc: &str,
    y_desc: &str,
) -> Result<(), PlotError> {
    let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
    // The range of one coordinate over every series.
    let range = |coord: fn(&(f64, f64)) -> f64, pad: f64| {
        let values = panel
            .series
            .iter()
            .flat_map(|s| s.points.iter().filter(finite));
        padded_range(values.map(coord), pad)
    };
    let xs = range(|p| p.0, 0.02);
    // Counts start at zero.
    let y_hi = range(|p| p.1, 0.05).end.max(1.0);
    let xd = tick_decimals(&xs);
    let yd = tick_decimals(&(0.0..y_hi));
    let (plot_area, legend_area) = area.split_horizontally(
        i32::try_from(area.dim_in_pixel().0.saturating_sub(LEGEND_WIDTH)).unwrap_or(0),
    );
    let mut chart = ChartBuilder::on(&plot_area)
        .caption(panel.title.as_str(), ("sans-serif", 16))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(64)
        .build_cartesian_2d(xs, 0.0..y_hi)?;
    draw_mesh(&mut chart, (x_desc, y_desc), (xd, yd))?;
    for (i, s) in panel.series.iter().enumerate() {
        let c = colour(i);
        let (width, radius) = line_style(i);
        let pts: Vec<(f64, f64)> = s.points.iter().filter(finite).copied().collect();
        chart.draw_series(plotters::series::LineSeries::new(
            pts.iter().copied(),
            c.stroke_width(width),
        ))?;
        chart.draw_series(pts.iter().map(|&p| Circle::new(p, radius, c.filled())))?;
    }
    for (i, s) in panel.series.iter().enumerate() {
        let c = colour(i);
        let (width, _) = line_style(i);
        let y = 48 + 22 * i as i32;
        legend_area.draw(&PathElement::new(
            vec![(8, y), (36, y)],
            c.stroke_width(width),
        ))?;
        legend_area.draw(&Text::new(
            s.name.clone(),
            (42, y - 7),
            ("sans-serif", 13).into_font(),
        ))?;
    }
    Ok(())
}

/// Line charts stacked vertically, one per panel, `panel_size` each.
pub fn line_panels_svg(
    panels: &[LinePanel],
    x_desc: &str,
    y_desc: &str,
    panel_size: (u32, u32),
) -> Result<String, PlotError> {
    let n = panels.len().max(1);
    let size = (panel_size.0, panel_size.1.saturating_mul(n as u32));
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE)?;
        let areas = root.split_evenly((n, 1));
        for (panel, area) in panels.iter().zip(&areas) {
            line_panel(area, panel, x_desc, y_desc)?;
        }
        root.present()?;
    }
    Ok(svg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scatter_draws_points_labels_and_legend() {
        let s = ScatterSeries {
            name: "scene a".into(),
            points: vec![
                LabelledPoint {
                    x: 10.0,
                    y: 1.0,
                    label: "0.5/0.4".into(),
                    y_range: Some((-1.0, 3.0)),
                },
                LabelledPoint {
                    x: f64::NAN,
                    y: 1.0,
                    label: "left out".into(),
                    y_range: None,
                },
            ],
        };
        let svg = scatter_svg("t", "x", "y", &[s], (400, 300)).unwrap();
        assert!(svg.starts_with("<svg"));
        assert!(svg.contains("0.5/0.4") && svg.contains("scene a"));
        assert!(!svg.contains("left out"));
    }

    /// Figure 6's legend lies in a strip right of the chart, outside the
    /// curves, and the first series is drawn widest, so that it shows where
    /// a later series lies on it.
    #[test]
    fn line_legend_is_outside_and_equal_series_stay_visible() {
        let same: Vec<(f64, f64)> = (0..10).map(|d| (d as f64, (d * d) as f64)).collect();
        let panel = LinePanel {
            title: "t".into(),
            series: ["std", "fast", "small"]
                .iter()
                .map(|n| LineSeries {
                    name: n.to_string(),
                    points: same.clone(),
                })
                .collect(),
        };
        let svg = line_panels_svg(&[panel], "depth", "leaves", (600, 300)).unwrap();
        // Each text element: its x attribute and its text.
        let texts: Vec<(f64, &str)> = svg
            .split("<text")
            .skip(1)
            .filter_map(|t| {
                let x = t.split("x=\"").nth(1)?.split('"').next()?.parse().ok()?;
                let body = t.split_once('>')?.1.split("</text>").next()?.trim();
                Some((x, body))
            })
            .collect();
        // The rightmost point of any curve (the series' coloured
        // polylines, not the black axes).
        let curves_end = svg
            .split("<polyline")
            .skip(1)
            .filter(|p| !p.contains("stroke=\"#000000\""))
            .flat_map(|p| {
                let points = p.split("points=\"").nth(1).unwrap_or("").split('"').next();
                points
                    .unwrap_or("")
                    .split_whitespace()
                    .filter_map(|xy| xy.split(',').next()?.parse::<f64>().ok())
                    .collect::<Vec<_>>()
            })
            .fold(f64::NEG_INFINITY, f64::max);
        assert!(curves_end.is_finite(), "no curve drawn");
        for name in ["std", "fast", "small"] {
            let (x, _) = texts
                .iter()
                .find(|(_, t)| *t == name)
                .expect("a legend entry");
            assert!(
                *x > curves_end,
                "{name} at x {x}, left of the curves' end at {curves_end}"
            );
        }
        let (std_width, _) = line_style(0);
        let (fast_width, _) = line_style(1);
        assert!(std_width > fast_width);
        assert!(svg.contains(&format!("stroke-width=\"{std_width}\"")));
    }

    /// The trade-off chart draws every finite point's label (the
    /// highlighted ones in bold, ringed), a legend entry per line and the
    /// front's dashed staircase, which steps through the front's points
    /// only.
    #[test]
    fn front_chart_highlights_presets_and_draws_the_front() {
        let pt = |x: f64, y: f64, label: &str, highlight, on_front| TradeOffPoint {
            x,
            x_range: (x - 0.5, x + 0.5),
            y,
            label: label.into(),
            highlight,
            on_front,
        };
        let points = [
            pt(1.0, 9.0, "fastest", false, true),
            pt(2.0, 5.0, "std", true, true),
            pt(3.0, 6.0, "behind", false, false),
            pt(4.0, 2.0, "smallest", false, true),
            pt(f64::NAN, 1.0, "left out", true, false),
        ];
        let lines = [TradeOffLine {
            name: "family a".into(),
            points: vec![0, 1, 2, 9],
        }];
        let svg = front_svg("t", "x", "y", &points, &lines, (600, 400)).unwrap();
        for label in [
            "fastest",
            "std",
            "behind",
            "smallest",
            "family a",
            "Pareto front",
        ] {
            assert!(svg.contains(label), "{label}");
        }
        assert!(!svg.contains("left out"));
        // Only the one finite highlighted point has a bold label.
        assert_eq!(svg.matches("font-weight=\"bold\"").count(), 1);
        // The staircase: three front points, two steps of two segments,
        // drawn as dashes of one grey.
        assert!(svg.matches("#6E6E6E").count() >= 4);
    }

    #[test]
    fn empty_charts_still_draw() {
        assert!(
            scatter_svg("t", "x", "y", &[], (200, 200))
                .unwrap()
                .starts_with("<svg")
        );
        let svg = line_panels_svg(&[], "x", "y", (200, 100)).unwrap();
        assert!(svg.starts_with("<svg"));
    }

    #[test]
    fn padded_range_handles_degenerate_input() {
        assert_eq!(padded_range([3.0, 3.0].into_iter(), 0.1), 2.5..3.5);
        assert_eq!(padded_range(std::iter::empty(), 0.1), 0.0..1.0);
        let r = padded_range([0.0, 10.0, f64::INFINITY].into_iter(), 0.1);
        assert_eq!(r, -1.0..11.0);
    }
}
