//! `drivescript bench`: throughput tables. Figures are from one run on a shared machine, so
//! compare rows of the same run rather than runs.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use drivescript::geom::{FrenetPath, Point, Polyline};
use drivescript::io::{
    check_output_not_input, check_replaces_own, discover, load_scenes, womd, LoadOptions,
};
use drivescript::scene::Turn;

#[derive(clap::Args)]
pub struct Args {
    /// What to measure.
    #[arg(value_enum)]
    what: What,
    /// Extra directory of scenes to time (e.g. ../shared/data/commonroad-ngsim).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Minimum time spent on each row, 0.05 to 3600 seconds (`bench io` and `bench cost`;
    /// default 1).
    #[arg(long, value_parser = super::ask::float)]
    seconds: Option<f64>,
    /// Scene for `bench cost`, cropped to 24 agents x 80 future steps (default: NGSIM US-101
    /// scene 23_1 from ../shared/data when present, else the US-101 sample with its 22 agents).
    #[arg(long)]
    scene: Option<PathBuf>,
    /// `bench sample`: the checkpoint to sample with (default: data/checkpoint).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// `bench sample`: runs per row (the median is printed), 1-1000 (default 3).
    #[arg(long)]
    repeat: Option<usize>,
    /// `bench sample`: only this row (train, unguided, output or denoiser).
    #[arg(long, value_parser = ["train", "unguided", "output", "denoiser"])]
    only: Option<String>,
    /// `bench sample`: also write the unguided run's inputs and outputs (safetensors) for
    /// benches/torch/, which checks a PyTorch port against them.
    #[arg(long)]
    export: Option<PathBuf>,
    /// `bench io`: keep the re-encoded WOMD file (of --data when given, else of the samples)
    /// at this path, for benches/womd/read.py to read with Python's protobuf.
    #[arg(long, value_name = "FILE", conflicts_with = "womd")]
    womd_out: Option<PathBuf>,
    /// `bench io`: time only reading this WOMD TFRecord file (into scenes, and into protos).
    #[arg(long, value_name = "FILE")]
    womd: Option<PathBuf>,
}

#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
enum What {
    /// Scene readers (scenes/s per format) and Frenet projections/s.
    Io,
    /// Cost + gradient of scripts against the same costs hand-written in Rust.
    Cost,
    /// Diffusion sampling (unguided, guided in output space, guided through the denoiser) and
    /// training steps, at the paper's sizes (24 agents, 200 lanes, 32 steps).
    Sample,
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
    let n = load_all(sources).with_context(|| format!("timing {name}"))?;
    let mut bytes = 0u64;
    for p in sources {
        bytes = bytes.saturating_add(drivescript::io::bytes_under(p)?);
    }
    let (r, reps) = rate(min, n, || load_all(sources).map(|_| ()))?;
    println!(
        "| {name:<40} | {n:>6} | {reps:>5} | {r:>10.1} | {:>9.2} | {:>10.1} |",
        1000.0 / r,
        r * bytes as f64 / n as f64 / 1e6
    );
    Ok(())
}

