//! SVG pictures of latency: a histogram with a logarithmic count axis and
//! marks at chosen percentiles (as the OSADL cyclictest plots), and
//! percentile curves of several distributions on one "1 - p" axis (as
//! HdrHistogram's percentile plots).
//!
//! The files are plain SVG, written with plotters' SVG backend alone: text
//! is SVG `<text>`, so no font files, browser or gnuplot are needed to make
//! them, and any browser or image viewer shows them.

use anyhow::{bail, ensure, Context, Result};
use hdrhistogram::Histogram;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::Path;

/// Size of every picture, pixels.
const SIZE: (u32, u32) = (900, 560);
/// Font family of every text (the viewer's sans-serif).
const FONT: &str = "sans-serif";
/// Fill of the histogram bars.
const BAR: RGBColor = RGBColor(70, 110, 180);
/// Colours of marks and curves, in order (each one different).
const PALETTE: [RGBColor; 8] = [
    RGBColor(0, 140, 70),
    RGBColor(230, 120, 0),
    RGBColor(200, 0, 0),
    RGBColor(40, 40, 40),
    RGBColor(130, 50, 170),
    RGBColor(0, 130, 180),
    RGBColor(150, 100, 40),
    RGBColor(220, 60, 150),
];
/// Bars in a histogram at most (then the bar width is rounded up to 1, 2
/// or 5 times a power of ten).
const MAX_BARS: f64 = 120.0;

/// Writes a histogram of `hist` to `path` as SVG: x the latency in displayed
/// units (`unit`, values of `hist` divided by `scale`, e.g. 1000.0 for ns
/// shown in us), y the samples per bar on a log scale, and for each of
/// `marks` (label, displayed value, e.g. `("p99", 12.5)`) a vertical line
/// labelled `p99 = 12.5 us`. Fails, writing nothing, when `hist` is empty.
pub fn histogram_svg(
    path: &Path,
    title: &str,
    unit: &str,
    hist: &Histogram<u64>,
    scale: f64,
    marks: &[(&str, f64)],
) -> Result<()> {
    ensure!(
        scale.is_finite() && scale > 0.0,
        "{title}: the scale must be a positive number, not {scale}"
    );
    if hist.is_empty() {
        bail!(
            "{title}: the histogram has no samples, nothing to plot (not writing {})",
            path.display()
        );
    }
    if let Some((label, v)) = marks.iter().find(|(_, v)| !v.is_finite()) {
        bail!("{title}: mark {label} is {v}, not a number");
    }
    // Bars of a round width over [lo, hi], counts from the recorded values
    // (each at its bucket's highest equivalent value, where the histogram's
    // quantiles and max put it too).
    let (min, max) = (hist.min() as f64 / scale, hist.max() as f64 / scale);
    let mark_min = marks.iter().map(|m| m.1).fold(min, f64::min);
    let mark_max = marks.iter().map(|m| m.1).fold(max, f64::max);
    // No bar narrower than the histogram's widest bucket (that of the max):
    // narrower ones would leave gaps between the buckets.
    let resolution = hist.equivalent_range(hist.max()) as f64 / scale;
    let spread = (mark_max - mark_min).max(resolution * 10.0);
    let width = nice_step(spread / MAX_BARS).max(nice_step(resolution));
    // From zero, as cyclictest's, unless that leaves most of the plot empty.
    let lo = if mark_min <= spread {
        0.0f64.min(mark_min)
    } else {
        ((mark_min - spread * 0.05) / width).floor() * width
    };
    let n_bars = ((mark_max - lo) / width).floor() as usize + 1;
    let mut bars = vec![0u64; n_bars];
    for v in hist.iter_recorded() {
        let x = v.value_iterated_to() as f64 / scale;
        let i = (((x - lo) / width).floor().max(0.0) as usize).min(n_bars - 1);
        bars[i] += v.count_at_value();
    }
    let hi = lo + (n_bars as f64 + 1.0) * width;
    let top = bars.iter().copied().max().unwrap_or(1).max(1) as f64 * 3.0;
    let bottom = 0.5;

    render(path, |root| {
        let mut chart =
            chart_on(root, title).build_cartesian_2d(lo..hi, (bottom..top).log_scale())?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .y_max_light_lines(0)
            .x_desc(format!("latency ({unit})"))
            .y_desc(format!(
                "samples per {} {unit} (log scale)",
                axis_text(width)
            ))
            .y_label_formatter(&|v| count_text(*v))
            .x_label_formatter(&|v| axis_text(*v))
            .axis_desc_style((FONT, 16))
            .draw()?;
        chart.draw_series(
            bars.iter()
                .enumerate()
                .filter(|(_, &n)| n > 0)
                .map(|(i, &n)| {
                    let x0 = lo + i as f64 * width;
                    Rectangle::new([(x0, bottom), (x0 + width, n as f64)], BAR.filled())
                }),
        )?;
        let (plot_x, _) = chart.plotting_area().get_pixel_range();
        for (i, (label, v)) in marks.iter().enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            chart.draw_series(std::iter::once(PathElement::new(
                vec![(*v, bottom), (*v, top)],
                colour.stroke_width(2),
            )))?;
            // Labels one below the other, right of the line, or left of it
            // near the right edge.
            let (px, py) = chart.backend_coord(&(*v, top));
            let right = px > plot_x.start + (plot_x.end - plot_x.start) * 3 / 4;
            let style = TextStyle::from((FONT, 14).into_font())
                .color(&colour)
                .pos(Pos::new(
                    if right { HPos::Right } else { HPos::Left },
                    VPos::Top,
                ));
            let at = (if right { px - 4 } else { px + 4 }, py + 4 + 17 * i as i32);
            root.draw(&Text::new(
                format!("{label} = {} {unit}", value_text(*v)),
                at,
                style,
            ))?;
        }
        Ok(())
    })
}

