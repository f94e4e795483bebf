//! `--plot`: the latency distributions `ppm-bench` measured, drawn as SVG.

use anyhow::{Context, Result};
use hdrhistogram::Histogram;
use ppm_tools::analysis::Percentiles;
use ppm_tools::plot;
use std::path::Path;

/// (quantile, value) points of a distribution known only by a few.
pub type Points = Vec<(f64, f64)>;

/// The latency distributions measured, kept for `--plot`.
#[derive(Default)]
pub struct Plots {
    /// Per receiver: samples and (quantile, us) of its ingress latency,
    /// known only as p50, p99 and max.
    pub ingress: Vec<(String, u64, Points)>,
    /// Per variant: the newest command's age at each frame start during the
    /// flood, ns.
    pub flood: Vec<(String, Histogram<u64>)>,
    /// Per timing and rate: send to the line, ns.
    pub e2e: Vec<(String, Histogram<u64>)>,
}

/// Makes `dir` for `--plot` and checks that files can be written in it,
/// before anything is measured.
pub fn plot_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("--plot: cannot create the directory {}", dir.display()))?;
    let probe = dir.join(format!(".ppm-bench-{}", std::process::id()));
    std::fs::write(&probe, b"")
        .with_context(|| format!("--plot: cannot write in the directory {}", dir.display()))?;
    let _ = std::fs::remove_file(probe);
    Ok(())
}

/// Writes the plots of what was measured to `dir` and prints their paths.
pub fn write_plots(dir: &Path, plots: &Plots) -> Result<()> {
    let mut written = Vec::new();
    let ingress: Vec<plot::Summary> = plots
        .ingress
        .iter()
        .filter(|(_, n, pts)| *n > 0 && pts.iter().all(|p| p.1.is_finite()))
        .map(|(l, n, pts)| (l.as_str(), *n, pts.as_slice()))
        .collect();
    if !ingress.is_empty() {
        let path = dir.join("ingress.svg");
        plot::summaries_svg(
            &path,
            "1. ingress: kernel receive to command handed over (p50, p99, max)",
            "us",
            &ingress,
        )?;
        written.push(path);
    }
    for (name, title, unit, runs, scale) in [
        (
            "flood.svg",
            "2. flood: newest command's age at ppmd's frame starts",
            "ms",
            &plots.flood,
            1e6,
        ),
        (
            "e2e.svg",
            "3. end to end: send to the first frame carrying the command",
            "ms",
            &plots.e2e,
            1e6,
        ),
    ] {
        let refs: Vec<(&str, &Histogram<u64>, f64)> = runs
            .iter()
            .filter(|(_, h)| !h.is_empty())
            .map(|(l, h)| (l.as_str(), h, scale))
            .collect();
        if refs.is_empty() {
            continue;
        }
        let path = dir.join(name);
        plot::distributions_svg(&path, title, unit, &refs)?;
        written.push(path);
    }
    for (label, h) in plots.e2e.iter().filter(|(_, h)| !h.is_empty()) {
        let p = Percentiles::of_histogram(h);
        let path = dir.join(format!(
            "e2e-{}hz.svg",
            label.replace(", ", "-").replace(" Hz", "")
        ));
        plot::histogram_svg(
            &path,
            &format!("3. end to end, {label}: send to the first frame carrying the command"),
            "ms",
            h,
            1e6,
            &[
                ("p50", p.p50 / 1e6),
                ("p90", p.p90 / 1e6),
                ("p99", p.p99 / 1e6),
                ("max", p.max / 1e6),
            ],
        )?;
        written.push(path);
    }
    for path in written {
        println!("plot: {}", path.display());
    }
    Ok(())
}