/// Refuses a flag the chosen benchmark does not read (it would be dropped without a word, and
/// the table taken for what was asked), and outputs that would replace an input or a file the
/// benchmark did not write.
fn check_flags(args: &Args) -> Result<()> {
    use clap::ValueEnum;
    let given: [(&str, bool, &[What]); 9] = [
        ("--data", args.data.is_some(), &[What::Io]),
        ("--seconds", args.seconds.is_some(), &[What::Io, What::Cost]),
        ("--scene", args.scene.is_some(), &[What::Cost]),
        ("--checkpoint", args.checkpoint.is_some(), &[What::Sample]),
        ("--repeat", args.repeat.is_some(), &[What::Sample]),
        ("--only", args.only.is_some(), &[What::Sample]),
        ("--export", args.export.is_some(), &[What::Sample]),
        ("--womd-out", args.womd_out.is_some(), &[What::Io]),
        ("--womd", args.womd.is_some(), &[What::Io]),
    ];
    let name = |w: &What| w.to_possible_value().map(|v| v.get_name().to_string());
    for (flag, is_given, kinds) in given {
        if is_given && !kinds.contains(&args.what) {
            let takes: Vec<String> = kinds
                .iter()
                .filter_map(|k| name(k).map(|n| format!("`bench {n}`")))
                .collect();
            anyhow::bail!(
                "{flag}: `bench {}` does not read it (only {} {})",
                name(&args.what).unwrap_or_default(),
                takes.join(" and "),
                if takes.len() > 1 { "do" } else { "does" }
            );
        }
    }
    if let Some(out) = &args.womd_out {
        let samples = super::samples_dir();
        let inputs: Vec<&Path> = args
            .data
            .iter()
            .map(|d| d.as_path())
            .chain([samples.as_path()])
            .collect();
        check_output_not_input(out, &inputs, "--womd-out")?;
        check_replaces_own(out, "--womd-out", "a WOMD TFRecord", |p| {
            womd::read_file(p).is_ok_and(|mut records| records.all(|r| r.is_ok()))
        })?;
    }
    if let Some(out) = &args.export {
        let ckpt = args
            .checkpoint
            .clone()
            .unwrap_or_else(|| super::samples_dir().join("../checkpoint"));
        let files: Vec<PathBuf> = ["model.safetensors", "optimizer.safetensors", "config.json"]
            .iter()
            .map(|f| ckpt.join(f))
            .collect();
        let inputs: Vec<&Path> = files.iter().map(|f| f.as_path()).collect();
        check_output_not_input(out, &inputs, "--export")?;
        check_replaces_own(out, "--export", "a `bench sample --export` file", |p| {
            candle_core::safetensors::load(p, &candle_core::Device::Cpu)
                .is_ok_and(|t| t.contains_key("x_final") && t.contains_key("sigmas"))
        })?;
    }
    Ok(())
}

pub fn run(args: Args) -> Result<ExitCode> {
    check_flags(&args)?;
    let seconds = args.seconds.unwrap_or(1.0);
    if !(0.05..=3600.0).contains(&seconds) {
        // As typed, in a few characters: `{:?}` wrote 1e9 as "1000000000.0".
        anyhow::bail!(
            "--seconds {}: give 0.05 to 3600 seconds per row",
            drivescript::geom::num(seconds)
        );
    }
    let min = Duration::from_secs_f64(seconds);
    match args.what {
        What::Io => bench_io(&args, min),
        What::Cost => bench_cost(&args, min),
        What::Sample => bench_sample(&args),
    }
}

fn time_per_call(min: Duration, mut f: impl FnMut()) -> (f64, usize) {
    f();
    let start = Instant::now();
    let mut reps = 0;
    while start.elapsed() < min || reps < 3 {
        f();
        reps += 1;
    }
    (start.elapsed().as_secs_f64() / reps as f64 * 1e6, reps)
}

