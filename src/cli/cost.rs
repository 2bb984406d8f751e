//! `drivescript cost`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use drivescript::cost::{BoundScript, Params, ScriptSpec, Trajectories};
use drivescript::io::rollout::Rollout;

#[derive(clap::Args)]
pub struct Args {
    /// The scene file or directory.
    scene: PathBuf,
    /// The cost script.
    #[arg(long)]
    script: PathBuf,
    /// Script parameters, name=value (visible as constants).
    #[arg(long = "param", num_args = 1.., value_parser = super::param_value)]
    params: Vec<String>,
    /// Evaluate this rollout's future instead of the recorded one.
    #[arg(long)]
    rollout: Option<PathBuf>,
    /// Which scene of a multi-scene source.
    #[arg(long, default_value_t = 0)]
    index: usize,
    /// Future steps to validate and evaluate on, as the sampler will (the shipped model
    /// samples 40): the recording is cut to them, or extended with unobserved steps (a script
    /// that indexes past the recording fails here rather than in `simulate`). Default: the
    /// recorded future, or the rollout's.
    #[arg(long, conflicts_with = "rollout", value_parser = clap::value_parser!(u64).range(1..=10000))]
    horizon: Option<u64>,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let mut scene = super::load_indexed(&args.scene, args.index)?;
    let rollout = match &args.rollout {
        Some(p) => Some(Rollout::read(p)?),
        None => None,
    };
    // A rollout's horizon is the model's, not the recording's: the script sees the rollout's
    // steps, the scene cut to them or extended with unobserved ones.
    if let Some(steps) = rollout
        .as_ref()
        .and_then(|r| r.agents.iter().map(|a| a.states.len()).max())
        .filter(|&n| n != scene.num_steps() && n > scene.meta.current_step + 1)
    {
        scene = scene.over_horizon(steps - scene.meta.current_step - 1);
    }
    if let Some(h) = args.horizon {
        scene = scene.over_horizon(h as usize);
    }
    let params = Params::parse(&args.params)?;
    let spec = ScriptSpec::from_file(&args.script, params)?;
    let name = spec.name.clone();
    let bound = BoundScript::new(spec, scene)?;
    let (scene, validation) = (bound.scene(), bound.validated_in());
    // A term that no perturbed future moves is said, not refused: the user may keep it as a
    // guard against something the probes do not try.
    let warnings: Vec<String> = bound.dead_terms()?.iter().map(|d| d.to_string()).collect();
    for w in &warnings {
        eprintln!(
            "warning: {}",
            drivescript::io::name::terminal_safe(&w.to_string())
        );
    }
    let traj = match (&args.rollout, &rollout) {
        (Some(p), Some(r)) => {
            // The checks `eval` and `render` make of a rollout (positions a car can drive
            // between, ids and steps of this scene): a 1e300 coordinate scored zeros here.
            r.apply_to(scene, p)?;
            Trajectories::from_rollout(scene, r)
                .map_err(|m| anyhow::anyhow!("{}: {m}", p.display()))?
        }
        _ => Trajectories::recorded(scene),
    };
    let report = bound.evaluate(&traj)?;
    let norms = report.agent_grad_norms();
    let mut agents: Vec<(i64, f64)> = scene
        .agents
        .iter()
        .zip(&norms)
        .map(|(a, n)| (a.id, *n))
        .filter(|(_, n)| *n > 0.0)
        .collect();
    agents.sort_by(|a, b| b.1.total_cmp(&a.1));
    if args.json {
        let v = serde_json::json!({
            "scene": scene.meta.scenario_id,
            "script": name,
            "source": if args.rollout.is_some() { "rollout" } else { "recorded" },
            "total": report.total,
            "terms": report.terms.iter().map(|t| serde_json::json!({
                "name": t.name, "line": t.line, "weight": t.weight, "value": t.value,
                "weighted": t.weight * t.value, "grad_norm": t.grad_norm(),
            })).collect::<Vec<_>>(),
            "agent_grad_norms": agents.iter().map(|(id, n)| serde_json::json!({"agent": id, "grad_norm": n})).collect::<Vec<_>>(),
            "eval_ms": report.elapsed.as_secs_f64() * 1000.0,
            "validation_ms": validation.as_secs_f64() * 1000.0,
            "prints": report.prints,
            "warnings": warnings,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{} on {} ({} future, {} steps)",
            name,
            scene.meta.scenario_id,
            if args.rollout.is_some() {
                "rollout"
            } else {
                "recorded"
            },
            traj.layout.steps
        );
        println!(
            "| {:<24} | line | weight |        value |     weighted |  grad norm |",
            "term"
        );
        println!(
            "|{}|------|--------|--------------|--------------|------------|",
            "-".repeat(26)
        );
        for t in &report.terms {
            println!(
                "| {:<24} | {:>4} | {:>6.2} | {:>12.5} | {:>12.5} | {:>10.4} |",
                t.name,
                t.line,
                t.weight,
                t.value,
                t.weight * t.value,
                t.grad_norm()
            );
        }
        println!("total {:.5}", report.total);
        let shown: Vec<String> = agents
            .iter()
            .take(8)
            .map(|(id, n)| format!("{id}: {n:.4}"))
            .collect();
        println!(
            "gradient norm by agent: {}",
            if shown.is_empty() {
                "all zero".into()
            } else {
                shown.join(", ")
            }
        );
        for p in &report.prints {
            println!("print: {p}");
        }
        // Both runs count against the user's patience, and each against the wall-time limit.
        println!(
            "evaluated in {:.3} ms (and validated, on the recorded scene, in {:.3} ms)",
            report.elapsed.as_secs_f64() * 1000.0,
            validation.as_secs_f64() * 1000.0
        );
    }
    Ok(ExitCode::SUCCESS)
}