/// Writes the percentile curves of several latency distributions to `path`
/// as SVG, each `series` entry (label, histogram, scale: values divided by
/// it are in `unit`) one curve: x the percentile on a "1 - p" log axis (0%,
/// 90%, 99%, 99.9%, ... up to one sample), y the latency. Fails, writing
/// nothing, when there is no series or one is empty.
pub fn distributions_svg(
    path: &Path,
    title: &str,
    unit: &str,
    series: &[(&str, &Histogram<u64>, f64)],
) -> Result<()> {
    let mut curves = Vec::new();
    for (label, hist, scale) in series {
        ensure!(
            scale.is_finite() && *scale > 0.0,
            "{title}: {label}: the scale must be a positive number, not {scale}"
        );
        if hist.is_empty() {
            bail!(
                "{title}: {label} has no samples, nothing to plot (not writing {})",
                path.display()
            );
        }
        let points = hist
            .iter_quantiles(5)
            .map(|v| {
                (
                    v.quantile_iterated_to(),
                    v.value_iterated_to() as f64 / scale,
                )
            })
            .collect();
        curves.push(Curve {
            label: label.to_string(),
            samples: hist.len(),
            points,
        });
    }
    percentile_chart(path, title, unit, &curves, false)
}

/// A distribution known by a few percentiles: label, number of samples and
/// (quantile, value) points, quantiles rising.
pub type Summary<'a> = (&'a str, u64, &'a [(f64, f64)]);

/// As [`distributions_svg`], for distributions known only by a few
/// percentiles: each `series` entry is a label, the number of samples and
/// (quantile, value in `unit`) points, such as `(0.5, p50)`, `(0.99, p99)`,
/// `(1.0, max)`; the points are drawn as dots joined by lines.
pub fn summaries_svg(path: &Path, title: &str, unit: &str, series: &[Summary]) -> Result<()> {
    let mut curves = Vec::new();
    for (label, samples, points) in series {
        if *samples == 0 || points.is_empty() {
            bail!(
                "{title}: {label} has no samples, nothing to plot (not writing {})",
                path.display()
            );
        }
        if let Some((q, v)) = points
            .iter()
            .find(|(q, v)| !(0.0..=1.0).contains(q) || !v.is_finite())
        {
            bail!("{title}: {label}: ({q}, {v}) is not a quantile and a value");
        }
        curves.push(Curve {
            label: label.to_string(),
            samples: *samples,
            points: points.to_vec(),
        });
    }
    percentile_chart(path, title, unit, &curves, true)
}

