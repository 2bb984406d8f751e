//! `drivescript bench`: throughput tables. Figures are from one run on a shared machine, so
//! compare rows of the same run rather than runs.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use drivescript::geom::{FrenetPath, Point, Polyline};
use drivescript::io::{discover, load_scenes, womd, LoadOptions};
use drivescript::scene::Turn;

#[derive(clap::Args)]
pub struct Args {
    /// What to measure.
    #[arg(value_enum)]
    what: What,
    /// Extra directory of scenes to time (e.g. ../shared/data/commonroad-ngsim).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Minimum time spent on each row.
    #[arg(long, default_value_t = 1.0)]
    seconds: f64,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum What {
    /// Scene readers (scenes/s per format) and Frenet projections/s.
    Io,
}

/// Runs `f` (which handles `n` items) until `min` has passed; returns items per second.
fn rate(min: Duration, n: usize, mut f: impl FnMut() -> Result<()>) -> Result<(f64, usize)> {
    f()?; // warm the page cache and allocator
    let start = Instant::now();
    let mut reps = 0;
    while start.elapsed() < min || reps == 0 {
        f()?;
        reps += 1;
    }
    Ok(((reps * n) as f64 / start.elapsed().as_secs_f64(), reps))
}

fn load_all(sources: &[PathBuf]) -> Result<usize> {
    let opts = LoadOptions::default();
    let mut n = 0;
    for s in sources {
        n += load_scenes(s, &opts)?.len();
    }
    Ok(n)
}

fn row(name: &str, sources: &[PathBuf], min: Duration) -> Result<()> {
    let n = load_all(sources).with_context(|| format!("loading the {name} scenes"))?;
    let (r, reps) = rate(min, n, || load_all(sources).map(|_| ()))?;
    println!(
        "| {name:<40} | {n:>6} | {reps:>5} | {r:>10.1} | {:>9.2} |",
        1000.0 / r
    );
    Ok(())
}

pub fn run(args: Args) -> Result<ExitCode> {
    let What::Io = args.what;
    let min = Duration::from_secs_f64(args.seconds.max(0.05));
    let samples = super::samples_dir();
    println!("## Scene readers\n");
    println!(
        "| {:<40} | scenes |  reps |   scenes/s |  ms/scene |",
        "format"
    );
    println!(
        "|{}|--------|-------|------------|-----------|",
        "-".repeat(42)
    );
    let cr = discover(&samples.join("commonroad"))?;
    row("CommonRoad XML (samples)", &cr, min)?;
    if let Some(d) = &args.data {
        let extra = discover(d)?;
        row(&format!("CommonRoad/any ({})", d.display()), &extra, min)?;
    }
    row("Argoverse 2 (sample)", &[samples.join("av2")], min)?;
    row("YAML (samples)", &discover(&samples.join("yaml"))?, min)?;
    let tmp =
        std::env::temp_dir().join(format!("drivescript-bench-{}.tfrecord", std::process::id()));
    let scenes: Vec<_> = cr
        .iter()
        .map(|p| load_scenes(p, &LoadOptions::default()))
        .collect::<Result<Vec<_>, _>>()?
        .into_iter()
        .flatten()
        .collect();
    womd::write_file(&tmp, &scenes)?;
    let res = row(
        "WOMD TFRecord (samples, re-encoded)",
        std::slice::from_ref(&tmp),
        min,
    );
    let _ = std::fs::remove_file(&tmp);
    res?;

    println!("\n## Frenet projection\n");
    let path = bench_path(&samples)?;
    let agents = 24;
    let steps = 91;
    let len = path.length();
    let pts: Vec<Point> = (0..agents * steps)
        .map(|k| {
            let (a, t) = (k / steps, k % steps);
            let s = len * (0.05 + 0.9 * ((a * 37 + t * 11) % 1000) as f64 / 1000.0);
            let d = -5.0 + 10.0 * ((a * 13 + t * 7) % 100) as f64 / 100.0;
            path.to_cartesian(s, d)
        })
        .collect();
    let mut sink = 0.0;
    let (r, reps) = rate(min, pts.len(), || {
        for p in &pts {
            let f = path.project(*p);
            sink += f.s + f.d + f.ds[0] + f.dd[1];
        }
        Ok(())
    })?;
    std::hint::black_box(sink);
    println!("| case                                              |  reps |  projections/s | µs per 24x91 batch |");
    println!("|---------------------------------------------------|-------|----------------|--------------------|");
    println!(
        "| {agents} agents x {steps} steps onto a {}-point lane path ({len:.0} m) | {reps:>5} | {r:>14.0} | {:>18.1} |",
        path.polyline().points().len(),
        1e6 * pts.len() as f64 / r
    );
    Ok(ExitCode::SUCCESS)
}

/// A real lane path from the Lankershim sample, resampled to 200 points.
fn bench_path(samples: &Path) -> Result<FrenetPath> {
    let scene = load_scenes(
        &samples.join("commonroad/USA_Lanker-1_1_T-1.xml"),
        &LoadOptions::default(),
    )?
    .remove(0);
    let best = scene
        .map
        .lanes()
        .iter()
        .filter_map(|l| scene.map.lane_path(l.id, 300.0, 100.0, Turn::Straight).ok())
        .max_by(|a, b| a.frenet.length().total_cmp(&b.frenet.length()))
        .context("the sample has no lanes")?;
    let line: Polyline = best.frenet.polyline().resample_count(200);
    Ok(FrenetPath::new(line))
}