fn bench_cost(args: &Args, min: Duration) -> Result<ExitCode> {
    use drivescript::cost::{handwritten, CostScript, Limits, Params, Trajectories};
    use std::rc::Rc;
    let samples = super::samples_dir();
    let shared = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/commonroad-ngsim/USA_US101-23_1_T-1.xml.gz");
    let path = args.scene.clone().unwrap_or_else(|| {
        if shared.exists() {
            shared
        } else {
            samples.join("commonroad/USA_US101-4_1_T-1.xml")
        }
    });
    let full = drivescript::io::load_scene(&path, 0, &LoadOptions::default())?;
    let scene = Rc::new(
        full.crop(24, 80)
            .with_context(|| format!("{}: the bench scene", path.display()))?,
    );
    if scene.agents.len() < 24 {
        println!(
            "note: only {} agents are observed at step {}; using all of them",
            scene.agents.len(),
            scene.meta.current_step
        );
    }
    // The rows judge a cut-in of one vehicle by another and collisions between vehicles: a
    // scene of one agent panicked here (index out of bounds), and one whose second agent was
    // a pedestrian printed half the table, then stopped at no_collisions.rhai.
    let vehicles: Vec<usize> = (0..scene.agents.len())
        .filter(|&i| scene.agents[i].agent_type == drivescript::scene::AgentType::Vehicle)
        .collect();
    let (vi, ci) = match vehicles[..] {
        [vi, ci, ..] => (vi, ci),
        _ => anyhow::bail!(
            "{}: the bench scene has {} vehicle(s) observed at step {}: `bench cost` times a \
             cut-in of one vehicle by another and collisions between vehicles, so it needs at \
             least two (--scene)",
            path.display(),
            vehicles.len(),
            scene.meta.current_step
        ),
    };
    let traj = Trajectories::filled(&scene);
    let (v, c) = (scene.agents[vi].id, scene.agents[ci].id);
    println!(
        "scene {} ({}), {} agents x {} future steps, victim {v}, cutter {c}\n",
        scene.meta.scenario_id,
        super::shown(&path),
        scene.agents.len(),
        traj.layout.steps
    );
    let scripts_dir = super::samples_dir().join("../../scripts");
    let load = |name: &str, params: Vec<String>| -> Result<CostScript> {
        let src = std::fs::read_to_string(scripts_dir.join(name))?;
        Ok(CostScript::compile(
            &src,
            name,
            scene.clone(),
            &Params::parse(&params)?,
            &Limits::default(),
        )?)
    };
    let pair_loop = "let vs = vehicles();\nlet total = 0.0;\nfor i in 0..vs.len() {\n  for j in (i + 1)..vs.len() {\n    total += collision_penalty(vs[i], vs[j], 0.5).sum();\n  }\n}\nterm(\"collisions\", total);\n";
    let rows: Vec<(&str, CostScript, Box<dyn Fn() -> f64>)> = vec![
        (
            "cut_in",
            load(
                "cut_in.rhai",
                vec![format!("cutter={c}"), format!("victim={v}")],
            )?,
            Box::new({
                let (s, t) = (scene.clone(), traj.clone());
                move || handwritten::cut_in(&s, &t, ci, vi, 5.0, 0.5).map_or(f64::NAN, |r| r.0)
            }),
        ),
        (
            "rightmost_lane",
            load("rightmost_lane.rhai", vec![format!("vehicle={v}")])?,
            Box::new({
                let (s, t) = (scene.clone(), traj.clone());
                move || handwritten::rightmost(&s, &t, vi, 0.5).map_or(f64::NAN, |r| r.0)
            }),
        ),
        (
            "no_collisions",
            load("no_collisions.rhai", vec!["margin=0.5".into()])?,
            Box::new({
                let (s, t) = (scene.clone(), traj.clone());
                move || handwritten::no_collisions(&s, &t, 0.5).0
            }),
        ),
        (
            "no_collisions, pair loop in Rhai",
            CostScript::compile(
                pair_loop,
                "pair-loop",
                scene.clone(),
                &Params::default(),
                &Limits::default(),
            )?,
            Box::new({
                let (s, t) = (scene.clone(), traj.clone());
                move || handwritten::no_collisions(&s, &t, 0.5).0
            }),
        ),
    ];
    println!(
        "| {:<34} | script µs | hand-written µs | ratio | script total | hand-written total |",
        "cost"
    );
    println!(
        "|{}|-----------|-----------------|-------|--------------|--------------------|",
        "-".repeat(36)
    );
    for (name, script, hand) in rows {
        let total = script.evaluate(&traj)?.total;
        let (ts, _) = time_per_call(min, || {
            std::hint::black_box(script.evaluate(&traj).expect("evaluated once already"));
        });
        let hand_total = hand();
        let (th, _) = time_per_call(min, || {
            std::hint::black_box(hand());
        });
        println!("| {name:<34} | {ts:>9.1} | {th:>15.1} | {:>5.2} | {total:>12.5} | {hand_total:>18.5} |", ts / th);
    }
    Ok(ExitCode::SUCCESS)
}

/// Peak resident memory of this process so far, from /proc (Linux), in MiB.
fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