/// One distribution on a percentile plot.
struct Curve {
    label: String,
    samples: u64,
    /// (quantile, displayed value), quantiles rising.
    points: Vec<(f64, f64)>,
}

/// Position of quantile `q` on the "1 - p" axis: its number of nines
/// (0 at 0%, 1 at 90%, 2 at 99%), 1.0 drawn at one sample in `samples`.
fn nines(q: f64, samples: u64) -> f64 {
    let rest = (1.0 - q).max(1.0 / samples.max(1) as f64);
    -rest.log10()
}

/// The percentile of `n` nines, as an axis label: 0%, 90%, 99%, 99.9%.
fn nines_text(n: f64) -> String {
    let pct = 100.0 * (1.0 - 10f64.powf(-n));
    let decimals = (n.ceil() as i64 - 2).max(0) as usize;
    format!("{pct:.decimals$}%")
}

fn percentile_chart(
    path: &Path,
    title: &str,
    unit: &str,
    curves: &[Curve],
    dots: bool,
) -> Result<()> {
    if curves.is_empty() {
        bail!(
            "{title}: no distribution to plot (not writing {})",
            path.display()
        );
    }
    let lines: Vec<Vec<(f64, f64)>> = curves
        .iter()
        .map(|c| {
            c.points
                .iter()
                .map(|&(q, v)| (nines(q, c.samples), v))
                .collect()
        })
        .collect();
    let all = || lines.iter().flatten();
    // Up to the last point (a little past it), whole nines labelled.
    let x_hi = all().map(|p| p.0).fold(1.0, f64::max) + 0.05;
    let y_hi = all().map(|p| p.1).fold(f64::MIN, f64::max);
    let y_lo = all().map(|p| p.1).fold(f64::MAX, f64::min);
    let y_hi = if y_hi > 0.0 { y_hi * 1.1 } else { 1.0 };
    let y_lo = y_lo.min(0.0);

    render(path, |root| {
        let mut chart = chart_on(root, title).build_cartesian_2d(0.0..x_hi, y_lo..y_hi)?;
        chart
            .configure_mesh()
            .x_labels(x_hi.floor() as usize + 1)
            .x_max_light_lines(0)
            .y_max_light_lines(1)
            .x_label_formatter(&|n| nines_text(*n))
            .y_label_formatter(&|v| axis_text(*v))
            .x_desc("percentile (log scale of 1 - p)")
            .y_desc(format!("latency ({unit})"))
            .axis_desc_style((FONT, 16))
            .draw()?;
        for (i, (curve, line)) in curves.iter().zip(&lines).enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            chart
                .draw_series(std::iter::once(PathElement::new(
                    line.clone(),
                    colour.stroke_width(2),
                )))?
                .label(format!("{} ({} samples)", curve.label, curve.samples))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            if dots {
                chart.draw_series(line.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
            }
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .label_font((FONT, 14))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()?;
        Ok(())
    })
}

/// A chart on `root` laid out as every picture is: `title` on top, the
/// margin, and room left and below for the axis labels.
fn chart_on<'a, 'b, 'c>(
    root: &'a DrawingArea<SVGBackend<'c>, Shift>,
    title: &str,
) -> ChartBuilder<'a, 'b, SVGBackend<'c>> {
    let mut builder = ChartBuilder::on(root);
    builder
        .caption(title, (FONT, 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(70);
    builder
}

/// Draws with `draw` on a white SVG page, then writes it to `path`.
fn render(
    path: &Path,
    draw: impl FnOnce(
        &DrawingArea<SVGBackend, Shift>,
    ) -> std::result::Result<(), Box<dyn std::error::Error>>,
) -> Result<()> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        let drawn = root
            .fill(&WHITE)
            .map_err(|e| e.into())
            .and_then(|()| draw(&root))
            .and_then(|()| root.present().map_err(|e| e.into()));
        if let Err(e) = drawn {
            bail!("drawing {}: {e}", path.display());
        }
    }
    std::fs::write(path, svg).with_context(|| format!("writing {}", path.display()))
}

