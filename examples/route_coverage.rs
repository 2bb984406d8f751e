//! How closely recorded futures follow a route of the lane graph (`scene::routes`), against the
//! straight line of the current heading that the cities model's futures are told from.
//!
//! Directories are read file by file. For every moving vehicle with a whole future of HORIZON steps from the current step (10), the
//! largest offset of its future across the route it strays from least, and across the line
//! of its current heading; the shares within each distance.
//!
//! It also counts which of the routes the sampler offers each of those vehicles
//! (`train::dataset::agent_route_lines`, the first straight on from the nearest lane) its
//! future strays from least: the prior an unconditional sample's route is drawn from.
//!
//!     cargo run --release --example route_coverage -- HORIZON SCENE_OR_DIR...

use std::path::Path;

use drivescript::geom::Point;
use drivescript::geom::{FrenetPath, Polyline};
use drivescript::io::{load_scenes, LoadOptions};
use drivescript::scene::routes::{candidate_routes, fit_route, route_residual};
use drivescript::scene::AgentType;
use drivescript::train::dataset::{agent_route_lines, to_frame};
use drivescript::train::WindowConfig;

const LIMITS: [f64; 5] = [0.5, 1.0, 1.75, 3.5, 7.0];

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        args.len() >= 2,
        "usage: route_coverage HORIZON SCENE_OR_DIR..."
    );
    let horizon: usize = args[0].parse()?;
    let cfg = WindowConfig {
        future: horizon,
        ..WindowConfig::cities()
    };
    // Per number of routes offered (the last row: that many or more), how often each is the
    // one the future strays from least.
    let mut chosen = [[0usize; MOST_OFFERED]; MOST_OFFERED];
    let (mut route_max, mut line_max, mut counts) = (Vec::new(), Vec::new(), Vec::new());
    let (mut no_route, mut still) = (0usize, 0usize);
    // Residual futures, along then across, in the route's frame and in the heading's.
    let (mut in_route, mut in_plane): (Vec<Vec<f64>>, Vec<Vec<f64>>) = (Vec::new(), Vec::new());
    let mut files = Vec::new();
    for arg in &args[1..] {
        let path = Path::new(arg);
        if path.is_dir() {
            let mut inside: Vec<_> = std::fs::read_dir(path)?
                .map(|e| e.map(|e| e.path()))
                .collect::<Result<_, _>>()?;
            inside.sort();
            files.extend(inside);
        } else {
            files.push(path.to_path_buf());
        }
    }
    for file in &files {
        for scene in load_scenes(file, &LoadOptions::default())? {
            let c = scene.meta.current_step;
            for (i, a) in scene.agents.iter().enumerate() {
                if a.agent_type != AgentType::Vehicle || a.is_static {
                    continue;
                }
                if c + horizon >= a.states.len() || !(c..=c + horizon).all(|t| a.is_valid(t)) {
                    continue;
                }
                let now = a.states[c];
                let pts: Vec<Point> = a.states[c + 1..=c + horizon]
                    .iter()
                    .map(|s| s.position())
                    .collect();
                let moved = pts.windows(2).map(|w| (w[1] - w[0]).norm()).sum::<f64>();
                if moved < 2.0 {
                    still += 1;
                    continue;
                }
                // The future in the current heading's frame: x along it, y across.
                let local: Vec<[f64; 3]> = pts
                    .iter()
                    .map(|p| to_frame([now.x, now.y, now.heading], *p, 0.0))
                    .collect();
                let line = local.iter().map(|f| f[1].abs()).fold(0.0, f64::max);
                // Metres a step at the current speed: the constant-speed anchor of both frames.
                let advance = now.speed() * scene.meta.dt;
                let routes =
                    candidate_routes(&scene.map, now.position(), now.heading, moved + 20.0);
                counts.push(routes.len());
                match fit_route(&routes, &pts) {
                    Some(f) => {
                        route_max.push(f.max_offset);
                        let future: Vec<Option<[f64; 3]>> = a.states[c + 1..=c + horizon]
                            .iter()
                            .map(|s| Some([s.x, s.y, s.heading]))
                            .collect();
                        let current = [now.x, now.y, now.heading];
                        let r = route_residual(&routes[f.route].frenet, current, &future, advance);
                        let r: Vec<[f64; 3]> = r.into_iter().flatten().collect();
                        in_route.push(
                            r.iter()
                                .map(|v| v[0])
                                .chain(r.iter().map(|v| v[1]))
                                .collect(),
                        );
                        let along = local
                            .iter()
                            .enumerate()
                            .map(|(t, f)| f[0] - advance * (t + 1) as f64);
                        let across = local.iter().map(|f| f[1]);
                        in_plane.push(along.chain(across).collect());
                    }
                    None => no_route += 1,
                }
                line_max.push(line);
                let offered = agent_route_lines(&scene, &cfg, c, i);
                let strays = |l: &Vec<Point>| {
                    let path = FrenetPath::new(Polyline::new(l.iter().copied())?);
                    Ok::<f64, drivescript::geom::GeomError>(
                        pts.iter()
                            .map(|p| path.project(*p).d.abs())
                            .fold(0.0, f64::max),
                    )
                };
                let mut best = (f64::INFINITY, 0);
                for (k, l) in offered.iter().enumerate() {
                    let m = strays(l)?;
                    if m < best.0 {
                        best = (m, k);
                    }
                }
                let row = offered.len().clamp(1, MOST_OFFERED) - 1;
                chosen[row][best.1.min(MOST_OFFERED - 1)] += 1;
            }
        }
    }
    let n = line_max.len();
    println!("{n} moving vehicles with {horizon} future steps ({still} moved under 2 m, left out); {no_route} with no route");
    counts.sort_unstable();
    if !counts.is_empty() {
        println!(
            "routes per vehicle: median {}, max {}",
            counts[counts.len() / 2],
            counts[counts.len() - 1]
        );
    }
    let share =
        |v: &[f64], lim: f64| v.iter().filter(|&&x| x <= lim).count() as f64 / n.max(1) as f64;
    println!(
        "largest offset     | {}",
        LIMITS.map(|l| format!("<= {l} m")).join(" | ")
    );
    println!(
        "best route         | {}",
        LIMITS
            .map(|l| format!("{:.3}", share(&route_max, l)))
            .join(" | ")
    );
    println!(
        "line of the heading | {}",
        LIMITS
            .map(|l| format!("{:.3}", share(&line_max, l)))
            .join(" | ")
    );
    for (name, rows) in [("route frame", &in_route), ("heading frame", &in_plane)] {
        let (along, across) = spread(rows, horizon);
        println!(
            "{name}: RMS residual along {along:.2} m, across {across:.2} m; PCA reconstruction RMS (m) with {}",
            [2, 4, 8, 12, 20].map(|k| format!("{k}: {:.3}", pca_rmse(rows, k))).join(", ")
        );
    }
    let first: usize = chosen.iter().map(|r| r[0]).sum();
    println!(
        "the sampler's routes: the first (straight on from the nearest lane) is the nearest for {first} of {n} ({:.3})",
        first as f64 / n.max(1) as f64
    );
    for (row, counts) in chosen.iter().enumerate() {
        let offered = if row + 1 == MOST_OFFERED {
            format!("{MOST_OFFERED} or more")
        } else {
            (row + 1).to_string()
        };
        let shown: Vec<String> = counts[..=row].iter().map(|c| c.to_string()).collect();
        println!("  {offered} offered: {}", shown.join(" / "));
    }
    Ok(())
}