fn bench_sample(args: &Args) -> Result<ExitCode> {
    use drivescript::cost::{CostScript, Limits, Params};
    use drivescript::model::{DenoiserConfig, Edm, Scores};
    use drivescript::sample::{prepare, reference_run, sample, Guidance, SampleConfig, Task};
    use drivescript::train::{load, train, TrainConfig, WindowConfig};
    use std::rc::Rc;
    let samples = super::samples_dir();
    let repeat = args.repeat.unwrap_or(3);
    anyhow::ensure!(
        (1..=1000).contains(&repeat),
        "--repeat {repeat}: give 1 to 1000 runs per row"
    );
    // The paper's sizes: 24 agents and 200 lanes (padded) per window.
    let window = WindowConfig {
        history: 11,
        future: 80,
        max_agents: 24,
        max_lanes: 200,
        lane_points: 20,
        stride: 10,
        centres_per_step: 8,
        pad_lanes: true,
        min_future: 0,
        nearest_lane_pose: false,
        route_times: 0,
        goals: false,
        route_frame: false,
    };
    let path = args
        .scene
        .clone()
        .unwrap_or_else(|| samples.join("commonroad/USA_US101-4_1_T-1.xml"));
    let scene = drivescript::io::load_scene(&path, 0, &LoadOptions::default())?;
    let ckpt = args
        .checkpoint
        .clone()
        .unwrap_or_else(|| samples.join("../checkpoint"));
    let mut trained = load(&ckpt).with_context(|| format!("loading {}", ckpt.display()))?;
    // The network does not depend on the window's size; its PCA horizon and the inputs it
    // reads stay the checkpoint's (a --nearest-lane-pose checkpoint failed with "shape
    // mismatch in matmul", a --route-times one with "the batch has no route inputs", a
    // --route-frame one with "the batch has no routes" after the table's first row).
    let own = &trained.meta.config.window;
    trained.meta.config.window = WindowConfig {
        future: own.future,
        nearest_lane_pose: own.nearest_lane_pose,
        route_times: own.route_times,
        goals: own.goals,
        route_frame: own.route_frame,
        ..window
    };
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let want = |what: &str| args.only.as_deref().is_none_or(|o| o == what);
    println!(
        "scene {} ({} agents, {} lanes) in a window of 24 agents and 200 lanes (padded); checkpoint {} (d = {}, {} layers per attention module, {} PCA components); 32 Heun steps (63 denoiser calls), batch of 1; median of {} runs\n",
        scene.meta.scenario_id,
        scene.agents.len(),
        scene.map.lanes().len(),
        super::shown(&ckpt),
        trained.meta.config.model.d,
        trained.meta.config.model.layers,
        trained.meta.config.model.k,
        repeat
    );
    println!("| what | seconds |\n|---|---|");
    if want("train") {
        // A fresh model of the same sizes; the first step (allocator warm-up) is not counted.
        let steps = repeat + 1;
        let cfg = TrainConfig {
            steps,
            batch: 4,
            window,
            model: DenoiserConfig {
                d: 64,
                layers: 3,
                k: 12,
                history: 11,
                noise_freqs: 8,
                scores: Scores::Normalised,
                attrs: 0,
                agent_lane_features: 4,
                route_times: 0,
                goals: false,
                route_frame: false,
            },
            edm: Edm::default(),
            eval_every: usize::MAX,
            ..TrainConfig::ngsim()
        };
        let mut step_times = Vec::new();
        let mut last = Instant::now();
        train(std::slice::from_ref(&scene), cfg, None, None, |_, _, _| {
            step_times.push(last.elapsed().as_secs_f64());
            last = Instant::now();
        })?;
        println!(
            "| training step (batch 4 windows, forward + backward + AdamW) | {:.3} |",
            median(step_times[1..].to_vec())
        );
    }
    let sim = prepare(&scene, &trained)?;
    let src = std::fs::read_to_string(samples.join("../../scripts/no_collisions.rhai"))?;
    let script = CostScript::compile(
        &src,
        "no_collisions.rhai",
        Rc::new(sim.clone()),
        &Params::default(),
        &Limits::default(),
    )?;
    for (what, name, lambda, g) in [
        ("unguided", "sampling, unguided", 0.0, Guidance::OutputSpace),
        (
            "output",
            "sampling, guided in output space (no_collisions)",
            0.05,
            Guidance::OutputSpace,
        ),
        (
            "denoiser",
            "sampling, guided through the denoiser (no_collisions)",
            0.05,
            Guidance::Denoiser,
        ),
    ] {
        if !want(what) {
            continue;
        }
        let cfg = SampleConfig {
            steps: 32,
            samples: 1,
            lambda,
            guidance: g,
            task: Task::Unconditional,
            ..SampleConfig::default()
        };
        let mut times = Vec::new();
        for _ in 0..repeat {
            let t = Instant::now();
            sample(&trained, &sim, std::slice::from_ref(&script), &cfg)?;
            times.push(t.elapsed().as_secs_f64());
        }
        println!("| {name} | {:.3} |", median(times));
    }
    println!(
        "\npeak resident memory: {}",
        peak_rss_mib().map_or("unknown".into(), |m| format!("{m:.0} MiB"))
    );
    if let Some(out) = &args.export {
        let cfg = SampleConfig {
            steps: 32,
            samples: 1,
            lambda: 0.0,
            task: Task::Unconditional,
            ..SampleConfig::default()
        };
        let tensors: std::collections::HashMap<String, candle_core::Tensor> =
            reference_run(&trained, &sim, &cfg)?.into_iter().collect();
        drivescript::io::write_atomic_from(out, |p| {
            candle_core::safetensors::save(&tensors, p).map_err(drivescript::model::error::message)
        })?;
        println!(
            "wrote {} (the unguided run's inputs and outputs)",
            super::shown(&out)
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn bench_io(args: &Args, min: Duration) -> Result<ExitCode> {
    let samples = super::samples_dir();
    // Inputs are checked before the table starts: an error under a header read as a
    // benchmark that began and broke.
    if let Some(f) = &args.womd {
        let meta = std::fs::metadata(f).with_context(|| format!("--womd {}", super::shown(f)))?;
        if !meta.is_file() {
            bail!(
                "--womd {}: not a regular file ({}): --womd times one WOMD TFRecord file",
                super::shown(f),
                if meta.is_dir() {
                    "a directory"
                } else {
                    "a FIFO, socket or device, which reading could block forever"
                }
            );
        }
    }
    let mut readable_of = None;
    let extra = match &args.data {
        Some(d) => {
            let extra = discover(d).with_context(|| format!("--data {}", super::shown(d)))?;
            // A set of no scenes was timed as a row of 0 scenes at "inf" ms each, and its
            // re-encoding failed naming an empty file in bench's own temporary directory.
            if extra.is_empty() {
                bail!(
                    "--data {}: no scene file in it, so there is nothing to time (supported: {})",
                    d.display(),
                    drivescript::io::SUPPORTED_FORMATS
                );
            }
            // Every file is tried before the table, and a bad one reported and left out of
            // the timed set: the first one stopped the benchmark (other commands go on), and
            // a row must say when it times fewer files than --data holds.
            let mut readable = Vec::new();
            for f in &extra {
                match load_scenes(f, &LoadOptions::default()) {
                    Ok(_) => readable.push(f.clone()),
                    Err(e) => super::print_error(&format!("--data: {e}")),
                }
            }
            if readable.is_empty() {
                bail!(
                    "--data {}: none of its {} scene files could be read (above), so there is \
                     nothing to time",
                    super::shown(d),
                    extra.len()
                );
            }
            readable_of = Some((readable.len(), extra.len()));
            readable
        }
        None => Vec::new(),
    };
    let data_name = |d: &Path| match readable_of {
        Some((ok, all)) if ok < all => {
            format!("--data {} ({ok} of {all} files)", super::shown(d))
        }
        _ => format!("--data {}", super::shown(d)),
    };
    println!("## Scene readers\n");
    println!(
        "| {:<40} | scenes |  reps |   scenes/s |  ms/scene | input MB/s |",
        "format"
    );
    println!(
        "|{}|--------|-------|------------|-----------|------------|",
        "-".repeat(42)
    );
    if let Some(f) = &args.womd {
        womd_file_rows(&super::shown(f), f, min)?;
        return Ok(ExitCode::SUCCESS);
    }
    let cr = discover(&samples.join("commonroad"))?;
    row("CommonRoad XML (samples)", &cr, min)?;
    if let Some(d) = &args.data {
        row(&data_name(d), &extra, min)?;
    }
    row("Argoverse 2 (sample)", &[samples.join("av2")], min)?;
    row("YAML (samples)", &discover(&samples.join("yaml"))?, min)?;
    // WOMD files are re-encoded from the scenes above (no WOMD file ships), each set into one
    // multi-record file; the larger --data set is the one closest to WOMD's record sizes.
    let mut sets = vec![("samples".to_string(), cr.clone())];
    if let Some(d) = &args.data {
        sets.push((data_name(d), extra.clone()));
    }
    let last = sets.len() - 1;
    // A directory of our own in the shared temporary directory, made new (an existing one is
    // an error, never used): a file of a name anyone can predict there could be a link
    // another user planted, which the write would follow.
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    let scratch =
        std::env::temp_dir().join(format!("drivescript-bench-{}-{nanos}", std::process::id()));
    std::fs::create_dir(&scratch).with_context(|| format!("creating {}", scratch.display()))?;
    let mut res = Ok(());
    for (k, (name, sources)) in sets.iter().enumerate() {
        let keep = args.womd_out.as_ref().filter(|_| k == last);
        let tmp = keep
            .cloned()
            .unwrap_or_else(|| scratch.join(format!("{k}.tfrecord")));
        res = womd_rows(name, sources, &tmp, min);
        if res.is_err() {
            break;
        }
    }
    let _ = std::fs::remove_dir_all(&scratch);
    res?;
    if let Some(p) = &args.womd_out {
        println!(
            "\nkept the last re-encoded WOMD file at {} (for benches/womd/read.py)",
            super::shown(&p)
        );
    }

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
    Ok(match readable_of {
        Some((ok, all)) if ok < all => ExitCode::FAILURE,
        _ => ExitCode::SUCCESS,
    })
}

/// Re-encodes `sources` as one WOMD TFRecord file at `path` and prints its rows.
fn womd_rows(name: &str, sources: &[PathBuf], path: &Path, min: Duration) -> Result<()> {
    let opts = LoadOptions::default();
    let mut scenes = Vec::new();
    for s in sources {
        scenes.extend(load_scenes(s, &opts).with_context(|| format!("loading {}", s.display()))?);
    }
    womd::write_file(path, &scenes)?;
    womd_file_rows(&format!("{name}, re-encoded"), path, min)
}

/// Two rows for one WOMD file: reading it into scenes (what every command does), and decoding
/// its Scenario protos only (what a protobuf library's parse does: the figure
/// benches/womd/compare.py sets against Python's protobuf).
fn womd_file_rows(name: &str, path: &Path, min: Duration) -> Result<()> {
    row(
        &format!("WOMD → scenes ({name})"),
        std::slice::from_ref(&path.to_path_buf()),
        min,
    )?;
    let bytes = std::fs::metadata(path)?.len();
    let decode = || -> Result<usize> {
        let f = std::fs::File::open(path)?;
        let reader = drivescript::io::tfrecord::TfRecordReader::new(
            std::io::BufReader::with_capacity(1 << 20, f),
        );
        let mut n = 0;
        for rec in reader {
            let sc = drivescript::io::womd_wire::decode_scenario(&rec?)?;
            std::hint::black_box(&sc);
            n += 1;
        }
        Ok(n)
    };
    let n = decode()?;
    let (r, reps) = rate(min, n, || decode().map(|_| ()))?;
    println!(
        "| {:<40} | {n:>6} | {reps:>5} | {r:>10.1} | {:>9.2} | {:>10.1} |",
        format!("WOMD → protos only ({name})"),
        1000.0 / r,
        r * bytes as f64 / n as f64 / 1e6
    );
    Ok(())
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