/// 1, 2 or 5 times a power of ten, at least `raw`.
fn nice_step(raw: f64) -> f64 {
    if !(raw.is_finite() && raw > 0.0) {
        return 1.0;
    }
    let e = 10f64.powf(raw.log10().floor());
    let f = raw / e;
    let m = if f <= 1.0 {
        1.0
    } else if f <= 2.0 {
        2.0
    } else if f <= 5.0 {
        5.0
    } else {
        10.0
    };
    m * e
}

/// A latency with the decimals its size needs.
fn value_text(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 || a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 10.0 {
        format!("{v:.1}")
    } else if a >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

/// An axis label: [`value_text`] without trailing zeros.
fn axis_text(v: f64) -> String {
    let s = value_text(v);
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// A count axis label: powers of ten only (1, 10, 100, 1000, 1e4).
fn count_text(v: f64) -> String {
    let e = v.log10();
    if v < 1.0 || (e - e.round()).abs() > 1e-6 {
        String::new()
    } else if v < 1e4 {
        format!("{v:.0}")
    } else {
        format!("1e{}", e.round())
    }
}

/// A histogram of `values` (negative and non-finite ones left out, the rest
/// rounded to whole units), 3 significant digits, for values kept in a list.
pub fn histogram_of(values: &[f64]) -> Histogram<u64> {
    let mut h = Histogram::new(3).expect("3 significant digits are valid");
    for v in values.iter().filter(|v| v.is_finite() && **v >= 0.0) {
        let _ = h.record(v.round() as u64);
    }
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A peaked latency distribution in ns: most samples 10..30 us, a tail
    /// to 80 us and one outlier at 150 us.
    fn latencies() -> Histogram<u64> {
        let mut h = Histogram::<u64>::new(3).unwrap();
        for i in 0..10_000u64 {
            // Triangular peak at 20 us.
            let v = 10_000 + (i % 100) * 100 + (i / 100 % 100) * 100;
            h.record(v).unwrap();
        }
        for i in 0..50u64 {
            h.record(30_000 + i * 1_000).unwrap();
        }
        h.record(150_000).unwrap();
        h
    }

    /// A file `name` in a directory of its own, removed when dropped.
    struct Temp(std::path::PathBuf);

    impl Temp {
        fn new(name: &str) -> Temp {
            let dir =
                std::env::temp_dir().join(format!("ppm-plot-test-{}-{name}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            Temp(dir.join(name))
        }
    }

    impl Drop for Temp {
        fn drop(&mut self) {
            if let Some(dir) = self.0.parent() {
                let _ = std::fs::remove_dir_all(dir);
            }
        }
    }

    /// The value of attribute `name` in the tag `tag`.
    fn attr<'a>(tag: &'a str, name: &str) -> Option<&'a str> {
        let at = tag.find(&format!(" {name}=\""))? + name.len() + 3;
        Some(&tag[at..at + tag[at..].find('"')?])
    }

    /// Every `<kind ...>` tag, with the text after it up to the next `<`.
    fn tags<'a>(svg: &'a str, kind: &str) -> Vec<(&'a str, &'a str)> {
        svg.match_indices(&format!("<{kind} "))
            .map(|(i, _)| {
                let end = i + svg[i..].find('>').unwrap();
                let text = &svg[end + 1..];
                (&svg[i..end], text[..text.find('<').unwrap_or(0)].trim())
            })
            .collect()
    }

    /// The SVG written to `path`, checked to be whole.
    fn read_svg(path: &Path) -> String {
        let svg = std::fs::read_to_string(path).unwrap();
        assert!(svg.starts_with("<svg "), "{}", &svg[..80.min(svg.len())]);
        assert!(svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<text").count(), svg.matches("</text>").count());
        svg
    }

    /// Asserts that each of `want` is the text of one of the SVG's `<text>`s.
    fn assert_texts(svg: &str, want: &[&str]) {
        let texts: Vec<&str> = tags(svg, "text").iter().map(|t| t.1).collect();
        for w in want {
            assert!(texts.contains(w), "{w} not in {texts:?}");
        }
    }

    /// The points of a `<polyline>` tag, in pixels.
    fn points(polyline: &str) -> Vec<(f64, f64)> {
        attr(polyline, "points")
            .unwrap()
            .split_whitespace()
            .map(|p| {
                let (x, y) = p.split_once(',').unwrap();
                (x.parse().unwrap(), y.parse().unwrap())
            })
            .collect()
    }

    /// x of the vertical line in the mark whose label starts with `label`:
    /// the polyline of the label's colour.
    fn mark_x(svg: &str, label: &str) -> f64 {
        let texts = tags(svg, "text");
        let (tag, _) = texts
            .iter()
            .find(|(_, t)| t.starts_with(&format!("{label} = ")))
            .unwrap_or_else(|| panic!("no label {label}"));
        let colour = attr(tag, "fill").unwrap();
        let lines: Vec<_> = tags(svg, "polyline")
            .into_iter()
            .filter(|(t, _)| attr(t, "stroke") == Some(colour))
            .collect();
        assert_eq!(lines.len(), 1, "one line of {colour}");
        let points = points(lines[0].0);
        assert_eq!(points.len(), 2);
        assert_eq!(points[0].0, points[1].0, "a vertical line");
        points[0].0
    }

    #[test]
    fn histogram_has_title_axes_marks_and_bars_in_place() {
        let h = latencies();
        let p = crate::analysis::Percentiles::of_histogram(&h);
        let tmp = Temp::new("hist.svg");
        let path = &tmp.0;
        let marks = [
            ("p50", p.p50 / 1e3),
            ("p99", p.p99 / 1e3),
            ("p99.9", p.p999 / 1e3),
            ("max", p.max / 1e3),
        ];
        histogram_svg(path, "jitter on test-host", "us", &h, 1000.0, &marks).unwrap();
        let svg = read_svg(path);
        assert_texts(
            &svg,
            &[
                "jitter on test-host",
                "latency (us)",
                "samples per 2 us (log scale)",
                "p50 = 19.9 us",
                "max = 150 us",
            ],
        );
        let texts: Vec<&str> = tags(&svg, "text").iter().map(|t| t.1).collect();
        assert!(texts.iter().any(|t| t.starts_with("p99 = ")));
        assert!(texts.iter().any(|t| t.starts_with("p99.9 = ")));
        // Marks left to right in the order of their values.
        let xs: Vec<f64> = ["p50", "p99", "p99.9", "max"]
            .iter()
            .map(|l| mark_x(&svg, l))
            .collect();
        assert!(xs.windows(2).all(|w| w[0] < w[1]), "{xs:?}");
        // The tallest bar is at the median, the last one at the max.
        let bars: Vec<(f64, f64, f64)> = tags(&svg, "rect")
            .iter()
            .filter(|(t, _)| attr(t, "fill") == Some("#466EB4"))
            .map(|(t, _)| {
                let f = |n| attr(t, n).unwrap().parse::<f64>().unwrap();
                (f("x"), f("width"), f("y"))
            })
            .collect();
        assert!(bars.len() > 20, "{} bars", bars.len());
        let tallest = bars.iter().min_by(|a, b| a.2.total_cmp(&b.2)).unwrap();
        assert!(
            (tallest.0 - xs[0]).abs() <= 2.0 * tallest.1 + 1.0,
            "tallest bar at {tallest:?}, p50 at {}",
            xs[0]
        );
        let last = bars.iter().max_by(|a, b| a.0.total_cmp(&b.0)).unwrap();
        assert!(last.0 <= xs[3] && xs[3] <= last.0 + last.1 + 1.0);
        assert!(bars.iter().all(|b| b.0 < xs[3] + 1.0));
    }

    #[test]
    fn empty_histogram_is_an_error_and_writes_nothing() {
        let tmp = Temp::new("empty.svg");
        let path = &tmp.0;
        let h = Histogram::<u64>::new(3).unwrap();
        let e = histogram_svg(path, "idle", "us", &h, 1.0, &[]).unwrap_err();
        assert!(e.to_string().contains("no samples"), "{e}");
        assert!(!path.exists());
        let e = distributions_svg(path, "idle", "us", &[("a", &h, 1.0)]).unwrap_err();
        assert!(e.to_string().contains("a has no samples"), "{e}");
        assert!(distributions_svg(path, "idle", "us", &[]).is_err());
        assert!(!path.exists());
    }

    #[test]
    fn unwritable_path_names_it() {
        let path = Path::new("/nonexistent-ppm-dir/x.svg");
        let e = histogram_svg(path, "t", "us", &latencies(), 1e3, &[]).unwrap_err();
        assert!(
            format!("{e:#}").contains("/nonexistent-ppm-dir/x.svg"),
            "{e:#}"
        );
    }

    #[test]
    fn distributions_have_a_labelled_curve_each() {
        let fast = latencies();
        let mut slow = Histogram::<u64>::new(3).unwrap();
        for v in fast.iter_recorded() {
            slow.record_n(v.value_iterated_to() * 3, v.count_at_value())
                .unwrap();
        }
        let tmp = Temp::new("dist.svg");
        let path = &tmp.0;
        distributions_svg(
            path,
            "grid and follow",
            "ms",
            &[("follow", &fast, 1e3), ("grid", &slow, 1e3)],
        )
        .unwrap();
        let svg = read_svg(path);
        assert_texts(
            &svg,
            &[
                "grid and follow",
                "latency (ms)",
                "percentile (log scale of 1 - p)",
                "follow (10051 samples)",
                "grid (10051 samples)",
                "90%",
                "99.9%",
                "99.99%",
            ],
        );
        // Each curve rises left to right, the slow one above the fast one.
        let curve = |colour: RGBColor| -> Vec<(f64, f64)> {
            let c = format!("#{:02X}{:02X}{:02X}", colour.0, colour.1, colour.2);
            let t = tags(&svg, "polyline")
                .into_iter()
                .filter(|(t, _)| attr(t, "stroke") == Some(c.as_str()))
                .max_by_key(|(t, _)| t.len())
                .unwrap();
            points(t.0)
        };
        let (f, s) = (curve(PALETTE[0]), curve(PALETTE[1]));
        assert!(f.len() > 10 && s.len() > 10);
        // Pixel y grows downwards.
        assert!(f.windows(2).all(|w| w[0].0 <= w[1].0 && w[0].1 >= w[1].1));
        assert!(f.last().unwrap().1 > s.last().unwrap().1);
        assert!(f[0].1 > s[0].1);
    }

    #[test]
    fn summaries_place_dots_at_their_percentiles() {
        let tmp = Temp::new("summary.svg");
        let path = &tmp.0;
        summaries_svg(
            path,
            "ingress",
            "us",
            &[
                (
                    "udp-ingress",
                    3000,
                    &[(0.5, 20.0), (0.99, 40.0), (1.0, 90.0)],
                ),
                ("Python", 3000, &[(0.5, 200.0), (0.99, 400.0), (1.0, 900.0)]),
            ],
        )
        .unwrap();
        let svg = read_svg(path);
        assert_eq!(svg.matches("<circle").count(), 6);
        assert_texts(&svg, &["udp-ingress (3000 samples)"]);
        assert!((nines(0.99, 3000) - 2.0).abs() < 1e-12);
        assert!((nines(1.0, 1000) - 3.0).abs() < 1e-12);
        assert_eq!(nines_text(0.0), "0%");
        assert_eq!(nines_text(1.0), "90%");
        assert_eq!(nines_text(3.0), "99.9%");
        let bad: &[(f64, f64)] = &[(1.5, 1.0)];
        assert!(summaries_svg(path, "t", "us", &[("x", 1, bad)]).is_err());
    }

    #[test]
    fn histogram_of_rounds_and_skips_invalid() {
        let h = histogram_of(&[1.4, 2.6, -1.0, f64::NAN, 3e9]);
        assert_eq!(h.len(), 3);
        assert_eq!(h.min(), 1);
        assert!(h.max() >= 3_000_000_000 && h.max() < 3_010_000_000);
        assert_eq!(
            (nice_step(0.13), nice_step(3.0), nice_step(7.0)),
            (0.2, 5.0, 10.0)
        );
    }
}