/// Rows of the route-choice table: vehicles offered this many routes or more share the last.
const MOST_OFFERED: usize = 4;

/// RMS of the along and the across halves of the residuals.
fn spread(rows: &[Vec<f64>], horizon: usize) -> (f64, f64) {
    let n = (rows.len() * horizon).max(1) as f64;
    let sq = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let along: f64 = rows.iter().map(|r| sq(&r[..horizon])).sum();
    let across: f64 = rows.iter().map(|r| sq(&r[horizon..])).sum();
    ((along / n).sqrt(), (across / n).sqrt())
}

/// Position RMS error (per point) of the residuals rebuilt from their first `k` principal
/// components (fitted on these same rows).
fn pca_rmse(rows: &[Vec<f64>], k: usize) -> f64 {
    let (n, dim) = (rows.len(), rows[0].len());
    let mean: Vec<f64> = (0..dim)
        .map(|j| rows.iter().map(|r| r[j]).sum::<f64>() / n as f64)
        .collect();
    let m = nalgebra::DMatrix::from_fn(n, dim, |i, j| rows[i][j] - mean[j]);
    let svd = m.clone().svd(false, true);
    let v = svd.v_t.expect("asked for");
    let mut order: Vec<usize> = (0..svd.singular_values.len()).collect();
    order.sort_by(|a, b| svd.singular_values[*b].total_cmp(&svd.singular_values[*a]));
    let basis = nalgebra::DMatrix::from_fn(k.min(order.len()), dim, |i, j| v[(order[i], j)]);
    let rebuilt = (&m * basis.transpose()) * &basis;
    let err = (m - rebuilt).map(|e| e * e).sum();
    (err / (n * dim / 2) as f64).sqrt()
}
